"""Scaling: step latency against the beam count, the candidate slots K, the track slots M and the GP
training-set size N; GP fit time against N; batch throughput against the chunk size; one figure.

* **Beams** 682 (URG-04LX), 1081 (UTM-30LX) and 2161 (a synthetic 0.125° scanner over 270°): the
  demo model's step on synthetic rooms with a few round objects (``_scene``), so that only the beam
  count changes.
* **K** and **M**: the demo model with ``max_candidates`` / ``max_tracks`` changed (both fix shapes:
  each value compiles its own step), on the URG-04LX scans of ``spl-crossing``.
* **N**: a GP fitted (``gtsjax.gp.fit``, one start) on N robot examples (the demo model's input
  columns), put in place of every GP of the demo model, once in the capped form ``gtsjax train``
  gives the classifier (mean on at most 512 inducing points, variance on the first 64) and once as
  the exact GP; the step's latency with each. Past the cap the capped step's cost stays flat; the
  exact one grows with N. The fit itself grows (O(N³) per evaluation).
* **Chunk size**: ``process_log`` (bit-exact path) throughput over ``spl-trajectory``.
"""

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from gtsjax.core.pipeline import init_state
from gtsjax.core.scan import Scan
from gtsjax.drivers.batch import process_log
from gtsjax.gp import GP, SparseGP
from gtsjax.io import to_scans
from gtsjax.sensors import URG_04LX, UTM_30LX, RangeNoise, SensorModel
from gtsjax.train import TrainConfig

from . import _data
from ._harness import closed_step

SECTION = "scaling"
INDUCING = TrainConfig().n_inducing_class  # the classifier's cap
INDUCING_VAR = TrainConfig().n_inducing_var

SYNTH_2161 = SensorModel(name="synthetic-2161", amin=0, amax=2160, ares=2880, afrt=1080, dmin_mm=20, dmax_mm=30000,
                         scan_rpm=2400, has_intensity=True, noise=RangeNoise(sigma=0.01))


def _scene(sensor, rng):
    """Ranges, intensities and valid mask of a 6 m × 7 m room with a few robots and posts (NumPy ray casting)."""
    ang = sensor.angles
    u = np.stack([np.cos(ang), np.sin(ang)], -1)
    best = np.full(ang.shape, np.inf)
    refl = np.full(ang.shape, 1500.0)
    for _ in range(int(rng.integers(2, 8))):
        rr, th, rad = rng.uniform(0.8, 3.6), rng.uniform(-1.8, 1.8), rng.choice([0.05, 0.15, 0.25])
        c = np.array([rr * math.cos(th), rr * math.sin(th)])
        b = u @ c
        disc = b * b - (c @ c - rad * rad)
        t = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        hit = (t > 0) & (t < best)
        best = np.where(hit, t, best)
        refl = np.where(hit, rng.uniform(2000, 6000), refl)
    with np.errstate(divide="ignore"):
        tx = np.where(u[:, 0] > 0, 5.0 / u[:, 0], np.where(u[:, 0] < 0, -1.0 / u[:, 0], np.inf))
        ty = np.where(u[:, 1] > 0, 4.0 / u[:, 1], np.where(u[:, 1] < 0, -3.0 / u[:, 1], np.inf))
    best = np.minimum(best, np.minimum(tx, ty))
    r = best + 0.01 * rng.standard_normal(best.shape)
    valid = np.isfinite(r) & (r >= sensor.range_min) & (r <= sensor.range_max) & (rng.random(r.shape) > 0.01)
    inten = refl / np.maximum(r, 0.1) if sensor.has_intensity else np.zeros_like(r)
    return np.where(valid, r, 0.0).astype(np.float32), np.where(valid, inten, 0.0).astype(np.float32), valid


def synthetic_scans(sensor, n: int, seed: int = 0) -> list[Scan]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        r, i, v = _scene(sensor, rng)
        out.append(Scan(jnp.asarray(r), jnp.asarray(i), jnp.asarray(v), jnp.asarray(sensor.angle_min, jnp.float32),
                        jnp.asarray(sensor.angle_increment, jnp.float32), jnp.asarray(sensor.period, jnp.float32)))
    return jax.block_until_ready(out)


class Stepper:
    """One configuration's compiled ``closed_step``, its state and its scans; each call steps one scan.
    Configurations of one model object share its step (``steps``: one trace and compilation)."""

    def __init__(self, model, scans: list[Scan], steps: dict | None = None):
        steps = {} if steps is None else steps
        if id(model) not in steps:
            steps[id(model)] = (model, closed_step(model))
        self.step = steps[id(model)][1]
        self.state = init_state(model)
        self.scans = scans
        self.i = 0

    def __call__(self, _):
        self.state, out = self.step(self.state, self.scans[self.i % len(self.scans)])
        self.i += 1
        return out


