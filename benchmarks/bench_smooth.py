"""The fixed-interval smoother of the tracks (``gtsjax.core.smooth``, issue 42): one track's backward
pass over T = 10⁵ scans (``--quick``: 2 000), float32 as the step runs, on whatever backend JAX uses
(the CPU here):

* **sequential**: ``rts_sequential``, the classic RTS recursion under a reversed ``lax.scan`` (one
  6 × 6 solve per step, one step after another);
* **associative**: ``rts_associative``, every step's element at once and ``lax.associative_scan``
  (O(log T) deep, O(T) more matrix products in all).

Each is jitted and compiled once (the warm-up call), then timed end to end (``block_until_ready``). The
filtered states come from gtsjax's own filter (``motion_model`` + ``kalman_update`` under ``lax.scan``)
on a robot circling at 0.3 m/s and turning through ±π every ~30 s, with 10 Hz jittered scan intervals.
The two smoothers' results are compared (``checks.smooth_agreement``).
"""

import jax
import jax.numpy as jnp
import numpy as np

from gtsjax.core.g_kalman import kalman_update, motion_model
from gtsjax.core.g_types import TrackerParams
from gtsjax.core.geometry import wrap
from gtsjax.core.smooth import rts_associative, rts_sequential

SECTION = "smooth"


def _filtered(T: int, params: TrackerParams):
    """``(mean, cov, dt, valid)``: T filtered states (float32) of one track, valid throughout."""
    rng = np.random.default_rng(0)
    dt = rng.uniform(0.09, 0.11, T)
    t = np.cumsum(dt)
    phi = 0.2 * t  # 0.3 m/s on a circle of 1.5 m
    truth = np.column_stack([1.5 * np.cos(phi), 1.5 * np.sin(phi), phi + np.pi / 2])
    R = np.diag([0.02**2, 0.02**2, np.radians(3.0) ** 2])
    z = truth + rng.multivariate_normal(np.zeros(3), R, T)
    z[:, 2] = wrap(z[:, 2])
    f32 = jnp.float32
    z, R32, dt32 = jnp.asarray(z, f32), jnp.asarray(R, f32), jnp.asarray(dt, f32)
    m0 = jnp.concatenate([z[0], jnp.zeros(3, f32)])
    P0 = jnp.diag(jnp.asarray([R[0, 0], R[1, 1], R[2, 2], 0.25, 0.25, 1.0], f32))

    @jax.jit
    def run(m0, P0, z, dt):
        def body(carry, x):
            m, P = carry
            zi, dti = x
            F, Q = motion_model(dti, params)
            m = F @ m
            m = m.at[2].set(wrap(m[2]))
            m, P = kalman_update(m, F @ P @ F.T + Q, zi, R32)
            return (m, P), (m, P)

        _, (ms, Ps) = jax.lax.scan(body, (m0, P0), (z[1:], dt[1:]))
        return jnp.concatenate([m0[None], ms]), jnp.concatenate([P0[None], Ps])

    mean, cov = run(m0, P0, z, dt32)
    return mean, cov, dt32, jnp.ones(T, bool)


def run(ctx) -> None:
    res = ctx.results
    T = 2_000 if ctx.quick else 100_000
    reps = 3 if ctx.quick else 10
    params = TrackerParams.default(jnp.array([False, True]))
    args = (*_filtered(T, params), params)
    seq, par = jax.jit(rts_sequential), jax.jit(rts_associative)
    ms, Ps = jax.block_until_ready(seq(*args))
    ma, Pa = jax.block_until_ready(par(*args))

    res.add("smooth.one_track.sequential", "ms", ctx.time_calls(lambda i: seq(*args), reps, warmup=1),
            section=SECTION, label=f"RTS smoother, one track, T = {T}: sequential (lax.scan)", steps=T,
            dtype="float32")
    res.add("smooth.one_track.associative", "ms", ctx.time_calls(lambda i: par(*args), reps, warmup=1),
            section=SECTION, label=f"RTS smoother, one track, T = {T}: associative (lax.associative_scan)",
            steps=T, dtype="float32")
    res.ratio("smooth.one_track.sequential_over_associative", "smooth.one_track.sequential",
              "smooth.one_track.associative", meaning="one track's smoothing: sequential time / associative time")

    d = np.asarray(ma, np.float64) - np.asarray(ms, np.float64)
    d[:, 2] = wrap(d[:, 2])
    scale = np.max(np.abs(np.asarray(Ps, np.float64)), axis=(-2, -1), keepdims=True)
    res.checks["smooth_agreement"] = {
        "steps": T,
        "max_abs_mean": float(np.max(np.abs(d))),
        "max_cov_relative_to_largest_entry": float(np.max(np.abs(np.asarray(Pa - Ps, np.float64)) / scale)),
        "finite": bool(np.all(np.isfinite(np.asarray(ma))) and np.all(np.isfinite(np.asarray(Pa)))),
    }
