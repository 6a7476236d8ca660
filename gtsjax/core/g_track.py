"""Stage g, pose tracking: a fixed table of ``M`` tracks, one extended Kalman filter each over
``(x, y, θ, vx, vy, ω)``, with per-class Mahalanobis gating and one-to-one assignment, all in JAX.

The paper's tracker predicts by inflating the covariance only and observes ``(x, y, θ)`` directly; it
is available as ``constant_velocity=False``. The default is a constant-velocity model (piecewise
white acceleration), which follows a walking robot with less lag. The observation is linear; what
makes the filter "extended" is the heading: innovations are wrapped to (−π, π], and the state's
heading is re-wrapped after each update.

**Heading outliers.** A single scan sometimes sees an asymmetric robot from a side that looks like
another side, and the pose regressor then returns a heading off by 90° or 180°. Association
therefore gates on position only (2 dof); the heading of an assigned detection updates the track
only if its own innovation passes ``heading_gate`` (χ², 1 dof), otherwise the update is
position-only. A detection of several sides (below) passes only where its side nearest the track's
heading does and its sides together do, each weighted by its probability
(:func:`~gtsjax.core.g_heading.gate_statistic`): a side the detection itself gives little
probability must lie that much nearer the track to be taken. A rejected heading also discards the turn-rate estimate (``ω = 0`` with its initial
variance): a turn rate learnt from misread headings would otherwise spin the track's heading past
every right one it rejects. ``ω`` is kept within its class's ``max_turn_rate``.

Gating cannot tell a misread whose own variance is large: it widens the gate it is tested
against. A detection whose heading variance is above its class's ``heading_var_max`` (learnt at
training: almost no good read of the class has one so large, ``train.calibrate``) is *vague*: it
updates the track's position only, and its heading neither supports nor rejects the track's. Unlike
a partial view (below) it may start and confirm a track.

Gating alone cannot undo a wrong start: a track born on a misread heading rejects every right one.
So the heading is a **mixture over side hypotheses** (Rao–Blackwellised: position and velocity are
shared, the heading is not). Each track keeps ``SIDES`` heading hypotheses, each with a variance and a
log-weight, and a *rest*: the weight of "the heading is none of them", a uniform heading. At birth
the hypotheses are its first detection's sides (stage e′: the refined poses from the GP's heading and
from it turned to the outline's other sides, each with a posterior probability), sharing
``1 − _REST_P`` of the weight. Each scan the hypotheses turn with the track's turn rate and grow as
uncertain as its heading; an assigned detection's evidence for hypothesis ``j`` is ``log Σ_h p(h)
N(z_h; φ_j, σ_j² + r)`` over its sides, with a floor for a heading none of them explains
(:func:`side_evidence`); the log-weights fade towards uniform with the time constant
``heading_memory`` and add the evidence; each hypothesis but the main one (below) takes its nearest
detection side (the likeliest to explain it: the largest ``log p(h) − (z_h − φ_j)² / 2(σ_j² + r)``, so
that a track a few degrees off does not take a side of little probability beside it over the one
the detection favours) as a one-dimensional Kalman update where it passes the heading gate. Under the rest,
any heading read is as likely as any other (``1/2π``); what it learns from the read is that the
heading is near it: its weight splits into a hypothesis at the read (``1 − _OUTLIER_P``: added to the hypothesis that already
explains the read, or, where none does, a new one in place of the weakest, whose weight goes back to
the rest) and a rest that stays uniform (``_OUTLIER_P``). A new hypothesis within ``_SAME_SIDE`` of
one (predicted) is that side again, the track's heading having fallen behind a turn: it also gets
``_NEW_P`` of that one's weight. Two hypotheses closer than ``_MERGE`` (3°) are one: the lighter
(never the main one) gives its weight to the other.

So a new hypothesis of another side starts from what the rest has kept: on a young track that is much
(a track born on a misread gives it up at the next right read), on one whose reads have long agreed it
is what the floor left over the last ``heading_memory``, and one or two misreads in a row cannot
outweigh that; the same reads for about ``heading_memory`` do. A track lagging a turning robot takes
the turned heading within a scan or two. The state's heading is one of the hypotheses, its
*main* one; where another becomes three times as probable, the state's heading becomes that
hypothesis (its variance, no correlation with the rest of the state), and the state's update then
uses the detection side nearest it. So a static robot whose scans disagree converges to the side the
evidence favours, summed over the last second, not to the last scan's or the majority's; a robot that
turns turns all its hypotheses. Detections without sides (a class without an outline) have one.

Track life cycle (the paper leaves it open): an unassigned detection of a tracked class starts a
tentative track in a free slot unless a live track of its class, or an earlier detection of its
class that may start one in the same scan, is closer than ``birth_exclusion``; a tentative track is
confirmed by its ``n_confirm``-th hit if its motion is plausible and most of its scans saw it as its
class (both below); a tentative track dies after ``m_tentative`` consecutive misses, a confirmed one
after ``m_delete``. A confirmed track is *reported* only while it has missed fewer than
``m_report`` scans in a row: a robot picked up or hidden behind another is not reported at a
predicted pose, yet its track (and id) lives on for ``m_delete`` scans to take it back when it
reappears. Ids are integers handed out in order and never reused.

**Plausible motion.** On real scans people's legs (1–1.5 m/s, faster in the swing) and clutter are
sometimes classified as robots, and such detections follow one another from scan to scan as a robot's
would. Each tracked class has a top speed ``max_speed`` and turn rate ``max_turn_rate`` (defaults
``DEFAULT_MAX_SPEED`` = 0.6 m/s, a Nao walks at most about 0.35 m/s, and ``DEFAULT_MAX_TURN_RATE`` =
3 rad/s, for every class; training may set them per class from labelled motion, and a user can
override them). A track's motion is *implausible* in a scan when, after that scan's update (or
prediction, without a detection), its speed exceeds its class's ``max_speed`` by more than two
standard deviations of the estimate, ``|v̂| > max_speed + 2 σ_v`` with ``σ_v²`` the largest eigenvalue
of the 2×2 velocity covariance, or its turn rate before clipping exceeds ``max_turn_rate`` by more
than ``2 σ_ω``. The margin lets a
robot at its top speed pass while a few scans' estimate is still loose (a new track's velocity is 0
± 0.5 m/s); a leg at twice the limit fails once three or four detections pin its velocity down. An
implausible scan restarts the track's confirmation: a tentative track is not confirmed, a confirmed
one loses its confirmation (it stops being reported; it keeps its id and slot, and dies after
``m_tentative`` misses like any tentative track), and its ``hits`` and ``contrary`` counters restart
at 0, so that it must earn confirmation again with ``n_confirm`` further hits, as a new track does.
A confirmed track's turn rate is not left to decide that: a heading that would turn it faster than its
class can is taken for a misread and rejected like one outside the heading gate (after a few missed
scans the gate is wide and misreads get through it; on the SPL scenarios, unconfirming the robot for
them instead cost 1 % of recall, 96.3 % instead of 97.4 % with three robots crossing).

Why a tentative track is not (yet) confirmed, for the user (a model whose top speed is too low
leaves every track tentative, and nothing reported): ``track_step(..., explain=True)`` also returns
per slot an index into :data:`HOLDS` (the test that held it in this scan) and its estimated speed and
turn rate (:class:`TrackHolds`), a few whole-array selects on what the step computes anyway.

**Majority confirmation.** Clutter that the classifier calls "robot" in some scans is called something
else in the others. The step also receives the scan's ``other`` candidates (kept by the front end's
binary filters, not detections of a tracked class: background, rejected, landmarks, another class,
outside the bounds), and a tentative track counts in ``contrary`` the scans in which it got no
detection but such a candidate lay within ``birth_exclusion`` of its predicted position. It is
confirmed only when ``hits > contrary``: most of the scans that saw something at its place saw it as
its class.

**Recapture.** A robot that changes direction abruptly (an omnidirectional walk turning into a
sidestep) can leave a confident track's gate for a few scans while its detections stay a few
centimetres from the prediction; the track then coasts away and a second track is born beside it.
So after the gated assignment, a detection left over that lies within ``birth_exclusion`` of a live
track of its class that is also left over (the distance under which a detection may not start a
track of its own) updates that track, nearest first.

Assignment is greedy on the Mahalanobis distance (repeatedly take the globally closest gated pair):
one-to-one, deterministic, and ``min(K, M)`` cheap iterations of fixed shape. With well-separated
robots it equals the optimal assignment; when two robots cross, the per-class gates and the velocity
state keep the pairs apart.

The code follows these concepts, one module each, beside this one: :mod:`.g_kalman` (the filter's
algebra), :mod:`.g_assign` (gating and assignment), :mod:`.g_heading` (the heading mixture) and
:mod:`.g_life` (birth, counters, confirmation, deletion, report), on the types of :mod:`.g_types`.
:func:`track_step` runs them in turn, one named phase each; this module re-exports their public names.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .g_assign import GUESS_MISSES as GUESS_MISSES
from .g_assign import GUESS_RADIUS as GUESS_RADIUS
from .g_assign import assign as assign
from .g_assign import associate
from .g_heading import _OUTLIER_P as _OUTLIER_P
from .g_heading import follow_state, main_heading_prior, weigh_headings
from .g_heading import heading_mixture as heading_mixture
from .g_heading import merge_duplicates as merge_duplicates
from .g_heading import side_evidence as side_evidence
from .g_identity import update_identities
from .g_kalman import innovation as innovation
from .g_kalman import inv2 as inv2
from .g_kalman import inv3 as inv3
from .g_kalman import kalman_update, predict
from .g_kalman import mahalanobis as mahalanobis
from .g_kalman import motion_model as motion_model
from .g_life import confirm_and_end, explain_holds, next_state, plausible_turn, scans_spanned, start_tracks
from .g_life import plausible as plausible
from .g_life import plausible_parts as plausible_parts
from .g_life import reported as reported
from .g_types import DEFAULT_MAX_SPEED as DEFAULT_MAX_SPEED
from .g_types import DEFAULT_MAX_TURN_RATE as DEFAULT_MAX_TURN_RATE
from .g_types import HOLDS as HOLDS
from .g_types import NX as NX
from .g_types import DetectionFlags, Detections, DetectionTable, TrackerParams, TrackerState, TrackHolds, _select
from .g_types import detection_sides as detection_sides


def update_tracks(
    state: TrackerState,
    has: Bool[Array, " tracks"],
    seen: Bool[Array, " tracks"],
    head_ok: Bool[Array, " tracks"],
    mean0: Float[Array, "tracks 6"],
    cov0: Float[Array, "tracks 6 6"],
    z: Float[Array, "tracks 3"],
    R: Float[Array, "tracks 3 3"],
    params: TrackerParams,
) -> tuple[Float[Array, "tracks 6"], Float[Array, "tracks 6 6"], Float[Array, " tracks"]]:
    """The measurement update of each track that has a detection (``has``), from the state
    :func:`~gtsjax.core.g_heading.main_heading_prior` gives, with the heading where the detection's is
    ``seen``, passes the heading gate (``head_ok``: its main hypothesis's,
    :func:`~gtsjax.core.g_heading.gate_statistic`, the χ² test of its nearest side for a detection of
    one side) and, on a confirmed track, turns it no faster than its class can; position-only
    otherwise (see the module docstring). Returns the new means and covariances (the prior's where no
    detection), with the turn rate clipped at its class's limit, and the updated turn rate before
    clipping, for the plausibility test."""
    # Both candidate updates, with the heading and position-only, in one batched call (a leading axis
    # of two); each test selects one of them.
    both_mean, both_cov = kalman_update(
        mean0[None], cov0[None], z[None], R[None], (jnp.arange(2, dtype=jnp.int32) == 0)[:, None]
    )
    pick = lambda ok: (
        jnp.where(ok[:, None], both_mean[0], both_mean[1]),
        jnp.where(ok[:, None, None], both_cov[0], both_cov[1]),
    )
    upd_mean, upd_cov = pick(head_ok & seen)
    # A confirmed track's heading that would turn it faster than its class can (``plausible``'s
    # turn-rate test on the updated estimate) is a misread, most often after a few scans without a
    # detection have widened the heading's gate: rejected like one that fails the gate.
    turn_ok = plausible_turn(upd_mean[:, 5], upd_cov, state.class_id, params)
    head_ok = head_ok & (turn_ok | ~state.confirmed)
    upd_mean, upd_cov = pick(head_ok & seen)
    # A rejected heading discards a turn rate learnt from headings (see the module docstring). One
    # already discarded (its variance back at omega_var0 or above) is left as it is, with its
    # correlation to the heading: over consecutive rejections the heading's variance then grows with
    # the square of the time, as a turn at up to that rate would move it, not linearly, and a robot
    # that really turns is taken back within a few scans instead of being coasted past.
    forget = seen & ~head_ok & (cov0[:, 5, 5] < params.omega_var0)
    i6 = jnp.arange(NX, dtype=jnp.int32)
    row5, col5 = (i6 == 5)[None, :, None], (i6 == 5)[None, None, :]
    upd_cov = jnp.where(forget[:, None, None] & (row5 | col5), jnp.where(row5 & col5, params.omega_var0, 0.0), upd_cov)
    omega_raw = jnp.where(forget, 0.0, upd_mean[:, 5])  # the turn rate before clipping, for plausible()
    turn_max = _select(params.max_turn_rate, state.class_id)
    upd_mean = jnp.where(i6 == 5, jnp.clip(omega_raw, -turn_max, turn_max)[:, None], upd_mean)
    mean = jnp.where(has[:, None], upd_mean, mean0)
    cov = jnp.where(has[:, None, None], upd_cov, cov0)
    return mean, cov, omega_raw


def track_step(
    state: TrackerState,
    det: Detections,
    dt: Float[Array, ""],
    params: TrackerParams,
    period: float | None = None,
    visible: Bool[Array, " tracks"] | None = None,
    span_dt: Float[Array, ""] | None = None,
    watchers: Int[Array, " tracks"] | None = None,
    explain: bool = False,
) -> "tuple[TrackerState, Bool[Array, ' dets']] | tuple[TrackerState, Bool[Array, ' dets'], TrackHolds]":
    """Stage g for one scan: predict, gate, assign, update, start, confirm and end tracks.

    ``period``: the scanner's scan period (s), where known. A track without a detection then counts
    as missed every scan period the ``dt`` spans (``max(1, round(dt / period))``), not one: after
    frames lost on the link or a stall, a robot lifted meanwhile is not reported past ``m_report``
    periods, nor kept past ``m_delete``, on the strength of one late scan. Without it (a scanner of
    unknown rate) each scan counts one.

    Several lasers (:mod:`gtsjax.core.multi`): ``visible`` marks the tracks this scan's laser could
    have seen (within its range and field of view); a track it could not see is not missed by it.
    ``span_dt`` is then the time since this laser's previous scan (the periods a miss spans), ``dt``
    the time since the previous scan of any laser (the prediction's step). ``watchers``: how many lasers
    can see each track (at least 1). Each of them that scans and misses the track counts a miss, so a
    track two lasers watch gathers misses twice as fast as one a single laser watches; its limits
    (``m_tentative``, ``m_delete``, ``m_report``) are multiplied by ``watchers``, so that a track ends
    (and stops being reported) after the same time unseen however many lasers watch it. (Counted per
    scan, a robot hidden for half a second from both of two lasers lost its track and its id.)

    Returns the new state and, per detection, whether it was used by an existing track; with
    ``explain``, also each slot's :class:`TrackHolds` (why it is not confirmed: :data:`HOLDS`).
    """
    state = predict(state, dt, params)
    flags = DetectionFlags.of(det, params)
    assoc = associate(state, det, flags, params)
    table = DetectionTable.of(det, flags, state.side_heading.shape[1])
    obs = table.rows(assoc.det_of_track)  # each track's detection
    # A partial view's heading comes from a cut outline: it updates the position only, and neither
    # supports nor rejects the track's heading. So does a vague one: a heading read with a variance
    # that good reads of the class almost never have is more often a misread than not.
    seen = assoc.has & ~obs.partial & ~obs.vague
    headings = weigh_headings(state, obs, seen, dt, params)
    mean0, cov0, z = main_heading_prior(state, headings, obs)
    # The state's heading is its main hypothesis: the detection passes its heading gate where it passes that one's.
    head_ok = _select(headings.gate, headings.main) <= params.heading_gate
    mean, cov, omega_raw = update_tracks(state, assoc.has, seen, head_ok, mean0, cov0, z, obs.cov, params)
    headings = follow_state(headings, mean, cov)
    spanned = scans_spanned(dt, period, visible, span_dt)
    tally = confirm_and_end(state, assoc.has, assoc.other_near, spanned, mean, cov, omega_raw, params, watchers)
    births = start_tracks(state, det, flags, assoc.used, tally.live, mean, table, params)
    new = next_state(state, tally, births, headings, mean, cov, params)
    if state.id_logp is not None:
        # Identities: each track adds its detection's tag reading; a born track starts from its own.
        assigned = jnp.where(births.born, births.det, jnp.where(assoc.has, assoc.det_of_track, -1))
        tag_ll = det.tag_ll if det.tag_ll is not None else jnp.zeros((det.mask.shape[0], state.id_logp.shape[1]),
                                                                      state.id_logp.dtype)
        tag_ll = jnp.where(det.mask[:, None], tag_ll, 0.0)
        id_logp = update_identities(state.id_logp, assigned, tag_ll, births.born | ~new.live)
        new = eqx.tree_at(lambda s: s.id_logp, new, id_logp, is_leaf=lambda x: x is None)
    if not explain:
        return new, assoc.used
    return new, assoc.used, explain_holds(new, births, tally, mean, params)
