"""Several lasers on one field (issue 18): each laser's scans through stages a–f on their own, one
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
leading axis of ``SeveralState.transforms``); every laser here uses the same model (one scanner type).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..model import Model
from .f_maptransform import Transform
from .g_track import TrackerState
from .pipeline import Output, in_coverage, perceive, update_view
from .precision import exact_products
from .scan import Scan


class SeveralState(eqx.Module):
    """What carries over between scans: one map transformation per laser (leading axis: the lasers),
    one track table, the scans each laser has given."""

    transforms: Transform
    tracker: TrackerState
    n_scans: Int[Array, " lasers"]


def init_several(model: Model, sensor_poses: Float[Array, "lasers 3"]) -> SeveralState:
    """Before the first scan: each laser's rough pose guess (the site's ``sensors``) as its first
    transform, no tracks."""
    poses = jnp.asarray(sensor_poses, jnp.float32)
    return SeveralState(
        transforms=jax.vmap(Transform.from_sensor_pose)(poses),
        tracker=TrackerState.empty(model.max_tracks),
        n_scans=jnp.zeros(poses.shape[0], jnp.int32),
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


@exact_products
def update_several(model: Model, state: SeveralState, p, scan: Scan, k: Int[Array, ""],
                   span_dt: Float[Array, ""]) -> tuple[SeveralState, Output]:
    """Stages f–g for laser ``k``'s scan: its own transform, the shared tracker. A track outside every
    laser's reach (by each laser's latest transform) is missed by whichever laser scans; a track
    within several lasers' reach may be missed by each of them as long as by one (``watchers``,
    :func:`~gtsjax.core.g_track.track_step`)."""
    xy = state.tracker.mean[:, :2]
    watched = jax.vmap(lambda tf: in_coverage(scan, tf, xy, model.range_max))(state.transforms)  # [lasers, tracks]
    n_watch = jnp.sum(watched, axis=0, dtype=jnp.int32)
    tf, tracker, out = update_view(model, _row(state.transforms, k), state.tracker, p, scan, span_dt=span_dt,
                                   several=True, unwatched=n_watch == 0, watchers=jnp.maximum(n_watch, 1))
    n = state.n_scans + (jnp.arange(state.n_scans.shape[0], dtype=jnp.int32) == k).astype(jnp.int32)
    return SeveralState(_put_row(state.transforms, k, tf), tracker, n), out


def step_several(model: Model, state: SeveralState, scan: Scan, k: Int[Array, ""], span_dt: Float[Array, ""]
                 ) -> tuple[SeveralState, Output]:
    """The whole pipeline for one scan of laser ``k`` among several: pure, not jitted (see
    :func:`~gtsjax.core.pipeline.step`)."""
    return update_several(model, state, perceive(model, scan), scan, k, span_dt)
