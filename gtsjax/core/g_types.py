"""Stage g's types: the tracker's tuning, its state, one scan's detections (and the flags and table
the tracker reads them through) and why a slot is not confirmed, with the constants they are built
from. In a module of their own so that every concept module of stage g (:mod:`.g_kalman`,
:mod:`.g_assign`, :mod:`.g_heading`, :mod:`.g_life`) and :mod:`.g_track`, which runs them in turn,
import them from one place without importing each other in a cycle. The behaviour they carry is
described in :mod:`~gtsjax.core.g_track`, which re-exports them.
"""

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .e_refine import SIDES
from .geometry import compose, relative, wrap

_F32 = jnp.float32
NX = 6  # x, y, theta, vx, vy, omega


# Defaults of the per-class motion limits (see :mod:`~gtsjax.core.g_track`): m/s and rad/s.
DEFAULT_MAX_SPEED = 0.6
DEFAULT_MAX_TURN_RATE = 3.0

# Why a live track slot is not confirmed after a scan (``TrackHolds.hold``, ``Output.track_hold``: an
# index into this): "none" for a confirmed slot or a free one; "speed" where its motion failed
# :func:`~gtsjax.core.g_life.plausible`'s speed test in this scan, "turn rate" where it failed the
# turn-rate test (and not the speed test); "majority" where it has its ``n_confirm`` hits but no more of them than ``contrary``
# scans; "too few scans" otherwise (fewer than ``n_confirm`` hits since its birth or its last
# implausible scan). For the host's diagnosis of a run (:mod:`gtsjax.drivers.diagnose`).
HOLDS = ("none", "too few scans", "majority", "speed", "turn rate")

# The weight a new track gives to a heading none of its first detection's sides is (the rest of its
# heading mixture, :mod:`.g_heading`); an empty slot holds the same mixture.
_REST_P = 0.1


