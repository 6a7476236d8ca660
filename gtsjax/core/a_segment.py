"""Stage a, segmentation: a padded scan into at most ``K`` object candidates of at most ``L`` beams.

The paper groups consecutive measurements whose Euclidean distance is below a criterion (Sec. 4.1 a,
Fig. 2). Here a candidate is a maximal run of consecutive valid beams with no break inside it, where
a break sits before beam ``i`` when

* beam ``i`` is the first of the scan, or beam ``i − 1`` is invalid (a hole, padding, a bad range), or
* ``‖p_i − p_{i−1}‖ > d0 + g · min(r_i, r_{i−1})``: the gap exceeds a base distance ``d0`` that grows
  by ``g`` per metre of the nearer range (neighbouring beams spread apart with range, and so does the
  range noise).

Everything runs on fixed shapes: break flags; the runs' start beams, all of them when there are at
most ``K``, else the ``K`` whose first return is nearest (``top_k``), in beam order; each run's end,
the first end beam after its start (a reverse running minimum); a gather pulls each run's window of
``L`` beams, and whether a nearer return lies just beside either end (the candidate is occluded
there). Nothing is dropped silently: runs beyond ``K`` (the farthest) are counted in ``n_overflow``; a run longer
than ``L`` beams is kept as a slot with ``too_long`` set and an *empty* point mask, so it can never be
truncated into a smaller, false object (a long wall is not a robot).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .scan import Scan

_F32 = jnp.float32
_I32 = jnp.int32


class Candidates(eqx.Module):
    """``K`` segments of one scan (all of them, or the ``K`` nearest), each as a window of ``L`` beams
    (stack: leading ``scans``).

        Slot ``k`` holds the ``k``-th kept segment in beam order when ``live[k]``; its beams are
        ``index[k, l] = start[k] + l`` for ``l < length[k]``. ``mask`` marks the window entries that are
        the segment's measurements; it is all False for dead slots and for ``too_long`` segments.
        ``ranges``, ``angles``, ``xy`` (the points in S) and ``intensities`` are gathered from the scan and 0
    where ``mask`` is False. These per-beam windows are None where batch training drops them
    (``frontend.front_end_batch(windows=False)``).
    """

    index: Int[Array, "*scans cands window"] | None
    mask: Bool[Array, "*scans cands window"] | None
    ranges: Float[Array, "*scans cands window"] | None
    angles: Float[Array, "*scans cands window"] | None
    xy: Float[Array, "*scans cands window 2"] | None  # the measurements in S, Cartesian
    intensities: Float[Array, "*scans cands window"] | None
    live: Bool[Array, "*scans cands"]  # the slot holds a segment
    too_long: Bool[Array, "*scans cands"]  # the segment has more than L beams (mask empty)
    start: Int[Array, "*scans cands"]  # first beam of the segment (n_beams for dead slots)
    length: Int[Array, "*scans cands"]  # beams in the segment, untruncated (0 for dead slots)
    n_segments: Int[Array, "*scans"]  # segments found in the scan, including those beyond K
    n_overflow: Int[Array, "*scans"]  # segments beyond K, not in any slot
    n_too_long: Int[Array, "*scans"]  # live slots with too_long set
    # A return nearer than the segment's end lies just beside it (the beam before its first or after
    # its last): something stands in front of it there, so its outline may be cut short.
    occluded: Bool[Array, "*scans cands"]

    @property
    def max_candidates(self) -> int:
        return self.index.shape[-2]

    @property
    def window(self) -> int:
        return self.index.shape[-1]


def break_flags(
    ranges: Float[Array, " beams"],
    x: Float[Array, " beams"],
    y: Float[Array, " beams"],
    valid: Bool[Array, " beams"],
    break_distance: Float[Array, ""],
    break_growth: Float[Array, ""],
) -> tuple[Bool[Array, " beams"], Bool[Array, " beams"]]:
    """``(starts, ends)``: valid beams that open and close a segment; ``x``, ``y`` are the points in S.

    Squared distances are compared, so no square root is taken on padded or invalid beams.
    """
    d2 = (x[1:] - x[:-1]) ** 2 + (y[1:] - y[:-1]) ** 2
    thr = break_distance + break_growth * jnp.minimum(ranges[1:], ranges[:-1])
    joined = valid[1:] & valid[:-1] & (d2 <= thr * thr)  # beam i+1 continues beam i's segment
    no = jnp.zeros((1,), dtype=bool)
    starts = valid & ~jnp.concatenate([no, joined])
    ends = valid & ~jnp.concatenate([joined, no])
    return starts, ends


def segment(
    scan: Scan,
    *,
    max_candidates: int,
    window: int,
    break_distance: Float[Array, ""],
    break_growth: Float[Array, ""],
) -> Candidates:
    """Segment one scan (stage a) into ``max_candidates`` slots of ``window`` beams.

    ``break_distance`` (m) and ``break_growth`` (m per m of range) set the break criterion (see the
    module docstring). Invalid beams always break a segment and never belong to one; so do beams
    marked valid whose range is not finite and positive.
    """
    n = scan.n_beams
    k_max, win = max_candidates, window
    angles = scan.angles()
    # Defensive: a beam marked valid with a non-finite or non-positive range is treated as invalid,
    # and invalid beams' values are zeroed before any arithmetic (finite values and gradients).
    valid = scan.valid & jnp.isfinite(scan.ranges) & (scan.ranges > 0)
    ranges = jnp.where(valid, scan.ranges, 0.0)
    intensities = jnp.where(valid & jnp.isfinite(scan.intensities), scan.intensities, 0.0)
    # Points in S once per beam: the candidates' ORS needs no trigonometry per window entry.
    x = ranges * jnp.cos(angles)
    y = ranges * jnp.sin(angles)
    starts, ends = break_flags(ranges, x, y, valid, break_distance, break_growth)
    beam = jnp.arange(n, dtype=_I32)
    # Segment number of each start/end beam: the count of starts up to and including it, minus one.
    n_segments = jnp.sum(starts, dtype=_I32)
    # The slots take every segment when there are at most K, else the K whose first return is nearest:
    # what lies beyond a field (far walls, cut into many pieces by the shadows of everything nearer)
    # goes before what stands on it. A UTM-30LX beside a 9 × 6 m field in a hall sees 40 segments,
    # and keeping the first K in beam order dropped the robots at one end of its view. The slots stay
    # in beam order (a sort of the chosen start beams; ties of range go to the lower beam).
    key = jnp.where(starts, -ranges, -jnp.inf)
    top, first = jax.lax.top_k(key, k_max)
    start = jnp.sort(jnp.where(top > -jnp.inf, first, n).astype(_I32))
    # Each segment's end: the first end beam at or after its start (a reverse running minimum).
    next_end = jnp.flip(jax.lax.cummin(jnp.flip(jnp.where(ends, beam, n - 1))))
    live = jnp.arange(k_max, dtype=_I32) < n_segments
    end = jnp.where(live, next_end[jnp.minimum(start, n - 1)], n - 1)
    length = jnp.where(live, end - start + 1, 0)
    too_long = live & (length > win)

    offset = jnp.arange(win, dtype=_I32)
    index = jnp.minimum(start[:, None] + offset[None, :], n - 1)
    mask = (live & ~too_long)[:, None] & (offset[None, :] < length[:, None])

    def take(a):
        return jnp.where(mask, a[index], jnp.zeros((), a.dtype))

    def nearer(beside, end):
        inside = (beside >= 0) & (beside < n)
        b = jnp.clip(beside, 0, n - 1)
        return inside & valid[b] & (ranges[b] < ranges[jnp.clip(end, 0, n - 1)])

    last = start + length - 1
    occluded = live & (nearer(start - 1, start) | nearer(last + 1, last))

    return Candidates(
        index=index,
        mask=mask,
        ranges=take(ranges),
        angles=take(angles),
        xy=jnp.stack([take(x), take(y)], axis=-1),
        intensities=take(intensities),
        live=live,
        too_long=too_long,
        start=start,
        length=length,
        n_segments=n_segments,
        n_overflow=jnp.maximum(n_segments - k_max, 0),
        n_too_long=jnp.sum(too_long, dtype=_I32),
        occluded=occluded,
    )
