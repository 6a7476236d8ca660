"""A robot's clock against the laptop's: the offset ``δ`` (robot clock − laptop clock, s) at which its
beliefs agree best with the ground truth.

Two passes, as the motion of a robot pins its clock:

* **coarse**, over the whole allowed range (``--max-offset``) on a 50 ms grid, before anyone knows
  which track is the robot: per 1 s window, the best agreement of the belief with *any* track (the
  mean of a capped squared distance, :data:`CAP_M`), summed over windows. Where the robot's frame is
  known that agreement is of poses; where it is to be fitted (``--frame NAME=fit``) poses cannot be
  compared yet, and it is of the motion profiles, speed and turn rate over 1 s, which no rigid
  transform changes.
* **fine**, on a 1 ms grid about the coarse value, against the robot's own tracks once the
  association has found them: the pose error with the robot's constant bias in its own frame taken
  out (a robot walking forwards that places itself 3 cm ahead looks 0.1 s early at 0.3 m/s; the two
  part only where it turns or changes speed, so they are estimated together, and the bias is reported
  as a finding of its own). The uncertainty is a block bootstrap over the 1 s windows (the errors
  of a self-localisation are correlated over a second or so, so samples are not independent).
"""

from dataclasses import dataclass

import numpy as np

from ..core.geometry import relative, wrap
from .series import interpolate, transform
from .truth import belief_profiles

#: Agreement is of distances capped here (m): a robot kidnapped 1 m off, or a track of another robot,
#: costs the same as one far off, whatever the distance.
CAP_M = 0.3
#: Windows (s) over which agreement is averaged before the best track is taken.
WINDOW_S = 1.0
COARSE_STEP_S = 0.1
#: The fine search: first a grid this far either side of the coarse value, with each row's cost
#: capped (a robust look for the least cost); then a grid :data:`NARROW_HALF_S` either side of that,
#: over the rows that are inliers at every offset of it, the least cost placed between grid points by
#: a parabola (the cost is smooth in the offset there, so the parabola places it to well under a
#: millisecond).
FINE_HALF_S = 0.3
NARROW_HALF_S = 0.05
FINE_STEP_S = 0.005
#: Motion profiles: a speed difference of this much (m/s) or a turn-rate difference of this much
#: (rad/s) counts as much as :data:`CAP_M` of distance.
PROFILE_SPEED = 0.1
PROFILE_TURN = 0.4
#: Heading residuals weigh as this many metres per radian in the fine search.
HEADING_M_PER_RAD = 0.2
BOOTSTRAP = 200
#: The bootstrap resamples blocks of this many windows: a self-localisation's error is correlated
#: over a second or more, and so are the speed's changes that tell the clock from a bias ahead.
BLOCK_WINDOWS = 5


@dataclass(frozen=True)
class Belief:
    """One robot's beliefs ready to compare: its own stamps and poses, and the transform taking its
    frame to the field's."""

    stamps: np.ndarray
    poses: np.ndarray
    frame: tuple[float, float, float]
    max_gap: float

    def __post_init__(self):
        object.__setattr__(self, "heading", np.unwrap(self.poses[:, 2]))

    def raw(self, t: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray]:
        """The belief at laptop times ``t`` for clock offset ``offset``, in its own frame."""
        return interpolate(t + offset, self.stamps, self.poses, self.max_gap, self.heading)

    def at(self, t: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray]:
        """The belief at laptop times ``t`` for clock offset ``offset``, in the field's frame."""
        p, ok = self.raw(t, offset)
        return transform(p, self.frame), ok

    def with_frame(self, frame: tuple[float, float, float]) -> "Belief":
        return Belief(self.stamps, self.poses, frame, self.max_gap)


def windowed_best(cost: np.ndarray, track: np.ndarray, window: np.ndarray, n_tracks: int, n_windows: int,
                  cover: np.ndarray) -> np.ndarray:
    """Per window, the least mean ``cost`` over the tracks that cover at least half their rows of it
    with a cost (NaN costs are rows without a belief); NaN for a window with none. ``cover``:
    ``[n_tracks, n_windows]`` rows of each track in each window."""
    ok = np.isfinite(cost)
    flat = track * n_windows + window
    size = n_tracks * n_windows
    s = np.bincount(flat[ok], cost[ok], size).reshape(n_tracks, n_windows)
    c = np.bincount(flat[ok], None, size).reshape(n_tracks, n_windows)
    mean = np.where(c >= 0.5 * cover, s / np.maximum(c, 1), np.inf)
    mean[c == 0] = np.inf
    best = mean.min(axis=0)
    return np.where(np.isfinite(best), best, np.nan)


