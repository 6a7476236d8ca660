"""Grading a robot's own localisation against the ground truth (``gtsjax grade``).

A team records what each robot believed (its self-localisation, in its own clock and perhaps its own
frame) while gtsjax records where the robots were. :func:`grade` answers, per robot: which tracks were
it and when (:mod:`.associate`), its clock against the laptop's (:mod:`.clock`), its frame against
the field's where asked (:mod:`.frame`), and how wrong it was (:mod:`.metrics`).

The order matters and is fixed: coarse clock offsets first (each robot against every track, nobody
yet known), then the frames to fit, then one association of all robots at once (a track is one
robot at a time), then each robot's fine clock offset and frame against its own rows, then the
association again with those, then the errors.
"""

import math
from dataclasses import dataclass

import numpy as np

from ..io.beliefs import Beliefs
from ..io.gtd import TrackRow
from .associate import associate, spans, windows
from .clock import CAP_M, Belief, Clock, Rows, coarse_curve, coarse_offset, fine_offset
from .frame import ransac_frame, refine_frame
from .metrics import ape, jumps, summarise
from .series import mirror_frame
from .truth import GroundTruth, from_rows, profiles

#: A belief is not interpolated across a gap longer than this (s), or three of its usual intervals
#: for a robot that sends its pose seldom (:func:`belief_gap`): the robot was not localising.
BELIEF_GAP_S = 1.0


def belief_gap(stamps: np.ndarray) -> float:
    dt = np.diff(stamps)
    return max(BELIEF_GAP_S, 3.0 * float(np.median(dt))) if dt.size else BELIEF_GAP_S
#: Rows taken for the coarse searches: at most one per track per this much time (s).
COARSE_ROW_S = 0.5
FRAMES = ("field", "mirrored", "fit")


@dataclass(frozen=True)
class RobotSpec:
    beliefs: Beliefs
    frame: str = "field"  # one of FRAMES
    offset: float | None = None  # the clock offset, given (s)


@dataclass(frozen=True)
class RobotGrade:
    name: str
    source: str
    frame_kind: str
    frame: tuple[float, float, float]  # from the robot's frame to the field's
    frame_support: float  # for a fitted frame: the share of windows that agreed with it
    clock: Clock
    spans: list[tuple[int, float, float]]  # (track id, first, last stamp)
    rows: np.ndarray  # the ground-truth rows graded (indices into GroundTruth's stamp order)
    track_ids: np.ndarray  # each graded row's track id
    errors: object  # metrics.Errors
    jumps: list
    summary: dict
    hint: str  # why it was not seen, where it was not


def _coarse_rows(gt: GroundTruth, window: np.ndarray, n_w: int, speed: np.ndarray, turn: np.ndarray) -> Rows:
    if gt.n == 0:
        return Rows(gt.stamps, gt.track, gt.poses, window, speed, turn, gt.ids.size, n_w)
    b = np.floor((gt.stamps - gt.stamps[0]) / COARSE_ROW_S).astype(np.int64)
    _, keep = np.unique(gt.track * (int(b.max()) + 1) + b, return_index=True)
    keep = np.sort(keep)
    return Rows(gt.stamps[keep], gt.track[keep], gt.poses[keep], window[keep], speed[keep], turn[keep],
                gt.ids.size, n_w)


def row_interval(gt: GroundTruth) -> float:
    """The ground truth's usual time between two rows of one track (s): a scan period for a laser's,
    seconds for a sparse one (a SLAM log's corrected poses)."""
    order = np.lexsort((gt.stamps, gt.track))
    t, k = gt.stamps[order], gt.track[order]
    same = k[1:] == k[:-1]
    dt = np.diff(t)[same]
    dt = dt[dt > 0]
    return float(np.median(dt)) if dt.size else 0.1


