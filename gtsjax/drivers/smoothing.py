"""A replay's ground truth smoothed (``replay --smooth``): after the forward pass, which decides the
data association, births, deaths and ids, each track's poses are re-estimated from all of its scans,
before and after, by the fixed-interval smoother of :mod:`gtsjax.core.smooth` over the forward
filter's states. The rows stay the forward pass's (stamps, ids, classes); their poses, variances and
x–y covariance become the smoothed ones.

**Where the forward pass is not a Kalman filter.** The forward pass holds several hypotheses of a
track's heading and reports the one with the most weight; where it switches side (the heading turning
by more than :data:`SIDE_SWITCH_RAD` in one scan) a life is split for smoothing, since smoothing
across would average the two sides. Where it throws information away outside the filter (a turn rate
forgotten after a rejected heading, the heading replaced by another hypothesis's), the smoother's
prediction into that scan is widened (:func:`resets`) so that the reset value is not read as a
measurement.

**Sides re-decided.** Before that, each scan's side is chosen again among the hypotheses the forward
pass kept, from the evidence of the ``heading_memory`` after the scan as well as before
(:mod:`gtsjax.core.smooth_sides`); where another side wins, the state's heading at that scan becomes
that hypothesis's (its variance, no correlation with the rest of the state), and the episode is
smoothed on its own like any other side. (Giving each episode the side that ended it, back through the
scans before the switch, was tried first: it changed the two-laser match's heading RMSE by 0.06°.)
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.geometry import wrap
from ..core.pipeline import init_state
from ..core.smooth import smooth_tracks
from ..core.smooth_sides import SIDE_RAD, smooth_sides

#: A heading turning more than this in one scan switched side: a robot turns at most a few radians a
#: second, a tenth of a radian a scan at 10 Hz.
SIDE_SWITCH_RAD = SIDE_RAD


#: Bytes ``replay --smooth`` holds per scan, as a multiple of the track table's state (the forward
#: pass's outputs and filtered states kept for the whole log, then the smoother's arrays over all of
#: them). Measured: peak memory of ``replay --smooth`` grew by 12.3 kB a scan between logs of 6 000 and
#: 20 000 scans with the demo model (8 slots, a 1.97 kB track table): 6.2 of it; 8 leaves room.
SMOOTH_BYTES_PER_STATE_BYTE = 8


def memory_needed(model, n_scans: int) -> int:
    """Bytes smoothing ``n_scans`` scans holds at once (about: :data:`SMOOTH_BYTES_PER_STATE_BYTE`),
    from the size of ``model``'s track table (site attached); nothing computed."""
    table = jax.eval_shape(init_state, model).tracker
    per_scan = sum(a.size * a.dtype.itemsize for a in jax.tree.leaves(table))
    return SMOOTH_BYTES_PER_STATE_BYTE * per_scan * int(n_scans)


