"""The whole of Fig. 1 as one pure function: ``step(model, state, scan) -> (state, output)``, and the
batch driver ``process_log`` that runs the same computation over a log.

The step splits in two:

* ``perceive`` (stages a–e): front end, classifier and pose regression, everything that depends on
  the scan alone. Batch replay can ``vmap`` it over chunks of scans (``vectorise=True``).
* ``update`` (stages f–g): map transformation and tracking, which carry state from scan to scan.
  Batch replay runs it under ``lax.scan``.

``step`` is ``update ∘ perceive``. ``process_log`` runs chunks of scans: by default through the same
compiled loop body as ``step`` (bit-for-bit equal results), or as ``scan(update) ∘ vmap(perceive)``.
Memory is bounded by the chunk size for logs of any length.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._classify import classify, gp_inputs
from ._filters import envelope_pass, partial_view, shape_quantities
from ._frontend import front_end_unjitted
from ._maptransform import Transform, poses_to_field, update_transform
from ._pose import regress, to_sensor_frame, vague_headings
from ._scan import Scan
from ._track import Detections, TrackerState, reported, track_step
from .model import Model

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
    partial: Bool[Array, " cands"]  # occluded view of a class seen whole (``_filters.partial_view``)
    vague: Bool[Array, " cands"]  # heading variance above its class's ``heading_var_max`` (``_pose``)
    scores: Float[Array, "cands classes"]
    pose_s: Float[Array, "cands 3"]
    cov_s: Float[Array, "cands 3 3"]
    n_segments: Int[Array, ""]
    n_kept: Int[Array, ""]
    overflow: Int[Array, ""]
    too_long: Int[Array, ""]
    unposed: Int[Array, ""]  # objects beyond their class's cap (see ``_pose.regress``), dropped
    unlike: Int[Array, ""]  # candidates unlike every training example of their class (open set), dropped
    off_envelope: Int[Array, ""]  # candidates whose best class's shape envelope they lie outside


class Output(eqx.Module):
    """One scan's result, fixed size. Tracks: ``M`` slots, reported where ``track_mask`` (confirmed)."""

    track_id: Int[Array, " tracks"]
    track_class: Int[Array, " tracks"]
    track_pose: Float[Array, "tracks 3"]
    track_var: Float[Array, "tracks 3"]
    track_mask: Bool[Array, " tracks"]
    transform: Transform
    landmark_residual: Float[Array, "landmarks 2"]
    landmark_seen: Bool[Array, " landmarks"]
    det_pose: Float[Array, "cands 3"]  # detections of tracked classes in O (diagnostics, evaluation)
    det_class: Int[Array, " cands"]
    det_mask: Bool[Array, " cands"]
    n_segments: Int[Array, ""]
    n_kept: Int[Array, ""]  # candidates passing the binary filters
    n_objects: Int[Array, ""]  # candidates classified as landmarks or tracked objects
    overflow: Int[Array, ""]  # segments beyond K, dropped
    too_long: Int[Array, ""]  # segments longer than L beams, filtered
    unposed: Int[Array, ""]  # objects beyond their class's cap (see ``_pose.regress``), dropped
    unlike: Int[Array, ""]  # candidates unlike every training example of their class (open set), dropped
    off_envelope: Int[Array, ""]  # candidates whose best class's shape envelope they lie outside
    degraded: Bool[Array, ""]  # too few landmarks: the previous transform was kept


def init_state(model: Model) -> PipelineState:
    """Before the first scan: the user's rough sensor pose as the first transform, no tracks."""
    return PipelineState(
        transform=Transform.from_sensor_pose(model.site.sensor_pose),
        tracker=TrackerState.empty(model.max_tracks),
        n_scans=jnp.asarray(0, jnp.int32),
    )


def landmark_cap(model: Model) -> int:
    """Landmark candidates worth a position per scan: as many as the site has landmarks, plus room for
    as many look-alikes as there may be objects (static: the site's landmark count is a shape)."""
    return model.site.landmark_xy.shape[0] + model.max_objects


def perceive(model: Model, scan: Scan, *, bucket: bool | None = None) -> Perception:
    """Stages a–e (segmentation … pose regression) of one scan; no state. ``bucket``: see
    :func:`~gtsjax._pose.regress`; off where ``perceive`` is ``vmap``ped, and by default on a CPU
    only: on a GPU each branch choice waits for its index on the host (an H100's step took 2.23 ms
    with it, 1.61 ms without)."""
    if bucket is None:
        bucket = jax.default_backend() == "cpu"
    fe = front_end_unjitted(model.frontend, scan)
    f = fe.features
    x = gp_inputs(f.vector, f.origin, f.height, model.gp_columns)
    rng = jnp.sqrt(jnp.sum(f.origin**2, axis=-1))
    in_env = envelope_pass(model.envelope, shape_quantities(f.width, f.height, f.n_points, rng), rng)
    dec = classify(model.classifier, x, fe.keep, in_env)
    cls, ok, scores = dec.cls, dec.ok, dec.scores
    rel, var, posed = regress(model.pose, x, cls, ok, scores, model.max_objects, landmark_cap(model), bucket)
    pose_s, cov_s = to_sensor_frame(f.origin, f.heading, rel, var)
    d = fe.diagnostics
    unposed = jnp.sum(ok & ~posed, dtype=jnp.int32)
    count = lambda m: jnp.sum(m, dtype=jnp.int32)
    partial = partial_view(model.envelope, cls, fe.candidates.occluded)
    vague = vague_headings(model.pose, cls, var)
    return Perception(cls, ok & posed, fe.keep, partial, vague, scores, pose_s, cov_s, d.n_segments, d.n_kept,
                      d.overflow_count, d.too_long_count, unposed, count(dec.unlike), count(dec.off_envelope))


