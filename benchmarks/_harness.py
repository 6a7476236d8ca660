"""Timing and result records shared by the benchmark sections.

Every measurement is a set of repeated wall-clock samples (``time.perf_counter_ns``), each call ending
in ``jax.block_until_ready`` so that JAX's asynchronous dispatch is inside the timed span, taken after
a warm-up (compilation and first-touch excluded). A measurement reports the median, the 99th
percentile and the number of samples; see ``benchmarks/__init__.py`` for the file layout.
"""

import dataclasses
import datetime
import gc
import os
import platform
import sys
import time
from collections.abc import Callable

import numpy as np

SCHEMA = "gtsjax-benchmarks/1"

_SCALE = {"us": 1e6, "ms": 1e3, "s": 1.0}


def block(x):
    """``jax.block_until_ready`` on whatever a call returned (JAX arrays, pytrees, or plain values)."""
    import jax

    return jax.block_until_ready(x)


def time_calls(fn: Callable[[int], object], repeats: int, warmup: int = 5) -> np.ndarray:
    """Seconds per call of ``fn(i)`` for ``i in range(repeats)``, after ``warmup`` untimed calls.
    Each call ends in ``block_until_ready``. The garbage collector is left on (the live loop has it
    too) but run once before the timed calls, so that an earlier section's garbage is not charged
    here."""
    for i in range(warmup):
        block(fn(i))
    gc.collect()
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        block(fn(i))
        out[i] = (time.perf_counter_ns() - t0) * 1e-9
    return out


@dataclasses.dataclass
class Results:
    """Everything one run produces; serialised by :meth:`to_json`."""

    quick: bool
    machine: dict = dataclasses.field(default_factory=dict)
    settings: dict = dataclasses.field(default_factory=dict)
    measurements: list = dataclasses.field(default_factory=list)
    ratios: list = dataclasses.field(default_factory=list)
    peers: dict = dataclasses.field(default_factory=dict)
    checks: dict = dataclasses.field(default_factory=dict)
    scaling: dict = dataclasses.field(default_factory=dict)
    targets: list = dataclasses.field(default_factory=list)
    profiles: dict = dataclasses.field(default_factory=dict)
    sections: dict = dataclasses.field(default_factory=dict)

    def add(self, name: str, unit: str, seconds, *, section: str, label: str | None = None, **params) -> dict:
        """A latency or duration: ``seconds`` are the samples, reported in ``unit`` (us, ms or s)."""
        s = np.asarray(seconds, float) * _SCALE[unit]
        rec = {"name": name, "section": section, "label": label or name, "unit": unit,
               "median": float(np.median(s)), "p99": float(np.percentile(s, 99)), "n": int(s.size),
               "min": float(s.min()), "params": params}
        self._put(rec)
        return rec

    def add_rate(self, name: str, count: int, seconds, *, section: str, unit: str = "scans/s",
                 label: str | None = None, **params) -> dict:
        """A throughput: ``count`` items per run, ``seconds`` the runs' durations. ``median`` is the rate
        at the median duration; ``p99`` the rate at the 99th-percentile duration (the slow tail)."""
        s = np.asarray(seconds, float)
        rec = {"name": name, "section": section, "label": label or name, "unit": unit,
               "median": float(count / np.median(s)), "p99": float(count / np.percentile(s, 99)),
               "n": int(s.size), "min": float(count / s.max()), "params": {"items_per_run": count, **params}}
        self._put(rec)
        return rec

    def _put(self, rec: dict) -> None:
        if any(m["name"] == rec["name"] for m in self.measurements):
            raise ValueError(f"duplicate measurement {rec['name']}")
        self.measurements.append(rec)

    def get(self, name: str) -> dict:
        for m in self.measurements:
            if m["name"] == name:
                return m
        raise KeyError(name)

    def has(self, name: str) -> bool:
        return any(m["name"] == name for m in self.measurements)

    def ratio(self, name: str, numerator: str, denominator: str, *, stat: str = "median", meaning: str) -> dict:
        """``numerator[stat] / denominator[stat]`` of two measurements of the same unit."""
        a, b = self.get(numerator), self.get(denominator)
        if a["unit"] != b["unit"]:
            raise ValueError(f"ratio of {a['unit']} to {b['unit']}")
        rec = {"name": name, "numerator": numerator, "denominator": denominator, "stat": stat,
               "value": float(a[stat] / b[stat]), "meaning": meaning}
        self.ratios.append(rec)
        return rec

    def get_ratio(self, name: str) -> dict:
        for r in self.ratios:
            if r["name"] == name:
                return r
        raise KeyError(name)

    def to_json(self) -> dict:
        return {"schema": SCHEMA, "quick": self.quick, "machine": self.machine, "settings": self.settings,
                "measurements": self.measurements, "ratios": self.ratios, "peers": self.peers,
                "checks": self.checks, "scaling": self.scaling, "targets": self.targets,
                "profiles": self.profiles, "sections": self.sections}


