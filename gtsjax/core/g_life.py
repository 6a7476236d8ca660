"""Stage g's track life cycle: how a slot's track is born, counts its hits, misses and contrary scans,
is confirmed (plausible motion, a majority of scans seeing it as its class), reported, and ended; and,
on request, why a live track is not confirmed. :mod:`~gtsjax.core.g_track` describes the rules and
why; this module applies them to the whole table of slots at once, with masks and selects.
"""

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .g_heading import Headings
from .g_types import (
    _REST_P,
    NX,
    DetectionFlags,
    Detections,
    DetectionTable,
    TrackerParams,
    TrackerState,
    TrackHolds,
    _select,
)

# How many standard deviations of its own estimate a track's speed or turn rate may exceed its
# class's limit by before its motion counts as implausible: one-sided, a robot at exactly its limit
# is flagged in at most 2.3 % of scans by a calibrated estimate (fewer with the upper bound on σ_v
# used, and the errors of consecutive scans are correlated, not independent trials), while a leg
# at twice the limit is flagged once σ_v is below half the limit (2 m > m + 2 σ_v), three or four scans.
_PLAUSIBLE_SIGMAS = 2.0


def plausible(
    mean: Float[Array, "tracks 6"],
    cov: Float[Array, "tracks 6 6"],
    omega: Float[Array, " tracks"],
    class_id: Int[Array, " tracks"],
    params: TrackerParams,
) -> Bool[Array, " tracks"]:
    """Whether each track's motion is one its class can make: both tests of :func:`plausible_parts`."""
    speed_ok, turn_ok = plausible_parts(mean, cov, omega, class_id, params)
    return speed_ok & turn_ok


def plausible_parts(
    mean: Float[Array, "tracks 6"],
    cov: Float[Array, "tracks 6 6"],
    omega: Float[Array, " tracks"],
    class_id: Int[Array, " tracks"],
    params: TrackerParams,
) -> tuple[Bool[Array, " tracks"], Bool[Array, " tracks"]]:
    """The two tests of :func:`plausible` apart, ``(speed_ok, turn_ok)``: whether each track's speed
    and turn rate are ones its class can make, ``|v̂| ≤ max_speed + 2 σ_v`` and
    ``|ω| ≤ max_turn_rate + 2 σ_ω`` (``omega``: the turn rate before clipping).

    ``σ_v²`` is the largest eigenvalue of the velocity covariance, ``(a + d)/2 + √(((a − d)/2)² + b²)``
    for ``[[a, b], [b, d]]``: the variance of the speed's estimate is that of the velocity along its
    own direction, which this bounds from above whatever the direction. So the test never rejects a
    robot for the orientation of its uncertainty, needs no direction of a near-zero velocity, and is
    the same for every heading of the track. Speeds are compared squared (no root of a zero speed)."""
    a, b, d = cov[:, 3, 3], cov[:, 3, 4], cov[:, 4, 4]
    disc = 0.25 * (a - d) ** 2 + b * b
    pos = disc > 0
    root = jnp.where(pos, jnp.sqrt(jnp.where(pos, disc, 1.0)), 0.0)  # double where: finite gradients at a = d, b = 0
    sigma_v = jnp.sqrt(jnp.maximum(0.5 * (a + d) + root, 0.0))
    v_max = _select(params.max_speed, class_id) + _PLAUSIBLE_SIGMAS * sigma_v
    return mean[:, 3] ** 2 + mean[:, 4] ** 2 <= v_max**2, plausible_turn(omega, cov, class_id, params)


def plausible_turn(
    omega: Float[Array, " tracks"],
    cov: Float[Array, "tracks 6 6"],
    class_id: Int[Array, " tracks"],
    params: TrackerParams,
) -> Bool[Array, " tracks"]:
    """The turn-rate half of :func:`plausible`: ``|ω| ≤ max_turn_rate + 2 σ_ω``."""
    sigma_w = jnp.sqrt(jnp.maximum(cov[:, 5, 5], 0.0))
    return jnp.abs(omega) <= _select(params.max_turn_rate, class_id) + _PLAUSIBLE_SIGMAS * sigma_w


def _count_up_to(x: Bool[Array, " n"]) -> Int[Array, " n"]:
    """``cumsum(x)`` as counts over a triangular mask: one reduction that fuses its inputs, where a
    cumulative sum is a chain of reduce-windows."""
    i = jnp.arange(x.shape[0], dtype=jnp.int32)
    return jnp.sum(x[None, :] & (i[None, :] <= i[:, None]), axis=1, dtype=jnp.int32)


def reported(
    state: TrackerState, params: TrackerParams, watchers: Int[Array, " tracks"] | None = None
) -> Bool[Array, " tracks"]:
    """Tracks to report: confirmed, and observed within the last ``m_report`` scans (of each of the
    ``watchers`` lasers that can see the track, where several do: see :func:`~gtsjax.core.g_track.track_step`)."""
    m_report = params.m_report if watchers is None else params.m_report * watchers
    return state.live & state.confirmed & (state.misses < m_report)


