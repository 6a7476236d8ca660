"""Which track is which robot, live (``run --beliefs``): the robots' own beliefs, as they arrive,
against the confirmed tracks, so that the GTD CSV, the terminal table and the view name each track.

The offline grader (:mod:`gtsjax.grade.associate`) sees a whole match and smooths each track's
votes both ways in time; a live run sees only the past, and must name a row when it writes it. So:

1. **per window** (:data:`WINDOW_S`, closed by the first scan after it, off the frame's path), each
   robot against each track seen in it: the mean distance, over the track's rows, between the track
   and the robot's belief at the row's stamp (interpolated by the laptop's receive time: the robots'
   clocks are not the laptop's), each distance capped at twice the gate; one assignment for the
   window (the Hungarian method, :func:`scipy.optimize.linear_sum_assignment`, every pair farther
   apart than :data:`GATE_M` left out, so a robot whose belief is lost matches nobody rather than
   the nearest stranger: :func:`window_winners`);
2. **hysteresis**: a track keeps its name through windows it matches nobody (a belief kidnapped 1 m
   off for a few seconds) and until another robot wins it :data:`SWITCH` windows running (one bad
   window where two robots cross does not swap them); an unnamed track takes a name nobody holds
   after :data:`ADOPT` window(s) won, a name another track holds after :data:`SWITCH`, which that
   track then loses. A track gone for a whole window is dead and its name free again: a robot picked
   up and put down gets its name back on the new track a window later.

A name is held by one track at a time (:attr:`OnlineIdentity.names` and its inverse change
together). The work per scan is appending its rows to a list; per window, a few small arrays and one
assignment (robots × tracks), under a millisecond for a match's 14 robots.
"""

from dataclasses import replace

import numpy as np

# The offline grader's gate and window (a robot farther than the gate from a track on average over a
# window is not it), and its assignment within the gate.
from .associate import GATE_M, window_winners
from .clock import WINDOW_S

#: Windows running another robot must win a named track (or a name held by another track) to take it.
SWITCH = 2
#: Windows running a robot must win an unnamed track to give it a name nobody holds.
ADOPT = 1
#: A track's rows in a window below which it does not vote (a track seen in 1–2 scans of a window).
MIN_ROWS = 3
#: A belief stands this long after the last pose received (beyond it, the robot has no belief there).
HOLD_S = 0.5
#: The share of a track's rows in a window that the robot's belief must cover to vote.
MIN_COVER = 0.5


def mean_distance(belief: np.ndarray, t: np.ndarray, xy: np.ndarray, gate: float = GATE_M) -> float:
    """A robot's beliefs (``[n, 5]``: receive time, its stamp, x, y, θ) against one track's rows at
    stamps ``t`` (positions ``xy``): the mean of the capped distances where the belief stands
    (:data:`HOLD_S`), ``inf`` where it covers fewer than :data:`MIN_COVER` of them."""
    if belief.shape[0] == 0:
        return np.inf
    tb = belief[:, 0]
    ok = (t >= tb[0] - HOLD_S) & (t <= tb[-1] + HOLD_S)
    if ok.sum() < MIN_COVER * t.size or not ok.any():
        return np.inf
    bx = np.interp(t[ok], tb, belief[:, 2])
    by = np.interp(t[ok], tb, belief[:, 3])
    d = np.minimum(np.hypot(bx - xy[ok, 0], by - xy[ok, 1]), 2.0 * gate)
    return float(d.mean())