def _inside(site, pose: Float[Array, "n 3"]) -> Bool[Array, " n"]:
    """Whether each pose lies inside the site's bounds (all True for a site without bounds)."""
    x, y = pose[:, 0], pose[:, 1]
    b = site.bounds
    return ~site.has_bounds | ((x >= b[0]) & (y >= b[1]) & (x <= b[2]) & (y <= b[3]))


# How far beyond a track's predicted centre its beams must reach for its spot to count as empty:
# more than any robot's radius is not needed (a robot that is there stops the beam before its centre);
# this covers the prediction's error while the track coasts.
SEE_THROUGH_MARGIN = 0.3


def seen_through(scan: Scan, tf: Transform, xy_o: Float[Array, "n 2"]) -> Bool[Array, " n"]:
    """Whether the scan sees through each field position: none of the three beams nearest its
    bearing returns before ``SEE_THROUGH_MARGIN`` past it (a beam with no return saw nothing within
    the sensor's range: on an open field, the usual view past a far robot). A position outside the
    field of view is never seen through."""
    xy_s = tf.mu_s[None, :] + jnp.linalg.solve(tf.A, (xy_o - tf.mu_o[None, :]).T).T
    rho = jnp.sqrt(jnp.sum(xy_s**2, axis=-1))
    beam = jnp.round((jnp.arctan2(xy_s[:, 1], xy_s[:, 0]) - scan.angle_min) / scan.angle_increment).astype(jnp.int32)
    idx = beam[:, None] + jnp.arange(-1, 2, dtype=jnp.int32)[None, :]  # [n, 3]
    n = scan.n_beams
    in_view = jnp.all((idx >= 0) & (idx < n), axis=1)
    idx = jnp.clip(idx, 0, n - 1)
    r, ok = scan.ranges[idx], scan.valid[idx]
    short = ok & (r <= rho[:, None] + SEE_THROUGH_MARGIN)
    return in_view & ~jnp.any(short, axis=1)


def update(model: Model, state: PipelineState, p: Perception, scan: Scan) -> tuple[PipelineState, Output]:
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
        state.transform, p.pose_s[:, :2], p.cls, is_landmark, site.landmark_xy, site.landmark_class,
        model.map_gate, model.map_min_spread,
    )
    pose_o, cov_o = poses_to_field(tf, p.pose_s, p.cov_s)
    cov_o = cov_o + jnp.diag(model.meas_var_floor)[None]
    tracked = p.ok & model.tracker.tracked[p.cls] & _inside(site, pose_o)
    det = Detections(pose_o, cov_o, p.cls, tracked, p.kept & ~tracked, p.partial, p.vague)
    tracker, _ = track_step(state.tracker, det, dt, model.tracker)
    ts = tracker
    out = Output(
        track_id=ts.track_id,
        track_class=ts.class_id,
        track_pose=ts.mean[:, :3],
        track_var=jnp.diagonal(ts.cov, axis1=1, axis2=2)[:, :3],
        # Confirmed, recently observed, inside the site's bounds (a coasting track may leave them), and
        # if missed in this scan, not where the scan sees through.
        track_mask=reported(ts, model.tracker) & _inside(site, ts.mean[:, :3])
        & ((ts.misses == 0) | ~seen_through(scan, tf, ts.mean[:, :2])),
        transform=tf,
        landmark_residual=residual,
        landmark_seen=seen,
        det_pose=pose_o,
        det_class=p.cls,
        det_mask=tracked,
        n_segments=p.n_segments,
        n_kept=p.n_kept,
        n_objects=jnp.sum(p.ok, dtype=jnp.int32),
        overflow=p.overflow,
        too_long=p.too_long,
        unposed=p.unposed,
        unlike=p.unlike,
        off_envelope=p.off_envelope,
        degraded=tf.degraded,
    )
    return PipelineState(tf, tracker, state.n_scans + 1), out


def step_unjitted(model: Model, state: PipelineState, scan: Scan) -> tuple[PipelineState, Output]:
    return update(model, state, perceive(model, scan), scan)


