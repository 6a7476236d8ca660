"""Stage g's association: which detection updates which track. Every detection is gated against every
predicted track on position (a misread side can throw the heading off by 90° or more), then assigned
one to one, greedily on the Mahalanobis distance, with a fallback pass that recaptures a track left
without a detection by one too close to it to start a track of its own. Partial views and guesses
only follow confirmed tracks, guesses only near their prediction. :mod:`~gtsjax.core.g_track`
describes the rules and why.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .g_kalman import mahalanobis
from .g_types import DetectionFlags, Detections, TrackerParams, TrackerState, _select

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


def assign(
    cost: Float[Array, "dets tracks"], fallback: Float[Array, "dets tracks"] | None = None
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
        c, f, idx = jax.lax.reduce(
            (jnp.where(taken, inf, cost), jnp.where(taken, inf, fallback), flat), init, first, (0, 1)
        )
        i, j = idx // m, idx % m
        col = ((c < inf) | (f < inf)) & (cols[0] == j)
        det_of_track = jnp.where(col, i, det_of_track)
        has = has | col
        taken = taken | (rows == i) | (cols == j)  # a round that takes none leaves only forbidden pairs
    return det_of_track, has


class Association(NamedTuple):
    """The assignment of one scan's detections to the predicted tracks (:func:`associate`)."""

    det_of_track: Int[Array, " tracks"]  # the detection each track takes, where ``has``
    has: Bool[Array, " tracks"]
    used: Bool[Array, " dets"]  # the detections a track takes
    other_near: Bool[Array, " tracks"]  # an ``other`` candidate lies within ``birth_exclusion`` of it


def associate(state: TrackerState, det: Detections, flags: DetectionFlags, params: TrackerParams) -> Association:
    """Gate every detection against every predicted track of its class and assign them one to one
    (:func:`assign`): first within the class's gate, then, among what is left, a detection within
    ``birth_exclusion`` of a track (recapture). Also which tracks have an ``other`` candidate near
    their prediction, for the majority test of their confirmation."""
    d2 = jax.vmap(lambda z, R: jax.vmap(lambda mu, P: mahalanobis(mu, P, z, R))(state.mean, state.cov))(
        det.pose, det.cov
    )  # [K, M]
    # A partial detection (an occluded view of a class seen whole) only follows a confirmed track.
    # So does a guess (a candidate the classifier took for something else), near its prediction only.
    may_update = flags.whole[:, None] | state.confirmed[None, :]  # [K, M]
    dist = jnp.linalg.norm(det.pose[:, None, :2] - state.mean[None, :, :2], axis=-1)  # [K, M]
    # A guess only keeps a track that was updated in the scan before where it is predicted: within
    # GUESS_RADIUS, not the gate a coasting track's grown covariance opens (a person's legs in front
    # of a hidden robot fit its outline too).
    near_prediction = ~flags.guess[:, None] | ((dist < GUESS_RADIUS) & (state.misses <= GUESS_MISSES)[None, :])
    same_class = det.class_id[:, None] == state.class_id[None, :]
    gated = (
        flags.tracked[:, None]
        & may_update
        & near_prediction
        & state.live[None, :]
        & same_class
        & (d2 <= _select(params.gate, det.class_id)[:, None])
    )
    # Recapture: a detection too close to a live track of its class to start one of its own
    # (``birth_exclusion``) goes to that track, nearest first, if both are left unmatched by the
    # gated assignment, whatever the gate says: the fallback pass of the same assignment.
    close = (
        (flags.tracked & ~flags.guess)[:, None]
        & may_update
        & state.live[None, :]
        & same_class
        & (dist < params.birth_exclusion)
    )
    det_of_track, has = assign(jnp.where(gated, d2, jnp.inf), jnp.where(close, dist, jnp.inf))
    # The detections taken (one-hot against an iota, not a scatter).
    used = jnp.any(
        has[None, :] & (det_of_track[None, :] == jnp.arange(det.mask.shape[0], dtype=jnp.int32)[:, None]), axis=1
    )
    # Majority confirmation: an ``other`` candidate near a track's predicted position (the same
    # distances), counted for tentative tracks left without a detection (``g_life``).
    other_near = jnp.any(flags.other[:, None] & (dist < params.birth_exclusion), axis=0)  # [M]
    return Association(det_of_track, has, used, other_near)
