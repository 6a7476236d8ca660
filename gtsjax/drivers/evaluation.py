"""Accuracy against labelled logs: the paper's experiment (Fig. 5–6: error by evaluation point) and the
figures the issues ask for (position and heading RMSE, recall, false tracks per scan, recovery of a
bumped sensor).

Matching: in each scan, every labelled object present (and inside the site's bounds) is matched to
the nearest confirmed track of its class within ``match_radius``, one to one, nearest pairs first.
A matched object counts towards recall and its errors towards the RMSEs; a confirmed track matched
to no object is a false track.

Id switches: a change of the track id matched to an object while the object stays present (one that
left and came back may get a new track without a switch).

Settling: a track needs a few scans to be confirmed after an object appears (is put down, or walks
into the bounds). Recall and the track errors count object-scans from ``settle_s`` seconds after the
object appeared; ``recall_incl_initiation`` counts every object-scan. False tracks count every scan.

Per-scan (the paper's "error for several samples on each testing pose"): the detection of the
object's class nearest each object, before tracking, within ``match_radius``; its errors are the
``det_*`` figures, and the fraction of object-scans with such a detection is ``det_recall``.
"""

import dataclasses

import numpy as np

from ..core.geometry import relative, wrap
from ..core.model import Model
from ..io.logs import ScanLog, fit_to_model, to_scans
from .batch import process_log


def heading_turns(model: Model) -> list[int]:
    """Per class, the half-turn symmetry its heading is read modulo (``PoseRegressor.turns``: 2 for a class
    that looks the same turned half a turn, else 1)."""
    return [1 if reg is None or reg.turns is None else int(reg.turns) for reg in model.pose]


def heading_error(d, turns: int):
    """A heading error modulo ``2π/turns``: what a class alike turned by that can be held to."""
    return wrap(turns * np.asarray(d, np.float64)) / turns if turns != 1 else wrap(d)


def match_scan(truth_xy, truth_ok, track_xy, track_ok, radius):
    """Greedy one-to-one matching by distance. Returns, per truth object, the track index or -1."""
    out = np.full(truth_xy.shape[0], -1)
    if not truth_ok.any() or not track_ok.any():
        return out
    d = np.linalg.norm(truth_xy[:, None, :] - track_xy[None, :, :], axis=-1)
    d[~truth_ok, :] = np.inf
    d[:, ~track_ok] = np.inf
    while True:
        i, j = np.unravel_index(np.argmin(d), d.shape)
        if not np.isfinite(d[i, j]) or d[i, j] > radius:
            return out
        out[i] = j
        d[i, :] = np.inf
        d[:, j] = np.inf


