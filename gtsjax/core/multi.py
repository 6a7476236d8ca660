"""Several lasers on one field: each laser's scans through stages a–f on their own, one
track table for all.

The paper's future work: one laser at the side of a full-size field sees a robot only within its
range and when no other robot stands in front of it; more lasers see the rest. Each laser keeps its
own map transformation (stage f: from the landmarks *it* sees, its own rough pose guess to start
from; a laser that sees too few keeps its last transform and is degraded, borrowing nothing from
the others); its detections, mapped into O with their covariances, update the one tracker, scan by
scan in the order of their stamps, whichever laser took them. The prediction steps over the time
since the previous scan of any laser; a track the scanning laser cannot see (outside its range or
field of view) is not missed by it (:func:`~gtsjax.core.g_track.track_step`'s ``visible``), so a
robot watched by one laser is not dropped for the scans of the other; one outside every laser's
reach is missed by all, so that it ends.

``step_several(model, state, scan, k, span_dt)``: laser ``k`` (a traced index: one compiled program
serves every laser of a model) scanned ``scan``; ``scan.dt`` is the time since the previous scan of
any laser, ``span_dt`` since laser ``k``'s previous one. The number of lasers is a static shape (the
leading axis of ``SeveralState.transforms``).

Lasers of different scanner models (a URG-04LX and a UTM-30LX) each use a model trained for their
scanner, with one track table: the models must agree on the classes and the number of track slots
(the host checks them: :func:`gtsjax.drivers.setup.check_models`). Each laser's reach (field of
view, range) is part of the state, so that every laser's coverage is judged by its own scanner. Live, each scanner model has its own compiled step
(its model closed over) on the one state; in batch, :func:`update_mixed` picks the scanning laser's
model with ``lax.switch``, its perception and scan padded to the widest model's.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..precision import exact_products
from .f_maptransform import Transform
from .g_track import TrackerState
from .model import Model
from .pipeline import SEE_THROUGH_MARGIN, Output, Perception, perceive, update_view
from .scan import Scan, within


class SeveralState(eqx.Module):
    """What carries over between scans: one map transformation per laser (leading axis: the lasers),
    one track table, the scans each laser has given."""

    transforms: Transform
    tracker: TrackerState
    n_scans: Int[Array, " lasers"]
    # Each laser's reach: the bearings of its first and last beams in S, its range (m). Constant.
    reach: Float[Array, "lasers 3"]


def laser_reach(model: Model) -> tuple[float, float, float]:
    """The reach of a laser of the scanner ``model`` was trained for: first and last beam's bearing,
    range (host floats). A model from before its geometry was kept reads its scanner's beams from
    ``sensor_beams`` (filled in by the host), or, for an unknown scanner, sees all round."""
    beams = model.beams
    if not (math.isfinite(beams.angle_min) and math.isfinite(beams.increment)):  # from before its geometry was kept
        if model.sensor_beams is None:
            return (-math.pi, math.pi, model.range_max)
        beams = model.sensor_beams
    return (beams.angle_min, beams.angle_max, model.range_max)


def init_several(model: "Model | tuple[Model, ...]", sensor_poses: Float[Array, "lasers 3"],
                 kinds: "tuple[int, ...] | None" = None) -> SeveralState:
    """Before the first scan: each laser's rough pose guess (the site's ``sensors``) as its first
    transform, no tracks. ``model``: every laser's, or one per scanner model with ``kinds`` (each
    laser's index into them)."""
    models = model if isinstance(model, tuple) else (model,)
    poses = jnp.asarray(sensor_poses, jnp.float32)
    kinds = kinds if kinds is not None else (0,) * poses.shape[0]
    if len(kinds) != poses.shape[0]:
        raise ValueError(f"{len(kinds)} kinds for {poses.shape[0]} lasers")
    return SeveralState(
        transforms=jax.vmap(Transform.from_sensor_pose)(poses),
        tracker=TrackerState.empty(models[0].max_tracks, ids=identities(models)),
        n_scans=jnp.zeros(poses.shape[0], jnp.int32),
        reach=jnp.asarray([laser_reach(models[i]) for i in kinds], jnp.float32),
    )


def _row(tree, k):
    """Row ``k`` of every leaf (a gather)."""
    return jax.tree_util.tree_map(lambda a: a[k], tree)


def _put_row(tree, k, row):
    """``tree`` with row ``k`` of every leaf replaced by ``row``'s (a select against an iota, not a scatter)."""
    def put(a, r):
        at = (jnp.arange(a.shape[0], dtype=jnp.int32) == k).reshape((-1,) + (1,) * (a.ndim - 1))
        return jnp.where(at, r[None], a)

    return jax.tree_util.tree_map(put, tree, row)


def miss_period(models: "tuple[Model, ...]") -> float | None:
    """The clock on which lasers of different rates count a track's misses: the fastest scanner's
    period (``None`` for one scanner model: each model counts in its own scans, as ever)."""
    periods = {m.scan_period for m in models}
    if len(periods) < 2 or None in periods:
        return None
    return min(periods)


def on_clock(model: Model, period: float | None) -> Model:
    """``model`` with its tracker's miss limits (``m_tentative``, ``m_delete``, ``m_report``, in its own
    scans) in scans of ``period``: a URG-04LX's 3 scans (0.3 s) are 12 of a UTM-30LX's 25 ms, so that
    a miss means the same time whichever laser counts it."""
    if period is None or model.scan_period is None:
        return model
    ratio = max(int(round(model.scan_period / period)), 1)
    t = model.tracker
    return eqx.tree_at(lambda m: (m.tracker.m_tentative, m.tracker.m_delete, m.tracker.m_report), model,
                       (t.m_tentative * ratio, t.m_delete * ratio, t.m_report * ratio))


