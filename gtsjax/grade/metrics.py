"""How wrong a robot's belief was, and when: absolute and relative pose errors against the ground
truth, time lost, and recoveries after jumps.

* **APE** per ground-truth row: the distance and the heading difference between the belief (at the
  robot's clock offset, in the field's frame) and the row. Each row also carries the ground truth's
  own uncertainty (2 σ from the CSV's variances): an error inside it is not the robot's to answer
  for, so the share of rows within it is given, and the RMSE with the ground truth's own mean
  variance taken out (the belief's error and the ground truth's add in squares when independent).
* **RPE** over 1 s and 5 s: the belief's motion between two rows that far apart against the ground
  truth's (each taken in the frame of its first pose, as evo's RPE does, with Δ in seconds rather
  than frames since the rows' rate changes when lasers see the robot or not).
* **Lost**: the share of rows whose error is over :data:`LOST_M` or :data:`LOST_RAD`.
* **Jumps**: where the belief moves more than :data:`JUMP_M` (or turns more than
  :data:`JUMP_RAD`) between two of its own poses less than :data:`JUMP_WITHIN_S` apart, faster than a
  robot moves (:data:`JUMP_SPEED`, :data:`JUMP_TURN_RATE`, and :data:`JUMP_FACTOR` times the belief's
  own motion about it: a wheeled robot's odometry delivered in bursts is no jump): a kick, a fall, a
  relocalisation; for each, whether it left the robot lost and how long it took to be
  back within the lost limits for :data:`SETTLE_S`.
"""

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.geometry import relative, wrap

LOST_M = 0.5
LOST_RAD = math.radians(30.0)
JUMP_M = LOST_M  # a smaller jump cannot lose a robot that was not lost already
JUMP_RAD = math.radians(45.0)
JUMP_WITHIN_S = 0.5
JUMP_SPEED = 2.0  # m/s
JUMP_TURN_RATE = 10.0  # rad/s
JUMP_FACTOR = 4.0  # times the belief's own median speed (turn rate) over the 2 s about it
SETTLE_S = 1.0
RPE_S = (1.0, 5.0)
RPE_TOLERANCE_S = 0.05  # a pair further than this from Δ apart is not one (half a 10 Hz period)


def stats(values: np.ndarray) -> dict:
    """RMSE, median, 95th percentile and max of absolute values (NaN for none)."""
    v = np.abs(np.asarray(values, np.float64))
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"rmse": math.nan, "median": math.nan, "p95": math.nan, "max": math.nan, "n": 0}
    return {"rmse": float(np.sqrt(np.mean(v**2))), "median": float(np.median(v)),
            "p95": float(np.percentile(v, 95)), "max": float(v.max()), "n": int(v.size)}


@dataclass(frozen=True)
class Jump:
    stamp: float  # laptop clock
    size_m: float
    turn_rad: float
    lost: bool  # the error after it was over the lost limits
    recovery_s: float  # until back within them for SETTLE_S (NaN: never, in the rows graded)


@dataclass(frozen=True)
class Errors:
    t: np.ndarray  # [n] laptop stamps of the graded rows
    pos: np.ndarray  # [n] m
    head: np.ndarray  # [n] rad, wrapped
    band_pos: np.ndarray  # [n] the ground truth's 2 σ in position (m)
    band_head: np.ndarray  # [n] and in heading (rad)
    belief: np.ndarray  # [n, 3] the belief in the field's frame
    truth: np.ndarray  # [n, 3] the ground-truth rows
    summary: dict = field(default_factory=dict)


def ape(t: np.ndarray, belief: np.ndarray, truth: np.ndarray, var: np.ndarray) -> Errors:
    pos = np.hypot(belief[:, 0] - truth[:, 0], belief[:, 1] - truth[:, 1])
    head = wrap(belief[:, 2] - truth[:, 2])
    band_pos = 2.0 * np.sqrt(var[:, 0] + var[:, 1])
    band_head = 2.0 * np.sqrt(var[:, 2])
    return Errors(t, pos, head, band_pos, band_head, belief, truth)


def rpe(e: Errors, delta: float) -> dict:
    """Relative pose error over ``delta`` seconds: translation (m) and rotation (rad) statistics."""
    if e.t.size < 2:
        return {"trans": stats([]), "rot": stats([])}
    j = np.searchsorted(e.t, e.t + delta)
    j = np.clip(j, 0, e.t.size - 1)
    jm = np.clip(j - 1, 0, e.t.size - 1)
    better = np.abs(e.t[jm] - e.t - delta) < np.abs(e.t[j] - e.t - delta)
    j = np.where(better, jm, j)
    ok = np.abs(e.t[j] - e.t - delta) < RPE_TOLERANCE_S
    i, j = np.flatnonzero(ok), j[ok]
    dt = relative(e.truth[i], e.truth[j])
    db = relative(e.belief[i], e.belief[j])
    err = relative(dt, db)
    return {"trans": stats(np.hypot(err[:, 0], err[:, 1])), "rot": stats(err[:, 2])}