class TrackerParams(eqx.Module):
    """Tuning of the tracker. All arrays, so that changing a value does not recompile the step.

    ``max_speed`` and ``max_turn_rate`` are per class (defaults ``DEFAULT_MAX_SPEED`` = 0.6 m/s and
    ``DEFAULT_MAX_TURN_RATE`` = 3 rad/s for every class): a track whose estimated motion exceeds its
    class's limits by more than twice the estimate's standard deviation is not confirmed, or loses its
    confirmation (see :mod:`~gtsjax.core.g_track`)."""

    q_pos: Float[Array, ""]  # acceleration noise density, (m/s²)²·s (constant velocity) or m²/s (inflate-only)
    q_theta: Float[Array, ""]  # same for heading, rad²/s³ (or rad²/s)
    vel_var0: Float[Array, ""]  # initial velocity variance of a new track, (m/s)²
    omega_var0: Float[Array, ""]  # initial turn-rate variance, (rad/s)²
    gate: Float[Array, " classes"]  # per-class Mahalanobis gate on position (χ², 2 dof)
    heading_gate: Float[Array, ""]  # gate on an assigned detection's heading innovation (χ², 1 dof)
    heading_memory: Float[Array, ""]  # s: time constant over which the heading hypotheses' evidence fades
    max_speed: Float[Array, " classes"]  # m/s: a track faster than its class's is implausible
    max_turn_rate: Float[Array, " classes"]  # rad/s: |ω| is kept below its class's; faster is implausible
    tracked: Bool[Array, " classes"]  # which classes are mobile (tracked); landmarks and background are not
    n_confirm: Int[Array, ""]
    m_tentative: Int[Array, ""]
    m_delete: Int[Array, ""]
    m_report: Int[Array, ""]
    birth_exclusion: Float[Array, ""]  # metres
    constant_velocity: Bool[Array, ""]
    # Each class's mean pose error in its own frame (ahead, left in m, heading in rad), measured at
    # training on held-out detections, taken off the reported rows (:meth:`off`); None: nothing taken off.
    pose_offset: Float[Array, "classes 3"] | None = None
    # Each class's variance floor of the reported rows (position m², added to var_x and var_y; heading
    # rad²), learnt at training so that the rows' 95 % ellipses hold 95 % of the held-out rows' errors
    # (:meth:`widened`); None: the filter's variances as they are.
    var_floor: Float[Array, "classes 2"] | None = None
    # Each class's heading against its direction of travel, learnt at training from its labels'
    # translating windows (``gtsjax.train.motion.motion_heading``): the mean offset (rad), the
    # concentration κ of a von Mises about it, and the share of travel in any other direction (a Nao's
    # sidesteps, a holonomic robot's everything). Evidence for the heading hypotheses of a moving track
    # (:func:`~gtsjax.core.g_heading.motion_evidence`); κ = 0 for a class that learnt none; None: no
    # class did.
    motion_heading: Float[Array, "classes 3"] | None = None

    def off(self, class_id, pose):
        """``pose`` [..., 3] of tracks of ``class_id`` [...] with their class's ``pose_offset`` taken off:
        moved back along the track's own axes (its heading first turned back by the heading's part).
        On the rows, with the track's heading, not on each detection: a detection read on the wrong
        side would move by twice the offset the wrong way (docs/accuracy.md)."""
        if self.pose_offset is None:
            return pose
        o = self.pose_offset[jnp.clip(class_id, 0, self.pose_offset.shape[0] - 1)]
        back = compose(pose, relative(o, jnp.zeros_like(o)))  # the offset's inverse, in the row's own frame
        return jnp.concatenate([back[..., :2], wrap(back[..., 2:])], axis=-1)

    def widened(self, class_id, var):
        """``var`` [..., 3] (var_x, var_y, var_theta) of tracks of ``class_id`` [...] with their class's
        ``var_floor`` added. The filter's variance is that of noise it averages away; a view's error is
        mostly its bias, the same scan after scan (docs/accuracy.md), which the filter's variance
        shrinks past: a floor, not a factor, stands for it."""
        if self.var_floor is None:
            return var
        f = self.var_floor[jnp.clip(class_id, 0, self.var_floor.shape[0] - 1)]
        return var + jnp.stack([f[..., 0], f[..., 0], f[..., 1]], axis=-1).astype(var.dtype)

    def with_row_corrections(self, offset=None, floor=None) -> "TrackerParams":
        """This tracker with both row corrections as arrays: ``offset`` (``pose_offset`` [classes, 3])
        and ``floor`` (``var_floor`` [classes, 2]) where given, zeros where not, which leave the rows
        as they are (to the last bit of a heading's wrap; :meth:`off`, :meth:`widened`). ``None`` and
        an array are two tree structures, so two compiled programs of every form of the step: training
        fills both before its tracking check and keeps them, so the model checked and the model saved
        share them (a batch chunk of the whole step is some 10 s of compiling on 2 cores)."""
        n = self.tracked.shape[0]
        offset = jnp.zeros((n, 3), jnp.float32) if offset is None else jnp.asarray(offset, jnp.float32)
        floor = jnp.zeros((n, 2), jnp.float32) if floor is None else jnp.asarray(floor, jnp.float32)
        return eqx.tree_at(lambda t: (t.pose_offset, t.var_floor), self, (offset, floor), is_leaf=lambda x: x is None)

    @classmethod
    def default(
        cls,
        tracked,
        *,
        rate_hz: float = 10.0,
        gate: float = 13.82,
        max_speed=DEFAULT_MAX_SPEED,
        max_turn_rate=DEFAULT_MAX_TURN_RATE,
        **overrides,
    ) -> "TrackerParams":
        """Defaults for a scanner at ``rate_hz``: confirmation after 0.5 s of hits (at least 3; a
        piece of clutter that looks like a robot for a moment, or a leg standing still between two
        strides, does not make a track), deletion of a confirmed
        track after 1 s without detections, of a tentative one after 0.3 s, reported while it has
        missed less than 0.3 s; position gate
        χ²₂(0.999) = 13.82, heading gate χ²₁(0.999) = 10.83, heading evidence fading over 1 s (a wrong
        heading is given up within about a second); turn-rate noise ``q_theta`` 0.02 rad²/s³ where
        nothing says otherwise (with the 0.5 of before, a few scans without a detection left a heading
        so uncertain that a misread passed its gate and took it; chosen on simulated seeds 3001–3004,
        not the README's; training learns it from the labels' motion, ``train.motion.turn_rate_noise``); speed at most 0.6 m/s (a Nao walks at most about
        0.35 m/s) and turn rate at most 3 rad/s (a humanoid turns at about 1 rad/s, a wheeled robot
        faster). ``max_speed`` and ``max_turn_rate`` are one value for every class or one per class."""
        tracked = jnp.asarray(tracked, dtype=bool)
        vals = dict(
            q_pos=0.05,
            q_theta=0.02,
            vel_var0=0.25,
            omega_var0=1.0,
            gate=jnp.full(tracked.shape, gate),
            heading_gate=10.83,
            heading_memory=1.0,
            max_speed=jnp.broadcast_to(jnp.asarray(max_speed, _F32), tracked.shape),
            max_turn_rate=jnp.broadcast_to(jnp.asarray(max_turn_rate, _F32), tracked.shape),
            tracked=tracked,
            n_confirm=max(3, round(0.5 * rate_hz)),
            m_tentative=max(1, round(0.3 * rate_hz)),
            m_delete=max(2, round(1.0 * rate_hz)),
            m_report=max(1, round(0.3 * rate_hz)),
            birth_exclusion=0.25,
            constant_velocity=True,
        )
        vals.update(overrides)
        ints = {"n_confirm", "m_tentative", "m_delete", "m_report"}
        return cls(
            **{
                k: (
                    jnp.asarray(v, jnp.int32)
                    if k in ints
                    else jnp.asarray(v, bool)
                    if k in ("tracked", "constant_velocity")
                    else jnp.asarray(v, _F32)
                )
                for k, v in vals.items()
            }
        )


