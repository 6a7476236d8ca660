"""The robot's frame against the field's, where it is asked to be fitted (``--frame NAME=fit``).

A robot that localises in a frame turned or moved from the field's (the other team's frame, or a map
built wrong) matches no track by position, so the fit starts from what no rigid transform changes,
the robot's motion: with the clock's coarse offset from motion profiles, each 5 s stretch of a track
whose speed and turn rate follow the belief's gives a hypothesis (the least-squares rigid transform
of the belief onto the track, :func:`kabsch`); the hypothesis under which the most windows of the
belief lie within :data:`~gtsjax.grade.clock.CAP_M` of some track wins (RANSAC over stretches), and is
refined by least squares over the robot's own rows once they are associated.
"""

import numpy as np

from ..core.geometry import compose, relative, wrap
from .clock import CAP_M, PROFILE_SPEED, PROFILE_TURN, Belief, Rows, windowed_best
from .series import interpolate
from .truth import belief_profiles

HYPOTHESIS_S = 5.0
MAX_HYPOTHESES = 400


def kabsch(p: np.ndarray, q: np.ndarray) -> tuple[float, float, float]:
    """The rigid transform ``(tx, ty, φ)`` taking points ``p [n, 2]`` closest to ``q [n, 2]`` in least
    squares."""
    pm, qm = p.mean(0), q.mean(0)
    a, b = p - pm, q - qm
    phi = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))
    c, s = np.cos(phi), np.sin(phi)
    t = qm - np.array([c * pm[0] - s * pm[1], s * pm[0] + c * pm[1]])
    return float(t[0]), float(t[1]), phi


def _apply(frame, xy: np.ndarray) -> np.ndarray:
    """Points ``xy`` of the robot's frame in the field's, under ``frame``."""
    return compose(np.asarray(frame, np.float64), xy)


def ransac_frame(rows: Rows, stamps: np.ndarray, poses: np.ndarray, max_gap: float, offset: float,
                 rng: np.random.Generator) -> tuple[tuple[float, float, float] | None, float]:
    """The frame hypothesis most windows agree with, and the share of windows that do (None where no
    stretch of any track moved like the belief)."""
    raw, ok = interpolate(rows.stamps + offset, stamps, poses, max_gap)
    sp, tr = belief_profiles(rows.stamps + offset, stamps, poses, max_gap)
    prof = np.minimum(((sp - rows.speed) / PROFILE_SPEED) ** 2 + (wrap(tr - rows.turn) / PROFILE_TURN) ** 2, 4.0)
    half = int(round(HYPOTHESIS_S / 2))
    stretch = rows.window // max(1, 2 * half + 1)
    n_s = int(stretch.max()) + 1 if stretch.size else 0
    flat = rows.track * n_s + stretch
    good = ok & np.isfinite(prof)
    s = np.bincount(flat[good], prof[good], rows.n_tracks * n_s)
    c = np.bincount(flat[good], None, rows.n_tracks * n_s)
    mean = np.where(c >= 8, s / np.maximum(c, 1), np.inf)
    cand = np.flatnonzero(np.isfinite(mean))
    cand = cand[np.argsort(mean[cand])][:MAX_HYPOTHESES]
    if cand.size == 0:
        return None, 0.0
    cover = rows.cover()
    n_seen = max(1, int(np.count_nonzero(np.bincount(rows.window[ok], None, rows.n_windows))))
    best, best_score = None, -1.0
    for f in cand:
        sel = good & (flat == f)
        xy = raw[sel, :2]
        if np.ptp(xy, axis=0).max() < 0.2:  # a stretch standing still says nothing of the rotation
            continue
        hyp = kabsch(xy, rows.poses[sel, :2])
        moved = _apply(hyp, raw[:, :2])
        d2 = np.where(ok, np.sum((moved - rows.poses[:, :2]) ** 2, -1), np.nan)
        w = windowed_best(np.minimum(d2, 4 * CAP_M**2), rows.track, rows.window, rows.n_tracks, rows.n_windows, cover)
        score = float(np.sum(w < CAP_M**2)) / n_seen
        if score > best_score:
            best, best_score = hyp, score
    return best, max(best_score, 0.0)


def refine_frame(t: np.ndarray, truth: np.ndarray, belief: Belief, offset: float, iterations: int = 20
                 ) -> tuple[tuple[float, float, float], tuple[float, float]]:
    """The least-squares frame over a robot's own rows (``t``, ``truth``) together with its bias in its
    own frame (ahead, left): a bias in the robot's frame turns with it, so it is told from the frame
    by the robot's turning, and the two are found by alternating the one given the other until they
    settle (a few iterations where the robot turned through every heading, more where it did not).
    Rows farther than the cap from the current frame's belief are left out."""
    raw, ok = belief.raw(t, offset)
    now = _apply(belief.frame, raw[:, :2])
    near = ok & (np.hypot(*(now - truth[:, :2]).T) < CAP_M)
    if near.sum() < 10:
        return belief.frame, (0.0, 0.0)
    raw, q = raw[near], truth[near, :2]
    facing = raw * np.array([0.0, 0.0, 1.0])  # the belief's heading alone: the robot's own axes
    frame, bias = belief.frame, np.zeros(2)
    for _ in range(iterations):
        frame = kabsch(raw[:, :2] - compose(facing, bias), q)
        # The residual taken back into the robot's map frame (through the fitted transform), then into
        # the robot's own axes, averaged.
        d = raw[:, :2] - relative(np.asarray(frame, np.float64), q)
        bias = relative(facing, d).mean(axis=0)
    return frame, (float(bias[0]), float(bias[1]))
