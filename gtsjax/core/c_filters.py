"""Stage c, binary filters: the heuristic conditions a candidate must meet before classification.

The paper applies a threshold on the bounding-box width (Sec. 4.1 c). Here a candidate is kept when
its slot is live, it is not an over-long segment, it has at least ``min_points`` measurements and
its width lies in ``[width_min, width_max]``.

Per class, the shape envelopes (:class:`Envelope`, learnt at training) then say which classes a kept
candidate may be: its width, depth and point count against range, and whether it is seen whole; the
classifier takes its argmax among those classes only (``d_classify.classify``).

The site's bounds are given in the field frame O, which the front end does not know: the pipeline
tests them (``geometry.in_bounds``) once stage f has mapped the regressed poses into O.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


def binary_filter(
    live: Bool[Array, " cands"],
    too_long: Bool[Array, " cands"],
    n_points: Int[Array, " cands"],
    width: Float[Array, " cands"],
    *,
    width_min: Float[Array, ""],
    width_max: Float[Array, ""],
    min_points: Int[Array, ""],
) -> Bool[Array, " cands"]:
    """Which candidates pass the binary filters (stage c)."""
    return live & ~too_long & (n_points >= min_points) & (width >= width_min) & (width <= width_max)


class Envelope(eqx.Module):
    """Per-class shape envelopes, learnt at training: for each class and range bin, the
    intervals that a candidate's width, depth and point count must lie in for the candidate to be of
    that class.

    The three quantities are the bounding box of the candidate's points in its ORS, across the beam
    (``width``) and along it (``depth``), and ``n_points · r``, the point count scaled by the range
    (the beams spread with range, so a solid object of a given width gives about the same ``n · r``
    at every range; a sparse one, seen through, gives fewer). Bin ``b`` covers ranges
    ``[b, b + 1) · bin_width`` and the last bin everything beyond. A class that was never seen in a
    bin takes the limits of the nearest bin it was seen in: the three quantities depend on range only
    through noise and beam spacing. The background class (index 0) is open: every candidate may be
    background.

    Why per class and per range bin, rather than the single width interval of the paper's filter:
    a 12 cm leg or a 60 cm table top passes a filter wide enough for every class, but not the
    envelope of a 20–30 cm robot seen at that range.
    """

    bin_width: Float[Array, ""]  # metres
    lo: Float[Array, "classes bins 3"]  # lower limits of (width, depth, n·r)
    hi: Float[Array, "classes bins 3"]  # upper limits
    whole: Bool[Array, " classes"]  # the class is seen unoccluded only

    @property
    def n_bins(self) -> int:
        return self.lo.shape[1]

    @classmethod
    def open(cls, n_classes: int, n_bins: int = 1) -> "Envelope":
        """An envelope that passes everything (a model trained without envelopes)."""
        inf = jnp.full((n_classes, n_bins, 3), jnp.inf, jnp.float32)
        return cls(jnp.asarray(1.0, jnp.float32), -inf, inf, jnp.zeros((n_classes,), bool))


def shape_quantities(width: Float[Array, "*c"], depth: Float[Array, "*c"], n_points: Int[Array, "*c"],
                     rng: Float[Array, "*c"]) -> Float[Array, "*c 3"]:
    """``(width, depth, n_points · r)`` of each candidate: what :class:`Envelope` bounds."""
    return jnp.stack([width, depth, n_points.astype(width.dtype) * rng], axis=-1)


def envelope_pass(env: Envelope, q: Float[Array, "cands 3"], rng: Float[Array, " cands"]) -> Bool[Array, "cands classes"]:
    """Which classes' shape envelopes each candidate lies in (``q`` from :func:`shape_quantities`,
    ``rng`` its range). One gather of the candidate's range bin, then elementwise comparisons."""
    b = jnp.clip(jnp.floor(rng / env.bin_width).astype(jnp.int32), 0, env.n_bins - 1)
    lo = jnp.swapaxes(env.lo[:, b], 0, 1)  # [cands, classes, 3]
    hi = jnp.swapaxes(env.hi[:, b], 0, 1)
    qq = q[:, None, :]
    return jnp.all((qq >= lo) & (qq <= hi), axis=-1)


def partial_view(env: Envelope, cls: Int[Array, " cands"], occluded: Bool[Array, " cands"]) -> Bool[Array, " cands"]:
    """Candidates occluded at an end (``Candidates.occluded``) whose class is seen whole: the tracker
    lets them update a confirmed track only, never start or confirm one."""
    return occluded & env.whole[cls]
