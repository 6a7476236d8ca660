"""Stage g's heading mixture: per track, ``SIDES`` heading hypotheses (Rao–Blackwellised: position and
velocity are shared, the heading is not), each with a variance and a log-weight, and a *rest*, the
weight of "the heading is none of them". A single scan sometimes sees an asymmetric robot from a side
that looks like another side; the mixture lets the evidence of the last ``heading_memory`` seconds,
not the first or the last scan, decide which side the state's heading (its *main* hypothesis) is.
:mod:`~gtsjax.core.g_track` describes the mixture in full; this module computes it.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.special
from jaxtyping import Array, Bool, Float, Int

from .g_types import NX, DetectionRows, TrackerParams, TrackerState, _select
from .geometry import wrap

# A detection's heading that none of its sides explains (a side the refinement did not try, a
# misread): its likelihood under any hypothesis is at least that of a uniform heading with this weight.
# It is also the share of the rest's weight that stays uniform after a read (see :mod:`~gtsjax.core.g_track`).
_OUTLIER_P = 0.01
# A new hypothesis within this angle of a hypothesis is that side seen again, the track's heading having
# fallen behind a turn (or run ahead): it starts with ``_NEW_P`` times that hypothesis's weight, as much
# as a second or two of reads can undo. Further from every one it is another side, and starts from the
# rest. (The outline's other sides are 40° and more away.)
_SAME_SIDE = 0.5
_NEW_P = 0.1
# Two hypotheses closer than this (3°) are one (the refinement's fits from two sides that converged to
# one heading; a new hypothesis next to one that took the same reads).
_MERGE = 0.05
# How much more weight another hypothesis needs before the state's heading becomes it: odds of 3 to 1.
_SWITCH_ODDS = 3.0
# The track's velocity read as one observation of its direction of travel per this many seconds: a
# constant-velocity filter's velocity averages about a second of positions, and taken at full weight
# in every scan the same motion would count ten or forty times over (:func:`motion_evidence`).
_MOTION_S = 1.0
# Slower than this (m/s), the direction of travel is not read: a robot standing still, whose filtered
# velocity is noise (its uncertainty already makes the reading weak; this makes it none).
_MOTION_MIN_SPEED = 0.05


def motion_evidence(state: TrackerState, params: TrackerParams, dt: Float[Array, ""]) -> Float[Array, "tracks sides"]:
    """Lever 2 of issue 55, the direction of travel as evidence for each heading hypothesis: the log of
    its likelihood against a uniform heading's, ``log((1 - u)·2π·VM(φ_j - travel - μ; κ') + u)`` with
    the class's learnt offset ``μ``, concentration ``κ`` and other share ``u``
    (``TrackerParams.motion_heading``), ``κ' = κ / (1 + κ σ²)`` where σ² is the variance of the
    track's direction of travel (its velocity's across-track variance over its speed²), weighted by
    ``dt / _MOTION_S``. Zero for a track slower than ``_MOTION_MIN_SPEED``, of a class that learnt no
    motion (κ = 0), or where nothing was learnt. A view that looks the same from two sides then leans
    to the side the robot walks towards; a holonomic robot's learnt ``u`` near 1 leaves its views to decide."""
    if params.motion_heading is None:
        return jnp.zeros_like(state.side_heading)
    mh = params.motion_heading[jnp.clip(state.class_id, 0, params.motion_heading.shape[0] - 1)]  # [M, 3]
    mu, kappa, other = mh[:, 0], jnp.maximum(mh[:, 1], 0.0), jnp.clip(mh[:, 2], 1e-3, 1.0)
    v = state.mean[:, 3:5]
    speed2 = jnp.maximum(jnp.sum(v**2, axis=-1), 1e-12)
    across = jnp.stack([-v[:, 1], v[:, 0]], axis=-1)  # the speed times the unit vector across the travel
    var_dir = jnp.einsum("mi,mij,mj->m", across, state.cov[:, 3:5, 3:5], across) / speed2**2
    k = kappa / (1.0 + kappa * var_dir)
    delta = wrap(state.side_heading - jnp.arctan2(v[:, 1], v[:, 0])[:, None] - mu[:, None])
    # 2π·VM(δ; k) = exp(k (cos δ - 1)) / i0e(k): finite for any k.
    ll = jnp.logaddexp(jnp.log1p(-other)[:, None] + k[:, None] * (jnp.cos(delta) - 1.0)
                       - jnp.log(jax.scipy.special.i0e(k))[:, None], jnp.log(other)[:, None])
    moving = params.constant_velocity & (speed2 >= _MOTION_MIN_SPEED**2) & (kappa > 0)
    weight = jnp.minimum(dt / _MOTION_S, 1.0)
    return jnp.where(moving[:, None] & jnp.isfinite(state.side_logw), weight * ll, 0.0)