def _local_median(t: np.ndarray, v: np.ndarray, at: np.ndarray, half: float = 1.0) -> np.ndarray:
    """The median of ``v`` over the samples within ``half`` seconds of each sample ``at`` (about 2 s of
    a belief: a jump is one or two of them, so it does not move the median)."""
    lo = np.searchsorted(t, t[at] - half)
    hi = np.searchsorted(t, t[at] + half, side="right")
    finite = np.where(np.isfinite(v), v, np.nan)
    return np.array([np.nanmedian(finite[a:b]) if b > a else np.nan for a, b in zip(lo, hi, strict=True)])


def jumps(stamps: np.ndarray, poses: np.ndarray, offset: float, e: Errors) -> list[Jump]:
    """The belief's jumps (its own stamps and poses, in its frame: a jump's size is the same in any)
    and the recovery after each, judged on the graded rows."""
    if stamps.size < 2:
        return []
    step = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    turn = np.abs(wrap(np.diff(poses[:, 2])))
    dt = np.diff(stamps)
    quick = dt < JUMP_WITHIN_S
    rate = dt > 0
    speed, turning = np.where(rate, step / np.where(rate, dt, 1.0), np.inf), np.where(rate, turn / np.where(rate, dt, 1.0), np.inf)
    # A robot's own motion is no jump, however quick it is: a step is one where it is faster than
    # any robot walks (JUMP_SPEED, JUMP_TURN_RATE) and than the belief moved about it.
    at = np.flatnonzero(quick & (((step > JUMP_M) & (speed > JUMP_SPEED)) | ((turn > JUMP_RAD) & (turning > JUMP_TURN_RATE))))
    usual_v, usual_w = _local_median(stamps[1:], speed, at), _local_median(stamps[1:], turning, at)
    keep = (((step[at] > JUMP_M) & (speed[at] > JUMP_FACTOR * usual_v))
            | ((turn[at] > JUMP_RAD) & (turning[at] > JUMP_FACTOR * usual_w)))
    at = at[keep]
    lost = (e.pos > LOST_M) | (np.abs(e.head) > LOST_RAD)
    out = []
    for k in at:
        t_jump = float(stamps[k + 1] - offset)
        after = np.flatnonzero(e.t >= t_jump)
        if after.size == 0:
            out.append(Jump(t_jump, float(step[k]), float(turn[k]), False, math.nan))
            continue
        first = after[0]
        was_lost = bool(lost[first]) if e.t[first] - t_jump < JUMP_WITHIN_S else False
        if not was_lost:
            out.append(Jump(t_jump, float(step[k]), float(turn[k]), False, 0.0))
            continue
        rec = math.nan
        for i in after:
            if lost[i]:
                continue
            stay = (e.t >= e.t[i]) & (e.t < e.t[i] + SETTLE_S)
            if not lost[stay].any() and e.t[stay][-1] - e.t[i] >= SETTLE_S * 0.8:
                rec = float(e.t[i] - t_jump)
                break
        out.append(Jump(t_jump, float(step[k]), float(turn[k]), True, rec))
    return out


def summarise(e: Errors, robot_jumps: list[Jump], seen_share: float, var: np.ndarray) -> dict:
    """The figures of one robot's grade, as the report and JSON give them."""
    lost = (e.pos > LOST_M) | (np.abs(e.head) > LOST_RAD)
    pos = stats(e.pos)
    gt_var = float(np.mean(var[:, 0] + var[:, 1])) if var.size else math.nan
    net = math.sqrt(max(0.0, pos["rmse"] ** 2 - gt_var)) if math.isfinite(pos["rmse"]) else math.nan
    recov = [j.recovery_s for j in robot_jumps if j.lost]
    return {
        "rows": int(e.t.size),
        "seen_share": seen_share,
        "position_m": pos,
        "position_rmse_net_of_gt_m": net,
        "heading_rad": stats(e.head),
        "within_gt_2sigma_share": float(np.mean(e.pos <= e.band_pos)) if e.t.size else math.nan,
        "lost_share": float(np.mean(lost)) if e.t.size else math.nan,
        "rpe": {f"{d:g}s": rpe(e, d) for d in RPE_S},
        "jumps": [j.__dict__ for j in robot_jumps],
        "recovery_s": stats(np.array([r for r in recov if math.isfinite(r)])) if recov else stats([]),
        "never_recovered": int(sum(1 for r in recov if not math.isfinite(r))),
    }