def cuts(live: np.ndarray, ids: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``[T, M]``: where a slot's new life begins the scan after another left it, or its heading
    switched side."""
    cut = np.zeros_like(live)
    both = live[1:] & live[:-1]
    cut[1:] = both & ((ids[1:] != ids[:-1]) | (np.abs(wrap(heading[1:] - heading[:-1])) > SIDE_SWITCH_RAD))
    return cut


#: The variance (rad², rad²/s²) by which the smoother's prediction into a scan is widened where the
#: forward pass threw away what it knew of a heading or turn rate: as good as knowing nothing.
RESET_VAR = 100.0


def resets(live: np.ndarray, ids: np.ndarray, cov: np.ndarray, main: np.ndarray, params) -> np.ndarray:
    """``[T, M, 6]``: variances to add to the smoother's prediction into each scan where the forward
    pass reset part of a track's state outside the Kalman filter: a turn rate forgotten after a
    rejected heading (its variance set back to ``omega_var0``, uncorrelated), a heading replaced by
    another hypothesis's (the main hypothesis changed). Without them the smoother would read the
    reset value as a measurement."""
    extra = np.zeros(cov.shape[:-1], np.float32)
    same = same_track(live, ids)
    omega0 = float(np.asarray(params.omega_var0))
    forgot = same & (np.abs(cov[..., 5, 5] - omega0) < 1e-6 * max(omega0, 1.0)) & (cov[..., 2, 5] == 0)
    switched = np.zeros_like(live)
    switched[1:] = same[1:] & (main[1:] != main[:-1])
    extra[..., 5] = np.where(forgot | switched, RESET_VAR, 0.0)
    extra[..., 2] = np.where(switched, RESET_VAR, 0.0)
    return extra


def same_track(live: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``[T, M]``: the slot holds the same track as at the scan before."""
    same = np.zeros_like(live)
    same[1:] = live[1:] & live[:-1] & (ids[1:] == ids[:-1])
    return same


def resided(filtered, live: np.ndarray, ids: np.ndarray, dt: np.ndarray, params):
    """The filtered means and covariances with each scan's heading on the side chosen over the track's
    life (:func:`~gtsjax.core.smooth_sides.smooth_sides`), and each scan's hypothesis. Where the side
    changed, the heading is that hypothesis's, with its variance and no correlation with the rest."""
    mean = np.array(filtered.mean, np.float32)
    cov = np.array(filtered.cov, np.float32)
    main = np.asarray(filtered.main)
    if filtered.side_heading is None:
        return mean, cov, main
    choice, _ = smooth_sides(jnp.asarray(filtered.side_heading), jnp.asarray(filtered.side_logw), jnp.asarray(main),
                             jnp.asarray(mean[..., 5]), jnp.asarray(dt), jnp.asarray(same_track(live, ids)),
                             params.heading_memory)
    choice = np.asarray(choice)
    changed = live & (choice != main)
    pick = lambda a: np.take_along_axis(np.asarray(a), choice[..., None], axis=-1)[..., 0]  # noqa: E731
    mean[..., 2] = np.where(changed, pick(filtered.side_heading), mean[..., 2])
    cov[..., 2, :] = np.where(changed[..., None], 0.0, cov[..., 2, :])
    cov[..., :, 2] = np.where(changed[..., None], 0.0, cov[..., :, 2])
    cov[..., 2, 2] = np.where(changed, pick(filtered.side_var), cov[..., 2, 2])
    return mean, cov, choice


def smooth_output(out, filtered, stamps: np.ndarray, params, parallel: bool = True, sides: bool = True):
    """The forward pass's stacked outputs (``out``, with its :class:`~gtsjax.drivers.batch.Filtered`
    states beside them, at host ``stamps``) with each live slot's pose, variances and x–y covariance
    smoothed. ``sides``: each scan's heading side re-decided over the track's life first (:func:`resided`)."""
    live = np.asarray(out.track_live, bool)
    ids = np.asarray(out.track_id)
    dt = np.diff(np.asarray(stamps, np.float64), prepend=float(stamps[0])).astype(np.float32)
    if sides:
        mean, cov, main = resided(filtered, live, ids, dt, params)
    else:
        mean, cov, main = np.array(filtered.mean, np.float32), np.array(filtered.cov, np.float32), np.asarray(filtered.main)
    cut = cuts(live, ids, mean[..., 2])
    extra = resets(live, ids, cov, main, params)
    ms, ps = smooth_tracks(jnp.asarray(mean), jnp.asarray(cov, jnp.float32), jnp.asarray(dt), jnp.asarray(live),
                           params, parallel=parallel, cut=jnp.asarray(cut), extra=jnp.asarray(extra))
    ms, ps = np.asarray(ms), np.asarray(ps)
    smoothed = np.asarray(params.off(jnp.asarray(np.asarray(out.track_class)), jnp.asarray(ms[..., :3])))
    pose = np.where(live[..., None], smoothed, np.asarray(out.track_pose))
    var = np.asarray(params.widened(jnp.asarray(np.asarray(out.track_class)),
                                    jnp.asarray(np.diagonal(ps, axis1=-2, axis2=-1)[..., :3])))
    var = np.where(live[..., None], var, np.asarray(out.track_var))
    cov_xy = np.where(live, ps[..., 0, 1], np.asarray(out.track_cov_xy))
    return eqx.tree_at(lambda o: (o.track_pose, o.track_var, o.track_cov_xy), out,
                       (pose.astype(np.float32), var.astype(np.float32), cov_xy.astype(np.float32)))