def round_robin(ctx, steppers: dict, reps: dict, blocks: int = 5) -> dict:
    """Seconds per call of every configuration, timed in turn: ``blocks`` rounds, each giving every
    configuration a block of its calls, so that a burst of load from other processes falls on all
    configurations alike instead of on whichever happened to run then."""
    for s in steppers.values():
        ctx.time_calls(s, 0, warmup=10)  # compile and warm up every configuration first
    out = {k: [] for k in steppers}
    for _ in range(blocks):
        for k, s in steppers.items():
            out[k].append(ctx.time_calls(s, max(1, reps[k] // blocks), warmup=2))
    return {k: np.concatenate(v) for k, v in out.items()}


def with_gp(model, gp):
    """``model`` with every GP (classifier and pose) replaced by ``gp``: the step's shapes as a model
    trained with that GP size would have them."""
    return jax.tree.map(lambda g: gp if isinstance(g, (GP, SparseGP)) else g, model,
                        is_leaf=lambda g: isinstance(g, (GP, SparseGP)))


def run(ctx) -> None:
    res = ctx.results
    q = ctx.quick
    reps = 150 if q else 1000
    log, site = _data.scenario("spl-crossing", 3, 60)
    model = _data.demo_model(site)
    series = {}
    steppers, reps_of, meta, steps = {}, {}, {}, {}

    # beams (with the defaults K = 32, M = 8). The smoke run takes one point per axis, the default
    # configuration, which the pipeline section has compiled already (each other value compiles a step
    # of its own, seconds apiece).
    beam_sensors = (URG_04LX,) if q else (URG_04LX, UTM_30LX, SYNTH_2161)
    for sensor in beam_sensors:
        name = f"scaling.beams.{sensor.n_beams}"
        steppers[name] = Stepper(model, synthetic_scans(sensor, 32), steps)
        reps_of[name] = reps
        meta[name] = (f"step vs beams: {sensor.n_beams} ({sensor.name})", {"beams": sensor.n_beams})

    # K and M, on the scans of spl-crossing
    crossing = [jax.tree.map(lambda a, i=i: a[i], to_scans(log, model.n_beams)) for i in range(log.n_scans)]
    axes = {"K": (32,) if q else (8, 16, 32, 64), "M": (8,) if q else (2, 8, 32, 128)}
    for axis, values in axes.items():
        for v in values:
            if (axis, v) in (("K", model.frontend.max_candidates), ("M", model.max_tracks)):
                m2 = model  # the model's own value: its step, compiled once for every axis
            elif axis == "K":
                m2 = eqx.tree_at(lambda mm: mm.frontend, model, dataclasses.replace(model.frontend, max_candidates=v))
            else:
                m2 = dataclasses.replace(model, max_tracks=v)
            name = f"scaling.{axis}.{v}"
            steppers[name] = Stepper(m2, crossing, steps)
            reps_of[name] = reps
            meta[name] = (f"step vs {axis}: {v}", {axis: v})

    # training-set size N: fit (timed), then the step with the fitted GP in both forms
    from gtsjax import gp as gplib

    sizes = (160,) if q else (100, 250, 500, 1000, 2000)
    ns = {"x": list(sizes), "dtc_median_us": [], "exact_median_us": [], "fit_s": [], "inducing": []}
    for n in sizes:
        x, y = _data.gp_problem(n)
        x = x[:, list(model.gp_columns)] if model.gp_columns else x
        jax.block_until_ready(gplib.fit(x, y, key=jax.random.key(0), restarts=1))  # compiles for this shape
        t0 = time.perf_counter()
        g = jax.block_until_ready(gplib.fit(x, y, key=jax.random.key(0), restarts=1))  # the same work again
        t = [time.perf_counter() - t0]
        res.add(f"scaling.N.{n}.fit", "s", t, section=SECTION, label=f"GP fit vs N: {n} (one start)", N=n)
        ns["fit_s"].append(float(np.median(t)))
        sparse = g.sparse(INDUCING, INDUCING_VAR).astype(jnp.float32)
        ns["inducing"].append(int(sparse.z.shape[0]))
        for kind, gp_ in (("dtc", sparse), ("exact", g.astype(jnp.float32))):
            name = f"scaling.N.{n}.step_{kind}"
            steppers[name] = Stepper(with_gp(model, gp_), crossing)
            reps_of[name] = reps // 2
            meta[name] = (f"step vs N: {n}, {f'DTC ≤{INDUCING} inducing' if kind == 'dtc' else 'exact GP'}",
                          {"N": n, "predictor": kind, "inducing": int(sparse.z.shape[0])})

    samples = round_robin(ctx, steppers, reps_of)
    for name, t in samples.items():
        label, params = meta[name]
        res.add(name, "us", t, section=SECTION, label=label, **params)
    for axis, values in (("beams", [s.n_beams for s in beam_sensors]), *axes.items()):
        recs = [res.get(f"scaling.{axis}.{v}") for v in values]
        series[axis] = {"x": list(values), "median_us": [r["median"] for r in recs], "p99_us": [r["p99"] for r in recs]}
    for n in sizes:
        for kind in ("dtc", "exact"):
            ns[f"{kind}_median_us"].append(res.get(f"scaling.N.{n}.step_{kind}")["median"])
    series["N"] = ns

    # chunk size
    tlog, _ = _data.scenario("spl-trajectory", 4, 256 if q else 2048)
    tscans = to_scans(tlog, model.n_beams)
    chunks = (256,) if q else (16, 64, 256, 1024)
    rates = []
    for c in chunks:
        t = ctx.time_calls(lambda i, c=c: process_log(model, tscans, chunk=c), 1 if q else 3, warmup=1)
        rates.append(res.add_rate(f"scaling.chunk.{c}", tlog.n_scans, t, section=SECTION,
                                  label=f"batch replay vs chunk: {c}", chunk=c)["median"])
    series["chunk"] = {"x": list(chunks), "scans_per_s": rates}
    res.scaling = series
    ctx.results.sections[SECTION] = {"plot": "scaling.png", "inducing_cap": INDUCING}
    plot(series, ctx.out_dir / "scaling.png", ctx.results.machine)


def plot(series: dict, path, machine: dict) -> None:
    """Six panels: latency vs beams, K, M, N (DTC vs exact); fit time vs N; throughput vs chunk."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 3, figsize=(13, 7.5))
    for a, key, xl in ((ax[0, 0], "beams", "beams per scan"), (ax[0, 1], "K", "candidate slots K"),
                       (ax[0, 2], "M", "track slots M")):
        s = series[key]
        a.plot(s["x"], np.asarray(s["median_us"]) / 1e3, "o-", label="median")
        a.plot(s["x"], np.asarray(s["p99_us"]) / 1e3, "s--", label="p99")
        a.set_xlabel(xl)
        a.set_ylabel("step latency [ms]")
        a.set_ylim(bottom=0)
        if key != "beams":
            a.set_xscale("log", base=2)
        a.set_xticks(s["x"], [str(v) for v in s["x"]])
        a.legend()
        a.grid(alpha=0.3)
    s = series["N"]
    a = ax[1, 0]
    a.plot(s["x"], np.asarray(s["dtc_median_us"]) / 1e3, "o-", label=f"DTC, ≤{INDUCING} inducing, variance on ≤{INDUCING_VAR} (classifier form)")
    for xv, yv, m in zip(s["x"], np.asarray(s["dtc_median_us"]) / 1e3, s["inducing"], strict=True):
        a.annotate(f"M={m}", (xv, yv), textcoords="offset points", xytext=(0, -12), fontsize=7, ha="center")
    a.plot(s["x"], np.asarray(s["exact_median_us"]) / 1e3, "s--", label="exact GP")
    a.axvline(INDUCING, color="grey", lw=0.8, ls=":")
    a.set_xlabel("GP training-set size N")
    a.set_ylabel("step latency, median [ms]")
    a.set_ylim(bottom=0)
    a.legend()
    a.grid(alpha=0.3)
    a = ax[1, 1]
    a.plot(s["x"], s["fit_s"], "o-", label="gtsjax.gp.fit, one start")
    a.set_xlabel("GP training-set size N")
    a.set_ylabel("fit time [s]")
    a.set_ylim(bottom=0)
    a.legend()
    a.grid(alpha=0.3)
    s = series["chunk"]
    a = ax[1, 2]
    a.plot(s["x"], s["scans_per_s"], "o-")
    a.set_xscale("log", base=2)
    a.set_xticks(s["x"], [str(v) for v in s["x"]])
    a.set_xlabel("chunk size (scans)")
    a.set_ylabel("batch replay [scans/s]")
    a.set_ylim(bottom=0)
    a.grid(alpha=0.3)
    fig.suptitle(f"gtsjax scaling — {machine.get('cpu_model', '?')}, {machine.get('cores', '?')} cores, "
                 f"JAX {machine.get('jax', '?')} ({machine.get('backend', '?')})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
