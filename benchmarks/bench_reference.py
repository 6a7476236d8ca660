"""gtsjax's step against the NumPy / scikit-learn / filterpy reference (``tests/reference/``),
on the same simulated log with the same trained model: first that both give the same tracks, then
the time per scan of each, one scan at a time as the live loop runs them.

The check compares, scan by scan, the confirmed track ids (and so their count) and the poses of
equal ids. The reference runs in float64 and gtsjax's step in float32, so poses agree to rounding
(micrometres), not bit for bit.

The profile of the reference (``cProfile`` over a pass of the log) says where a NumPy user's time
goes: scikit-learn's predict calls, the per-segment feature loop, filterpy, and the rest.
"""

import cProfile
import pstats

import jax
import numpy as np

from gtsjax.core.pipeline import init_state
from gtsjax.io import to_scans

from . import _data
from ._harness import LiveCall, closed_step
from .reference import ReferencePipeline, compare_tracks, scans_to_numpy

SECTION = "reference"


def _cum(stats: pstats.Stats, fn) -> float:
    """Cumulative seconds spent in ``fn`` (a plain function or method) during the profile."""
    code = getattr(fn, "__wrapped__", fn).__code__
    return stats.stats.get((code.co_filename, code.co_firstlineno, code.co_name), (0, 0, 0, 0.0, 0))[3]


def _profile(ref: ReferencePipeline, arrays, n: int) -> dict:
    """Where the reference's time goes over ``n`` scans: cumulative time per component, as shares of
    the whole step (``cProfile``; its own overhead inflates the per-call Python parts a little)."""
    from filterpy.kalman import KalmanFilter
    from sklearn.gaussian_process import GaussianProcessRegressor

    from .reference import SklearnGP, Tracker

    prof = cProfile.Profile()
    ref.reset()
    prof.enable()
    for i in range(n):
        ref.step(*(a[i] for a in arrays))
    prof.disable()
    st = pstats.Stats(prof)
    total = max(_cum(st, ReferencePipeline.step), 1e-12)
    gps = _cum(st, SklearnGP.predict) + _cum(st, SklearnGP.predict_mean)
    parts = {
        "GP predictions (d, e): scikit-learn GPR predict, plus the DTC variance term": gps,
        "  of which inside GaussianProcessRegressor.predict": _cum(st, GaussianProcessRegressor.predict),
        "segmentation, ORS, features (a-c; Python loop over segments)": _cum(st, ReferencePipeline.candidates),
        "tracking (g): gating, assignment, life cycle": _cum(st, Tracker.step),
        "  of which filterpy KalmanFilter predict + update": _cum(st, KalmanFilter.predict)
        + _cum(st, KalmanFilter.update),
        "map transformation (f)": _cum(st, ReferencePipeline.update_transform),
    }
    top = sum(v for k, v in parts.items() if not k.startswith("  "))
    parts["rest of the step (frames, S to O, bookkeeping)"] = max(total - top, 0.0)
    return {"scans": n, "profiled_ms_per_scan": 1e3 * total / n,
            "share": {k: round(v / total, 4) for k, v in parts.items()}}


def run(ctx) -> None:
    res = ctx.results
    n = 60 if ctx.quick else 300
    log, site = _data.scenario("spl-trajectory", 7, n)
    model = _data.demo_model(site)
    scans = to_scans(log, model.n_beams)
    arrays = scans_to_numpy(scans)
    one = [jax.tree.map(lambda a, i=i: a[i], scans) for i in range(n)]
    ref = ReferencePipeline(model)

    # Same tracks? gtsjax's live-loop step over the log, then the reference over the same scans.
    step = closed_step(model)
    state = init_state(model)
    outs = []
    for s in one:
        state, o = step(state, s)
        outs.append(o)
    outs = jax.tree.map(lambda *a: np.stack(a), *jax.device_get(outs))
    ref.reset()
    ref_out = []

    def ref_step(i):
        ref_out.append(ref.step(*(a[i] for a in arrays)))

    ref_times = ctx.time_calls(ref_step, n, warmup=0)
    agreement = compare_tracks(outs, ref_out)
    agreement["degraded_scans_gtsjax"] = int(np.sum(outs.degraded))
    agreement["log"] = f"spl-trajectory seed 7, {n} scans, demo model"
    res.checks["reference_tracks"] = agreement

    res.add("reference.urg-04lx.numpy_sklearn_filterpy", "us", ref_times, section=SECTION,
            label="reference pipeline (NumPy + scikit-learn + filterpy), per scan", scans=n)
    g_step = LiveCall(model, scans)  # the step as the live loop calls it
    res.add("reference.urg-04lx.gtsjax_step", "us", ctx.time_calls(g_step, 3 * n, warmup=n), section=SECTION,
            label="gtsjax step (as the live loop calls it: LiveStep), same log, per scan", scans=n)
    res.ratio("reference_over_gtsjax.median", "reference.urg-04lx.numpy_sklearn_filterpy",
              "reference.urg-04lx.gtsjax_step", meaning="how many times faster gtsjax's step is per scan (median)")
    res.ratio("reference_over_gtsjax.p99", "reference.urg-04lx.numpy_sklearn_filterpy",
              "reference.urg-04lx.gtsjax_step", stat="p99",
              meaning="how many times faster gtsjax's step is per scan (p99)")
    res.profiles["reference"] = _profile(ref, arrays, min(n, 30 if ctx.quick else 150))