class OnlineIdentity:
    """The live association (see the module). ``beliefs``: what has
    :meth:`~gtsjax.io.beliefs_udp.BeliefListener.snapshot` (``since`` → robot → ``[n, 5]`` array).
    :meth:`label` names one scan's rows (on the frame's path: a dictionary look-up per row);
    :meth:`observe` takes them (after the latency is taken) and closes a window when one is due."""

    def __init__(self, beliefs, *, window_s: float = WINDOW_S, gate_m: float = GATE_M, switch: int = SWITCH,
                 adopt: int = ADOPT):
        self.beliefs = beliefs
        self.window_s, self.gate, self.switch, self.adopt = window_s, gate_m, switch, adopt
        self.names: dict[int, str] = {}  # track id -> robot: read on the frame's path
        self.holder: dict[str, int] = {}  # robot -> track id: the inverse
        self._streak: dict[int, tuple[str, int]] = {}  # track id -> (robot winning it, windows running)
        self._rows: list[tuple[float, int, float, float]] = []
        self._t0: float | None = None
        self.windows = 0
        self.active_s: dict[str, float] = {}  # robot -> time it sent beliefs (whole windows)
        self.named_s: dict[str, float] = {}  # robot -> of which a track held its name
        self.renames = 0  # a named track given another robot's name

    def label(self, rows: list) -> list:
        """``rows`` (:class:`~gtsjax.io.gtd.TrackRow`) with their track's robot, where it has one and the
        row is not already named by its tag (a model that reads tags: the laser's reading of the robot
        itself wins over an association of poses)."""
        names = self.names
        if not names:
            return rows
        return [replace(r, robot=names[r.track_id]) if r.track_id in names and not r.robot else r for r in rows]

    def observe(self, stamp: float, rows: list) -> None:
        """One scan's rows, stamped ``stamp`` (laptop time); closes the window when ``stamp`` is past it."""
        if self._t0 is None:
            self._t0 = stamp
        elif stamp - self._t0 >= self.window_s:
            self.close_window(self._t0, stamp)
            self._t0 = stamp
        for r in rows:
            self._rows.append((stamp, r.track_id, r.x, r.y))

    # ------------------------------------------------------------------------------- one window
    def close_window(self, t0: float, t1: float) -> None:
        """The window ``[t0, t1)``'s rows against the beliefs (see the module), then the names."""
        rows, self._rows = self._rows, []
        self.windows += 1
        beliefs = self.beliefs.snapshot(since=t0 - 2.0 * HOLD_S - self.window_s)
        robots = sorted(beliefs)
        present: list[int] = []
        if rows:
            a = np.asarray(rows, np.float64)
            ids = a[:, 1].astype(np.int64)
            seen, counts = np.unique(ids, return_counts=True)
            present = [int(k) for k in seen]
            voting = [int(k) for k, c in zip(seen, counts, strict=True) if c >= MIN_ROWS]
            cost = np.full((len(robots), len(voting)), np.inf)
            for j, k in enumerate(voting):
                mine = ids == k
                t, xy = a[mine, 0], a[mine, 2:4]
                for i, r in enumerate(robots):
                    cost[i, j] = mean_distance(beliefs[r], t, xy, self.gate)
            won = window_winners(cost, self.gate)
            for j, k in enumerate(voting):
                self._vote(k, robots[won[j]] if won[j] >= 0 else None)
        for k in [k for k in self.names if k not in present]:  # gone a whole window: dead, its name free
            del self.holder[self.names.pop(k)]
        for k in [k for k in self._streak if k not in present]:
            del self._streak[k]
        span = t1 - t0
        for r in robots:
            if np.any((beliefs[r][:, 0] >= t0) & (beliefs[r][:, 0] < t1)):
                self.active_s[r] = self.active_s.get(r, 0.0) + span
                if r in self.holder:
                    self.named_s[r] = self.named_s.get(r, 0.0) + span

    def _vote(self, k: int, robot: str | None) -> None:
        """Track ``k`` won ``robot`` (``None``: nobody) this window: the hysteresis of the module."""
        cur = self.names.get(k)
        if robot is None or robot == cur:
            self._streak.pop(k, None)
            return
        prev, n = self._streak.get(k, (None, 0))
        n = n + 1 if prev == robot else 1
        need = self.adopt if cur is None and robot not in self.holder else self.switch
        if n < need:
            self._streak[k] = (robot, n)
            return
        self._streak.pop(k, None)
        other = self.holder.get(robot)
        if other is not None:
            del self.names[other]
        if cur is not None:
            del self.holder[cur]
            self.renames += 1
        self.names[k] = robot
        self.holder[robot] = k

    # ---------------------------------------------------------------------------------- summary
    def named_share(self) -> dict[str, float]:
        """Per robot that sent beliefs for a whole window: the share of that time a track held its name."""
        return {r: self.named_s.get(r, 0.0) / s for r, s in self.active_s.items() if s > 0}
