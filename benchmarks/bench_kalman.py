"""The Kalman filter of stage g against filterpy and dynamax, on the same constant-velocity model.

The model is gtsjax's (``g_track.motion_model`` with the demo model's tuning, dt = 0.1 s), observing
``(x, y, θ)`` of a robot walking the simulated SPL trajectory with noise ``R``:

* **one step** (predict + update of one track, one call): filterpy ``KalmanFilter.predict`` and
  ``update``; gtsjax ``g_track.predict`` + ``kalman_update`` jitted; dynamax ``lgssm_filter`` on a
  one-step sequence, jitted.
* **a sequence** of T steps, time per step: filterpy in a Python loop; gtsjax's predict + update
  under ``lax.scan``; dynamax ``lgssm_filter`` (which also accumulates the marginal likelihood).
  The filtered means are compared (gtsjax runs in float32 as its step does; the others in float64).
* **a scan's tracking** with M = 8 tracks and 8 detections: gtsjax ``track_step`` (gating,
  assignment, updates, life cycle, all M slots) against the reference's filterpy tracker
  (``tests/reference/track.py``) doing the same.
"""

import jax
import jax.numpy as jnp
import numpy as np

from gtsjax.core.g_track import Detections, TrackerState, kalman_update, motion_model, predict, track_step
from gtsjax.core.geometry import wrap

from . import _data

SECTION = "kalman"
DT = 0.1


def _observations(T: int):
    """``T`` noisy poses of the simulated robot, and ``R``."""
    from gtsjax.sim.scenarios import plan_scenario

    truth = plan_scenario("spl-trajectory", seed=7, n_scans=T).robots[:, 0]
    rng = np.random.default_rng(0)
    R = np.diag([0.02**2, 0.02**2, np.radians(3.0) ** 2])
    z = truth + rng.multivariate_normal(np.zeros(3), R, T)
    z[:, 2] = np.unwrap(z[:, 2])  # the linear peers do not wrap angles: keep the sequence continuous
    return z, R