def scans_spanned(
    dt: Float[Array, ""], period: float | None, visible: Bool[Array, " tracks"] | None, span_dt: Float[Array, ""] | None
) -> Int[Array, "*tracks"]:
    """How many scans a track without a detection has missed in this one: every scan period that the
    time since this laser's previous scan spans (one where the period is unknown), so that frames lost
    on the link do not keep a lifted robot reported; none where this laser could not have seen it
    (several lasers: see :func:`~gtsjax.core.g_track.track_step`)."""
    gap = dt if span_dt is None else span_dt
    spanned = (
        jnp.ones((), jnp.int32)
        if period is None
        else jnp.maximum(jnp.round(gap / jnp.asarray(period, gap.dtype)), 1).astype(jnp.int32)
    )
    if visible is not None:
        spanned = spanned * visible.astype(jnp.int32)
    return spanned


class Tally(NamedTuple):
    """Each slot's counters and standing after a scan's update, before births (:func:`confirm_and_end`)."""

    hits: Int[Array, " tracks"]
    misses: Int[Array, " tracks"]
    contrary: Int[Array, " tracks"]
    confirmed: Bool[Array, " tracks"]
    live: Bool[Array, " tracks"]
    speed_ok: Bool[Array, " tracks"]  # this scan's plausibility tests (:func:`plausible_parts`)
    turn_ok: Bool[Array, " tracks"]
    omega: Float[Array, " tracks"]  # the turn rate the turn-rate test saw (before clipping)


def confirm_and_end(
    state: TrackerState,
    has: Bool[Array, " tracks"],
    other_near: Bool[Array, " tracks"],
    spanned: Int[Array, "*tracks"],
    mean: Float[Array, "tracks 6"],
    cov: Float[Array, "tracks 6 6"],
    omega_raw: Float[Array, " tracks"],
    params: TrackerParams,
    watchers: Int[Array, " tracks"] | None,
) -> Tally:
    """Count each predicted track's hit or miss (``spanned`` scans, :func:`scans_spanned`) and contrary
    scan, test its motion, confirm it, and end it after too many misses. ``mean``, ``cov``: after the
    scan's update; ``omega_raw``: the updated turn rate before clipping."""
    hits = state.hits + has.astype(jnp.int32)
    misses = jnp.where(has, 0, state.misses + spanned)
    contrary = state.contrary + (~has & ~state.confirmed & other_near).astype(jnp.int32)
    # Plausibility of the motion after this scan: the updated estimate, or for a track without a
    # detection the predicted one (same velocity, larger covariance, turn rate clipped at its last
    # update: coasting never makes a plausible track implausible). An implausible scan restarts
    # confirmation, of a tentative and a confirmed track alike.
    omega_used = jnp.where(has, omega_raw, state.mean[:, 5])
    speed_ok, turn_ok = plausible_parts(mean, cov, omega_used, state.class_id, params)
    sane = speed_ok & turn_ok
    hits = jnp.where(sane, hits, 0)
    contrary = jnp.where(sane, contrary, 0)
    confirmed = state.live & sane & (state.confirmed | ((hits >= params.n_confirm) & (hits > contrary)))
    # Each laser that can see a track counts its misses: the limits are per laser (see ``track_step``).
    w = jnp.ones((), jnp.int32) if watchers is None else watchers
    dead = state.live & jnp.where(confirmed, misses >= params.m_delete * w, misses >= params.m_tentative * w)
    live = state.live & ~dead
    return Tally(hits, misses, contrary, confirmed, live, speed_ok, turn_ok, omega_used)


class Births(NamedTuple):
    """The tracks a scan starts (:func:`start_tracks`), per slot, where ``born``."""

    born: Bool[Array, " tracks"]
    rank: Int[Array, " tracks"]  # the slot's rank among the free ones: its id is ``next_id`` plus it
    mean: Float[Array, "tracks 6"]
    cov: Float[Array, "tracks 6 6"]
    class_id: Int[Array, " tracks"]
    side_heading: Float[Array, "tracks sides"]
    side_var: Float[Array, "tracks 1"]  # the detection's heading variance, every hypothesis's
    side_logp: Float[Array, "tracks sides"]
    count: Int[Array, ""]
    det: Int[Array, " tracks"] | None = None  # the detection each born track starts from


