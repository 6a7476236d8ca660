"""Re-deciding a track's heading side after the forward pass (issue 42, item 2): each scan's choice
among the heading hypotheses the forward pass kept (:mod:`.g_heading`), from the evidence of the
scans after it as well as before.

The forward pass weighs each hypothesis by its evidence over the last ``heading_memory`` seconds: its
log-weight is a fading sum, ``w_t = f_t w_{t−1} + e_t`` up to a constant per scan, with ``f_t =
exp(−dt_t / heading_memory)``. So the evidence a scan brought to hypothesis ``j`` is recovered from the
weights themselves, ``e_t(j) = w_t(j) − f_t w_{t−1}(j)``, taken relative to the scan's best. The
backward pass sums the same fading window over the scans after: ``b_t = f_{t+1} (b_{t+1} +
e_{t+1})``, a reversed ``lax.scan``. The smoothed weight is ``w_t + b_t``, the evidence of the
``heading_memory`` before and after each scan.

A hypothesis is followed from scan to scan in its slot while the slot holds the same track, both scans
use it, and its heading is where the previous one's, turned by the track's turn rate, puts it (within
:data:`_CONTINUES`); otherwise the slot holds a new hypothesis (one of the forward pass's replacements or
merges), and the old one, the weakest, is given the least future evidence of the others.

The choice changes a scan's side only where another side (more than :data:`SIDE_RAD` away) has
:data:`SMOOTH_SIDE_LOG_ODDS` more smoothed log-weight than the forward pass's main hypothesis: a
hypothesis on the main one's side is the same heading read a few degrees apart, for the RTS smoother to
settle, not a side to choose.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .geometry import wrap

#: A heading further than this (rad) from another hypothesis is another side.
SIDE_RAD = 0.5
#: A slot's heading further than this (rad) from where the previous scan's, turned, puts it holds a new
#: hypothesis: a one-dimensional Kalman update moves a hypothesis by a fraction of the read's innovation,
#: well under this within the heading gate.
_CONTINUES = 0.3
#: How much more smoothed log-weight (e⁵ ≈ 150 to 1) another side needs to replace the forward pass's.
#: Chosen on a 60 s two-laser match of seed 3 (log-odds 3 to 10 within 0.3° of each other in heading
#: RMSE); not on the seeds the figures of docs/smoothing.md are measured on.
SMOOTH_SIDE_LOG_ODDS = 5.0


@jax.jit
def smooth_sides(
    side_heading: Float[Array, "T tracks sides"],
    side_logw: Float[Array, "T tracks sides"],
    main: Int[Array, "T tracks"],
    omega: Float[Array, "T tracks"],
    dt: Float[Array, " T"],
    same: Bool[Array, "T tracks"],
    memory: Float[Array, ""],
    log_odds: Float[Array, ""] = SMOOTH_SIDE_LOG_ODDS,
) -> tuple[Int[Array, "T tracks"], Float[Array, "T tracks sides"]]:
    """Each scan's hypothesis (an index into its slot's ``sides``), and the smoothed log-weights.

    ``side_heading``, ``side_logw``, ``main``: the forward pass's hypotheses after each scan (log-weights
    ``-inf`` where unused); ``omega``: the slot's filtered turn rate; ``dt``: seconds since the previous
    scan; ``same``: the slot holds the same track as at the previous scan; ``memory``: the tracker's
    ``heading_memory``."""
    used = jnp.isfinite(side_logw)
    w = jnp.where(used, side_logw, 0.0)
    fade = jnp.exp(-dt / memory)[:, None, None]
    prev_h = jnp.concatenate([side_heading[:1], side_heading[:-1]])
    prev_w = jnp.concatenate([w[:1], w[:-1]])
    prev_used = jnp.concatenate([jnp.zeros_like(used[:1]), used[:-1]])
    prev_omega = jnp.concatenate([omega[:1], omega[:-1]])[..., None]
    turned = wrap(side_heading - prev_h - prev_omega * dt[:, None, None])
    cont = same[..., None] & used & prev_used & (jnp.abs(turned) < _CONTINUES)
    e = jnp.where(cont, w - fade * prev_w, -jnp.inf)
    e = jnp.where(cont, e - jnp.max(e, axis=-1, keepdims=True), 0.0)

    def back(b_next, xs):
        c, e_next, f_next = xs
        b = f_next * (b_next + e_next)
        least = jnp.min(jnp.where(c, b, jnp.inf), axis=-1, keepdims=True)
        b = jnp.where(c, b, jnp.where(jnp.isfinite(least), least, 0.0))
        return b, b

    # b_t from scan t+1's continuation, evidence and fade; the last scan has no future.
    shift = lambda a: jnp.concatenate([a[1:], jnp.zeros_like(a[:1])])  # noqa: E731
    _, b = jax.lax.scan(back, jnp.zeros_like(w[0]), (shift(cont), shift(e), shift(jnp.broadcast_to(fade, w.shape))),
                        reverse=True)
    smoothed = jnp.where(used, w + b, -jnp.inf)
    best = jnp.argmax(smoothed, axis=-1).astype(jnp.int32)
    pick = lambda a, i: jnp.take_along_axis(a, i[..., None], axis=-1)[..., 0]  # noqa: E731
    other_side = jnp.abs(wrap(pick(side_heading, best) - pick(side_heading, main))) > SIDE_RAD
    better = pick(smoothed, best) - pick(smoothed, main) > log_odds
    return jnp.where(other_side & better, best, main), smoothed
