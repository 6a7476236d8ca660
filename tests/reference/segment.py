"""Stage a, segmentation: a break between two consecutive beams wherever either has no return or
their points lie farther apart than ``break_distance + break_growth · min(r_i, r_i+1)``."""

import numpy as np


def segments(ranges, valid, angles, break_distance: float, break_growth: float, max_segments: int):
    """``(start, end)`` beam indices of the segments, in beam order: all of them, or where there are
    more than ``max_segments`` the ``max_segments`` whose first return is nearest (ties: the lower
    beam); the ranges (0 where invalid) and the points in S."""
    valid = valid & np.isfinite(ranges) & (ranges > 0)
    r = np.where(valid, ranges, 0.0)
    x, y = r * np.cos(angles), r * np.sin(angles)
    d2 = np.diff(x) ** 2 + np.diff(y) ** 2
    thr = break_distance + break_growth * np.minimum(r[1:], r[:-1])
    joined = valid[1:] & valid[:-1] & (d2 <= thr * thr)
    starts = np.flatnonzero(valid & ~np.concatenate([[False], joined]))
    ends = np.flatnonzero(valid & ~np.concatenate([joined, [False]]))
    pairs = list(zip(starts, ends, strict=True))
    if len(pairs) > max_segments:
        nearest = sorted(range(len(pairs)), key=lambda i: (r[pairs[i][0]], pairs[i][0]))[:max_segments]
        pairs = [pairs[i] for i in sorted(nearest)]
    return pairs, r, x, y