@dataclass(frozen=True)
class Rows:
    """The rows a search runs over: stamps, track index, pose, window index, and the tracks' speed
    and turn rate (for profiles)."""

    stamps: np.ndarray
    track: np.ndarray
    poses: np.ndarray
    window: np.ndarray
    speed: np.ndarray
    turn: np.ndarray
    n_tracks: int
    n_windows: int

    def subset(self, keep: np.ndarray) -> "Rows":
        return Rows(self.stamps[keep], self.track[keep], self.poses[keep], self.window[keep], self.speed[keep],
                    self.turn[keep], self.n_tracks, self.n_windows)

    def cover(self) -> np.ndarray:
        return np.bincount(self.track * self.n_windows + self.window, None,
                           self.n_tracks * self.n_windows).reshape(self.n_tracks, self.n_windows)


def coarse_curve(rows: Rows, belief: Belief, offsets: np.ndarray, profile: bool) -> np.ndarray:
    """The coarse cost at each offset: the mean over windows of the best track's mean capped cost
    (NaN where fewer than a quarter of the windows had a belief to compare)."""
    cover = rows.cover()
    out = np.full(offsets.size, np.nan)
    n_seen = max(1, int(np.count_nonzero(cover.sum(axis=0))))
    for i, d in enumerate(offsets):
        if profile:
            sp, tr = belief_profiles(rows.stamps + d, belief.stamps, belief.poses, belief.max_gap)
            e = ((sp - rows.speed) / PROFILE_SPEED) ** 2 + (wrap(tr - rows.turn) / PROFILE_TURN) ** 2
            cost = np.minimum(e, 1.0)
        else:
            b, ok = belief.at(rows.stamps, d)
            e = np.where(ok, np.sum((b[:, :2] - rows.poses[:, :2]) ** 2, -1), np.nan)
            cost = np.minimum(e, CAP_M**2) / CAP_M**2
        best = windowed_best(cost, rows.track, rows.window, rows.n_tracks, rows.n_windows, cover)
        seen = np.isfinite(best)
        if seen.sum() >= 0.25 * n_seen:
            out[i] = float(np.mean(best[seen]))
    return out


def coarse_offset(rows: Rows, belief: Belief, max_offset: float, profile: bool, centre: float = 0.0
                  ) -> tuple[float, np.ndarray, np.ndarray]:
    """The coarse offset (its grid, and the cost on it) within ``centre ± max_offset``."""
    n = int(round(max_offset / COARSE_STEP_S))
    offsets = centre + COARSE_STEP_S * np.arange(-n, n + 1)
    curve = coarse_curve(rows, belief, offsets, profile)
    if not np.isfinite(curve).any():
        return float("nan"), offsets, curve
    return float(offsets[np.nanargmin(curve)]), offsets, curve


@dataclass(frozen=True)
class Clock:
    offset: float  # s, robot clock − laptop clock
    se: float  # s, its standard error (bootstrap over windows)
    bias: tuple[float, float, float]  # the belief's mean error in its own frame: ahead (m), left (m), heading (rad)
    fixed: bool = False  # given with --offset, not estimated


def _residuals(t: np.ndarray, truth: np.ndarray, belief: Belief, d: float):
    """Per row, the belief's error at offset ``d`` in the belief's own frame (ahead, left, heading·w),
    NaN where there is no belief."""
    b, ok = belief.at(t, d)
    r = -relative(b, truth)  # the truth seen from the belief, turned round: the belief's error
    r[:, 2] *= HEADING_M_PER_RAD
    r[~ok] = np.nan
    return r


def _grid(centre: float, half: float) -> np.ndarray:
    n = int(round(half / FINE_STEP_S))
    return centre + FINE_STEP_S * np.arange(-n, n + 1)


def _prior(t: np.ndarray) -> float:
    """The weight of the prior that a self-localisation has no bias, as a share of the rows: one
    second's worth of them. Where the robot's motion tells its clock from a bias (it turns, changes
    speed) this is nothing beside the rows' evidence; where it cannot (a robot walking a straight
    line at one speed: ahead by 3 cm and 0.1 s early look the same), it picks the offset with the
    smaller bias rather than anywhere along the valley, and the bootstrap says how wide the valley is."""
    span = float(t.max() - t.min()) if t.size > 1 else 1.0
    return 1.0 / max(span, 1.0)


