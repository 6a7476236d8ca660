"""``run --smooth-lag S`` (issue 42, ``gtsjax.drivers.fixed_lag``): what the fixed-lag smoothed rows
gain and what they cost per scan.

* **Accuracy**: the README's five held-out scenarios (``spl-eval:2001`` … ``spl-bumped:2005``; ``--quick``:
  the first 20 s of the first) through the forward pass as the live loop computes it (each scan's whole
  step in turn, the filtered states kept), then its rows through :class:`~gtsjax.drivers.fixed_lag.FixedLag`
  at lags of 0.5 s and 1 s (5 and 10 scans at 10 Hz), and through ``replay --smooth``'s whole-life
  smoother for comparison: position and heading RMSE of each against the simulation's truth (each
  row against the nearest true robot of its scan), in ``checks.smooth_lag``.
* **Cost**: the live loop against the emulated URG-04LX (10 Hz) on a pseudo-terminal, as
  ``bench_live`` runs it, forward only and with ``smooth_lag`` 0.5 s and 1 s: the frame-to-GTD latency
  of the live rows (the filtered states now come with them) and the time the smoothing adds per scan
  after that latency is taken (:class:`~gtsjax.drivers.fixed_lag.LagStats`: the window updated, one
  jitted RTS call over it, the smoothed rows written), measured by the loop itself.
"""

import tempfile
from pathlib import Path

import numpy as np

from gtsjax.core.geometry import wrap
from gtsjax.drivers.batch import process_log
from gtsjax.drivers.fixed_lag import FixedLag, lag_scans, pack_filtered
from gtsjax.drivers.live import pack_tracks, rows_from_packed, run_live, warm_up
from gtsjax.drivers.smoothing import smooth_output
from gtsjax.io.gtd import rows_from_output
from gtsjax.io.logs import to_scans
from gtsjax.io.serial import Link
from gtsjax.sensors import URG_04LX
from gtsjax.sim.emulator import SensorEmulator

from . import _data

SECTION = "smooth_lag"
SCENARIOS = (("spl-eval", 2001), ("spl-trajectory", 2002), ("spl-crossing", 2003), ("spl-legs", 2004),
             ("spl-bumped", 2005))
LAGS_S = (0.5, 1.0)


class _Keep:
    def __init__(self):
        self.scans = []

    def write(self, rows):
        self.scans.append(rows)

    def close(self):
        pass


def _rmse(rows, stamps, truth):
    """Position (m) and heading (rad) RMSE of rows against the nearest true robot of their scan."""
    at = {float(s): i for i, s in enumerate(stamps)}
    pos, head = [], []
    for r in rows:
        tr = truth[at[r.stamp]]
        d = np.hypot(tr[:, 0] - r.x, tr[:, 1] - r.y)
        if np.all(np.isnan(d)):
            continue
        k = int(np.nanargmin(d))
        pos.append(d[k])
        head.append(wrap(r.theta - tr[k, 2]))
    pos, head = np.asarray(pos), np.asarray(head)
    return float(np.sqrt(np.mean(pos**2))), float(np.sqrt(np.mean(head**2))), int(pos.size)