def evaluate_outputs(model: Model, log: ScanLog, out, *, match_radius: float = 0.3, settle_s: float = 1.0,
                     appear_s: float = 0.5) -> dict:
    """Metrics from a replay's stacked outputs. The first ``settle_s`` seconds after an object
    appears are left out of the error statistics (the track is still being confirmed) but not out
    of recall. Each appearance's heading ``appear_s`` seconds after it is scored on its own
    (``appear_heading_*``: is the robot just put down reported, and with the right heading?)."""
    T = log.n_scans
    classes = [model.classes.index(str(c)) for c in log.truth_classes]
    present, since = _presence(model, log)
    bars = hasattr(out, "track_var") and hasattr(out, "track_cov_xy")  # the rows' variances (not a test's stand-in)
    tally = _score_tracks(log, out, classes, present, since, match_radius, settle_s, appear_s, heading_turns(model),
                          bars)
    e_pos, e_th = np.asarray(tally.e_pos), np.asarray(tally.e_th)
    settled = present & (since >= settle_s)
    d_pos, d_th, d_found = _detection_errors(log, out, classes, present, match_radius, heading_turns(model))
    res = {
        "scans": T,
        "objects_present": int(present.sum()),
        "recall": float((tally.matched & settled).sum() / max(settled.sum(), 1)),
        "recall_incl_initiation": float(tally.matched.sum() / max(present.sum(), 1)),
        "false_tracks_per_scan": tally.false_tracks / T,
        "id_switches": tally.id_switches,
        "n_errors": int(e_pos.size),
        "position_rmse_m": float(np.sqrt(np.mean(e_pos**2))) if e_pos.size else float("nan"),
        "position_median_m": float(np.median(e_pos)) if e_pos.size else float("nan"),
        "heading_rmse_deg": float(np.degrees(np.sqrt(np.mean(e_th**2)))) if e_th.size else float("nan"),
        "heading_median_deg": float(np.degrees(np.median(np.abs(e_th)))) if e_th.size else float("nan"),
        "degraded_scans": int(np.sum(out.degraded)),
        "det_recall": float(d_found / max(present.sum(), 1)),
        "det_position_rmse_m": float(np.sqrt(np.mean(d_pos**2))) if d_pos.size else float("nan"),
        "det_heading_rmse_deg": float(np.degrees(np.sqrt(np.mean(d_th**2)))) if d_th.size else float("nan"),
        "det_heading_median_deg": float(np.degrees(np.median(np.abs(d_th)))) if d_th.size else float("nan"),
        "det_misread_fraction": float(np.mean(np.abs(d_th) > np.radians(30))) if d_th.size else float("nan"),
    }
    res.update(_appearance_figures(np.asarray(tally.e_appear, float)))
    if bars:
        e_full = np.asarray(tally.e_full, np.float64).reshape(-1, 10)
        res.update(error_bar_figures(e_full[:, :8]))
        res.update(view_figures(e_full))
    names = log.extra.get("truth_names")
    if getattr(out, "track_robot", None) is not None and names is not None and getattr(model, "tag_names", ()):
        res.update(identity_figures(log, out, model.tag_names, names, classes, present, match_radius))
    sensor_truth = log.extra.get("truth_sensor_pose")
    if sensor_truth is not None:
        res.update(_sensor_figures(log, out, sensor_truth))
    from .diagnose import tally_outputs

    if hasattr(out, "track_hold") and hasattr(model, "tracker"):  # the step's outputs (not a test's stand-in)
        res["diagnosis"] = tally_outputs(model, out)
    res["_errors"] = (np.asarray(tally.scan_of_err), np.asarray(tally.obj_of_err), e_pos, e_th)
    return res


#: The 0.95 quantiles of χ² with 2 and 1 degrees of freedom: a calibrated row's position error lies
#: inside its 95 % ellipse, and its heading error inside its ±1.96 σ, 95 % of the time.
CHI2_95 = {2: 5.991464547107979, 1: 3.841458820694124}


def error_bar_figures(e: np.ndarray) -> dict:
    """How well the rows' own variances describe their errors, and the errors' mean in the robot's own
    frame (issue 55), from the settled errors ``e`` [n, 8] (``_TrackTally.e_full``): the share of
    position errors inside the row's 95 % ellipse (from var_x, var_y, cov_xy) and of heading errors
    inside its 95 % interval (from var_theta), 0.95 for a calibrated ground truth; the mean normalised
    squared errors (NEES: 2 and 1 for a calibrated one); and the bias, the mean error ahead of and to
    the left of the robot (in its true heading's frame) and of the heading, which no filter removes."""
    keys = ("position_within_95", "heading_within_95", "position_nees", "heading_nees", "bias_ahead_m",
            "bias_left_m", "heading_bias_deg")
    if e.shape[0] == 0:
        return {k: float("nan") for k in keys}
    dx, dy, eth, vx, vy, cxy, vth, _ = e.T
    det = vx * vy - cxy**2
    with np.errstate(divide="ignore", invalid="ignore"):  # a row without a variance is outside any ellipse
        nees_pos = np.where(det > 0, (vy * dx**2 - 2 * cxy * dx * dy + vx * dy**2) / det, np.nan)
        nees_th = np.where(vth > 0, eth**2 / vth, np.nan)
    ahead, left = _ahead_left(e)
    mean = lambda a: float(np.nanmean(a)) if np.isfinite(a).any() else float("nan")  # noqa: E731
    return {"position_within_95": float(np.mean(nees_pos <= CHI2_95[2])),
            "heading_within_95": float(np.mean(nees_th <= CHI2_95[1])),
            "position_nees": mean(nees_pos), "heading_nees": mean(nees_th),
            "bias_ahead_m": float(np.mean(ahead)), "bias_left_m": float(np.mean(left)),
            "heading_bias_deg": float(np.degrees(np.mean(eth)))}


