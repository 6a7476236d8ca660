"""The whole of Fig. 1 as one pure function: ``step(model, state, scan) -> (state, output)``.

The step splits in two:

* ``perceive`` (stages a–e): front end, classifier and pose regression, everything that depends on
  the scan alone. Batch replay can ``vmap`` it over chunks of scans (``vectorise=True``).
* ``update`` (stages f–g): map transformation and tracking, which carry state from scan to scan.
  Batch replay runs it under ``lax.scan``.

``step`` is ``update ∘ perceive``; it is not jitted here: the drivers (``gtsjax.drivers``) jit it,
batch replay as a loop over chunks or as ``scan(update) ∘ vmap(perceive)``.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..precision import exact_products
from . import buckets
from .c_filters import envelope_pass, partial_view, shape_quantities
from .d_classify import classify, gp_inputs
from .e_pose import regress, to_sensor_frame, vague_headings
from .e_refine import refine_candidates
from .e_tags import read_candidates
from .f_maptransform import Transform, poses_to_field, update_transform
from .frontend import front_end
from .g_identity import report_identities
from .g_track import Detections, TrackerState, reported, track_step
from .geometry import in_bounds, wrap
from .model import Model
from .scan import Beams, Scan

_F32 = jnp.float32


class PipelineState(eqx.Module):
    """What carries over from one scan to the next: the map transformation and the track table."""

    transform: Transform
    tracker: TrackerState
    n_scans: Int[Array, ""]


class Perception(eqx.Module):
    """Stages a–e of one scan: every candidate's class and pose in S, before the map transformation."""

    cls: Int[Array, " cands"]
    ok: Bool[Array, " cands"]  # kept by the filters and classified as an object (not background)
    kept: Bool[Array, " cands"]  # kept by the binary filters (stage c), whatever the classifier said
    partial: Bool[Array, " cands"]  # occluded view of a class seen whole (``c_filters.partial_view``)
    vague: Bool[Array, " cands"]  # heading variance above its class's ``heading_var_max`` (``e_pose``)
    scores: Float[Array, "cands classes"]
    pose_s: Float[Array, "cands 3"]
    cov_s: Float[Array, "cands 3 3"]
    side_pose: Float[Array, "cands sides 3"]  # side hypotheses in S (stage e′)
    side_logp: Float[Array, "cands sides"]
    refined: Bool[Array, " cands"]  # the pose comes from the outline fit (stage e′), not the GP
    guess: Bool[Array, " cands"]  # not ok, but posed as the tracked class ``cls`` (``d_classify.classify``)
    at_s: Float[Array, "cands 2"]  # where the candidate is in S (its ORS origin), whatever became of it
    reason: Int[Array, " cands"]  # what became of it: an index into ``REASONS``
    n_segments: Int[Array, ""]
    n_kept: Int[Array, ""]
    n_overflow: Int[Array, ""]
    n_too_long: Int[Array, ""]
    unposed: Int[Array, ""]  # objects beyond their class's cap (see ``e_pose.regress``), dropped
    unlike: Int[Array, ""]  # candidates unlike every training example of their class (open set), dropped
    off_envelope: Int[Array, ""]  # candidates whose best class's shape envelope they lie outside
    tag_ll: Float[Array, "cands ids"] | None = None  # each candidate's identity log-likelihoods (stage e″)


# What became of each candidate slot of a scan (``Perception.reason``, ``Output.cand_reason``), for the
# view and diagnostics: no segment in the slot; dropped by stage c's binary filters (or longer than the
# window); taken for background by the classifier (or scored under its class's threshold); unlike every
# training example of its class (open set); outside its best class's shape envelope; an object beyond
# its class's cap of posed candidates; an object (landmark or tracked class), posed.
REASONS = ("none", "filtered", "background", "unlike", "off envelope", "unposed", "object")