def accuracy(ctx, name: str, seed: int, seconds: float | None) -> dict:
    log, site = _data.scenario(name, seed, seconds=seconds)
    model = _data.demo_model(site)
    scans = to_scans(log, model.n_beams)
    _, (out, filt) = process_log(model, scans, filtered=True)
    T, M = out.track_live.shape
    dt = np.asarray(scans.dt, np.float32)
    stamps = np.asarray(log.stamps, np.float64)
    live_rows, tables = [], []
    for t in range(T):
        o = _at(out, t)
        packed = np.asarray(pack_tracks(o))
        block = np.asarray(pack_filtered(_at(filt, t)))
        tables.append(np.concatenate([packed, np.pad(block, ((0, 1), (0, 0)))], axis=1))
        live_rows.append(rows_from_packed(float(stamps[t]), packed, model.classes))
    doc = {"scans": T, "rows": sum(map(len, live_rows))}
    doc["forward"] = _rmse([r for rs in live_rows for r in rs], stamps, log.truth_poses)
    for s in LAGS_S:
        keep = _Keep()
        lag = FixedLag(model.tracker, lag_scans(s, URG_04LX.rate_hz), M, None, writer=keep)
        for t in range(T):
            lag.push(tables[t], live_rows[t], float(dt[t]))
        lag.close()
        doc[f"lag_{s:g}s"] = _rmse([r for rs in keep.scans for r in rs], stamps, log.truth_poses)
    sm = smooth_output(out, filt, stamps, model.tracker)
    whole = [r for t in range(T) for r in rows_from_output(float(stamps[t]), sm.track_id[t], sm.track_class[t],
                                                           sm.track_pose[t], sm.track_var[t], sm.track_mask[t],
                                                           model.classes, sm.track_cov_xy[t])]
    doc["whole_life"] = _rmse(whole, stamps, log.truth_poses)
    ctx.log(f"smooth_lag {name}:{seed}: " + ", ".join(
        f"{k} {v[0] * 100:.2f} cm {np.degrees(v[1]):.2f}°" for k, v in doc.items() if isinstance(v, tuple)))
    return doc


def _at(tree, t):
    import jax

    return jax.tree.map(lambda a: None if a is None else a[t], tree)


def live_case(ctx, key: str, log, model, duration: float, smooth_lag: float | None) -> None:
    """The live loop on the emulated URG-04LX replaying ``log`` for ``duration`` s, with ``smooth_lag``."""
    with tempfile.TemporaryDirectory(prefix="gtsjax-bench-") as tmp:
        compiled = warm_up(model, URG_04LX, filtered=smooth_lag is not None)
        with SensorEmulator(URG_04LX, log) as emu:
            link = Link(emu.path, intensity=False)
            link.start()
            try:
                stats = run_live(link, model, Path(tmp) / "gtd.csv", duration=duration, compiled=compiled,
                                 smooth_lag=smooth_lag)
            finally:
                link.stop()
    lat = np.asarray(stats.latencies_ms) / 1e3
    what = "forward only" if smooth_lag is None else f"--smooth-lag {smooth_lag:g}"
    ctx.results.add(f"smooth_lag.live_latency.{key}", "ms", lat, section=SECTION,
                    label=f"live, frame read → GTD row flushed, URG-04LX at 10 Hz, {what}", frames=stats.frames,
                    rows=stats.rows)
    if smooth_lag is not None:
        lag = stats.smoothing
        ctx.results.add(f"smooth_lag.added_per_scan.{key}", "ms", np.asarray(lag.ms) / 1e3, section=SECTION,
                        label=f"added per scan after the latency, --smooth-lag {smooth_lag:g} ({lag.lag} scans)",
                        lag_scans=lag.lag, rows=lag.rows, scans=lag.scans)


def run(ctx) -> None:
    quick = ctx.quick
    scenarios = SCENARIOS[:1] if quick else SCENARIOS
    # --quick: the scenario's first 20 s (a static grid's first poses, each held 3 s; 200 scans spread
    # over all 64 poses held each for 0.3 s, too short for a track, and read 55° off)
    ctx.results.checks["smooth_lag"] = {f"{n}:{s}": accuracy(ctx, n, s, 20.0 if quick else None) for n, s in scenarios}
    duration = 3.0 if quick else 20.0
    log, site = _data.scenario("spl-trajectory", 7, 300)
    model = _data.demo_model(site)
    live_case(ctx, "forward", log, model, duration, None)
    for s in LAGS_S[:1] if quick else LAGS_S:  # the smoke run: the loop with a lag once, not each lag's cost
        live_case(ctx, f"lag_{s:g}s", log, model, duration, s)
