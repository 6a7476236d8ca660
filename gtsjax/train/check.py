"""The whole step on the labelled logs after training: can the model *track*, not only classify?

A classifier that finds the robot in every scan is no ground truth if the tracker never confirms it
(a top speed learnt as 0 m/s from a robot turned on the spot did exactly that, silently). So after
fitting, ``gtsjax train`` replays each labelled log through the complete step (stages a–g, tracker
included, step by step as the live loop runs it) and scores, per tracked class, the scans of the held-out seconds (the
tracker runs through the whole log, so that a held-out second is tracked as a live run would track it):

- detection rate: scans with the class in view in which the step detected it (within ``radius``); in
  view meaning that the scan has returns on it (:func:`seen`): a robot hidden behind another, or
  beyond the laser's reach, is not a miss of the model's;
- rows: of those scans, the share with a ground-truth row of the class there, once each appearance is
  older than the tracker's confirmation time plus half a second (a robot put down at its next pose
  between two scans, as a training grid is recorded, appears anew);
- position and heading RMSE of those rows;
- where each scan without a row was lost, by stage (:data:`STAGES`): not segmented, the binary
  filters, the classifier, the open-set test, the shape envelope, the cap of posed objects, the
  field's bounds, and, for a detection without a row, the tracker's confirmation (too few scans, the
  majority test, implausible speed or turn rate: ``core.g_track.HOLDS``).

:func:`verdict` turns that into one line naming the stage and the option to change where rows cover
fewer than 90 % of the scans in which the robot was detected.
"""

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..core.g_track import HOLDS, Detections, TrackerState, reported, track_step
from ..core.geometry import relative, wrap
from ..core.model import Model
from ..core.pipeline import REASONS
from ..drivers.batch import process_log
from ..drivers.evaluation import heading_error, heading_turns
from ..io.logs import ScanLog, to_scans
from ..io.site import Site
from .labels import scan_groups

STAGES = ("not segmented", "filters", "classifier", "open set", "envelope", "cap", "bounds",
          "confirmation", "majority", "speed", "turn rate", "tracker")
# What to change where a stage loses the robot (the verdict's advice).
ADVICE = {
    "not segmented": "the robot is rarely a segment of its own: check the range window and the segmentation",
    "filters": "the binary filters drop it: the robot's views differ from the filters' size limits",
    "classifier": "the classifier takes it for something else: record more views of the robot (or --max-mobile)",
    "open set": "the open-set test rejects it: record more, and more varied, views of the robot",
    "envelope": "its shape envelope rejects it: record the robot at more ranges",
    "cap": "more objects than the model poses per scan (--max-tracks)",
    "bounds": "it is outside the site's bounds: check the site's bounds and the sensor pose guess",
    "confirmation": "its tracks end before they are confirmed: the robot leaves view within half a second, or its "
                    "detections are too far apart to be one track",
    "majority": "its tracks are seen as another class in most scans: record more views of the robot",
    "speed": "its tracks move faster than the class's max speed: retrain with --max-speed CLASS=M_PER_S",
    "turn rate": "its tracks turn faster than the class's max turn rate: retrain with --max-turn-rate CLASS=RAD_PER_S",
    "tracker": "its detections start no track: check --max-tracks and the tracker's gates",
}
ROWS_PER_DETECTION = 0.9  # rows for at least this share of the scans in which the robot was detected
DETECTION = 0.9  # the robot detected in at least this share of the held-out scans in which it is in view
JUMP_SPEED = 2.0  # m/s: a labelled object faster than this between two scans was put down elsewhere
JUMP_TURN = np.radians(2.0)  # rad: and one turned by this much more than its class's top turn rate allows
MIN_RETURNS = 3  # returns on an object for it to be in view (a scan's lone return is a mixed pixel)


def _counts() -> dict:
    """Per class, what :func:`_score` counts (summed over logs by :func:`summarise`)."""
    return {"in_view": 0, "settled": 0, "detected": 0, "detected_settled": 0, "rows": 0, "rows_detected": 0,
            "lost": dict.fromkeys(STAGES, 0), "undetected": dict.fromkeys(STAGES, 0), "err_xy": [], "err_th": [],
            "det_err": [], "row_err": []}