def ab_machine() -> str:
    """The machine line of an interleaved A/B script's report (``scripts/ab_*.py``): the CPU, its
    cores, the time, and the load average as the comparison ends."""
    return (f"{_cpu_model()}, {os.cpu_count()} cores; {datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds')}; "
            f"load average at the end {os.getloadavg()[0]:.2f}")


def emit_report(lines: list[str], out) -> None:
    """Print a Markdown report's ``lines``, and write them to ``out`` where given."""
    text = "\n".join(lines) + "\n"
    print(text)
    if out:
        out.write_text(text)


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """What the figures were taken on: CPU, cores, library versions, JAX backend, date, load."""
    import jax
    import jaxlib
    import scipy
    import sklearn

    try:
        from threadpoolctl import threadpool_info

        pools = [{k: p.get(k) for k in ("user_api", "internal_api", "num_threads", "version")} for p in threadpool_info()]
    except ImportError:
        pools = []
    backend = jax.default_backend()
    return {
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "scikit_learn": sklearn.__version__,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "backend": backend,
        "devices": [str(d) for d in jax.devices()],
        "gpu": ("measured on this backend" if backend == "gpu" else
                "not measured: no GPU machine was lent to the session that took these figures"),
        "thread_pools": pools,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) and x > 0


@dataclasses.dataclass
class Context:
    """What every section's ``run(ctx)`` gets: the run's settings, the results to add to, a logger,
    and which optional peers are importable."""

    quick: bool
    results: Results
    out_dir: "os.PathLike"
    log: Callable[[str], None] = print
    time_calls: Callable = staticmethod(time_calls)

    def peer(self, name: str) -> bool:
        """Whether the optional peer library ``name`` is importable; recorded in ``results.peers``."""
        import importlib.metadata
        import importlib.util

        dist = {"sklearn": "scikit-learn"}.get(name, name)
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a broken or deliberately blocked install counts as missing
            found = False
        if not found:
            self.results.peers[dist] = "skipped: not installed"
            return False
        try:
            self.results.peers[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            self.results.peers[dist] = "installed (version unknown)"
        return True


def jsonable(obj):
    """``obj`` with NumPy scalars and arrays made plain, and non-finite floats made ``None`` (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating | float):
        return float(obj) if np.isfinite(obj) else None
    return obj


def closed_step(model):
    """The pipeline's step jitted once with the model closed over (a constant of the program), on
    the pipeline's own pytrees: ``f(state, scan) -> (state, output)``. What the stage breakdown and
    the output comparisons read; the live loop calls the same step through :class:`LiveCall`."""
    import jax

    from gtsjax.core.pipeline import step

    return jax.jit(lambda state, scan: step(model, state, scan))


class LiveCall:
    """The pipeline's step as the live loop calls it (:class:`gtsjax.drivers.live.LiveStep`: the
    model closed over, the frame passed as the link delivers it, the state and output packed into a
    few buffers). ``call(i)`` steps the ``i``-th of ``scans`` (cycled; a stacked
    :class:`~gtsjax.core.scan.Scan`, turned into frames before any timing) from the state the last
    call left, and returns the GTD rows' array, what the live loop waits for."""

    def __init__(self, model, scans):
        from gtsjax.drivers.live import LiveStep
        from gtsjax.sensors import get_model

        self.step = LiveStep(model, get_model(model.sensor_model))
        self.state = self.step.initial_state()
        ranges, intensities, dts = (np.asarray(a) for a in (scans.ranges, scans.intensities, scans.dt))
        self.frames = [(ranges[i], intensities[i], float(dts[i])) for i in range(ranges.shape[0])]

    def __call__(self, i: int):
        self.state, _, packed = self.step(self.state, *self.frames[i % len(self.frames)])
        return packed