@exact_products
def update_several(model: Model, state: SeveralState, p, scan: Scan, k: Int[Array, ""],
                   span_dt: Float[Array, ""], period: float | None = None) -> tuple[SeveralState, Output]:
    """Stages f–g for laser ``k``'s scan: its own transform, the shared tracker. A track outside every
    laser's reach (by each laser's latest transform) is missed by whichever laser scans; a track
    within several lasers' reach may be missed by each of them as long as by one (``watchers``,
    :func:`~gtsjax.core.g_track.track_step`). ``period``: the clock misses are counted on where the
    lasers' scanners differ in rate (:func:`miss_period`; ``model``'s limits are put on it)."""
    model = on_clock(model, period)
    xy = state.tracker.mean[:, :2]
    watched = jax.vmap(lambda tf, r: within(tf, xy, r[0], r[1], 0.0, r[2] - SEE_THROUGH_MARGIN))(
        state.transforms, state.reach)  # [lasers, tracks]
    n_watch = jnp.sum(watched, axis=0, dtype=jnp.int32)
    tf, tracker, out = update_view(model, _row(state.transforms, k), state.tracker, p, scan, span_dt=span_dt,
                                   several=True, unwatched=n_watch == 0, watchers=jnp.maximum(n_watch, 1),
                                   period=period)
    n = state.n_scans + (jnp.arange(state.n_scans.shape[0], dtype=jnp.int32) == k).astype(jnp.int32)
    return SeveralState(_put_row(state.transforms, k, tf), tracker, n, state.reach), out


def identities(models: "tuple[Model, ...]") -> int:
    """The robot identities the shared track table tells apart: the most any of the models reads. A
    laser whose model reads no tags (a scanner without intensities) adds no evidence of identity: its
    detections' tag log-likelihoods are zeros (:func:`pad_perception`), whichever model is given first."""
    return max(m.n_identities for m in models)


def widest(models: "tuple[Model, ...]") -> tuple[int, int]:
    """The candidate slots and beams a perception and a scan are padded to for :func:`update_mixed`."""
    return max(m.frontend.max_candidates for m in models), max(m.n_beams for m in models)


def pad_perception(p: Perception, n_cands: int, n_ids: int = 0) -> Perception:
    """``p`` with its candidate axis padded to ``n_cands`` (slots neither kept nor objects), and, from a
    model that reads no tags where another laser's does (``n_ids`` identities, :func:`identities`), tag
    log-likelihoods of zero: every laser's perception then has one structure, as one program needs."""
    if n_ids and p.tag_ll is None:
        p = eqx.tree_at(lambda q: q.tag_ll, p, jnp.zeros(p.ok.shape + (n_ids,), jnp.float32),
                        is_leaf=lambda x: x is None)
    return jax.tree.map(lambda a: a if a.ndim == p.ok.ndim - 1 else _pad_axis(a, p.ok.ndim - 1, n_cands), p)


def _pad_axis(a, axis: int, size: int):
    pad = [(0, 0)] * a.ndim
    pad[axis] = (0, size - a.shape[axis])
    return jnp.pad(a, pad)


def update_mixed(models: "tuple[Model, ...]", state: SeveralState, p: Perception, scan: Scan, k: Int[Array, ""],
                 kind: Int[Array, ""], span_dt: Float[Array, ""]) -> tuple[SeveralState, Output]:
    """:func:`update_several` for laser ``k``, whose scanner's model is ``models[kind]`` (traced: one
    program serves every laser). ``p`` and ``scan`` are padded to :func:`widest`; the chosen model
    reads its own candidate slots and beams, and the output's detections are padded back."""
    n_cands, _ = widest(models)
    period = miss_period(models)

    def branch(m: Model):
        def run(state, p, scan, k, span_dt):
            c, b = m.frontend.max_candidates, m.n_beams
            mine = jax.tree.map(lambda a: a if a.ndim == 0 else a[:c], p)
            sc = Scan(scan.ranges[:b], scan.intensities[:b], scan.valid[:b], scan.angle_min, scan.angle_increment,
                      scan.dt)
            new, out = update_several(m, state, mine, sc, k, span_dt, period)
            per_cand = lambda o: (o.det_pose, o.det_class, o.det_mask, o.cand_xy, o.cand_class, o.cand_reason)  # noqa: E731
            return new, eqx.tree_at(per_cand, out, tuple(_pad_axis(a, 0, n_cands) for a in per_cand(out)))
        return run

    if len(models) == 1:
        return branch(models[0])(state, p, scan, k, span_dt)
    return jax.lax.switch(kind, [branch(m) for m in models], state, p, scan, k, span_dt)


def step_several(model: Model, state: SeveralState, scan: Scan, k: Int[Array, ""], span_dt: Float[Array, ""],
                 period: float | None = None) -> tuple[SeveralState, Output]:
    """The whole pipeline for one scan of laser ``k`` among several: pure, not jitted (see
    :func:`~gtsjax.core.pipeline.step`). ``period``: see :func:`update_several`."""
    return update_several(model, state, perceive(model, scan), scan, k, span_dt, period)