class TrackerState(eqx.Module):
    """``M`` track slots; a slot is in use where ``live``."""

    mean: Float[Array, "tracks 6"]
    cov: Float[Array, "tracks 6 6"]
    class_id: Int[Array, " tracks"]
    track_id: Int[Array, " tracks"]
    live: Bool[Array, " tracks"]
    confirmed: Bool[Array, " tracks"]
    hits: Int[Array, " tracks"]  # detections since birth or since the last implausible scan
    misses: Int[Array, " tracks"]  # consecutive scans without a detection
    contrary: Int[Array, " tracks"]  # while tentative: scans with no detection but an ``other`` candidate near
    side_heading: Float[Array, "tracks sides"]  # the heading hypotheses (see :mod:`~gtsjax.core.g_track`)
    side_var: Float[Array, "tracks sides"]  # their variances
    side_logw: Float[Array, "tracks sides"]  # their log-weights, normalised with the rest's; -inf: unused
    side_rest: Float[Array, " tracks"]  # the log-weight of a heading none of them is (uniform)
    main: Int[Array, " tracks"]  # the hypothesis the state's heading is
    next_id: Int[Array, ""]
    # Each track's posterior over the robot identities of the tags (:mod:`.g_identity`), normalised log
    # probabilities; None: the model reads no tags.
    id_logp: Float[Array, "tracks ids"] | None = None

    @classmethod
    def empty(cls, max_tracks: int, sides: int = SIDES, ids: int = 0) -> "TrackerState":
        m = max_tracks
        return cls(
            mean=jnp.zeros((m, NX), _F32),
            cov=jnp.broadcast_to(jnp.eye(NX, dtype=_F32), (m, NX, NX)),
            class_id=jnp.zeros(m, jnp.int32),
            track_id=jnp.full(m, -1, jnp.int32),
            live=jnp.zeros(m, bool),
            confirmed=jnp.zeros(m, bool),
            hits=jnp.zeros(m, jnp.int32),
            misses=jnp.zeros(m, jnp.int32),
            contrary=jnp.zeros(m, jnp.int32),
            side_heading=jnp.zeros((m, sides), _F32),
            side_var=jnp.ones((m, sides), _F32),
            side_logw=jnp.full((m, sides), -jnp.inf, _F32).at[:, 0].set(jnp.log1p(-_REST_P)),
            side_rest=jnp.full(m, jnp.log(_REST_P), _F32),
            main=jnp.zeros(m, jnp.int32),
            next_id=jnp.asarray(0, jnp.int32),
            id_logp=jnp.full((m, ids), -jnp.log(jnp.asarray(ids, _F32)), _F32) if ids else None,
        )


class Detections(eqx.Module):
    """Pose observations in O for one scan: ``K`` slots, used where ``mask``. Where ``other``, the slot
    is instead a candidate that is not a detection of a tracked class (background, rejected by the
    classifier, a landmark, another class, outside the bounds), whose position in O is in ``pose``: it
    counts against the confirmation of a tentative track it lies near (see :mod:`~gtsjax.core.g_track`).
    ``None``: no such candidates. Where ``partial``, the detection is of a class that is seen whole
    (``Envelope.whole``) but is occluded at an end: it may update a confirmed track, never start or
    confirm one (``None``: none is partial). Where ``vague``, the detection's heading variance is above
    its class's ``heading_var_max`` (``train.calibrate``): it updates a track's position only, and its
    heading neither supports nor rejects the track's (``None``: none is vague). Where ``guess``, the
    candidate was not classified as the class but could be it (``d_classify.classify``): like a partial
    view it may update a confirmed track, never start or confirm one, and only within ``GUESS_RADIUS``
    of its prediction; it is never recaptured (``None``: none is a guess)."""

    pose: Float[Array, "dets 3"]
    cov: Float[Array, "dets 3 3"]
    class_id: Int[Array, " dets"]
    mask: Bool[Array, " dets"]
    other: Bool[Array, " dets"] | None = None
    partial: Bool[Array, " dets"] | None = None
    vague: Bool[Array, " dets"] | None = None
    # The side hypotheses of each detection (stage e′): pose in O and log-probability per side (-inf
    # where unused). ``None``: one side, ``pose``.
    side_pose: Float[Array, "dets sides 3"] | None = None
    side_logp: Float[Array, "dets sides"] | None = None
    guess: Bool[Array, " dets"] | None = None
    # Each detection's log-likelihood of each robot identity from its tag (:mod:`.e_tags`; all 0 where
    # unreadable). ``None``: the model reads no tags.
    tag_ll: Float[Array, "dets ids"] | None = None