def _seen_share(gt: GroundTruth, rows: np.ndarray, belief: Beliefs, offset: float, row_dt: float) -> float:
    """The share of the robot's time (its beliefs' span on the laptop's clock, within the log's) that
    has ground-truth rows of it: rows closer than :func:`seen_gap` count as seeing it in between, and
    each stretch of rows a row interval more."""
    if gt.n == 0 or belief.n == 0 or not math.isfinite(offset):
        return 0.0
    lo = max(belief.stamps[0] - offset, gt.stamps[0])
    hi = min(belief.stamps[-1] - offset, gt.stamps[-1])
    t = gt.stamps[rows]
    t = t[(t >= lo) & (t <= hi)]
    if hi <= lo or t.size == 0:
        return 0.0
    dt = np.diff(t)
    near = dt <= seen_gap(row_dt)
    seen = float(np.sum(dt[near])) + row_dt * (int(np.count_nonzero(~near)) + 1)
    return min(1.0, seen / max(hi - lo, row_dt))


def seen_gap(row_dt: float) -> float:
    """Rows of a robot at most this far apart (s) see it in between: half a second, or a few row
    intervals of a sparse ground truth."""
    return max(0.5, 2.5 * row_dt)


def grade(rows: list[TrackRow], robots: list[RobotSpec], *, centre: tuple[float, float] = (0.0, 0.0),
          max_offset: float = 5.0, classes: set[str] | None = None, seed: int = 0) -> list[RobotGrade]:
    """Grade each robot's beliefs against the GTD rows (see the module for the order of the steps).
    ``centre``: the field's centre, about which a ``mirrored`` frame is turned."""
    rng = np.random.default_rng(seed)
    gt = from_rows(rows, classes)
    row_dt = row_interval(gt)
    window, n_w = windows(gt.stamps)
    need_profiles = any(r.frame == "fit" for r in robots)
    speed, turn = profiles(gt) if need_profiles else (np.full(gt.n, np.nan), np.full(gt.n, np.nan))
    coarse = _coarse_rows(gt, window, n_w, speed, turn)

    beliefs: list[Belief] = []
    offsets: list[float] = []
    support = [math.nan] * len(robots)
    for spec in robots:  # the robots whose frame is known: their clocks by pose
        b = spec.beliefs
        frame = mirror_frame(centre) if spec.frame == "mirrored" else (0.0, 0.0, 0.0)
        beliefs.append(Belief(b.stamps, b.poses, frame, belief_gap(b.stamps)))
        d = spec.offset
        if d is None and spec.frame != "fit":
            d, _, _ = coarse_offset(coarse, beliefs[-1], max_offset, profile=False)
        offsets.append(d if d is not None and math.isfinite(d) else 0.0)
    fit = [r for r, spec in enumerate(robots) if spec.frame == "fit"]
    if fit:
        # A frame is fitted among the tracks the robots of known frames leave: a rigid transform can lay
        # any stretch of straight walking onto another, and a robot already explained needs no stranger.
        known = [r for r in range(len(robots)) if r not in fit]
        free = coarse
        if known:
            taken = associate(coarse.track, coarse.stamps, coarse.poses, coarse.n_tracks,
                              [(beliefs[r], offsets[r]) for r in known])
            claimed = np.zeros(coarse.stamps.size, bool)
            for rows_r in taken.rows:
                claimed[rows_r] = True
            free = coarse.subset(~claimed)
        for r in fit:
            spec, b = robots[r], robots[r].beliefs
            d = spec.offset
            if d is None:
                d, _, _ = coarse_offset(free, beliefs[r], max_offset, profile=True)
            if d is None or not math.isfinite(d):
                continue
            fitted, support[r] = ransac_frame(free, b.stamps, b.poses, beliefs[r].max_gap, d, rng)
            if fitted is not None:
                beliefs[r] = beliefs[r].with_frame(fitted)
                if spec.offset is None:  # the clock again, now by pose, near the motion's answer
                    d, _, _ = coarse_offset(free, beliefs[r], 0.5, profile=False, centre=d)
            offsets[r] = d if math.isfinite(d) else 0.0

    clocks: list[Clock] = [Clock(o, math.nan, (0.0, 0.0, 0.0), s.offset is not None) for o, s in zip(offsets, robots, strict=True)]
    for first in (True, False):
        assoc = associate(gt.track, gt.stamps, gt.poses, gt.ids.size, list(zip(beliefs, [c.offset for c in clocks], strict=True)))
        for r, spec in enumerate(robots):
            mine = assoc.rows[r]
            if mine.size < 10:
                continue
            t, truth = gt.stamps[mine], gt.poses[mine]
            clocks[r] = fine_offset(t, truth, window[mine], beliefs[r], clocks[r].offset, rng, spec.offset,
                                    wide=first)
            if spec.frame == "fit":
                fitted, _ = refine_frame(t, truth, beliefs[r], clocks[r].offset)
                beliefs[r] = beliefs[r].with_frame(fitted)
    assoc = associate(gt.track, gt.stamps, gt.poses, gt.ids.size, list(zip(beliefs, [c.offset for c in clocks], strict=True)))

    out = []
    for r, spec in enumerate(robots):
        mine = assoc.rows[r]
        clock = clocks[r]
        b, ok = beliefs[r].at(gt.stamps[mine], clock.offset)
        mine, b = mine[ok], b[ok]
        e = ape(gt.stamps[mine], b, gt.poses[mine], gt.var[mine])
        share = _seen_share(gt, mine, spec.beliefs, clock.offset, row_dt)
        js = jumps(spec.beliefs.stamps, spec.beliefs.poses, clock.offset, e)
        summary = summarise(e, js, share, gt.var[mine])
        hint = ("" if share >= 0.5 and not summary["lost_share"] > 0.5
                else _hint(spec, coarse, beliefs[r], clock.offset, centre, share, summary["lost_share"]))
        if not hint and spec.frame == "fit":
            hint = _straight(spec, gt.poses[mine])
        out.append(RobotGrade(spec.beliefs.name, spec.beliefs.source, spec.frame, beliefs[r].frame, support[r], clock,
                              spans(mine, gt.track, gt.stamps, gt.ids), mine, gt.ids[gt.track[mine]], e, js, summary,
                              hint))
    return out