def _score(r: dict, found: bool, settled: bool, row: "tuple | None", lost) -> None:
    """One object in one scan into the counts ``r``: whether it was detected, whether it is old enough to
    be tracked, its row's position and heading errors and its error with the row's variances (the
    columns of :func:`row_errors`; None: no row) and, for a scan without one, ``lost()``, the stage that
    lost it."""
    r["in_view"] += 1
    r["detected"] += int(found)
    if not found:
        r["undetected"][lost()] += 1
    if not settled:
        return
    r["settled"] += 1
    r["detected_settled"] += int(found)
    if row is None:
        r["lost"][lost()] += 1
        return
    r["rows"] += 1
    r["rows_detected"] += int(found)
    r["err_xy"].append(row[0])
    r["err_th"].append(row[1])
    if len(row) > 2:  # with its variances (the labelled logs' rows; the simulated checks' have none)
        r["row_err"].append(row[2])


def _stage_of_hold(hold: int) -> str:
    """The stage of :data:`STAGES` a tentative track's hold (an index into ``HOLDS``) stands for."""
    name = HOLDS[hold]
    return {"too few scans": "confirmation", "none": "tracker"}.get(name, name)


def _since(xy: np.ndarray, stamps: np.ndarray, present: np.ndarray, theta: "np.ndarray | None" = None,
           turn_rate: "np.ndarray | float" = np.inf) -> np.ndarray:
    """Seconds since each object (``xy`` [T, M, 2]) appeared, or last jumped (a labelled robot put down at
    its next grid pose between two scans: no tracker follows that, nor should it), or, given its
    headings ``theta`` [T, M], last turned faster than ``turn_rate`` (rad/s, per object) allows (a robot
    turned by hand between two scans of a recording turned on the spot: the track's heading follows
    it within a few scans, and those scans are the recording's habit, not the model's error)."""
    since = np.zeros(present.shape)
    for t in range(1, len(stamps)):
        dt = stamps[t] - stamps[t - 1]
        jump = np.hypot(*(xy[t] - xy[t - 1]).T) > JUMP_SPEED * dt + 0.02
        if theta is not None:
            turned = np.abs(wrap(np.nan_to_num(theta[t] - theta[t - 1])))
            jump = jump | (turned > np.asarray(turn_rate) * dt + JUMP_TURN)
        since[t] = np.where(present[t] & present[t - 1] & ~jump, since[t - 1] + dt, 0.0)
    return since


def _lost_at(out, t: int, xy: np.ndarray, cls: int, radius: float) -> str:
    """Where scan ``t``'s object at ``xy`` of class ``cls`` was lost (a stage of :data:`STAGES`)."""
    det = np.asarray(out.det_mask[t]) & (np.asarray(out.det_class[t]) == cls)
    if det.any() and np.min(np.linalg.norm(out.det_pose[t][det, :2] - xy, axis=1)) <= radius:
        ok = np.asarray(out.track_live[t]) & ~np.asarray(out.track_mask[t]) & (np.asarray(out.track_class[t]) == cls)
        if not ok.any():
            return "tracker"
        d = np.linalg.norm(out.track_pose[t][:, :2] - xy, axis=1)
        d[~ok] = np.inf
        j = int(np.argmin(d))
        return _stage_of_hold(int(out.track_hold[t][j])) if d[j] <= radius else "tracker"
    d = np.linalg.norm(out.cand_xy[t] - xy, axis=1)
    reason = np.asarray(out.cand_reason[t])
    d[reason == REASONS.index("none")] = np.inf
    if not np.isfinite(d).any() or d.min() > radius:
        return "not segmented"
    why = REASONS[int(reason[int(np.argmin(d))])]
    return {"filtered": "filters", "background": "classifier", "unlike": "open set", "off envelope": "envelope",
            "unposed": "cap"}.get(why, "classifier" if int(out.cand_class[t][int(np.argmin(d))]) != cls else "bounds")