def side_evidence(
    heading: Float[Array, "tracks sides"],
    var: Float[Array, "tracks sides"],
    z: Float[Array, "tracks zsides"],
    z_logp: Float[Array, "tracks zsides"],
    r: Float[Array, " tracks"],
):
    """The evidence of one detection per track for each of its heading hypotheses, ``log p(z | j) =
    log Σ_h p(h) N(z_h; φ_j, σ_j² + r)`` over the detection's sides ``h`` (with a floor, ``_OUTLIER_P``
    of a uniform heading); for each hypothesis the detection side nearest it, the innovation and its
    variance, and the statistic its heading gate tests (:func:`gate_statistic`)."""
    nu = wrap(z[:, None, :] - heading[:, :, None])  # [M, j, h]
    S = var[:, :, None] + r[:, None, None]
    d2 = nu**2 / S
    usable = jnp.isfinite(z_logp)[:, None, :]
    ll = jnp.where(usable, z_logp[:, None, :] - 0.5 * d2 - 0.5 * jnp.log(2 * jnp.pi * S), -jnp.inf)
    mixture = jax.nn.logsumexp(ll, axis=-1)  # [M, j]: log Σ_h p(h) N(z_h; φ_j, S_j)
    ev = jnp.logaddexp(mixture, jnp.log(_OUTLIER_P / (2 * jnp.pi)))
    # The side that most likely explains each hypothesis: its probability times its likelihood there
    # (S is one for all sides). The nearest side alone would let a track that drifted a few degrees
    # take the detection's least likely side beside it over its most likely one.
    near = jnp.argmax(ll, axis=-1).astype(jnp.int32)  # [M, j]
    S = S[..., 0]  # the same for every side h
    return ev, near, _select(nu, near), S, gate_statistic(_select(d2, near), mixture, S)


def gate_statistic(d2_near: Float[Array, "*b"], mixture: Float[Array, "*b"], S: Float[Array, "*b"]) -> Float[Array, "*b"]:
    """What a hypothesis's heading gate (``heading_gate``, χ² of 1 dof) tests against a detection of
    several sides: the larger of its nearest side's squared normalised innovation and the sides'
    together, ``-2 log Σ_h p(h) exp(-d_h² / 2)`` (from ``mixture``, ``log Σ_h p(h) N(z_h; φ, S)``).
    One sure side is the χ² test itself; a side the detection gives little probability must lie that
    much nearer to pass, by ``-2 log p(h)``. (Tested alone, a misread 125° off, sure of itself, passed
    the gate with its least likely side, 0.02 and 18° off a track whose gate a rejected read had just
    widened, and swung the track 40° off for half a second: spl-legs:2004 at 44 s.)"""
    return jnp.maximum(d2_near, -2.0 * mixture - jnp.log(2 * jnp.pi * S))