class TrackHolds(eqx.Module):
    """Per track slot after a scan, why it is not (yet) confirmed and its estimated motion
    (:func:`~gtsjax.core.g_track.track_step` with ``explain=True``)."""

    hold: Int[Array, " tracks"]  # an index into ``HOLDS``
    speed: Float[Array, " tracks"]  # |v̂|, m/s (0 for a free slot or a track born in this scan)
    turn_rate: Float[Array, " tracks"]  # |ω̂| before clipping at the class's limit, rad/s (0 likewise)


def _select(values: Array, index: Int[Array, "..."]) -> Array:
    """``values[..., index]`` along the last axis (a few entries: sides, classes) as a chain of selects,
    ``values`` broadcast against ``index``: elementwise, so that it fuses into its consumers where a
    gather is a kernel of its own. ``index`` is within range."""
    out = jnp.broadcast_to(values[..., 0], jnp.broadcast_shapes(values.shape[:-1], index.shape))
    for c in range(1, values.shape[-1]):
        out = jnp.where(index == c, values[..., c], out)
    return out


def detection_sides(det: "Detections", sides: int) -> tuple[Float[Array, "dets sides 3"], Float[Array, "dets sides"]]:
    """A detection's side poses and log-probabilities; a detection without them has one side, its pose.
    (The tracker reads the sides' headings; their positions are the detection's, ``e_refine.refine``.)"""
    if det.side_pose is not None and det.side_logp is not None:
        return det.side_pose, det.side_logp
    k = det.pose.shape[0]
    logp = jnp.full((k, sides), -jnp.inf, det.pose.dtype).at[:, 0].set(0.0)
    return jnp.broadcast_to(det.pose[:, None, :], (k, sides, 3)), logp


class DetectionFlags(NamedTuple):
    """What each detection slot is, and so what it may do to a track (see :class:`Detections`): the
    optional fields read as all false where absent, so that one step serves every caller."""

    tracked: Bool[Array, " dets"]  # a detection of a tracked class
    partial: Bool[Array, " dets"]
    guess: Bool[Array, " dets"]
    vague: Bool[Array, " dets"]
    other: Bool[Array, " dets"]
    whole: Bool[Array, " dets"]  # neither partial nor a guess: may start and confirm a track

    @classmethod
    def of(cls, det: Detections, params: TrackerParams) -> "DetectionFlags":
        no = jnp.zeros(det.mask.shape, bool)
        partial = no if det.partial is None else det.partial
        guess = no if det.guess is None else det.guess
        return cls(
            tracked=det.mask & _select(params.tracked, det.class_id),
            partial=partial,
            guess=guess,
            vague=no if det.vague is None else det.vague,
            other=no if det.other is None else det.other,
            whole=~(partial | guess),
        )


class DetectionRows(NamedTuple):
    """One detection's values per row (per track, or per new track): :meth:`DetectionTable.rows`."""

    pose: Float[Array, "n 3"]
    cov: Float[Array, "n 3 3"]
    side_heading: Float[Array, "n zsides"]
    side_logp: Float[Array, "n zsides"]
    partial: Bool[Array, " n"]
    vague: Bool[Array, " n"]
    class_id: Int[Array, " n"]


class DetectionTable(NamedTuple):
    """Every per-detection value a track reads, in one table (pose, covariance, side headings and
    log-probabilities, partial, vague, class), so that the detections of the tracks (and of the new
    tracks) are one gather each, not one per array."""

    values: Float[Array, "dets columns"]
    sides: int  # the detections' sides (columns of side headings, and of log-probabilities)

    @classmethod
    def of(cls, det: Detections, flags: DetectionFlags, sides: int) -> "DetectionTable":
        """The table of ``det``, whose detections without sides get ``sides`` (one used)."""
        side_pose, side_logp = detection_sides(det, sides)
        k = det.mask.shape[0]
        bits = jnp.stack([flags.partial, flags.vague], -1)
        values = jnp.concatenate(
            [
                det.pose,
                det.cov.reshape(k, 9),
                side_pose[..., 2],
                side_logp,
                bits.astype(det.pose.dtype),
                det.class_id.astype(det.pose.dtype)[:, None],
            ],
            -1,
        )
        return cls(values, side_logp.shape[1])

    def rows(self, idx: Int[Array, " n"]) -> DetectionRows:
        """The detections ``idx``, one row each."""
        t, n = self.values[idx], self.sides
        o = 12 + 2 * n
        return DetectionRows(
            t[:, :3],
            t[:, 3:12].reshape(-1, 3, 3),
            t[:, 12 : 12 + n],
            t[:, 12 + n : o],
            t[:, o] > 0,
            t[:, o + 1] > 0,
            t[:, o + 2].astype(jnp.int32),
        )