class Output(eqx.Module):
    """One scan's result, fixed size. Tracks: ``M`` slots, reported where ``track_mask`` (confirmed)."""

    track_id: Int[Array, " tracks"]
    track_class: Int[Array, " tracks"]
    track_pose: Float[Array, "tracks 3"]
    track_var: Float[Array, "tracks 3"]  # the marginal variances of x, y, θ
    track_cov_xy: Float[Array, " tracks"]  # the x–y covariance
    track_mask: Bool[Array, " tracks"]
    track_live: Bool[Array, " tracks"]  # slot in use: a tentative or confirmed track
    track_hold: Int[Array, " tracks"]  # why a live slot is not confirmed: an index into ``g_track.HOLDS``
    track_speed: Float[Array, " tracks"]  # estimated speed |v̂|, m/s
    track_turn_rate: Float[Array, " tracks"]  # estimated turn rate |ω̂| before clipping, rad/s
    transform: Transform
    sensor_pose: Float[Array, "3"]  # the sensor in O as this scan's transform sees it
    landmark_residual: Float[Array, "landmarks 2"]
    landmark_seen: Bool[Array, " landmarks"]
    det_pose: Float[Array, "cands 3"]  # detections of tracked classes in O (diagnostics, evaluation)
    det_class: Int[Array, " cands"]
    det_mask: Bool[Array, " cands"]
    cand_xy: Float[Array, "cands 2"]  # every candidate slot in O, its class and what became of it (``REASONS``)
    cand_class: Int[Array, " cands"]
    cand_reason: Int[Array, " cands"]
    n_segments: Int[Array, ""]
    n_kept: Int[Array, ""]  # candidates passing the binary filters
    n_objects: Int[Array, ""]  # candidates classified as landmarks or tracked objects
    n_overflow: Int[Array, ""]  # segments beyond K, dropped
    n_too_long: Int[Array, ""]  # segments longer than L beams, filtered
    unposed: Int[Array, ""]  # objects beyond their class's cap (see ``e_pose.regress``), dropped
    unlike: Int[Array, ""]  # candidates unlike every training example of their class (open set), dropped
    off_envelope: Int[Array, ""]  # candidates whose best class's shape envelope they lie outside
    degraded: Bool[Array, ""]  # too few landmarks: the previous transform was kept
    # The identity each track reports (an index into ``Model.tag_names``, -1: none); None: the model
    # reads no tags (:mod:`~gtsjax.core.g_identity`).
    track_robot: Int[Array, " tracks"] | None = None


def init_state(model: Model) -> PipelineState:
    """Before the first scan: the user's rough sensor pose as the first transform, no tracks."""
    return PipelineState(
        transform=Transform.from_sensor_pose(model.site.sensor_pose),
        tracker=TrackerState.empty(model.max_tracks, ids=model.n_identities),
        n_scans=jnp.asarray(0, jnp.int32),
    )


def landmark_cap(model: Model) -> int:
    """Landmark candidates worth a position per scan: as many as the site has landmarks, plus room for
    as many look-alikes as there may be objects (static: the site's landmark count is a shape)."""
    return model.site.landmark_xy.shape[0] + model.max_objects