def _run_scans(model: Model, state: PipelineState, scans: Scan, n_real: Int[Array, ""]):
    """``step`` over the first ``n_real`` scans of a stack, in a ``while_loop`` whose trip count is a
    runtime value. The loop body is one scan's whole step, compiled as a computation of its own, the
    same whether the stack holds 1 scan (``step``) or a chunk (batch replay): that is what makes the
    two bit-for-bit equal. Outputs past ``n_real`` are zeros."""
    one = jax.tree.map(lambda a: a[0], scans)
    out_shape = jax.eval_shape(lambda st, sc: step_unjitted(model, st, sc)[1], state, one)
    size = scans.dt.shape[0]
    buf0 = jax.tree.map(lambda sd: jnp.zeros((size,) + sd.shape, sd.dtype), out_shape)

    def cond(c):
        return c[0] < n_real

    def body(c):
        i, st, buf = c
        sc = jax.tree.map(lambda a: jax.lax.dynamic_index_in_dim(a, i, keepdims=False), scans)
        st, o = step_unjitted(model, st, sc)
        buf = jax.tree.map(lambda b, x: jax.lax.dynamic_update_index_in_dim(b, x, i, 0), buf, o)
        return i + 1, st, buf

    _, state, buf = jax.lax.while_loop(cond, body, (jnp.asarray(0, jnp.int32), state, buf0))
    return state, buf


@jax.jit
def step(model: Model, state: PipelineState, scan: Scan) -> tuple[PipelineState, Output]:
    """The whole pipeline for one scan (Fig. 1, stages a–g), jitted once per model shape.

    Run as the one-scan case of batch replay's loop (the barrier keeps the compiler from seeing that
    the loop runs once and inlining it), so that replay and stepping give identical bits."""
    n = jax.lax.optimization_barrier(jnp.asarray(1, jnp.int32))
    state, out = _run_scans(model, state, jax.tree.map(lambda a: a[None], scan), n)
    return state, jax.tree.map(lambda a: a[0], out)


def make_step(model: Model):
    """``step`` with ``model`` closed over: ``f(state, scan) -> (state, output)``, jitted once.

    The live loop's form. The model becomes a constant of the compiled program, so a call no longer
    flattens the model's hundred-odd arrays on the host (about a third of a step's time on a 2-core
    laptop). The computation is ``step``'s; XLA may fold the constants, so results agree with ``step``
    to float32 rounding rather than bit for bit."""
    return jax.jit(lambda state, scan: step_unjitted(model, state, scan))


def _pad_chunk(scans: Scan, start: int, stop: int, size: int) -> Scan:
    """Scans ``start:stop`` padded to ``size`` by repeating the last one (so shapes never change)."""
    part = jax.tree.map(lambda a: a[start:stop], scans)
    pad = size - (stop - start)
    if pad == 0:
        return part
    return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), part)


@jax.jit(static_argnames="vectorise")
def process_chunk(model: Model, state: PipelineState, scans: Scan, n_real: Int[Array, ""], vectorise: bool = False
                  ) -> tuple[PipelineState, Output]:
    """A chunk of scans (leading axis). Scans at index ``>= n_real`` (padding of the last chunk) leave
    the state as it was.

    ``vectorise=False``: the chunk runs through the very loop ``step`` compiles (:func:`_run_scans`),
    so the tracks are bit-for-bit those of calling ``step`` scan by scan. ``vectorise=True``:
    ``perceive`` (stages a–e) is ``vmap``ped over the chunk and ``update`` (f–g) runs under
    ``lax.scan``; batched reductions may then round differently (about 1e-7 relative)."""
    if not vectorise:
        return _run_scans(model, state, scans, n_real)
    percepts = jax.vmap(lambda sc: perceive(model, sc, bucket=False))(scans)

    def body(s, inp):
        p, sc, i = inp
        new, out = update(model, s, p, sc)
        keep = i < n_real
        return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, s), out

    idx = jnp.arange(scans.dt.shape[0], dtype=jnp.int32)
    return jax.lax.scan(body, state, (percepts, scans, idx))


def process_log(model: Model, scans: Scan, *, chunk: int = 256, state: PipelineState | None = None,
                callback=None, vectorise: bool = False) -> tuple[PipelineState, Output]:
    """Run a stack of scans through the pipeline ``chunk`` at a time. Returns the final state and the
    stacked outputs as NumPy arrays on the host; ``callback(n_done)`` is called after each chunk.

    Device memory is bounded by the chunk size whatever the log's length (the last chunk is padded,
    and its padding does not touch the state); the outputs accumulate on the host.
    """
    import numpy as np

    state = init_state(model) if state is None else state
    n = scans.ranges.shape[0]
    chunk = max(1, min(chunk, n))
    outs = []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        part = _pad_chunk(scans, start, stop, chunk)
        state, out = process_chunk(model, state, part, jnp.asarray(stop - start, jnp.int32), vectorise=vectorise)
        real = stop - start
        outs.append(jax.tree.map(lambda a, real=real: np.asarray(a)[:real], out))
        if callback is not None:
            callback(stop)
    return state, jax.tree.map(lambda *a: np.concatenate(a), *outs)
