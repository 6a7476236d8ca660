"""Stage c, binary filters: the heuristic conditions a candidate must meet before classification.

The paper applies a threshold on the bounding-box width (Sec. 4.1 c). Here a candidate is kept when
its slot is live, it is not an over-long segment, it has at least ``min_points`` measurements and
its width lies in ``[width_min, width_max]``.

The site's bounds are given in the field frame O, which the front end does not know: the map
transformation (stage f) maps candidates into O later in the step. So the bounds test is its own
function of positions in O, :func:`in_bounds`, which the pipeline applies (``keep & in_bounds(...)``)
once the ORS origins (or the regressed poses) have been mapped into O; :func:`binary_filter` also
takes the mapped origins and the bounds directly, when the caller already has them.
"""

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
    origin_o: Float[Array, "cands 2"] | None = None,
    bounds: Float[Array, "4"] | None = None,
) -> Bool[Array, " cands"]:
    """Which candidates pass the binary filters (stage c).

    ``origin_o`` (ORS origins mapped into O) and ``bounds`` (``[xmin, ymin, xmax, ymax]`` in O) are
    optional and used only together; without them no bounds test is made.
    """
    keep = live & ~too_long & (n_points >= min_points) & (width >= width_min) & (width <= width_max)
    if origin_o is not None and bounds is not None:
        keep = keep & in_bounds(origin_o, bounds)
    return keep


def in_bounds(xy: Float[Array, "*n 2"], bounds: Float[Array, "4"]) -> Bool[Array, "*n"]:
    """Whether points of O lie inside ``bounds = [xmin, ymin, xmax, ymax]`` (edges included).
    Non-finite points are outside."""
    x, y = xy[..., 0], xy[..., 1]
    return (x >= bounds[0]) & (y >= bounds[1]) & (x <= bounds[2]) & (y <= bounds[3])