@exact_products
def perceive(model: Model, scan: Scan, *, bucket: bool | None = None, axis_name=None) -> Perception:
    """Stages a–e′ (segmentation … pose regression, outline refinement) of one scan; no state. ``bucket``: see
    :func:`~gtsjax.core.e_pose.regress`; by default :func:`~gtsjax.core.buckets.enabled` (on a CPU only:
    on a GPU each branch choice waits for its index on the host, an H100's step took 2.23 ms with it,
    1.61 ms without; ``GTSJAX_SIZE_BUCKETS`` says otherwise). Where
    ``perceive`` is ``vmap``ped, pass the mapped axis's ``axis_name`` with ``bucket`` (one bucket for
    the batch), or turn ``bucket`` off."""
    if bucket is None:
        bucket = buckets.enabled()
    fe = front_end(model.frontend, scan)
    f = fe.features
    x = gp_inputs(f.vector, f.origin, f.height, model.gp_columns)
    rng = jnp.sqrt(jnp.sum(f.origin**2, axis=-1))
    in_env = envelope_pass(model.envelope, shape_quantities(f.width, f.height, f.n_points, rng), rng)
    dec = classify(model.classifier, x, fe.keep, in_env, bucket, axis_name, model.tracker.tracked)
    ok, scores = dec.ok, dec.scores
    cls = jnp.where(dec.guess, dec.guess_cls, dec.cls)
    rel, var, posed = regress(model.pose, x, cls, ok | dec.guess, scores, model.max_objects, landmark_cap(model),
                              bucket, axis_name)
    pose_s, cov_s = to_sensor_frame(f.origin, f.heading, rel, var)
    c = fe.candidates
    to_refine = (ok | dec.guess) & posed & model.tracker.tracked[cls]
    # Stage e″ (the tags) reads on stage e′'s own rows where the model has outlines (sharing their selection).
    reads = model.tags is not None and model.outline is not None
    sides = refine_candidates(model.outline, model.max_objects, cls, to_refine, scores, c.xy, c.mask, pose_s, cov_s,
                              bucket, axis_name, reader=model.tags if reads else None, ranges=c.ranges,
                              intensities=c.intensities)
    d = fe.diagnostics
    unposed = jnp.sum(ok & ~posed, dtype=jnp.int32)
    count = lambda m: jnp.sum(m, dtype=jnp.int32)
    partial = partial_view(model.envelope, cls, fe.candidates.occluded)
    vague = vague_headings(model.pose, cls, var)
    reason = jnp.where(ok & posed, 6, jnp.where(ok, 5, jnp.where(dec.unlike, 3, jnp.where(
        dec.off_envelope, 4, jnp.where(fe.keep, 2, jnp.where(c.live, 1, 0)))))).astype(jnp.int32)
    tag_ll = sides.tag_ll
    if model.tags is not None and not reads:  # outlines left out: the tags read from the GP's sides alone
        tag_ll = read_candidates(model.tags, model.max_objects, cls, to_refine, scores, c.xy, c.ranges,
                                 c.intensities, c.mask, sides.side_pose, sides.side_logp)
    return Perception(cls, ok & posed, fe.keep, partial, vague & ~sides.refined, scores, sides.pose, sides.cov,
                      sides.side_pose, sides.side_logp, sides.refined, dec.guess & posed & sides.refined, f.origin,
                      reason, d.n_segments, d.n_kept, d.n_overflow, d.n_too_long, unposed, count(dec.unlike),
                      count(dec.off_envelope), tag_ll)


def _inside(site, pose: Float[Array, "n 3"]) -> Bool[Array, " n"]:
    """Whether each pose lies inside the site's bounds (all True for a site without bounds)."""
    return ~site.has_bounds | in_bounds(pose[:, :2], site.bounds)


# How far beyond a track's predicted centre its beams must reach for its spot to count as empty:
# more than any robot's radius is not needed (a robot that is there stops the beam before its centre);
# this covers the prediction's error while the track coasts.
SEE_THROUGH_MARGIN = 0.3

# Several lasers: the variance (m²) of a laser's map transformation at a detection, added to its
# measurement covariance (see ``update_view``).
TRANSFORM_VAR = 0.015**2