def seen(log: ScanLog, sensor_pose: np.ndarray, truth_xy: np.ndarray, present: np.ndarray,
         landmark_xy: np.ndarray, radius: float) -> np.ndarray:
    """Which labelled objects (``truth_xy`` [T, M, 2] where ``present``) each scan has at least
    :data:`MIN_RETURNS` returns on: returns within ``radius`` of the object whose nearest labelled
    object or site landmark (``landmark_xy`` [L, 2]) it is, the scan placed in O at ``sensor_pose``
    [T, 3] (the step's own map transformation). A robot behind another robot, out of the laser's
    reach or field of view has none, and is not counted as a scan the model missed it in."""
    T, M = present.shape
    out = np.zeros((T, M), bool)
    angles = log.angles()
    valid = log.valid()
    for t in range(T):
        if not present[t].any():
            continue
        r = log.ranges[t, valid[t]].astype(np.float64)
        a = sensor_pose[t, 2] + angles[valid[t]]
        pts = sensor_pose[t, :2] + r[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1)
        objs = np.concatenate([np.where(present[t][:, None], truth_xy[t], np.inf), landmark_xy])
        d = np.linalg.norm(pts[:, None, :] - objs[None, :, :], axis=2)
        near = np.argmin(d, axis=1) if len(objs) else np.zeros(0, int)
        on = d[np.arange(len(pts)), near] <= radius
        out[t] = np.bincount(near[on], minlength=len(objs))[:M] >= MIN_RETURNS
    return out


def check_log(model: Model, log: ScanLog, held: np.ndarray, tracked: Sequence[str], *, radius: float = 0.3,
              settle_s: float | None = None) -> dict:
    """Per tracked class of ``log``'s labels, counts over the held-out scans (``held`` [T]) of ``log``
    replayed whole through ``model`` (its site attached) step by step, as the live loop and ``gtsjax
    evaluate`` run it (the vectorised form of ``replay`` gives the same to round-off in 0.6 times the
    time, a second on a training log: the same program as evaluate's, compiled once where a model is
    trained and then evaluated in one process), for the classes ``tracked``; summed over logs by
    :func:`summarise`."""
    classes = list(model.classes)
    _, out = process_log(model, to_scans(log, model.n_beams))
    rate = 1.0 / max(float(np.median(np.diff(log.stamps))) if log.n_scans > 1 else 0.1, 1e-3)
    settle = settle_s if settle_s is not None else float(model.tracker.n_confirm) / rate + 0.5
    truth = log.truth_poses
    present = ~np.isnan(truth[..., 0])
    if bool(model.site.has_bounds):
        b = np.asarray(model.site.bounds)
        x, y = np.nan_to_num(truth[..., 0]), np.nan_to_num(truth[..., 1])
        present &= (x >= b[0]) & (y >= b[1]) & (x <= b[2]) & (y <= b[3])
    rates = np.array([float(model.tracker.max_turn_rate[classes.index(str(c))]) if str(c) in classes else np.inf
                      for c in log.truth_classes])
    since = _since(truth[..., :2], log.stamps, present, truth[..., 2], rates)
    in_view = present & seen(log, np.asarray(out.sensor_pose, np.float64), np.nan_to_num(truth[..., :2]), present,
                             np.asarray(model.site.landmark_xy, np.float64), radius)
    res: dict[str, dict] = {}
    turns = heading_turns(model)
    for i, name in enumerate(log.truth_classes):
        name = str(name)
        if name not in tracked:
            continue
        c = classes.index(name)
        r = res.setdefault(name, _counts())
        for t in np.flatnonzero(in_view[:, i] & held):
            xy = truth[t, i, :2]
            det = np.asarray(out.det_mask[t]) & (np.asarray(out.det_class[t]) == c)
            gap = np.where(det, np.linalg.norm(out.det_pose[t][:, :2] - xy, axis=1), np.inf)
            found = bool(gap.min() <= radius)
            if found:  # the detection's error in the object's own frame (its pose before the tracker)
                r["det_err"].append(frame_error(out.det_pose[t][int(np.argmin(gap))], truth[t, i], turns[c]))
            rows = np.asarray(out.track_mask[t]) & (np.asarray(out.track_class[t]) == c)
            d = np.where(rows, np.linalg.norm(out.track_pose[t][:, :2] - xy, axis=1), np.inf)
            j = int(np.argmin(d))
            row = None
            if d[j] <= radius:
                e_th = float(heading_error(out.track_pose[t][j, 2] - truth[t, i, 2], turns[c]))
                var = np.asarray(out.track_var[t][j], np.float64)
                full = (*(np.asarray(out.track_pose[t][j, :2], np.float64) - truth[t, i, :2]), e_th, var[0], var[1],
                        float(out.track_cov_xy[t][j]), var[2], float(truth[t, i, 2]))
                row = (float(d[j]), e_th, full)
            _score(r, found, since[t, i] >= settle, row, lambda t=t, xy=xy, c=c: _lost_at(out, t, xy, c, radius))
    return res