def _robust_offset(t: np.ndarray, truth: np.ndarray, belief: Belief, around: float) -> float:
    """The offset about ``around`` (± :data:`FINE_HALF_S`) with the least mean capped squared error
    once each offset's median error (the bias, shrunk as :func:`_prior` says) is taken out: robust to
    kidnaps and to rows that cross a jump of the belief as the offset changes, and to a start a few
    tenths of a second off."""
    offsets = _grid(around, FINE_HALF_S)
    cost = np.full(offsets.size, np.inf)
    prior = _prior(t)
    for i, d in enumerate(offsets):
        r = _residuals(t, truth, belief, d)
        r = r[np.all(np.isfinite(r), -1)]
        if r.shape[0] >= 10:
            m = np.median(r, axis=0) / (1.0 + prior)
            cost[i] = float(np.mean(np.minimum(np.sum((r - m) ** 2, -1), CAP_M**2)) + prior * np.sum(m**2))
    return float(offsets[int(np.argmin(cost))]) if np.isfinite(cost).any() else around


def fine_offset(t: np.ndarray, truth: np.ndarray, window: np.ndarray, belief: Belief, around: float,
                rng: np.random.Generator, fixed: float | None = None, wide: bool = True) -> Clock:
    """The fine offset about ``around`` against the robot's own rows (``t``, ``truth`` poses, their
    window index), with its block bootstrap standard error and the bias estimated with it; ``fixed``:
    the offset given, only the bias estimated; ``wide``: look :data:`FINE_HALF_S` either side first
    (else only :data:`NARROW_HALF_S`)."""
    if fixed is not None:
        offsets = np.array([fixed])
    else:
        offsets = _grid(_robust_offset(t, truth, belief, around) if wide else around, NARROW_HALF_S)
    _, win = np.unique(window // BLOCK_WINDOWS, return_inverse=True)
    n_w = int(win.max()) + 1 if win.size else 0
    # Inliers: rows whose error is within the cap of the median at every offset of the narrow grid (a
    # kidnap, a wrong side of the track's heading, are left out of the clock, not averaged into it;
    # and a row near a jump of the belief, which some offsets put before the jump and some after, is
    # left out at all of them, or the cost would step wherever it changes sides).
    res = np.stack([_residuals(t, truth, belief, d) for d in offsets])
    mid = res[len(offsets) // 2]
    med = np.nanmedian(mid, axis=0) if np.isfinite(mid).any() else np.zeros(3)
    inlier = np.all(np.isfinite(res), (0, 2)) & np.all(np.linalg.norm(res - med, axis=-1) < CAP_M, axis=0)
    if inlier.sum() < 10:
        return Clock(float(offsets[len(offsets) // 2]), float("nan"), tuple(float(v) for v in med), fixed is not None)
    res, wi = res[:, inlier], win[inlier]
    s1 = np.stack([np.stack([np.bincount(wi, r[:, j], n_w) for j in range(3)], -1) for r in res])
    s2 = np.stack([np.bincount(wi, np.sum(r**2, -1), n_w) for r in res])
    cnt = np.broadcast_to(np.bincount(wi, None, n_w), s2.shape)

    def best(weights: np.ndarray) -> tuple[float, np.ndarray]:
        S1 = np.einsum("w,iwj->ij", weights, s1)
        S2 = s2 @ weights
        N = np.maximum(cnt @ weights, 1)
        lam = prior * N
        cost = (S2 - np.sum(S1**2, -1) / (N + lam)) / N  # what is left once the (shrunk) bias is taken out
        i = int(np.argmin(cost))
        d = float(offsets[i])
        if 0 < i < offsets.size - 1:  # a parabola through the least cost and its neighbours
            a, b, c = cost[i - 1], cost[i], cost[i + 1]
            den = a - 2 * b + c
            if den > 0:
                d += 0.5 * (a - c) / den * FINE_STEP_S
        return d, S1[i] / (N[i] + lam[i])

    prior = _prior(t)
    d, bias = best(np.ones(n_w))
    if fixed is not None or n_w < 4:
        se = float("nan")
    else:
        draws = rng.integers(0, n_w, (BOOTSTRAP, n_w))
        boot = [best(np.bincount(k, None, n_w).astype(float))[0] for k in draws]
        se = float(np.std(boot))
    bias = (float(bias[0]), float(bias[1]), float(bias[2] / HEADING_M_PER_RAD))
    return Clock(d, se, bias, fixed is not None)
