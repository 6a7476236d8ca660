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
position-only. A rejected heading also discards the turn-rate estimate (``ω = 0`` with its initial
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
detection side as a one-dimensional Kalman update where it passes the heading gate. Under the rest,
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
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .e_refine import SIDES
from .geometry import wrap

_F32 = jnp.float32
NX = 6  # x, y, theta, vx, vy, omega


# Defaults of the per-class motion limits (see the module docstring): m/s and rad/s.
DEFAULT_MAX_SPEED = 0.6
DEFAULT_MAX_TURN_RATE = 3.0
# How many standard deviations of its own estimate a track's speed or turn rate may exceed its
# class's limit by before its motion counts as implausible: one-sided, a robot at exactly its limit
# is flagged in at most 2.3 % of scans by a calibrated estimate (fewer with the upper bound on σ_v
# used, and the errors of consecutive scans are correlated, not independent trials), while a leg
# at twice the limit is flagged once σ_v is below half the limit (2 m > m + 2 σ_v), three or four scans.
_PLAUSIBLE_SIGMAS = 2.0

# Why a live track slot is not confirmed after a scan (``TrackHolds.hold``, ``Output.track_hold``: an
# index into this): "none" for a confirmed slot or a free one; "speed" where its motion failed
# :func:`plausible`'s speed test in this scan, "turn rate" where it failed the turn-rate test (and not
# the speed test); "majority" where it has its ``n_confirm`` hits but no more of them than ``contrary``
# scans; "too few scans" otherwise (fewer than ``n_confirm`` hits since its birth or its last
# implausible scan). For the host's diagnosis of a run (:mod:`gtsjax.drivers.diagnose`).
HOLDS = ("none", "too few scans", "majority", "speed", "turn rate")


class TrackerParams(eqx.Module):
    """Tuning of the tracker. All arrays, so that changing a value does not recompile the step.

    ``max_speed`` and ``max_turn_rate`` are per class (defaults ``DEFAULT_MAX_SPEED`` = 0.6 m/s and
    ``DEFAULT_MAX_TURN_RATE`` = 3 rad/s for every class): a track whose estimated motion exceeds its
    class's limits by more than twice the estimate's standard deviation is not confirmed, or loses its
    confirmation (see the module docstring)."""

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

    @classmethod
    def default(cls, tracked, *, rate_hz: float = 10.0, gate: float = 13.82, max_speed=DEFAULT_MAX_SPEED,
                max_turn_rate=DEFAULT_MAX_TURN_RATE, **overrides) -> "TrackerParams":
        """Defaults for a scanner at ``rate_hz``: confirmation after 0.5 s of hits (at least 3; a
        piece of clutter that looks like a robot for a moment, or a leg standing still between two
        strides, does not make a track), deletion of a confirmed
        track after 1 s without detections, of a tentative one after 0.3 s, reported while it has
        missed less than 0.3 s; position gate
        χ²₂(0.999) = 13.82, heading gate χ²₁(0.999) = 10.83, heading evidence fading over 1 s (a wrong
        heading is given up within about a second); turn-rate noise ``q_theta`` 0.02 rad²/s³ (the turn
        rate of a robot changes slowly: with the 0.5 of before, a few scans without a detection left a
        heading so uncertain that a misread passed its gate and took it; chosen on simulated seeds
        3001–3004, not the README's); speed at most 0.6 m/s (a Nao walks at most about
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
        return cls(**{
            k: (jnp.asarray(v, jnp.int32) if k in ints else jnp.asarray(v, bool) if k in ("tracked", "constant_velocity")
                else jnp.asarray(v, _F32))
            for k, v in vals.items()
        })


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
    side_heading: Float[Array, "tracks sides"]  # the heading hypotheses (see the module docstring)
    side_var: Float[Array, "tracks sides"]  # their variances
    side_logw: Float[Array, "tracks sides"]  # their log-weights, normalised with the rest's; -inf: unused
    side_rest: Float[Array, " tracks"]  # the log-weight of a heading none of them is (uniform)
    main: Int[Array, " tracks"]  # the hypothesis the state's heading is
    next_id: Int[Array, ""]

    @classmethod
    def empty(cls, max_tracks: int, sides: int = SIDES) -> "TrackerState":
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
        )


class Detections(eqx.Module):
    """Pose observations in O for one scan: ``K`` slots, used where ``mask``. Where ``other``, the slot
    is instead a candidate that is not a detection of a tracked class (background, rejected by the
    classifier, a landmark, another class, outside the bounds), whose position in O is in ``pose``: it
    counts against the confirmation of a tentative track it lies near (see the module docstring).
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


def _select(values: Array, index: Int[Array, "..."]) -> Array:
    """``values[..., index]`` along the last axis (a few entries: sides, classes) as a chain of selects,
    ``values`` broadcast against ``index``: elementwise, so that it fuses into its consumers where a
    gather is a kernel of its own. ``index`` is within range."""
    out = jnp.broadcast_to(values[..., 0], jnp.broadcast_shapes(values.shape[:-1], index.shape))
    for c in range(1, values.shape[-1]):
        out = jnp.where(index == c, values[..., c], out)
    return out


def motion_model(dt: Float[Array, ""], params: TrackerParams) -> tuple[Float[Array, "6 6"], Float[Array, "6 6"]]:
    """Transition ``F`` and process noise ``Q`` over ``dt`` seconds.

    Constant velocity: per axis ``F = [[1, dt], [0, 1]]`` and ``Q = q [[dt³/3, dt²/2], [dt²/2, dt]]``.
    Inflate-only (the paper's): ``F = I`` and ``Q = q dt`` on the pose, velocities untouched.
    """
    z3, i3 = jnp.zeros((3, 3), _F32), jnp.eye(3, dtype=_F32)
    q = jnp.stack([params.q_pos, params.q_pos, params.q_theta])
    F_cv = jnp.block([[i3, dt * i3], [z3, i3]])
    Q_cv = jnp.block([
        [jnp.diag(q * dt**3 / 3), jnp.diag(q * dt**2 / 2)],
        [jnp.diag(q * dt**2 / 2), jnp.diag(q * dt)],
    ])
    F_in = jnp.eye(NX, dtype=_F32)
    Q_in = jnp.block([[jnp.diag(q * dt), z3], [z3, z3]])
    cv = params.constant_velocity
    return jnp.where(cv, F_cv, F_in), jnp.where(cv, Q_cv, Q_in)


def predict(state: TrackerState, dt: Float[Array, ""], params: TrackerParams) -> TrackerState:
    """Time update of every slot (dead slots too: they are masked everywhere else and stay finite)."""
    F, Q = motion_model(dt, params)
    mean = jnp.einsum("ij,mj->mi", F, state.mean)
    mean = jnp.where(jnp.arange(NX, dtype=jnp.int32) == 2, wrap(mean), mean)
    cov = jnp.einsum("ij,mjk,lk->mil", F, state.cov, F) + Q[None]
    # The heading hypotheses turn with the state's heading, and grow as uncertain as it does.
    turn = mean[:, 2:3] - state.mean[:, 2:3]
    side_heading = wrap(state.side_heading + wrap(turn))
    side_var = state.side_var + (cov[:, 2:3, 2] - state.cov[:, 2:3, 2])
    return eqx.tree_at(lambda s: (s.mean, s.cov, s.side_heading, s.side_var), state,
                       (mean, cov, side_heading, side_var))


def innovation(mean: Float[Array, "6"], cov: Float[Array, "6 6"], z: Float[Array, "3"], R: Float[Array, "3 3"]):
    """Innovation (heading wrapped) and its covariance ``S = H P Hᵀ + R`` with ``H = [I₃ 0]``."""
    nu = z - mean[:3]
    nu = nu.at[2].set(wrap(nu[2]))
    S = cov[:3, :3] + R
    return nu, S


def inv3(S: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3 3"]:
    """Inverse of a symmetric positive definite 3×3 matrix by its adjugate: a handful of multiplies,
    where a general LU solve on such small batched matrices dominates the step's cost."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    d, e, f = S[..., 1, 1], S[..., 1, 2], S[..., 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    det = a * A + b * B + c * C
    adj = jnp.stack([jnp.stack([A, B, C], -1), jnp.stack([B, D, E], -1), jnp.stack([C, E, F], -1)], -2)
    return adj / det[..., None, None]


def inv2(S: Float[Array, "2 2"]) -> Float[Array, "2 2"]:
    """Inverse of a symmetric positive definite 2×2 matrix."""
    a, b, d = S[0, 0], S[0, 1], S[1, 1]
    return jnp.stack([jnp.stack([d, -b]), jnp.stack([-b, a])]) / (a * d - b * b)


def mahalanobis(mean, cov, z, R) -> Float[Array, ""]:
    """Squared Mahalanobis distance of a detection's position from a track's (2 dof): association
    ignores the heading, which a misread side of the robot can throw off by 90° or more."""
    nu, S = innovation(mean, cov, z, R)
    return nu[:2] @ inv2(S[:2, :2]) @ nu[:2]


def heading_consistent(mean, cov, z, R, gate) -> Bool[Array, ""]:
    """Whether a detection's heading agrees with the track's: ``ν_θ² / S_θθ ≤ gate`` (1 dof)."""
    nu, S = innovation(mean, cov, z, R)
    return nu[2] ** 2 <= gate * S[2, 2]


def _mm(a, b):
    """``a @ b`` over the last two axes (batched, broadcast) as a sum of outer products, one per index
    of the contracted axis: elementwise, so XLA fuses it with its neighbours instead of running a dot."""
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for c in range(1, a.shape[-1]):
        out = out + a[..., :, c:c + 1] * b[..., c:c + 1, :]
    return out


def kalman_update(mean: Float[Array, "*#b 6"], cov: Float[Array, "*#b 6 6"], z: Float[Array, "*#b 3"],
                  R: Float[Array, "*#b 3 3"], use_heading: Bool[Array, "*#b"] | bool = True):
    """Measurement update with ``H = [I₃ 0]``: gain ``K = P Hᵀ S⁻¹``, Joseph-form covariance
    ``(I − KH) P (I − KH)ᵀ + K R Kᵀ``, which stays symmetric positive definite in float32.

    With ``use_heading`` False the update is position-only (``H = [I₂ 0]``): the heading row of the
    gain is zero, which is the 3-row update with the heading's innovation zeroed and the heading's
    row and column of ``S⁻¹`` removed.

    Batched over leading axes (broadcast against each other), in whole-array form: the products with
    ``H`` are the first three rows or columns, ``(I − KH) P = P − K P₃`` and ``A (I − KH)ᵀ = A − A₃ Kᵀ``,
    each product a sum of three outer products."""
    i3 = jnp.arange(3, dtype=jnp.int32)
    i6 = jnp.arange(NX, dtype=jnp.int32)
    nu = z - mean[..., :3]
    nu = jnp.where(i3 == 2, wrap(nu), nu)
    S = cov[..., :3, :3] + R
    a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
    zero = jnp.zeros_like(a)
    pos_only = jnp.stack([jnp.stack([d, -b, zero], -1), jnp.stack([-b, a, zero], -1),
                          jnp.stack([zero, zero, zero], -1)], -2) / (a * d - b * b)[..., None, None]
    s_inv = jnp.where(jnp.asarray(use_heading)[..., None, None], inv3(S), pos_only)
    K = _mm(cov[..., :, :3], s_inv)  # S is symmetric
    mean = mean + _mm(K, nu[..., :, None])[..., 0]
    mean = jnp.where(i6 == 2, wrap(mean), mean)
    A = cov - _mm(K, cov[..., :3, :])
    Kt = jnp.swapaxes(K, -1, -2)
    cov = A - _mm(A[..., :, :3], Kt) + _mm(_mm(K, R), Kt)
    return mean, 0.5 * (cov + jnp.swapaxes(cov, -1, -2))


def assign(cost: Float[Array, "dets tracks"], fallback: Float[Array, "dets tracks"] | None = None
           ) -> tuple[Int[Array, " tracks"], Bool[Array, " tracks"]]:
    """Greedy one-to-one assignment on a cost matrix with ``inf`` for forbidden pairs, then, if
    ``fallback`` is given, greedy on ``fallback`` among the rows and columns left: for each track,
    the index of its detection and whether it has one.

    ``min(K, M)`` rounds, unrolled, each one XLA reduction: the first pair in the order (a finite
    ``cost`` before a finite ``fallback`` only, then the lower value, then the lower flat index, as
    ``argmin`` breaks ties) among the rows and columns no earlier round took (masks from iotas and
    the earlier rounds' picks, recomputed inside the reduction, so that no matrix is carried from
    round to round). Both passes fit in these rounds: the first takes finite costs while any is left
    among the free rows and columns, exactly as greedy on ``cost`` alone would (a fallback pair never
    comes before one), and once none is left the free rows and columns are the ones that pass leaves,
    where the rest is greedy on ``fallback``; each round that takes a pair takes a new track."""
    k, m = cost.shape
    fallback = jnp.full_like(cost, jnp.inf) if fallback is None else fallback
    rows = jnp.arange(k, dtype=jnp.int32)[:, None]
    cols = jnp.arange(m, dtype=jnp.int32)[None, :]
    flat = rows * m + cols
    inf = jnp.asarray(jnp.inf, cost.dtype)

    def first(a, b):  # of two pairs (cost, fallback, flat index), the one greedy takes first
        (ca, fa, ia), (cb, fb, ib) = a, b
        rank_a = jnp.where(ca < jnp.inf, 0, jnp.where(fa < jnp.inf, 1, 2))
        rank_b = jnp.where(cb < jnp.inf, 0, jnp.where(fb < jnp.inf, 1, 2))
        va, vb = jnp.where(rank_a == 0, ca, fa), jnp.where(rank_b == 0, cb, fb)
        a_first = (rank_a < rank_b) | ((rank_a == rank_b) & ((va < vb) | ((va == vb) & (ia < ib))))
        return tuple(jnp.where(a_first, x, y) for x, y in ((ca, cb), (fa, fb), (ia, ib)))

    det_of_track, has = jnp.zeros(m, jnp.int32), jnp.zeros(m, bool)
    taken = jnp.zeros((k, m), bool)
    init = (inf, inf, jnp.asarray(k * m, jnp.int32))
    for _ in range(min(k, m)):
        c, f, idx = jax.lax.reduce((jnp.where(taken, inf, cost), jnp.where(taken, inf, fallback), flat), init,
                                   first, (0, 1))
        i, j = idx // m, idx % m
        col = ((c < inf) | (f < inf)) & (cols[0] == j)
        det_of_track = jnp.where(col, i, det_of_track)
        has = has | col
        taken = taken | (rows == i) | (cols == j)  # a round that takes none leaves only forbidden pairs
    return det_of_track, has


# A detection's heading that none of its sides explains (a side the refinement did not try, a
# misread): its likelihood under any hypothesis is at least that of a uniform heading with this weight.
# It is also the share of the rest's weight that stays uniform after a read (see the module docstring).
_OUTLIER_P = 0.01
# The weight a new track gives to a heading none of its first detection's sides is.
_REST_P = 0.1
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


# A guess (``Detections.guess``) updates a track only within GUESS_RADIUS (m) of its predicted position,
# and only a track updated in at least one of the last GUESS_MISSES + 1 scans. A robot's position one
# scan ahead is predicted to a centimetre or two (the prediction carries its velocity); a person's legs
# in front of a hidden robot, or a box beside it, fit its outline as well but lie further off, and a
# track that has coasted longer has lost the position that would tell them apart. (On the simulated
# person walking across the SPL field, spl-legs, the track's gate alone let the legs pull a hidden
# robot's track 10-20 cm off, 1.9 cm position RMSE for 1.2; with this radius it is 1.2 again. A robot
# walking past a box that looks like its side must be bridged over a scan or two in which its guess
# failed the outline fit: one scan was too few, its walk reported in 86 % of scans.)
GUESS_RADIUS = 0.03
GUESS_MISSES = 2


def detection_sides(det: "Detections", sides: int) -> tuple[Float[Array, "dets sides 3"], Float[Array, "dets sides"]]:
    """A detection's side poses and log-probabilities; a detection without them has one side, its pose.
    (The tracker reads the sides' headings; their positions are the detection's, ``e_refine.refine``.)"""
    if det.side_pose is not None and det.side_logp is not None:
        return det.side_pose, det.side_logp
    k = det.pose.shape[0]
    logp = jnp.full((k, sides), -jnp.inf, det.pose.dtype).at[:, 0].set(0.0)
    return jnp.broadcast_to(det.pose[:, None, :], (k, sides, 3)), logp


def side_evidence(heading: Float[Array, "tracks sides"], var: Float[Array, "tracks sides"],
                  z: Float[Array, "tracks zsides"], z_logp: Float[Array, "tracks zsides"], r: Float[Array, " tracks"]):
    """The evidence of one detection per track for each of its heading hypotheses, ``log p(z | j) =
    log Σ_h p(h) N(z_h; φ_j, σ_j² + r)`` over the detection's sides ``h`` (with a floor, ``_OUTLIER_P``
    of a uniform heading); for each hypothesis the detection side nearest it, the innovation and its
    variance, and the squared normalised innovation."""
    nu = wrap(z[:, None, :] - heading[:, :, None])  # [M, j, h]
    S = var[:, :, None] + r[:, None, None]
    d2 = nu**2 / S
    usable = jnp.isfinite(z_logp)[:, None, :]
    ll = jnp.where(usable, z_logp[:, None, :] - 0.5 * d2 - 0.5 * jnp.log(2 * jnp.pi * S), -jnp.inf)
    ev = jnp.logaddexp(jax.nn.logsumexp(ll, axis=-1), jnp.log(_OUTLIER_P / (2 * jnp.pi)))
    near = jnp.argmin(jnp.where(usable, d2, jnp.inf), axis=-1).astype(jnp.int32)  # [M, j]
    return ev, near, _select(nu, near), S[..., 0], _select(d2, near)  # S is the same for every side h


def heading_mixture(state: TrackerState, ev, nu, S, d2, seen, z_best, r, dt, params: TrackerParams):
    """Weights and headings of every track's hypotheses after this scan's evidence (see the module
    docstring): the log-weights (the rest's too) fade towards uniform over ``heading_memory`` and add
    the evidence; each hypothesis but the main one within the heading gate of its nearest detection side
    takes it as a one-dimensional Kalman update; the rest's share of the read goes to the hypothesis that explains
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
    # state's gate and turn-rate test), written back after it.
    upd = seen[:, None] & used & (d2 <= params.heading_gate) & (side != state.main[:, None])
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


def merge_duplicates(heading: Float[Array, "tracks sides"], lw: Float[Array, "tracks sides"],
                     main: Int[Array, " tracks"]) -> Float[Array, "tracks sides"]:
    """Log-weights after merging hypotheses within ``_MERGE`` of each other (a fixed angle: variances
    grown through missed scans would merge distinct hypotheses): each one that another outranks (the
    main one outranks all, then the heavier, then the first) gives its weight to the highest-ranked of
    those and becomes unused (``-inf``). The survivor keeps its heading and variance."""
    used = jnp.isfinite(lw)
    n = lw.shape[1]
    idx = jnp.arange(n, dtype=jnp.int32)
    close = (used[:, :, None] & used[:, None, :] & (idx[:, None] != idx[None, :])[None]
             & (jnp.abs(wrap(heading[:, :, None] - heading[:, None, :])) < _MERGE))
    rank = jnp.where(idx[None, :] == main[:, None], jnp.inf, lw)  # [M, j]
    above = (rank[:, :, None] > rank[:, None, :]) | ((rank[:, :, None] == rank[:, None, :]) & (idx[:, None] < idx[None, :])[None])
    over = close & above  # [M, j, k]: j outranks its near-duplicate k
    dropped = jnp.any(over, axis=1)  # [M, k]
    into = jnp.argmax(jnp.where(over, rank[:, :, None], -jnp.inf), axis=1).astype(jnp.int32)  # [M, k]: the top one outranking k
    gets = over & (idx[None, :, None] == into[:, None, :])  # [M, j, k]
    add = jax.nn.logsumexp(jnp.where(gets, lw[:, None, :], -jnp.inf), axis=-1)  # [M, j]
    return jnp.where(dropped, -jnp.inf, jnp.logaddexp(lw, add))


class TrackHolds(eqx.Module):
    """Per track slot after a scan, why it is not (yet) confirmed and its estimated motion
    (:func:`track_step` with ``explain=True``)."""

    hold: Int[Array, " tracks"]  # an index into ``HOLDS``
    speed: Float[Array, " tracks"]  # |v̂|, m/s (0 for a free slot or a track born in this scan)
    turn_rate: Float[Array, " tracks"]  # |ω̂| before clipping at the class's limit, rad/s (0 likewise)


def plausible(mean: Float[Array, "tracks 6"], cov: Float[Array, "tracks 6 6"], omega: Float[Array, " tracks"],
              class_id: Int[Array, " tracks"], params: TrackerParams) -> Bool[Array, " tracks"]:
    """Whether each track's motion is one its class can make: both tests of :func:`plausible_parts`."""
    speed_ok, turn_ok = plausible_parts(mean, cov, omega, class_id, params)
    return speed_ok & turn_ok


def plausible_parts(mean: Float[Array, "tracks 6"], cov: Float[Array, "tracks 6 6"], omega: Float[Array, " tracks"],
                    class_id: Int[Array, " tracks"], params: TrackerParams
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


def plausible_turn(omega: Float[Array, " tracks"], cov: Float[Array, "tracks 6 6"], class_id: Int[Array, " tracks"],
                   params: TrackerParams) -> Bool[Array, " tracks"]:
    """The turn-rate half of :func:`plausible`: ``|ω| ≤ max_turn_rate + 2 σ_ω``."""
    sigma_w = jnp.sqrt(jnp.maximum(cov[:, 5, 5], 0.0))
    return jnp.abs(omega) <= _select(params.max_turn_rate, class_id) + _PLAUSIBLE_SIGMAS * sigma_w


def _count_up_to(x: Bool[Array, " n"]) -> Int[Array, " n"]:
    """``cumsum(x)`` as counts over a triangular mask: one reduction that fuses its inputs, where a
    cumulative sum is a chain of reduce-windows."""
    i = jnp.arange(x.shape[0], dtype=jnp.int32)
    return jnp.sum(x[None, :] & (i[None, :] <= i[:, None]), axis=1, dtype=jnp.int32)


def reported(state: TrackerState, params: TrackerParams, watchers: Int[Array, " tracks"] | None = None
             ) -> Bool[Array, " tracks"]:
    """Tracks to report: confirmed, and observed within the last ``m_report`` scans (of each of the
    ``watchers`` lasers that can see the track, where several do: see :func:`track_step`)."""
    m_report = params.m_report if watchers is None else params.m_report * watchers
    return state.live & state.confirmed & (state.misses < m_report)


def track_step(
    state: TrackerState, det: Detections, dt: Float[Array, ""], params: TrackerParams, period: float | None = None,
    visible: Bool[Array, " tracks"] | None = None, span_dt: Float[Array, ""] | None = None,
    watchers: Int[Array, " tracks"] | None = None, explain: bool = False,
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
    d2 = jax.vmap(lambda z, R: jax.vmap(lambda mu, P: mahalanobis(mu, P, z, R))(state.mean, state.cov))(
        det.pose, det.cov
    )  # [K, M]
    tracked_det = det.mask & _select(params.tracked, det.class_id)
    # A partial detection (an occluded view of a class seen whole) only follows a confirmed track.
    # So does a guess (a candidate the classifier took for something else), near its prediction only.
    no = jnp.zeros(det.mask.shape, bool)
    guess = no if det.guess is None else det.guess
    partial = no if det.partial is None else det.partial
    whole = ~(partial | guess)
    may_update = whole[:, None] | state.confirmed[None, :]  # [K, M]
    dist = jnp.linalg.norm(det.pose[:, None, :2] - state.mean[None, :, :2], axis=-1)  # [K, M]
    # A guess only keeps a track that was updated in the scan before where it is predicted: within
    # GUESS_RADIUS, not the gate a coasting track's grown covariance opens (a person's legs in front
    # of a hidden robot fit its outline too).
    near_prediction = ~guess[:, None] | ((dist < GUESS_RADIUS) & (state.misses <= GUESS_MISSES)[None, :])
    gated = (
        tracked_det[:, None]
        & may_update
        & near_prediction
        & state.live[None, :]
        & (det.class_id[:, None] == state.class_id[None, :])
        & (d2 <= _select(params.gate, det.class_id)[:, None])
    )
    # Recapture: a detection too close to a live track of its class to start one of its own
    # (``birth_exclusion``) goes to that track, nearest first, if both are left unmatched by the
    # gated assignment, whatever the gate says: the fallback pass of the same assignment.
    close = (
        (tracked_det & ~guess)[:, None] & may_update & state.live[None, :]
        & (det.class_id[:, None] == state.class_id[None, :])
        & (dist < params.birth_exclusion)
    )
    det_of_track, has = assign(jnp.where(gated, d2, jnp.inf), jnp.where(close, dist, jnp.inf))
    # The detections taken (one-hot against an iota, not a scatter).
    used = jnp.any(has[None, :] & (det_of_track[None, :] == jnp.arange(det.mask.shape[0], dtype=jnp.int32)[:, None]), axis=1)
    # Majority confirmation: an ``other`` candidate near a track's predicted position (the same
    # distances), counted below for tentative tracks left without a detection.
    other = jnp.zeros(det.mask.shape, bool) if det.other is None else det.other
    other_near = jnp.any(other[:, None] & (dist < params.birth_exclusion), axis=0)  # [M]

    # Every per-detection value a track reads, in one table, so that the detections of the tracks
    # (and below, of the new tracks) are one gather each, not one per array.
    side_pose, side_logp = detection_sides(det, state.side_heading.shape[1])
    k, n_sides = det.mask.shape[0], side_logp.shape[1]
    flags = jnp.stack([partial, no if det.vague is None else det.vague], -1)
    table = jnp.concatenate([det.pose, det.cov.reshape(k, 9), side_pose[..., 2], side_logp,
                             flags.astype(det.pose.dtype), det.class_id.astype(det.pose.dtype)[:, None]], -1)

    def rows(idx):  # pose, covariance, side headings and log-probabilities, partial, vague, class
        t = table[idx]
        o = 12 + 2 * n_sides
        return (t[:, :3], t[:, 3:12].reshape(-1, 3, 3), t[:, 12:12 + n_sides], t[:, 12 + n_sides:o], t[:, o] > 0,
                t[:, o + 1] > 0, t[:, o + 2].astype(jnp.int32))

    z_pose, R, zs, zlp, z_partial, z_vague, _ = rows(det_of_track)  # zs, zlp: [M, sides]
    # A partial view's heading comes from a cut outline: it updates the position only, and neither
    # supports nor rejects the track's heading. So does a vague one: a heading read with a variance
    # that good reads of the class almost never have is more often a misread than not.
    seen = has & ~z_partial & ~z_vague
    # The heading hypotheses: evidence, weights, their own updates; the state's heading becomes the
    # most probable one where it wins clearly (its variance, no correlation with the rest of the state).
    ev, near, nu_h, S_h, d2_h = side_evidence(state.side_heading, state.side_var, zs, zlp, R[:, 2, 2])
    side_heading, side_var, side_logw, side_rest, main, switch = heading_mixture(
        state, ev, nu_h, S_h, d2_h, seen, z_pose[:, 2], R[:, 2, 2], dt, params)
    theta0 = jnp.where(switch, _select(state.side_heading, main), state.mean[:, 2])
    # Row and column 2 of the covariance (masks from iotas): the column is the row's (symmetric), and
    # where the heading switched, both are zero but for the hypothesis's variance.
    i6 = jnp.arange(NX, dtype=jnp.int32)
    row2, col2 = (i6 == 2)[None, :, None], (i6 == 2)[None, None, :]
    cov0 = jnp.where(col2 & ~row2, jnp.swapaxes(state.cov, 1, 2), state.cov)
    cov0 = jnp.where(switch[:, None, None] & (row2 | col2),
                     jnp.where(row2 & col2, _select(state.side_var, main)[:, None, None], 0.0), cov0)
    mean0 = jnp.where(i6 == 2, theta0[:, None], state.mean)
    # The measurement: the detection's position, and the heading of its side nearest the state's.
    z = jnp.concatenate([z_pose[:, :2], _select(zs, _select(near, main))[:, None]], -1)
    head_ok = jax.vmap(heading_consistent, in_axes=(0, 0, 0, 0, None))(mean0, cov0, z, R, params.heading_gate)
    # A confirmed track's heading that would turn it faster than its class can (``plausible``'s
    # turn-rate test on the updated estimate) is a misread, most often after a few scans without a
    # detection have widened the heading's gate: rejected like one that fails the gate.
    # Both candidate updates, with the heading and position-only, in one batched call (a leading axis
    # of two); each test selects one of them.
    both_mean, both_cov = kalman_update(mean0[None], cov0[None], z[None], R[None],
                                        (jnp.arange(2, dtype=jnp.int32) == 0)[:, None])
    pick = lambda ok: (jnp.where(ok[:, None], both_mean[0], both_mean[1]),  # noqa: E731
                       jnp.where(ok[:, None, None], both_cov[0], both_cov[1]))
    upd_mean, upd_cov = pick(head_ok & seen)
    turn_ok = plausible_turn(upd_mean[:, 5], upd_cov, state.class_id, params)
    head_ok = head_ok & (turn_ok | ~state.confirmed)
    upd_mean, upd_cov = pick(head_ok & seen)
    # A rejected heading discards a turn rate learnt from headings (see the module docstring). One
    # already discarded (its variance back at omega_var0 or above) is left as it is, with its
    # correlation to the heading: over consecutive rejections the heading's variance then grows with
    # the square of the time, as a turn at up to that rate would move it, not linearly, and a robot
    # that really turns is taken back within a few scans instead of being coasted past.
    forget = seen & ~head_ok & (cov0[:, 5, 5] < params.omega_var0)
    row5, col5 = (i6 == 5)[None, :, None], (i6 == 5)[None, None, :]
    upd_cov = jnp.where(forget[:, None, None] & (row5 | col5), jnp.where(row5 & col5, params.omega_var0, 0.0), upd_cov)
    omega_raw = jnp.where(forget, 0.0, upd_mean[:, 5])  # the turn rate before clipping, for plausible()
    turn_max = _select(params.max_turn_rate, state.class_id)
    upd_mean = jnp.where(i6 == 5, jnp.clip(omega_raw, -turn_max, turn_max)[:, None], upd_mean)
    mean = jnp.where(has[:, None], upd_mean, mean0)
    cov = jnp.where(has[:, None, None], upd_cov, cov0)
    # The state's heading is its main hypothesis: the hypothesis takes the state's update.
    onehot = jnp.arange(side_heading.shape[1], dtype=jnp.int32)[None, :] == main[:, None]
    side_heading = jnp.where(onehot, mean[:, 2:3], side_heading)
    side_var = jnp.where(onehot, cov[:, 2:3, 2], side_var)
    hits = state.hits + has.astype(jnp.int32)
    gap = dt if span_dt is None else span_dt
    spanned = jnp.ones((), jnp.int32) if period is None else jnp.maximum(
        jnp.round(gap / jnp.asarray(period, gap.dtype)), 1).astype(jnp.int32)
    if visible is not None:
        spanned = spanned * visible.astype(jnp.int32)
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
    w = jnp.ones((), jnp.int32) if watchers is None else watchers
    dead = state.live & jnp.where(confirmed, misses >= params.m_delete * w, misses >= params.m_tentative * w)
    live = state.live & ~dead

    # Births: the i-th free slot takes the i-th unused detection of a tracked class.
    dist = jnp.linalg.norm(det.pose[:, None, :2] - mean[None, :, :2], axis=-1)
    near_live = jnp.any(live[None, :] & (det.class_id[:, None] == state.class_id[None, :]) & (dist < params.birth_exclusion), 1)
    born_ok = tracked_det & ~used & ~near_live & whole
    # Nor may two detections of a class closer than that start two tracks in one scan (a robot seen
    # in two pieces): the first of them in slot order starts it.
    dd = jnp.linalg.norm(det.pose[:, None, :2] - det.pose[None, :, :2], axis=-1)  # [K, K]
    k = det.mask.shape[0]
    earlier = jnp.arange(k)[None, :] < jnp.arange(k)[:, None]  # [j, i]: i comes before j
    shadowed = jnp.any(earlier & born_ok[None, :] & (det.class_id[:, None] == det.class_id[None, :])
                       & (dd < params.birth_exclusion), axis=1)
    born_ok = born_ok & ~shadowed
    free = ~live
    rank_det = _count_up_to(born_ok) - 1
    rank_slot = _count_up_to(free) - 1
    match = free[:, None] & born_ok[None, :] & (rank_slot[:, None] == rank_det[None, :])  # [M, K]
    born = jnp.any(match, axis=1)
    src = jnp.argmax(match, axis=1)
    z0, P0_pose, new_sides, new_logp, _, _, new_class = rows(src)
    vel_diag = (i6[:, None] == i6[None, :]) & (i6 >= 3)[None, :]  # the velocities' and turn rate's variances
    P0 = jnp.where(vel_diag[None], jnp.where(i6 == 5, params.omega_var0, params.vel_var0)[None, None, :],
                   jnp.pad(P0_pose, ((0, 0), (0, NX - 3), (0, NX - 3))))
    mean0 = jnp.pad(z0, ((0, 0), (0, NX - 3)))
    n_born = jnp.sum(born).astype(jnp.int32)

    new = TrackerState(
        mean=jnp.where(born[:, None], mean0, mean),
        cov=jnp.where(born[:, None, None], P0, cov),
        class_id=jnp.where(born, new_class, state.class_id),
        track_id=jnp.where(born, state.next_id + rank_slot, jnp.where(live, state.track_id, -1)),
        live=live | born,
        confirmed=jnp.where(born, params.n_confirm <= 1, confirmed & live),
        hits=jnp.where(born, 1, jnp.where(live, hits, 0)),
        misses=jnp.where(born | ~live, 0, misses),
        contrary=jnp.where(born | ~live, 0, contrary),
        side_heading=jnp.where(born[:, None], new_sides, side_heading),
        side_var=jnp.where(born[:, None], P0_pose[:, 2:3, 2], side_var),
        side_logw=jnp.where(born[:, None], new_logp + jnp.log1p(-_REST_P), side_logw),
        side_rest=jnp.where(born, jnp.log(_REST_P), side_rest),
        main=jnp.where(born, jnp.argmax(new_logp, axis=-1).astype(jnp.int32), main),
        next_id=state.next_id + n_born,
    )
    used_by_track = used
    if not explain:
        return new, used_by_track
    # Why each slot is not confirmed (``HOLDS``), whole-array selects: a track born in this scan
    # waits for its scans; one that lives on, for the first test it failed in this scan.
    majority = (hits >= params.n_confirm) & (hits <= contrary)
    why = jnp.where(~speed_ok, 3, jnp.where(~turn_ok, 4, jnp.where(majority, 2, 1)))
    hold = jnp.where(new.live & ~new.confirmed, jnp.where(born, 1, why), 0).astype(jnp.int32)
    on = new.live & ~born
    v2 = mean[:, 3] ** 2 + mean[:, 4] ** 2
    speed = jnp.where(on & (v2 > 0), jnp.sqrt(jnp.where(v2 > 0, v2, 1.0)), 0.0)  # double where: no root of 0
    turn = jnp.where(on, jnp.abs(omega_used), 0.0)
    return new, used_by_track, TrackHolds(hold, speed, turn)