def seen_through(scan: Scan, tf: Transform, xy_o: Float[Array, "n 2"], range_max: float | None = None
                 ) -> Bool[Array, " n"]:
    """Whether the scan sees through each field position: none of the three beams nearest its
    bearing returns before ``SEE_THROUGH_MARGIN`` past it (a beam with no return saw nothing within
    the sensor's range: on an open field, the usual view past a far robot). A position outside the
    field of view is never seen through; with ``range_max`` (several lasers), nor one beyond the
    laser's range less the margin, which another laser may be watching."""
    xy_s = tf.to_sensor(xy_o)
    rho = jnp.sqrt(jnp.sum(xy_s**2, axis=-1))
    in_range = jnp.ones(rho.shape, bool) if range_max is None else rho <= range_max - SEE_THROUGH_MARGIN
    beam = jnp.round((jnp.arctan2(xy_s[:, 1], xy_s[:, 0]) - scan.angle_min) / scan.angle_increment).astype(jnp.int32)
    idx = beam[:, None] + jnp.arange(-1, 2, dtype=jnp.int32)[None, :]  # [n, 3]
    n = scan.n_beams
    in_view = jnp.all((idx >= 0) & (idx < n), axis=1)
    idx = jnp.clip(idx, 0, n - 1)
    r, ok = scan.ranges[idx], scan.valid[idx]
    short = ok & (r <= rho[:, None] + SEE_THROUGH_MARGIN)
    return in_view & in_range & ~jnp.any(short, axis=1)


def in_coverage(scan: Scan, tf: Transform, xy_o: Float[Array, "n 2"], range_max: float) -> Bool[Array, " n"]:
    """Whether each field position lies where the scan's laser can see: inside its field of view
    and its range (less ``SEE_THROUGH_MARGIN``), as its transform ``tf`` places it."""
    beams = Beams(scan.angle_min, scan.angle_increment, scan.n_beams,
                  range_max=jnp.asarray(range_max, scan.angle_min.dtype))
    return beams.reach(tf, xy_o, margin=SEE_THROUGH_MARGIN)


@exact_products
def update(model: Model, state: PipelineState, p: Perception, scan: Scan) -> tuple[PipelineState, Output]:
    """Stages f–g of one laser's scan (see :func:`update_view`)."""
    tf, tracker, out = update_view(model, state.transform, state.tracker, p, scan)
    return PipelineState(tf, tracker, state.n_scans + 1), out


def field_detections(model: Model, tf: Transform, p: Perception, several: bool) -> tuple[Detections, Bool[Array, " K"]]:
    """This scan's detections placed in O by its transform ``tf``, with their covariances (the GP's,
    the model's floor, and with several lasers each transform's own error), side hypotheses and
    masks, as the tracker takes them; and which of them are of a tracked class inside the bounds."""
    site = model.site
    pose_o, cov_o = poses_to_field(tf, p.pose_s, p.cov_s)
    cov_o = cov_o + jnp.diag(model.meas_var_floor)[None]
    if several:
        # Each laser's transform carries its own error (a centimetre or two, from its landmarks'
        # detection noise), not in the GP's variance, and different from the other lasers'. Scans of
        # two lasers interleave (two UTM-30LX: one every 12.5 ms), so to the tracker these errors, and
        # the detections' own, look like speed: the speed test took robots walking near their top
        # speed for implausible and they went unreported (two UTM-30LX on spl-match-2-utm:2000:
        # recall 97.8 % with the floor alone, 98.8 % with this). Counted as measurement noise.
        cov_o = cov_o + jnp.diag(jnp.asarray([TRANSFORM_VAR, TRANSFORM_VAR, 0.0], cov_o.dtype))[None]
    side_o = jnp.concatenate([tf.apply(p.side_pose[..., :2]), wrap(p.side_pose[..., 2:] + tf.heading())], -1)
    inside = _inside(site, pose_o)
    tracked = p.ok & model.tracker.tracked[p.cls] & inside
    guess = p.guess & inside
    det = Detections(pose_o, cov_o, p.cls, tracked | guess, p.kept & ~tracked, p.partial, p.vague, side_o, p.side_logp,
                     guess, p.tag_ll)
    return det, tracked