def start_tracks(
    state: TrackerState,
    det: Detections,
    flags: DetectionFlags,
    used: Bool[Array, " dets"],
    live: Bool[Array, " tracks"],
    mean: Float[Array, "tracks 6"],
    table: DetectionTable,
    params: TrackerParams,
) -> Births:
    """Births: the i-th free slot takes the i-th detection of a tracked class that no track took, that
    is whole (no partial view or guess), and that no live track of its class lies within
    ``birth_exclusion`` of. A new track has its detection's pose and covariance, no velocity or turn
    rate (with their initial variances), and the detection's sides as its heading hypotheses."""
    dist = jnp.linalg.norm(det.pose[:, None, :2] - mean[None, :, :2], axis=-1)
    near_live = jnp.any(
        live[None, :] & (det.class_id[:, None] == state.class_id[None, :]) & (dist < params.birth_exclusion), 1
    )
    born_ok = flags.tracked & ~used & ~near_live & flags.whole
    # Nor may two detections of a class closer than that start two tracks in one scan (a robot seen
    # in two pieces): the first of them in slot order starts it.
    dd = jnp.linalg.norm(det.pose[:, None, :2] - det.pose[None, :, :2], axis=-1)  # [K, K]
    k = det.mask.shape[0]
    earlier = jnp.arange(k)[None, :] < jnp.arange(k)[:, None]  # [j, i]: i comes before j
    shadowed = jnp.any(
        earlier & born_ok[None, :] & (det.class_id[:, None] == det.class_id[None, :]) & (dd < params.birth_exclusion),
        axis=1,
    )
    born_ok = born_ok & ~shadowed
    free = ~live
    rank_det = _count_up_to(born_ok) - 1
    rank_slot = _count_up_to(free) - 1
    match = free[:, None] & born_ok[None, :] & (rank_slot[:, None] == rank_det[None, :])  # [M, K]
    born = jnp.any(match, axis=1)
    src = jnp.argmax(match, axis=1).astype(jnp.int32)
    first = table.rows(src)
    i6 = jnp.arange(NX, dtype=jnp.int32)
    vel_diag = (i6[:, None] == i6[None, :]) & (i6 >= 3)[None, :]  # the velocities' and turn rate's variances
    P0 = jnp.where(
        vel_diag[None],
        jnp.where(i6 == 5, params.omega_var0, params.vel_var0)[None, None, :],
        jnp.pad(first.cov, ((0, 0), (0, NX - 3), (0, NX - 3))),
    )
    mean0 = jnp.pad(first.pose, ((0, 0), (0, NX - 3)))
    return Births(
        born,
        rank_slot,
        mean0,
        P0,
        first.class_id,
        first.side_heading,
        first.cov[:, 2:3, 2],
        first.side_logp,
        jnp.sum(born).astype(jnp.int32),
        src,
    )


def next_state(
    state: TrackerState,
    tally: Tally,
    births: Births,
    headings: Headings,
    mean: Float[Array, "tracks 6"],
    cov: Float[Array, "tracks 6 6"],
    params: TrackerParams,
) -> TrackerState:
    """The table after the scan: each slot's updated track, emptied where it ended, or the track born
    in it. A new track's heading mixture is its detection's sides, sharing ``1 − _REST_P`` of the
    weight, and its main hypothesis the most probable side; it is confirmed at once only where one hit
    is enough (``n_confirm`` ≤ 1). Ids are handed out in slot order and never reused."""
    b, live = births.born, tally.live
    return TrackerState(
        mean=jnp.where(b[:, None], births.mean, mean),
        cov=jnp.where(b[:, None, None], births.cov, cov),
        class_id=jnp.where(b, births.class_id, state.class_id),
        track_id=jnp.where(b, state.next_id + births.rank, jnp.where(live, state.track_id, -1)),
        live=live | b,
        confirmed=jnp.where(b, params.n_confirm <= 1, tally.confirmed & live),
        hits=jnp.where(b, 1, jnp.where(live, tally.hits, 0)),
        misses=jnp.where(b | ~live, 0, tally.misses),
        contrary=jnp.where(b | ~live, 0, tally.contrary),
        side_heading=jnp.where(b[:, None], births.side_heading, headings.heading),
        side_var=jnp.where(b[:, None], births.side_var, headings.var),
        side_logw=jnp.where(b[:, None], births.side_logp + jnp.log1p(-_REST_P), headings.logw),
        side_rest=jnp.where(b, jnp.log(_REST_P), headings.rest),
        main=jnp.where(b, jnp.argmax(births.side_logp, axis=-1).astype(jnp.int32), headings.main),
        next_id=state.next_id + births.count,
    )


def explain_holds(
    new: TrackerState, births: Births, tally: Tally, mean: Float[Array, "tracks 6"], params: TrackerParams
) -> TrackHolds:
    """Why each slot is not confirmed (``HOLDS``), whole-array selects: a track born in this scan waits
    for its scans; one that lives on, for the first test it failed in this scan. With its estimated
    speed (``mean`` after the update) and turn rate, for the host's diagnosis of a run."""
    born = births.born
    majority = (tally.hits >= params.n_confirm) & (tally.hits <= tally.contrary)
    why = jnp.where(~tally.speed_ok, 3, jnp.where(~tally.turn_ok, 4, jnp.where(majority, 2, 1)))
    hold = jnp.where(new.live & ~new.confirmed, jnp.where(born, 1, why), 0).astype(jnp.int32)
    on = new.live & ~born
    v2 = mean[:, 3] ** 2 + mean[:, 4] ** 2
    speed = jnp.where(on & (v2 > 0), jnp.sqrt(jnp.where(v2 > 0, v2, 1.0)), 0.0)  # double where: no root of 0
    turn = jnp.where(on, jnp.abs(tally.omega), 0.0)
    return TrackHolds(hold, speed, turn)