def _ahead_left(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each error's position part (``e[:, :2]``, field frame) seen from the robot's true heading
    (``e[:, 7]``): how far ahead of it and to its left the row put it."""
    heading = np.column_stack([np.zeros((e.shape[0], 2)), e[:, 7]])
    return tuple(relative(heading, e[:, :2]).T)


def view_figures(e: np.ndarray, min_rows: int = 5) -> dict:
    """Each error split into the bias of its view and noise (issue 55), where the robot stood still: the
    settled errors ``e`` [n, 10] (``_TrackTally.e_full``) grouped by the true pose (to the millimetre
    and the hundredth of a radian), groups of at least ``min_rows`` rows, each a view of the robot
    from one place. Per view, the bias is the mean error (the heading's; the position's in the robot's
    frame) and the noise the rows' spread about it; over views, the RMS of each, and the largest
    heading bias. A bias no more scans of the same view remove; noise they average. NaN without two
    such views (a robot that moves all the time)."""
    keys = ("views", "view_heading_bias_rms_deg", "view_heading_bias_max_deg", "view_heading_noise_rms_deg",
            "view_position_bias_rms_m", "view_position_noise_rms_m")
    nan = {k: float("nan") for k in keys} | {"views": 0}
    if e.shape[0] == 0:
        return nan
    eth = e[:, 2]
    ahead, left = _ahead_left(e)
    place = np.column_stack([np.round(e[:, 8], 3), np.round(e[:, 9], 3), np.round(e[:, 7], 2)])
    _, group, count = np.unique(place, axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    big = np.flatnonzero(count >= min_rows)
    if big.size < 2:
        return nan
    hb, hn, pb, pn = [], [], [], []
    for g in big:
        sel = group == g
        hb.append(np.mean(eth[sel]))
        hn.append(np.mean((eth[sel] - hb[-1]) ** 2))
        mean = np.array([np.mean(ahead[sel]), np.mean(left[sel])])
        pb.append(np.linalg.norm(mean))
        pn.append(np.mean((ahead[sel] - mean[0]) ** 2 + (left[sel] - mean[1]) ** 2))
    hb, hn, pb, pn = map(np.asarray, (hb, hn, pb, pn))
    return {"views": int(big.size), "view_heading_bias_rms_deg": float(np.degrees(np.sqrt(np.mean(hb**2)))),
            "view_heading_bias_max_deg": float(np.degrees(np.max(np.abs(hb)))),
            "view_heading_noise_rms_deg": float(np.degrees(np.sqrt(np.mean(hn)))),
            "view_position_bias_rms_m": float(np.sqrt(np.mean(pb**2))),
            "view_position_noise_rms_m": float(np.sqrt(np.mean(pn)))}


def _presence(model: Model, log: ScanLog) -> tuple[np.ndarray, np.ndarray]:
    """Per scan and object: present (labelled, inside the site's bounds) and the seconds since it
    appeared; a step of its own since both matching and the settled statistics are counted on them."""
    T = log.n_scans
    truth = log.truth_poses
    bounds = model.site.bounds if bool(model.site.has_bounds) else None
    present = ~np.isnan(truth[..., 0])
    if bounds is not None:
        b = np.asarray(bounds)
        x, y = np.nan_to_num(truth[..., 0]), np.nan_to_num(truth[..., 1])
        present &= (x >= b[0]) & (y >= b[1]) & (x <= b[2]) & (y <= b[3])
    since = np.zeros_like(present, dtype=float)
    for t in range(1, T):
        since[t] = np.where(present[t] & present[t - 1], since[t - 1] + (log.stamps[t] - log.stamps[t - 1]), 0.0)
    return present, since


@dataclasses.dataclass
class _TrackTally:
    """What the scan-by-scan pass over the confirmed tracks counts: matches, false tracks, id switches,
    the appearances' heading errors and the settled errors (with the scan and object of each)."""

    matched: np.ndarray
    false_tracks: int = 0
    id_switches: int = 0
    e_appear: list = dataclasses.field(default_factory=list)
    e_pos: list = dataclasses.field(default_factory=list)
    e_th: list = dataclasses.field(default_factory=list)
    obj_of_err: list = dataclasses.field(default_factory=list)
    scan_of_err: list = dataclasses.field(default_factory=list)
    # per settled error: dx, dy (row − truth, field frame), the heading error, the row's var_x, var_y,
    # cov_xy and var_theta, and the true pose's heading, x and y (the robot's own frame, the view)
    e_full: list = dataclasses.field(default_factory=list)


def _match_classes(out, t: int, truth_t: np.ndarray, present_t: np.ndarray, classes, radius) -> np.ndarray:
    """Scan ``t``'s objects matched to its confirmed tracks, each class on its own (a track is never
    matched to an object of another class): per object, the track index or -1."""
    tr_ok = np.asarray(out.track_mask[t])
    tr_xy = np.asarray(out.track_pose[t, :, :2], np.float64)
    m = np.full(truth_t.shape[0], -1)
    for c in set(classes):
        sel = np.array([k == c for k in classes])
        ok_c = tr_ok & (np.asarray(out.track_class[t]) == c)
        mm = match_scan(np.nan_to_num(truth_t[:, :2]), present_t & sel, tr_xy, ok_c, radius)
        m = np.where(sel, mm, m)
    return m


def _score_tracks(log: ScanLog, out, classes, present, since, radius, settle_s, appear_s, turns,
                  bars: bool = False) -> _TrackTally:
    """Scan by scan, the confirmed tracks against the labelled objects: a pass of its own since the
    id switches and the appearances' headings depend on the scans before. Headings modulo
    ``2π/turns[class]`` (:func:`heading_error`)."""
    truth = log.truth_poses
    # Each appearance's heading error ``appear_s`` after it (NaN: no track reported for it yet).
    crossed = (since >= appear_s) & np.vstack([np.zeros((1, present.shape[1]), bool), since[:-1] < appear_s])
    tally = _TrackTally(matched=np.zeros_like(present))
    ids = {}
    for t in range(log.n_scans):
        tr_ok = np.asarray(out.track_mask[t])
        m = _match_classes(out, t, truth[t], present[t], classes, radius)
        tally.false_tracks += int(tr_ok.sum() - (m >= 0).sum())
        for i in np.flatnonzero(~present[t]):
            ids.pop(i, None)  # gone (picked up, left the field): a new track when it is back is no switch
        for i in np.flatnonzero(crossed[t]):
            tally.e_appear.append(abs(heading_error(float(out.track_pose[t, m[i], 2]) - truth[t, i, 2],
                                                    turns[classes[i]])) if m[i] >= 0 else np.nan)
        for i in np.flatnonzero(m >= 0):
            tally.matched[t, i] = True
            tid = int(out.track_id[t, m[i]])
            if i in ids and ids[i] != tid:
                tally.id_switches += 1
            ids[i] = tid
            if since[t, i] >= settle_s:
                p = np.asarray(out.track_pose[t, m[i]], np.float64)
                tally.e_pos.append(np.linalg.norm(p[:2] - truth[t, i, :2]))
                tally.e_th.append(heading_error(p[2] - truth[t, i, 2], turns[classes[i]]))
                if bars:
                    var = np.asarray(out.track_var[t, m[i]], np.float64)
                    tally.e_full.append((*(p[:2] - truth[t, i, :2]), tally.e_th[-1], var[0], var[1],
                                         float(out.track_cov_xy[t, m[i]]), var[2], truth[t, i, 2],
                                         truth[t, i, 0], truth[t, i, 1]))
                tally.obj_of_err.append(i)
                tally.scan_of_err.append(t)
    return tally


def identity_figures(log: ScanLog, out, tag_names, truth_names, classes, present, radius: float,
                     after_s: float = 2.0) -> dict:
    """The identities read from tags (``Output.track_robot``) against the log's ``truth_names``, over the
    rows matched to a labelled robot more than ``after_s`` after their track was first reported (issue
    43's measure): the shares right, wrong and without an identity; and the same over every matched row.
    And each put-down (a robot present again after an absence, not at the log's start): the seconds until
    a row names it right (``identity_back_s``, NaN: never), and the share back within 1 s."""
    first: dict[int, float] = {}
    right = wrong = none = all_right = all_rows = 0
    put_down: dict[int, float] = {}  # robot index -> when it was put down, while its name is not back
    back: list[float] = []
    for t in range(log.n_scans):
        for i in np.flatnonzero(present[t] & ~present[t - 1]) if t > 0 else ():
            if i in put_down:
                back.append(np.nan)  # put down again before its name came back
            put_down[int(i)] = float(log.stamps[t])
        m = _match_classes(out, t, log.truth_poses[t], present[t], classes, radius)
        for i in np.flatnonzero(m >= 0):
            tid = int(out.track_id[t, m[i]])
            first.setdefault(tid, float(log.stamps[t]))
            r = int(out.track_robot[t, m[i]])
            ok = r >= 0 and tag_names[r] == str(truth_names[i])
            if ok and int(i) in put_down:
                back.append(float(log.stamps[t]) - put_down.pop(int(i)))
            all_rows += 1
            all_right += int(ok)
            if log.stamps[t] - first[tid] < after_s:
                continue
            right += int(ok)
            wrong += int(r >= 0 and not ok)
            none += int(r < 0)
    back += [np.nan] * len(put_down)
    n = max(right + wrong + none, 1)
    b = np.asarray(back, float)
    return {"identity_rows": right + wrong + none, "identity_right": right / n, "identity_wrong": wrong / n,
            "identity_none": none / n, "identity_right_all_rows": all_right / max(all_rows, 1),
            "identity_put_downs": int(b.size),
            "identity_back_within_1s": float(np.mean(np.nan_to_num(b, nan=np.inf) <= 1.0)) if b.size else float("nan"),
            "identity_back_median_s": float(np.nanmedian(b)) if np.isfinite(b).any() else float("nan")}


def _appearance_figures(e_appear: np.ndarray) -> dict:
    """The ``appear_*`` figures (none if no object appeared): how soon a robot just put down is
    reported with the right heading, a question apart from the settled errors."""
    if not e_appear.size:
        return {}
    # Of the objects that appeared (put down, walked in), the share reported with a heading within
    # 5° of the truth ``appear_s`` after they appeared, and the worst such heading.
    return {
        "appear_heading_ok_fraction": float(np.mean(np.nan_to_num(e_appear, nan=np.inf) <= np.radians(5))),
        "appear_heading_max_deg": float(np.degrees(np.nanmax(e_appear))) if np.isfinite(e_appear).any()
        else float("nan"),
        "appear_unreported": int(np.sum(np.isnan(e_appear))),
    }


def _sensor_figures(log: ScanLog, out, sensor_truth: np.ndarray) -> dict:
    """The sensor's own pose against the log's truth for it (a simulated bump), and how long after
    the bump it was recovered: figures only a log with ``truth_sensor_pose`` has."""
    res = {}
    org, th = out.sensor_pose[:, :2], out.sensor_pose[:, 2]
    e_s = np.linalg.norm(org - sensor_truth[:, :2], axis=1)
    e_sth = np.abs(wrap(th - sensor_truth[:, 2]))
    res["sensor_position_error_m_median"] = float(np.median(e_s))
    res["sensor_heading_error_deg_median"] = float(np.degrees(np.median(e_sth)))
    jumps = np.flatnonzero(np.any(np.abs(np.diff(sensor_truth, axis=0)) > 1e-9, axis=1))
    if jumps.size:
        j = jumps[0] + 1
        tol_xy, tol_th = 0.01 + 2 * np.median(e_s[:j]), np.radians(0.3) + 2 * np.median(e_sth[:j])
        ok = (e_s[j:] < tol_xy) & (e_sth[j:] < tol_th)
        first = int(np.argmax(ok)) if ok.any() else None
        res["bump_recovered_after_s"] = None if first is None else float(log.stamps[j + first] - log.stamps[j])
    return res


def _detection_errors(log: ScanLog, out, classes, present, radius, turns):
    """Per object-scan, the nearest detection of the object's class (before tracking) within
    ``radius``: position errors, heading errors (modulo ``2π/turns[class]``) and how many object-scans
    had one."""
    truth = log.truth_poses
    e_pos, e_th, found = [], [], 0
    for t, i in zip(*np.nonzero(present), strict=True):
        ok = np.asarray(out.det_mask[t]) & (np.asarray(out.det_class[t]) == classes[i])
        if not ok.any():
            continue
        pose = np.asarray(out.det_pose[t], np.float64)
        d = np.linalg.norm(pose[:, :2] - truth[t, i, :2], axis=1)
        d[~ok] = np.inf
        j = int(np.argmin(d))
        if d[j] > radius:
            continue
        found += 1
        e_pos.append(d[j])
        e_th.append(heading_error(pose[j, 2] - truth[t, i, 2], turns[classes[i]]))
    return np.asarray(e_pos), np.asarray(e_th), found


def evaluate_log(model: Model, log: ScanLog, *, where: object = "scan log", fitted: bool = False, smooth: bool = False,
                 **kw) -> dict:
    """Replay ``log`` (``model`` must have its site attached) and score it. A log from another scanner
    geometry than the model's is refused (:func:`~gtsjax.io.logs.fit_to_model`, naming ``where``), never
    cropped: an accuracy figure is for the scans as they were recorded. ``fitted``: the caller has
    checked the log so already (``evaluate`` checks every log before the first is replayed).
    ``smooth``: score the smoothed rows (:mod:`gtsjax.drivers.smoothing`)."""
    if not fitted:
        log = fit_to_model(log, model, where)
    _, out = process_log(model, to_scans(log, model.n_beams), filtered=smooth)
    if smooth:
        from .smoothing import smooth_output

        out = smooth_output(out[0], out[1], log.stamps, model.tracker)
    return evaluate_outputs(model, log, out, **kw)


def per_point(log: ScanLog, res: dict, decimals: int = 2):
    """Errors grouped by the object's (rounded) position: the static evaluation points of Fig. 5–6.
    Returns points [P, 2], position RMSE [P] (m), heading RMSE [P] (rad), counts [P]."""
    scans, objs, e_pos, e_th = res["_errors"]
    if scans.size == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, int)
    keys = np.round(log.truth_poses[scans, objs, :2], decimals)
    pts, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    pos = np.array([np.sqrt(np.mean(e_pos[inv == k] ** 2)) for k in range(len(pts))])
    th = np.array([np.sqrt(np.mean(e_th[inv == k] ** 2)) for k in range(len(pts))])
    cnt = np.bincount(inv, minlength=len(pts))
    return pts, pos, th, cnt