#: A fitted robot's path narrower than this (m, across its main direction) cannot fix its frame.
STRAIGHT_M = 0.3


def _straight(spec: RobotSpec, xy: np.ndarray) -> str:
    """A warning where a fitted frame rests on a path too straight to fix it: along a straight line
    walked at one speed, a frame slid along the line and a clock shifted to match fit as well."""
    if xy.shape[0] < 3:
        return ""
    c = xy[:, :2] - xy[:, :2].mean(0)
    across = 4.0 * float(np.sqrt(np.linalg.eigvalsh(c.T @ c / c.shape[0])[0]))
    if across >= STRAIGHT_M:
        return ""
    return (f"its path is {across:.2f} m across its main direction, nearly a straight line: a fitted frame may "
            f"slide along it with the clock; give --offset {spec.beliefs.name}=SECONDS if the clock is known")


def _hint(spec: RobotSpec, coarse: Rows, belief: Belief, offset: float, centre, share: float, lost: float) -> str:
    """Why a robot was seen so little, where the data says: its poses agree with the tracks turned half
    a turn (the other team's frame), or with none at all."""
    if spec.frame == "field" and coarse.stamps.size:
        as_is = coarse_curve(coarse, belief, np.array([offset]), profile=False)[0]
        turned = Belief(belief.stamps, belief.poses, mirror_frame(centre), belief.max_gap)
        d, _, curve = coarse_offset(coarse, turned, 5.0, profile=False)
        if np.isfinite(curve).any() and np.nanmin(curve) < 0.5 * (as_is if math.isfinite(as_is) else 1.0):
            return (f"its poses agree with the tracks turned half a turn about the field's centre: "
                    f"--frame {spec.beliefs.name}=mirrored")
    if share >= 0.5:
        return (f"lost (over 0.5 m or 30° off) for {100 * lost:.0f} % of the rows graded: if it localises in a frame "
                f"of its own, --frame {spec.beliefs.name}=fit")
    if share == 0.0:
        return (f"its poses are within {CAP_M:g} m of no track at any clock offset tried: off the field, in view of "
                f"no laser, or in a frame of its own (--frame {spec.beliefs.name}=fit)")
    return (f"a ground-truth row for {100 * share:.0f} % of its time: in view of no laser the rest, or matched "
            f"no track (--frame {spec.beliefs.name}=fit if it localises in a frame of its own)")
