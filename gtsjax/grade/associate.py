"""Which track is which robot: identity by association.

Track ids are anonymous, and a robot is not one track: picked up and put down, hidden for a second, or
taken over by another robot's track where two cross, it comes back under another id. So identity is
decided per window of time and then smoothed along each track:

1. **per window** (1 s), each robot against each track present: the mean distance between the
   robot's belief (at its clock offset, in its frame) and the track, capped; one assignment for the
   window (the Hungarian method, :func:`scipy.optimize.linear_sum_assignment`, with every pair farther
   apart than :data:`GATE_M` left out, so a robot whose belief is lost matches nobody rather than
   the nearest stranger);
2. **along each track**, the windows' votes smoothed: a run of another robot's votes shorter than
   :data:`MIN_RUN` windows between two runs of one robot is a bad belief, not a swap, and is given
   back to that robot; windows where the track matched nobody (the robot's belief kidnapped 1 m off,
   say) are the robot's that holds the track on both sides, or at the track's ends the robot that
   holds it next to them (at most :data:`MAX_END_FILL` windows). A track voted for two robots in long runs was really taken over: it is
   split there. A stretch so given must have been voted for its robot in most of its windows
   (:data:`MIN_SUPPORT`), or it is nobody's;
3. **per robot and instant**, where two tracks are still its (a track born before the old one died),
   the one voted for it in that window over one given by smoothing, then the closer one.
"""

from dataclasses import dataclass

import numpy as np

from .clock import CAP_M, WINDOW_S, Belief

GATE_M = 0.5
MIN_RUN = 3
#: The share of a stretch's windows that must have voted for the robot it is given to.
MIN_SUPPORT = 0.5
#: At a track's start or end, at most this many windows matching nobody are given to the robot next to
#: them: further from its votes, the track may have been taken over by a robot not graded.
MAX_END_FILL = 3
NONE = -1
ABSENT = -2


@dataclass(frozen=True)
class Association:
    rows: list[np.ndarray]  # per robot, the ground-truth rows that are it, in stamp order
    votes: np.ndarray  # [K, W] per track and window, the robot the window's assignment chose (NONE, ABSENT)
    labels: np.ndarray  # [K, W] the same after smoothing
    distance: np.ndarray  # [R, N] each robot's belief against each row (m; NaN where no belief)


def window_winners(cost: np.ndarray, gate: float = GATE_M) -> np.ndarray:
    """Per track (columns of ``cost``, robots × tracks, ``inf`` where not comparable), the robot one
    window's assignment gives it, or −1: the assignment of least total cost among pairs within
    ``gate``, as many pairs as can be made (a pair beyond the gate costs more than any within)."""
    R, K = cost.shape
    won = np.full(K, -1, np.int64)
    allowed = cost <= gate
    if R == 0 or K == 0 or not allowed.any():
        return won
    from scipy.optimize import linear_sum_assignment  # here: every command imports this module

    big = gate * 10.0 * max(R, K)  # an excluded pair never buys two allowed ones
    ri, ci = linear_sum_assignment(np.where(allowed, cost, big))
    for r, c in zip(ri, ci, strict=True):
        if allowed[r, c]:
            won[c] = r
    return won


def windows(stamps: np.ndarray) -> tuple[np.ndarray, int]:
    """Each stamp's window index and the number of windows."""
    if stamps.size == 0:
        return np.zeros(0, np.int64), 0
    w = np.floor((stamps - stamps[0]) / WINDOW_S).astype(np.int64)
    return w, int(w[-1]) + 1


def _runs(seq: np.ndarray) -> list[list[int]]:
    """Runs of equal values: ``[value, start, stop]`` each."""
    runs, start = [], 0
    for i in range(1, seq.size + 1):
        if i == seq.size or seq[i] != seq[start]:
            runs.append([int(seq[start]), start, i])
            start = i
    return runs