def summarise(parts: Sequence[dict]) -> dict:
    """Per class, the rates and RMSEs of :func:`check_log`'s counts summed over logs."""
    total: dict[str, dict] = {}
    for part in parts:
        for name, r in part.items():
            t = total.setdefault(name, _counts())
            for k in ("in_view", "settled", "detected", "detected_settled", "rows", "rows_detected"):
                t[k] += r[k]
            for k in STAGES:
                t["lost"][k] += r["lost"][k]
                t["undetected"][k] += r["undetected"][k]
            t["err_xy"] += r["err_xy"]
            t["err_th"] += r["err_th"]
    out = {}
    for name, t in total.items():
        exy, eth = np.asarray(t["err_xy"]), np.asarray(t["err_th"])
        missed = t["settled"] - t["rows"]
        out[name] = {
            "scans_in_view": t["in_view"], "scans_scored": t["settled"],
            "detection_rate": t["detected"] / t["in_view"] if t["in_view"] else None,
            "rows_per_scan": t["rows"] / t["settled"] if t["settled"] else None,
            "rows_per_detected_scan": t["rows_detected"] / t["detected_settled"] if t["detected_settled"] else None,
            "position_rmse_m": float(np.sqrt(np.mean(exy**2))) if exy.size else None,
            "heading_rmse_deg": float(np.degrees(np.sqrt(np.mean(eth**2)))) if eth.size else None,
            "lost": {k: v for k, v in t["lost"].items() if v},
            "lost_share": {k: v / missed for k, v in t["lost"].items() if v} if missed else {},
            "undetected": {k: v for k, v in t["undetected"].items() if v},
        }
    return out


def _gathered(parts: Sequence[dict], key: str, width: int) -> dict[str, np.ndarray]:
    """Per class, the ``key`` lists of :func:`check_log`'s counts over logs, as ``[n, width]``."""
    out: dict[str, list] = {}
    for part in parts:
        for name, r in part.items():
            out.setdefault(name, []).extend(r[key])
    return {name: np.asarray(e, np.float64).reshape(-1, width) for name, e in out.items()}


def detection_errors(parts: Sequence[dict]) -> dict[str, np.ndarray]:
    """Per class, the errors of :func:`check_log`'s detections in the object's own frame (ahead, left,
    heading; :func:`frame_error`) over logs: ``[n, 3]``."""
    return _gathered(parts, "det_err", 3)


def row_errors(parts: Sequence[dict]) -> dict[str, np.ndarray]:
    """Per class, :func:`check_log`'s settled rows over logs, ``[n, 8]``: the position error (x, y in
    the field), the heading error, the row's var_x, var_y, cov_xy and var_theta, and the true heading
    (the columns of ``gtsjax evaluate``'s errors, ``drivers.evaluation.error_bar_figures``)."""
    return _gathered(parts, "row_err", 8)


def frame_error(estimate, truth, turns: "int | None") -> tuple[float, float, float]:
    """``estimate − truth`` of a pose in the object's own frame: ahead, left (m) and heading (rad).
    For an object alike turned by a ``1/turns`` of a turn, the truth's turn nearest the estimate's."""
    truth = np.asarray(truth, np.float64)
    step = 2 * np.pi / (turns or 1)
    turned = truth + (0.0, 0.0, step * round(float(wrap(estimate[2] - truth[2])) / step))
    return tuple(float(v) for v in relative(turned, np.asarray(estimate, np.float64)))