def heading_mixture(state: TrackerState, ev, nu, S, gate, seen, z_best, r, dt, params: TrackerParams):
    """Weights and headings of every track's hypotheses after this scan's evidence (see
    :mod:`~gtsjax.core.g_track`): the log-weights (the rest's too) fade towards uniform over ``heading_memory`` and add
    the evidence; each hypothesis but the main one whose heading gate the detection passes (``gate``:
    :func:`gate_statistic`) takes its nearest side as a one-dimensional Kalman update; the rest's share of the read goes to the hypothesis that explains
    the detection's most probable side ``z_best``, or to a new one there; near-duplicates merge.
    Returns the new headings, variances, log-weights, the rest's log-weight and the hypothesis the
    state's heading becomes (the most probable one, where its odds over the present one exceed
    ``_SWITCH_ODDS``), and whether that is a switch."""
    used = jnp.isfinite(state.side_logw)
    fade = jnp.exp(-dt / params.heading_memory)
    lw = jnp.where(used, fade * jnp.where(used, state.side_logw, 0.0) + jnp.where(seen[:, None], ev, 0.0), -jnp.inf)
    rest = fade * state.side_rest
    side = jnp.arange(lw.shape[1], dtype=jnp.int32)[None, :]
    # The main hypothesis is the state's heading: its update is the state's own (``track_step``, with the
    # state's gate and turn-rate test), written back after it (:func:`follow_state`).
    upd = seen[:, None] & used & (gate <= params.heading_gate) & (side != state.main[:, None])
    gain = state.side_var / S
    heading = jnp.where(upd, wrap(state.side_heading + gain * nu), state.side_heading)
    var = jnp.where(upd, (1.0 - gain) * state.side_var, state.side_var)
    # The rest's read: most of its weight goes to a hypothesis at the read, the rest stays uniform.
    d2_best = jnp.where(used, wrap(z_best[:, None] - heading) ** 2 / (var + r[:, None]), jnp.inf)
    explained = jnp.any(d2_best <= params.heading_gate, axis=-1)
    spawn = rest + jnp.log((1.0 - _OUTLIER_P) / (2 * jnp.pi))
    rest = jnp.where(seen, rest + jnp.log(_OUTLIER_P / (2 * jnp.pi)), rest)
    weakest = jnp.argmin(jnp.where(side == state.main[:, None], jnp.inf, lw), axis=-1).astype(jnp.int32)
    new = (side == weakest[:, None]) & (seen & ~explained)[:, None]
    rest = jnp.logaddexp(rest, jnp.max(jnp.where(new, lw, -jnp.inf), axis=-1))  # the replaced one's weight
    heading = jnp.where(new, z_best[:, None], heading)
    var = jnp.where(new, r[:, None], var)
    lw = jnp.where(new, -jnp.inf, lw)
    target = jnp.where(explained, jnp.argmin(d2_best, axis=-1).astype(jnp.int32), weakest)
    lw = jnp.where(seen[:, None] & (side == target[:, None]), jnp.logaddexp(lw, spawn[:, None]), lw)
    # A new hypothesis near one that was there (the same side, turned further) also gets _NEW_P of its weight.
    same_side = used & (jnp.abs(wrap(z_best[:, None] - state.side_heading)) < _SAME_SIDE)
    kin = jnp.max(jnp.where(same_side & ~new, lw, -jnp.inf), axis=-1) + jnp.log(_NEW_P)
    lw = jnp.where(new, jnp.logaddexp(lw, kin[:, None]), lw)
    lw = merge_duplicates(heading, lw, state.main)
    total = jnp.logaddexp(jax.nn.logsumexp(lw, axis=-1), rest)
    lw, rest = lw - total[:, None], rest - total
    best = jnp.argmax(lw, axis=-1).astype(jnp.int32)
    switch = _select(lw, best) - _select(lw, state.main) > jnp.log(_SWITCH_ODDS)
    return heading, var, lw, rest, jnp.where(switch, best, state.main), switch


def merge_duplicates(
    heading: Float[Array, "tracks sides"], lw: Float[Array, "tracks sides"], main: Int[Array, " tracks"]
) -> Float[Array, "tracks sides"]:
    """Log-weights after merging hypotheses within ``_MERGE`` of each other (a fixed angle: variances
    grown through missed scans would merge distinct hypotheses): each one that another outranks (the
    main one outranks all, then the heavier, then the first) gives its weight to the highest-ranked of
    those and becomes unused (``-inf``). The survivor keeps its heading and variance."""
    used = jnp.isfinite(lw)
    n = lw.shape[1]
    idx = jnp.arange(n, dtype=jnp.int32)
    close = (
        used[:, :, None]
        & used[:, None, :]
        & (idx[:, None] != idx[None, :])[None]
        & (jnp.abs(wrap(heading[:, :, None] - heading[:, None, :])) < _MERGE)
    )
    rank = jnp.where(idx[None, :] == main[:, None], jnp.inf, lw)  # [M, j]
    above = (rank[:, :, None] > rank[:, None, :]) | (
        (rank[:, :, None] == rank[:, None, :]) & (idx[:, None] < idx[None, :])[None]
    )
    over = close & above  # [M, j, k]: j outranks its near-duplicate k
    dropped = jnp.any(over, axis=1)  # [M, k]
    into = jnp.argmax(jnp.where(over, rank[:, :, None], -jnp.inf), axis=1).astype(
        jnp.int32
    )  # [M, k]: the top one outranking k
    gets = over & (idx[None, :, None] == into[:, None, :])  # [M, j, k]
    add = jax.nn.logsumexp(jnp.where(gets, lw[:, None, :], -jnp.inf), axis=-1)  # [M, j]
    return jnp.where(dropped, -jnp.inf, jnp.logaddexp(lw, add))