def smooth_track(votes: np.ndarray) -> np.ndarray:
    """One track's votes over the windows it is present in (robot indices, :data:`NONE`) smoothed as
    the module says."""
    lab = votes.copy()
    for _ in range(2):  # short runs between equal neighbours, until nothing changes (twice is enough)
        runs = [r for r in _runs(lab) if r[0] != NONE]
        for a, b, c in zip(runs, runs[1:], runs[2:], strict=False):
            if a[0] == c[0] != b[0] and b[2] - b[1] < MIN_RUN:
                lab[b[1]:b[2]] = a[0]
    runs = _runs(lab)
    for i, (v, s, e) in enumerate(runs):
        if v != NONE:
            continue
        before = runs[i - 1][0] if i > 0 else None
        after = runs[i + 1][0] if i + 1 < len(runs) else None
        if before is not None and after is not None:
            if before == after:
                lab[s:e] = before
        elif (before is not None or after is not None) and e - s <= MAX_END_FILL:
            lab[s:e] = before if before is not None else after
    # A stretch given to a robot must have been voted for it in most of its windows: a robot whose
    # belief crossed a stranger's track for a window or two (a belief in the wrong frame, say) does
    # not take over the track's whole life by the filling above.
    for v, s, e in _runs(lab):
        if v != NONE and np.count_nonzero(votes[s:e] == v) < MIN_SUPPORT * (e - s):
            lab[s:e] = NONE
    return lab


def associate(rows_track: np.ndarray, rows_t: np.ndarray, rows_pose: np.ndarray, n_tracks: int,
              robots: list[tuple[Belief, float]]) -> Association:
    """Robots (belief, clock offset) against the ground-truth rows (track index, stamp, pose)."""
    window, n_w = windows(rows_t)
    R, N = len(robots), rows_t.size
    dist = np.full((R, N), np.nan)
    for r, (belief, offset) in enumerate(robots):
        b, ok = belief.at(rows_t, offset)
        dist[r, ok] = np.hypot(b[ok, 0] - rows_pose[ok, 0], b[ok, 1] - rows_pose[ok, 1])
    flat = rows_track * n_w + window
    size = n_tracks * n_w
    present = np.bincount(flat, None, size).reshape(n_tracks, n_w)
    mean = np.full((R, n_tracks, n_w), np.inf)
    for r in range(R):
        ok = np.isfinite(dist[r])
        s = np.bincount(flat[ok], np.minimum(dist[r, ok], 2 * CAP_M), size).reshape(n_tracks, n_w)
        c = np.bincount(flat[ok], None, size).reshape(n_tracks, n_w)
        mean[r] = np.where((c > 0) & (c >= 0.5 * present), s / np.maximum(c, 1), np.inf)
    votes = np.where(present > 0, NONE, ABSENT)
    for w in range(n_w):
        ks = np.flatnonzero(present[:, w])
        if ks.size == 0 or R == 0:
            continue
        won = window_winners(mean[:, ks, w])
        votes[ks[won >= 0], w] = won[won >= 0]
    labels = votes.copy()
    for k in range(n_tracks):
        on = votes[k] != ABSENT
        if on.any():
            labels[k, on] = smooth_track(votes[k, on])
    row_label = labels[rows_track, window]
    out = []
    for r in range(R):
        mine = np.flatnonzero(row_label == r)
        # One row per instant: where two of its tracks share a stamp, the one voted for it, then the
        # closer (a missing belief counts as far).
        d = np.where(np.isfinite(dist[r, mine]), dist[r, mine], np.inf)
        filled = votes[rows_track[mine], window[mine]] != r
        order = np.lexsort((d, filled, rows_t[mine]))
        mine = mine[order]
        keep = np.ones(mine.size, bool)
        keep[1:] = rows_t[mine[1:]] != rows_t[mine[:-1]]
        out.append(mine[keep])
    return Association(out, votes, labels, dist)


def spans(rows: np.ndarray, rows_track: np.ndarray, rows_t: np.ndarray, ids: np.ndarray) -> list[tuple[int, float, float]]:
    """A robot's rows as (track id, first stamp, last stamp) per stretch on one track, in time order."""
    if rows.size == 0:
        return []
    out = []
    start = 0
    for i in range(1, rows.size + 1):
        if i == rows.size or rows_track[rows[i]] != rows_track[rows[start]]:
            out.append((int(ids[rows_track[rows[start]]]), float(rows_t[rows[start]]), float(rows_t[rows[i - 1]])))
            start = i
    return out
