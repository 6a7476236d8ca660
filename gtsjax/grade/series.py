"""Pose series in time: a robot's beliefs and a track's rows are both stamps and poses (x, y, θ),
sampled when their source had them. Grading compares them at common instants, so each is read at
other stamps by interpolation: linear in position, and in the heading along the shorter way round
(the series is unwrapped first, so a heading crossing ±π interpolates through π, not through 0).

A series says nothing between two samples far apart (a robot that stopped publishing, a track
that lost its robot): :func:`interpolate` answers only where both neighbours are within ``max_gap``
of each other, and never outside the series' span.
"""

import numpy as np

from ..core.geometry import compose, relative, wrap


def interpolate(t: np.ndarray, stamps: np.ndarray, poses: np.ndarray, max_gap: float,
                heading: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``poses`` (``[n, 3]``, at increasing ``stamps``) read at the times ``t``: ``(values [len(t), 3],
    ok [len(t)])``; ``ok`` false (values NaN) outside the span or between samples more than ``max_gap``
    apart. A time equal to a sample's stamp reads that sample. ``heading``: the poses' headings
    unwrapped already (``np.unwrap(poses[:, 2])``), for a caller that reads one series many times."""
    t = np.asarray(t, np.float64)
    out = np.full(t.shape + (3,), np.nan)
    n = stamps.size
    if n == 0:
        return out, np.zeros(t.shape, bool)
    j = np.searchsorted(stamps, t, side="right")  # stamps[j-1] <= t < stamps[j]
    exact_last = (n > 0) & (t == stamps[-1])
    lo = np.clip(j - 1, 0, n - 1)
    hi = np.clip(j, 0, n - 1)
    hi = np.where(exact_last, lo, hi)
    inside = (j >= 1) & ((j <= n - 1) | exact_last)
    gap = stamps[hi] - stamps[lo]
    ok = inside & (gap <= max_gap)
    heading = np.unwrap(poses[:, 2]) if heading is None else heading
    w = np.where(gap > 0, (t - stamps[lo]) / np.where(gap > 0, gap, 1.0), 0.0)
    xy = poses[lo, :2] + w[..., None] * (poses[hi, :2] - poses[lo, :2])
    th = wrap(heading[lo] + w * (heading[hi] - heading[lo]))
    out[ok, :2] = xy[ok]
    out[ok, 2] = th[ok]
    return out, ok


def transform(poses: np.ndarray, frame: tuple[float, float, float]) -> np.ndarray:
    """Poses mapped by the planar transform ``frame = (tx, ty, φ)``: ``p ↦ R(φ) p + t``, ``θ ↦ θ + φ``
    (wrapped): :func:`~gtsjax.core.geometry.compose` with the heading wrapped."""
    out = compose(np.asarray(frame, np.float64), np.asarray(poses))
    out[..., 2] = wrap(out[..., 2])
    return out


def mirror_frame(centre: tuple[float, float]) -> tuple[float, float, float]:
    """The other team's frame: the field turned half a turn about its centre (as a transform from
    that frame to the field's; it is its own inverse)."""
    cx, cy = centre
    return (2.0 * cx, 2.0 * cy, np.pi)


def invert(frame: tuple[float, float, float]) -> tuple[float, float, float]:
    """The inverse of :func:`transform`'s ``frame``: the field's origin seen from the frame."""
    inv = relative(np.asarray(frame, np.float64), np.zeros(3))
    return (float(inv[0]), float(inv[1]), float(-frame[2]))