def update_view(model: Model, prev_tf: Transform, tracker: TrackerState, p: Perception, scan: Scan, *,
                span_dt=None, several: bool = False, unwatched=None, watchers=None, period: float | None = None
                ) -> tuple[Transform, TrackerState, Output]:
    """Stages f–g: re-estimate the map transformation from this scan's landmarks, map detections into
    O, and track. The transform estimated from a scan is used for that same scan's detections.

    A confirmed track is reported while it is observed, and for up to ``m_report`` scans without a
    detection (a missed scan or two), unless this scan sees through the spot it is predicted at:
    then the robot was lifted or walked out of the scan plane, and reporting it would be a false
    track."""
    dt = scan.dt
    site = model.site
    is_landmark = p.ok & model.landmark_mask[p.cls]
    tf, residual, seen = update_transform(
        prev_tf, p.pose_s[:, :2], p.cls, is_landmark, site.landmark_xy, site.landmark_class,
        model.map_gate, model.map_min_spread,
    )
    det, tracked = field_detections(model, tf, p, several)
    pose_o = det.pose
    # Several lasers: a track this laser cannot see (out of its range or field of view) is not missed
    # by it, nor is it seen through there (another laser may be watching it).
    # A track no laser can see (``unwatched``: outside every laser's reach) is missed by each, so that
    # one that left the lasers' reach is not kept for ever.
    visible = None
    if several:
        visible = in_coverage(scan, tf, tracker.mean[:, :2], model.range_max)
        if unwatched is not None:
            visible = visible | unwatched
    period = model.scan_period if period is None else period  # lasers of different rates: a common clock
    tracker, _, holds = track_step(tracker, det, dt, model.tracker, period, visible=visible, span_dt=span_dt,
                                   watchers=watchers, explain=True)
    ts = tracker
    out = Output(
        track_id=ts.track_id,
        track_class=ts.class_id,
        track_pose=model.tracker.off(ts.class_id, ts.mean[:, :3]),
        track_var=model.tracker.widened(ts.class_id, jnp.diagonal(ts.cov, axis1=1, axis2=2)[:, :3]),
        track_cov_xy=ts.cov[:, 0, 1],
        # Confirmed, recently observed, inside the site's bounds (a coasting track may leave them), and
        # if missed in this scan, not where the scan sees through.
        track_mask=reported(ts, model.tracker, watchers) & _inside(site, ts.mean[:, :3])
        & ((ts.misses == 0) | ~seen_through(scan, tf, ts.mean[:, :2], model.range_max if several else None)),
        track_live=ts.live,
        track_hold=holds.hold,
        track_speed=holds.speed,
        track_turn_rate=holds.turn_rate,
        transform=tf,
        sensor_pose=tf.sensor_pose(),
        landmark_residual=residual,
        landmark_seen=seen,
        det_pose=pose_o,
        det_class=p.cls,
        det_mask=tracked,
        cand_xy=tf.apply(p.at_s),
        cand_class=p.cls,
        cand_reason=p.reason,
        n_segments=p.n_segments,
        n_kept=p.n_kept,
        n_objects=jnp.sum(p.ok, dtype=jnp.int32),
        n_overflow=p.n_overflow,
        n_too_long=p.n_too_long,
        unposed=p.unposed,
        unlike=p.unlike,
        off_envelope=p.off_envelope,
        degraded=tf.degraded,
    )
    if ts.id_logp is not None:
        out = eqx.tree_at(lambda o: o.track_robot, out, report_identities(ts.id_logp, out.track_mask),
                          is_leaf=lambda x: x is None)
    return tf, tracker, out


def step(model: Model, state: PipelineState, scan: Scan) -> tuple[PipelineState, Output]:
    """The whole pipeline for one scan (Fig. 1, stages a–g): pure and not jitted. Each driver owns
    its jit: the live loop (``drivers.live``, the model closed over, one frame per call), batch replay
    (``drivers.batch``, chunks of scans in one compiled loop), the benchmarks; a user's own loop
    wraps it in ``jax.jit``. The model's shape-fixing integers are static, its thresholds arrays, so
    one compilation serves every model of a shape."""
    return update(model, state, perceive(model, scan), scan)