class Headings(NamedTuple):
    """Every track's heading hypotheses after a scan (:func:`weigh_headings`)."""

    heading: Float[Array, "tracks sides"]
    var: Float[Array, "tracks sides"]
    logw: Float[Array, "tracks sides"]  # normalised with the rest's; -inf: unused
    rest: Float[Array, " tracks"]
    main: Int[Array, " tracks"]  # the hypothesis the state's heading is
    switch: Bool[Array, " tracks"]  # whether that is another one than before the scan
    near: Int[Array, "tracks sides"]  # for each hypothesis, the detection side nearest it
    gate: Float[Array, "tracks sides"]  # for each hypothesis, what its heading gate tests (``gate_statistic``)


def weigh_headings(
    state: TrackerState, obs: DetectionRows, seen: Bool[Array, " tracks"], dt: Float[Array, ""], params: TrackerParams
) -> Headings:
    """The hypotheses after each track's detection ``obs`` (whose heading counts where ``seen``): its
    evidence for each (:func:`side_evidence`), their weights and their own updates
    (:func:`heading_mixture`), and which is the state's heading now."""
    ev, near, nu, S, gate = side_evidence(
        state.side_heading, state.side_var, obs.side_heading, obs.side_logp, obs.cov[:, 2, 2]
    )
    ev = ev + motion_evidence(state, params, dt)
    heading, var, logw, rest, main, switch = heading_mixture(
        state, ev, nu, S, gate, seen, obs.pose[:, 2], obs.cov[:, 2, 2], dt, params
    )
    return Headings(heading, var, logw, rest, main, switch, near, gate)


def main_heading_prior(
    state: TrackerState, h: Headings, obs: DetectionRows
) -> tuple[Float[Array, "tracks 6"], Float[Array, "tracks 6 6"], Float[Array, "tracks 3"]]:
    """The state the scan's measurement update starts from, and its measurement: where the main
    hypothesis switched, the state's heading becomes the new main one, with its variance and no
    correlation with the rest of the state (what the state knew of the old heading says nothing of
    this one); the measurement is the detection's position and the heading of its side nearest the
    main hypothesis, so that a detection seen from another side still updates the state's heading."""
    theta0 = jnp.where(h.switch, _select(state.side_heading, h.main), state.mean[:, 2])
    # Row and column 2 of the covariance (masks from iotas): the column is the row's (symmetric), and
    # where the heading switched, both are zero but for the hypothesis's variance.
    i6 = jnp.arange(NX, dtype=jnp.int32)
    row2, col2 = (i6 == 2)[None, :, None], (i6 == 2)[None, None, :]
    cov0 = jnp.where(col2 & ~row2, jnp.swapaxes(state.cov, 1, 2), state.cov)
    cov0 = jnp.where(
        h.switch[:, None, None] & (row2 | col2),
        jnp.where(row2 & col2, _select(state.side_var, h.main)[:, None, None], 0.0),
        cov0,
    )
    mean0 = jnp.where(i6 == 2, theta0[:, None], state.mean)
    z = jnp.concatenate([obs.pose[:, :2], _select(obs.side_heading, _select(h.near, h.main))[:, None]], -1)
    return mean0, cov0, z


def follow_state(h: Headings, mean: Float[Array, "tracks 6"], cov: Float[Array, "tracks 6 6"]) -> Headings:
    """The main hypothesis takes the state's update: it is the state's heading, updated with the
    state's gate and turn-rate test, which :func:`heading_mixture` leaves to the state."""
    onehot = jnp.arange(h.heading.shape[1], dtype=jnp.int32)[None, :] == h.main[:, None]
    return h._replace(heading=jnp.where(onehot, mean[:, 2:3], h.heading), var=jnp.where(onehot, cov[:, 2:3, 2], h.var))