def check_pipeline(model: Model, logs: Sequence[ScanLog], sites: Sequence[Site], held: Sequence[np.ndarray],
                   tracked: Sequence[str]) -> tuple[dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """:func:`check_log` over every labelled log (each with its site and held-out scans), summarised;
    the detections' errors in each class's own frame (:func:`detection_errors`); and the rows' errors
    with their variances (:func:`row_errors`)."""
    parts = [check_log(model.with_site(site), log, h, tracked) for log, site, h in zip(logs, sites, held, strict=True)]
    return summarise(parts), detection_errors(parts), row_errors(parts)


def verdict(summary: dict, simulated: dict | None = None, min_scored: int = 30) -> list[str]:
    """One line per tracked class the step cannot track: rows for fewer than 90 % of the scans in which
    it was detected, on the labelled logs' held-out seconds (``summary``, where they hold at least
    ``min_scored`` scans in view long enough to be tracked) or on the simulated stay and walk
    (``simulated``, :func:`check_tracker`), naming the stage that lost most of them and what to change;
    and one per tracked class detected in fewer than 90 % of the held-out scans in which it is in view,
    naming the stage of the step that lost most of those."""
    lines = []
    simulated = simulated or {}
    for name, s in summary.items():
        rate = s["detection_rate"]
        if s["scans_in_view"] >= min_scored and rate is not None and rate < DETECTION and s["undetected"]:
            stage = max(s["undetected"], key=s["undetected"].get)
            share = 100 * s["undetected"][stage] / sum(s["undetected"].values())
            lines.append(f"{name}: detected in only {100 * rate:.0f} % of the held-out scans in which it is in view: "
                         f"{share:.0f} % of the misses lost at {stage} ({ADVICE[stage]})")
    for name in dict.fromkeys([*summary, *simulated]):
        for where, s in (("held-out scans", summary.get(name)), ("a simulated stay and walk", simulated.get(name))):
            if s is None or s["scans_scored"] < min_scored:
                continue
            rate = s["rows_per_detected_scan"]
            if rate is None or rate < ROWS_PER_DETECTION:
                stage = max(s["lost"], key=s["lost"].get) if s["lost"] else "tracker"
                share = 100 * s["lost_share"].get(stage, 0.0)
                lines.append(f"{name}: detected in {100 * (s['detection_rate'] or 0):.0f} % of {where} but reported "
                             f"in {100 * (rate or 0):.0f} % of those: {share:.0f} % of the missing rows lost at "
                             f"{stage} ({ADVICE[stage]})")
    return lines


def simulated_checks(model: Model, heldout: dict, mobiles: Sequence[str], rate_hz: float, seed: int = 0) -> dict:
    """:func:`check_tracker` for each tracked class, with the errors of its held-out examples (the
    training report's ``heldout``): its recall, position RMSE, the heading error's median as a
    Gaussian's (misreads aside) and its misread share."""
    out = {}
    for name in mobiles:
        cls = heldout.get("per_class", {}).get(name, {})
        pose = heldout.get("pose", {}).get(name, {})
        out[name] = check_tracker(
            model, name, detection_rate=float(cls.get("recall", 0.9)),
            position_sigma=max(float(pose.get("rmse_xy_m", 0.02)) / np.sqrt(2), 0.005),
            heading_sigma=max(np.radians(float(pose.get("median_theta_deg", 3.0))) / 0.6745, np.radians(1.0)),
            misread=float(pose.get("misread_fraction", 0.0)), rate_hz=rate_hz, seed=seed)
    return out


def held_mask(log: ScanLog, log_index: int, ex_where: np.ndarray, ex_group: np.ndarray, held) -> np.ndarray:
    """Which scans of labelled log ``log_index`` lie in held-out groups (:func:`~.labels.scan_groups`):
    the groups of its held-out examples (``Examples.where``/``group``)."""
    groups = scan_groups(log)
    sel = (ex_where[:, 0] == log_index) & np.isin(ex_group, held)
    return np.isin(groups, np.unique(groups[ex_where[sel, 1]]))


# ------------------------------------------------------------ the tracker on a simulated walk and stay


def _synthetic_truth(rate_hz: float, rng: np.random.Generator, speed: float = 0.3) -> np.ndarray:
    """A robot put down at six poses for 2 s each (1 s away between them), then walking for 30 s at up
    to ``speed`` m/s and turning at up to 1 rad/s: ``[T, 3]`` poses in O (NaN: away)."""
    from ..sim.scenarios import lissajous, path_poses

    period = 1.0 / rate_hz
    hold, gap = int(round(2.0 * rate_hz)), int(round(1.0 * rate_hz))
    static = []
    for (x, y), th in zip([(1.0, 1.0), (3.0, 1.5), (5.0, 1.0), (1.5, 2.8), (4.0, 3.0), (2.5, 2.0)],
                          rng.uniform(-np.pi, np.pi, 6), strict=True):
        static += [np.full((gap, 3), np.nan), np.repeat([[x, y, th]], hold, 0)]
    static = np.concatenate(static)
    walk = path_poses(lissajous(3.0, 2.0, 2.0, 1.2, rng.uniform(0, 2 * np.pi)), int(round(30.0 * rate_hz)), period,
                      rng, v_min=0.1, v_max=speed, max_turn_rate=1.0)
    return np.concatenate([static, np.full((int(round(rate_hz)), 3), np.nan), walk])


def check_tracker(model: Model, name: str, *, detection_rate: float, position_sigma: float, heading_sigma: float,
                  misread: float, rate_hz: float, seed: int = 0, radius: float = 0.3) -> dict:
    """The tracker of ``model`` on detections of class ``name`` made from a simulated stay-and-walk
    (:func:`_synthetic_truth`) with the errors measured on held-out examples: found with probability
    ``detection_rate``, position off by ``position_sigma`` (m, per axis), heading by ``heading_sigma``
    (rad), and a ``misread`` share of headings read on another side (±90°, 180°). Where the labelled
    logs are too short to track (one scan per pose, a few scans per heading), this is the check of
    stage g: of its motion limits, confirmation and gates. Scored as :func:`check_log` scores a log."""
    rng = np.random.default_rng(seed)
    truth = _synthetic_truth(rate_hz, rng)
    n, c = len(truth), list(model.classes).index(name)
    present = ~np.isnan(truth[:, 0])
    found = present & (rng.random(n) < detection_rate)
    z = np.nan_to_num(truth).copy()
    z[:, :2] += rng.normal(0, position_sigma, (n, 2))
    flip = rng.random(n) < misread
    z[:, 2] += rng.normal(0, heading_sigma, n) + flip * rng.choice([-np.pi / 2, np.pi / 2, np.pi], n)
    z[:, 2] = wrap(z[:, 2])
    var = np.array([position_sigma**2, position_sigma**2, heading_sigma**2])
    f32 = jnp.float32
    cov = jnp.diag(jnp.asarray(var, f32))[None]
    period = 1.0 / rate_hz
    params = model.tracker

    def body(state, zm):
        det = Detections(pose=zm[0], cov=cov, class_id=jnp.full((1,), c, jnp.int32), mask=zm[1])
        state, _, holds = track_step(state, det, jnp.asarray(period, f32), params, period=period, explain=True)
        return state, (state.mean[:, :3], reported(state, params), state.live, holds.hold)

    _, (xy, rep, live, hold) = jax.jit(lambda s, d: jax.lax.scan(body, s, d))(
        TrackerState.empty(model.max_tracks), (jnp.asarray(z[:, None], f32), jnp.asarray(found[:, None])))
    xy, rep, live, hold = (np.asarray(a) for a in (xy, rep, live, hold))
    settle = float(params.n_confirm) / rate_hz + 0.5
    since = _since(np.nan_to_num(truth[:, None, :2]), np.arange(n) * period, present[:, None])[:, 0]
    r = _counts()

    def lost(t):  # the nearest live unreported track's hold, where one is near
        d = np.where(live[t] & ~rep[t], np.linalg.norm(xy[t, :, :2] - truth[t, :2], axis=1), np.inf)
        j = int(np.argmin(d))
        return _stage_of_hold(int(hold[t, j])) if d[j] <= radius else "tracker"

    for t in np.flatnonzero(present):
        d = np.where(rep[t], np.linalg.norm(xy[t, :, :2] - truth[t, :2], axis=1), np.inf)
        j = int(np.argmin(d))
        row = (float(d[j]), float(wrap(xy[t, j, 2] - truth[t, 2]))) if d[j] <= radius else None
        _score(r, bool(found[t]), since[t] >= settle, row, lambda t=t: lost(t))
    return summarise([{name: r}])[name]


def coverage(logs: Sequence[ScanLog], sites: Sequence[Site], tracked: Sequence[str], *, cell: float = 1.0,
             share: float = 0.5, sides: int = 8, side_share: float = 0.05) -> tuple[dict, list[str]]:
    """Where on the field each tracked class was labelled: the share of the field's ``cell``-sized squares
    (the sites' bounds) holding at least one labelled pose, and a warning line where under ``share``.
    A model sees a robot where it was recorded: a few placements (seconds at each of a handful of poses)
    pass every held-out test at those places and miss the robot elsewhere (a box robot labelled at 4
    points: 78 % of its scans detected on a walk across the field).

    And from which sides the laser saw it: the robot's heading less the laser's bearing to it, in
    ``sides`` sectors, each to hold at least ``side_share`` of the labelled poses. A robot walking paths
    across the laser's view is seen side-on: trained on two minutes of that, 42 % of a static robot's
    heading reads on the SPL field were misread (5 % trained turned on the spot), and its tracked
    position was 3.5 cm off."""
    cells: dict[str, set] = {}
    views: dict[str, list] = {}
    total: set = set()
    for log, site in zip(logs, sites, strict=True):
        sx, sy, _ = site.sensor_pose
        for m, name in enumerate(log.truth_classes):
            q = log.truth_poses[:, m]
            q = q[~np.isnan(q[:, 0]) & ~np.isnan(q[:, 2])]
            if str(name) in tracked and len(q):
                views.setdefault(str(name), []).append(wrap(q[:, 2] - np.arctan2(q[:, 1] - sy, q[:, 0] - sx)))
        if site.bounds is None:
            continue
        x0, y0, x1, y1 = site.bounds
        nx, ny = max(1, int(np.ceil((x1 - x0) / cell - 1e-9))), max(1, int(np.ceil((y1 - y0) / cell - 1e-9)))
        total |= {(i, j) for i in range(nx) for j in range(ny)}
        for m, name in enumerate(log.truth_classes):
            if str(name) not in tracked:
                continue
            p = log.truth_poses[:, m, :2]
            p = p[~np.isnan(p[:, 0])]
            i = np.clip(((p[:, 0] - x0) // cell).astype(int), 0, nx - 1)
            j = np.clip(((p[:, 1] - y0) // cell).astype(int), 0, ny - 1)
            inside = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
            cells.setdefault(str(name), set()).update(zip(i[inside].tolist(), j[inside].tolist(), strict=True))
    report, lines = {}, []
    for name in tracked:
        if name not in views:
            continue
        v = np.concatenate(views[name])
        seen = np.histogram(v, bins=sides, range=(-np.pi, np.pi))[0] / v.size
        report[name] = {"side_shares": [round(float(x), 3) for x in seen]}
        rare = int(np.sum(seen < side_share))
        if rare:
            lines.append(f"{name} is seen from {sides - rare} of {sides} sides in its labels ({rare} sides of "
                         f"{360 // sides}° in under {100 * side_share:.0f} % of its poses, the laser's view of it): "
                         "its heading, and with it its position, may be misread from those sides; record it "
                         "turned through every heading (on the spot, or put down at each)")
    if not total:
        return report, lines
    for name in tracked:
        got = len(cells.get(name, set()))
        report.setdefault(name, {}).update({"cells": got, "of": len(total), "cell_m": cell, "share": got / len(total)})
        if got / len(total) < share:
            lines.append(f"{name} is labelled in {got} of the field's {len(total)} squares of {cell:g} m "
                         f"({100 * got / len(total):.0f} %): the model has not seen it elsewhere, where its "
                         "detection and pose may fail; record it all over the field")
    return report, lines