def run(ctx) -> None:
    res = ctx.results
    T = 200 if ctx.quick else 1000
    reps = 300 if ctx.quick else 3000
    log, site = _data.scenario("spl-crossing", 3, 60)
    params = _data.demo_model(site).tracker
    F32, Q32 = motion_model(jnp.asarray(DT, jnp.float32), params)
    F, Q = np.asarray(F32, np.float64), np.asarray(Q32, np.float64)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    z, R = _observations(T)
    x0 = np.concatenate([z[0], np.zeros(3)])
    P0 = np.diag([R[0, 0], R[1, 1], R[2, 2], 0.25, 0.25, 1.0])

    # ---- one step
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.x, kf.P, kf.H = x0[:, None].copy(), P0.copy(), H

    def fp_one(i):
        kf.predict(F=F, Q=Q)
        kf.update(z[i % T], R=R)

    res.add("kalman.one_step.filterpy", "us", ctx.time_calls(fp_one, reps, warmup=20), section=SECTION,
            label="KF predict+update, one track, one call: filterpy")

    empty = TrackerState.empty(1)

    @jax.jit
    def g_one(mean, cov, zi, Ri):
        s = predict(_set(empty, mean, cov), jnp.asarray(DT, jnp.float32), params)
        return kalman_update(s.mean[0], s.cov[0], zi, Ri)

    st1 = _with(empty, x0, P0)
    z32, R32 = jnp.asarray(z, jnp.float32), jnp.asarray(R, jnp.float32)
    zs = [z32[i] for i in range(T)]
    one = {"m": st1.mean[0], "c": st1.cov[0]}

    def g_call(i):
        one["m"], one["c"] = g_one(one["m"], one["c"], zs[i % T], R32)
        return one["m"]

    res.add("kalman.one_step.gtsjax", "us", ctx.time_calls(g_call, reps, warmup=20),
            section=SECTION, label="KF predict+update, one track, one call: gtsjax (jitted)")
    res.ratio("kalman.one_step.filterpy_over_gtsjax", "kalman.one_step.filterpy", "kalman.one_step.gtsjax",
              meaning="one KF step, one call: filterpy time / gtsjax time")

    # ---- a sequence
    def fp_seq():
        k = KalmanFilter(dim_x=6, dim_z=3)
        k.x, k.P, k.H = x0[:, None].copy(), P0.copy(), H
        out = np.empty((T, 6))
        for t in range(T):
            k.predict(F=F, Q=Q)
            k.update(z[t], R=R)
            out[t] = k.x[:, 0]
        return out

    @jax.jit
    def g_seq(state, zz, Ri):
        def body(s, zi):
            s = predict(s, jnp.asarray(DT, jnp.float32), params)
            m, c = kalman_update(s.mean[0], s.cov[0], zi, Ri)
            return _set(s, m, c), m

        return jax.lax.scan(body, state, zz)[1]

    seq_reps = 3 if ctx.quick else 10
    ref_means = fp_seq()
    t_fp = ctx.time_calls(lambda i: fp_seq(), seq_reps, warmup=0) / T
    res.add("kalman.sequence.filterpy", "us", t_fp, section=SECTION, label=f"KF per step over {T} steps: filterpy loop",
            steps=T)
    g_means = np.asarray(g_seq(st1, z32, R32), np.float64)
    t_g = ctx.time_calls(lambda i: g_seq(st1, z32, R32), seq_reps, warmup=1) / T
    res.add("kalman.sequence.gtsjax", "us", t_g, section=SECTION, label=f"KF per step over {T} steps: gtsjax lax.scan",
            steps=T)
    res.ratio("kalman.sequence.filterpy_over_gtsjax", "kalman.sequence.filterpy", "kalman.sequence.gtsjax",
              meaning="KF over a sequence, per step: filterpy / gtsjax")
    diffs = {"gtsjax_vs_filterpy_max_abs_mean": _max_diff(g_means, ref_means)}

    if ctx.peer("dynamax"):
        from dynamax.linear_gaussian_ssm import lgssm_filter
        from dynamax.linear_gaussian_ssm.inference import make_lgssm_params

        m0 = F @ x0  # dynamax conditions first, then predicts: its prior for t = 0 is gtsjax's prediction
        p = make_lgssm_params(jnp.asarray(m0), jnp.asarray(F @ P0 @ F.T + Q), jnp.asarray(F), jnp.asarray(Q),
                              jnp.asarray(H), jnp.asarray(R))
        dyn = jax.jit(lgssm_filter)
        zz = jnp.asarray(z)
        d_means = np.asarray(dyn(p, zz).filtered_means)
        t_d = ctx.time_calls(lambda i: dyn(p, zz), seq_reps, warmup=1) / T
        res.add("kalman.sequence.dynamax", "us", t_d, section=SECTION,
                label=f"KF per step over {T} steps: dynamax lgssm_filter", steps=T)
        res.ratio("kalman.sequence.dynamax_over_gtsjax", "kalman.sequence.dynamax", "kalman.sequence.gtsjax",
                  meaning="KF over a sequence, per step: dynamax / gtsjax")
        diffs["dynamax_vs_filterpy_max_abs_mean"] = _max_diff(d_means, ref_means)
        z1 = zz[:1]
        res.add("kalman.one_step.dynamax", "us", ctx.time_calls(lambda i: dyn(p, z1), reps, warmup=20),
                section=SECTION, label="KF condition+predict, one track, one call: dynamax lgssm_filter (T=1, jitted)")
        res.ratio("kalman.one_step.dynamax_over_gtsjax", "kalman.one_step.dynamax", "kalman.one_step.gtsjax",
                  meaning="one KF step, one call: dynamax / gtsjax")
    res.checks["kalman_agreement"] = diffs

    # ---- one scan's tracking, M = 8 tracks, 8 detections
    tracking_m8(ctx, params, reps // 3)


def _max_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Largest difference of two filtered-mean sequences, headings compared modulo 2π (gtsjax wraps
    its heading, the linear filters carry it unwrapped)."""
    d = a - b
    d[:, 2] = wrap(d[:, 2])
    return float(np.max(np.abs(d)))


def _with(state: TrackerState, x0, P0) -> TrackerState:
    """``state`` with slot 0 live at mean ``x0`` and covariance ``P0``."""
    import equinox as eqx

    return eqx.tree_at(lambda s: (s.mean, s.cov, s.live, s.confirmed), state,
                       (jnp.asarray(x0[None], jnp.float32), jnp.asarray(P0[None], jnp.float32),
                        jnp.ones(1, bool), jnp.ones(1, bool)))


def _set(state: TrackerState, m, c) -> TrackerState:
    import equinox as eqx

    return eqx.tree_at(lambda s: (s.mean, s.cov), state, (m[None], c[None]))


def tracking_m8(ctx, params, reps: int) -> None:
    """Stage g for one scan with 8 robots: gtsjax ``track_step`` against the filterpy reference tracker."""
    from .reference import Tracker

    res = ctx.results
    m = 8
    rng = np.random.default_rng(1)
    base = np.column_stack([np.linspace(0.5, 5.5, m), np.tile([1.0, 3.0], m // 2), np.zeros(m)])
    n_steps = 64
    t = np.arange(n_steps)[:, None, None] * DT
    poses = base[None] + t * np.array([0.2, 0.1, 0.3])[None, None] + rng.normal(0, 0.01, (n_steps, m, 3))
    poses[..., 2] = wrap(poses[..., 2])
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 3e-3]), (m, 3, 3)).copy()
    cls = np.full(m, 2)  # the demo model's robot class

    ref = Tracker(params, m)
    for k in range(8):  # confirm the tracks first
        ref.step(poses[k], cov, cls, DT)

    def ref_call(i):
        ref.step(poses[8 + i % (n_steps - 8)], cov, cls, DT)

    res.add("kalman.track_step_m8.reference", "us", ctx.time_calls(ref_call, reps, warmup=5), section=SECTION,
            label="tracking, 8 tracks + 8 detections: filterpy reference tracker")

    tstep = jax.jit(lambda s, d: track_step(s, d, jnp.asarray(DT, jnp.float32), params)[0])
    dets = [Detections(jnp.asarray(p, jnp.float32), jnp.asarray(cov, jnp.float32), jnp.asarray(cls, jnp.int32),
                       jnp.ones(m, bool)) for p in poses]
    state = {"s": TrackerState.empty(m)}
    for k in range(8):
        state["s"] = tstep(state["s"], dets[k])

    def g_call(i):
        state["s"] = tstep(state["s"], dets[8 + i % (n_steps - 8)])
        return state["s"]

    res.add("kalman.track_step_m8.gtsjax", "us", ctx.time_calls(g_call, reps, warmup=5), section=SECTION,
            label="tracking, 8 tracks + 8 detections: gtsjax track_step (jitted)")
    res.ratio("kalman.track_step_m8.reference_over_gtsjax", "kalman.track_step_m8.reference",
              "kalman.track_step_m8.gtsjax", meaning="one scan's tracking with 8 tracks: filterpy reference / gtsjax")
    live = int(np.sum(np.asarray(state["s"].confirmed)))
    ctx.results.checks["kalman_agreement"]["track_step_m8_confirmed_tracks"] = {
        "gtsjax": live, "reference": sum(1 for s in ref.slots if s is not None and s.confirmed)}
