"""Can the bias of a view be calibrated away? (issue 55, levers 4 and 5)

A static robot's pose error is mostly a bias of its view, constant over the view's scans (evaluate's
third table: heading bias of a view against the noise within it). If that bias were a function of
where the laser stands as seen from the robot (its bearing in the robot's frame, and its range), a
table learnt on held-out labelled views at training could remove it. This script measures whether
it is: the per-scan detections (stage e′'s poses, before the tracker) of a model on a calibration
scene are matched to the simulator's truth, their errors in the robot's frame (ahead, left, heading)
fitted by

- a constant offset (lever 5: one mean per output),
- a Fourier series in the laser's bearing, orders 1–3 (the bearing as the step knows it: from the
  estimated pose),
- a table of 8 bearings × 3 ranges (0–2.5, 2.5–4, over 4 m), bins of fewer than 10 views left at 0,

and each fit is applied to the detections of other scenes (other seeds, a walk). A calibration that
holds removes bias on the other scenes too; one that learns the calibration scene's own draws
removes it there only. Static scenes are also split per view (one placement: one pose of the robot
seen from one laser): the RMS of the views' mean errors (bias) against the RMS within views (noise).

    python scripts/view_bias.py [--model M.npz] [--fit SCENARIO:SEED] [--check SCENARIO:SEED ...]

Prints Markdown tables (RMS of ahead, left in mm, heading in degrees; detections more than 30° off,
the wrong side, are left out of every figure and counted)."""

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtsjax.cli.demo import demo_model_path  # noqa: E402
from gtsjax.core.geometry import wrap  # noqa: E402
from gtsjax.drivers.batch import process_log  # noqa: E402
from gtsjax.io import to_scans  # noqa: E402
from gtsjax.io.modelfile import load_model  # noqa: E402
from gtsjax.sim import simulate  # noqa: E402
from gtsjax.train.check import frame_error  # noqa: E402

RADIUS = 0.3  # m: a detection this near a labelled robot is that robot's
WRONG_SIDE = np.radians(30.0)
RANGE_EDGES = (2.5, 4.0)
BEARINGS = 8


def detections(model, name: str, seed: int) -> dict:
    """Every detection matched to a labelled robot in scenario ``name`` of ``seed``: its error in the
    robot's frame, the laser's bearing and range as the step sees them (from the detection), and its
    view (the robot's truth pose and the laser: equal for the scans of one static placement)."""
    log, site = simulate(name, seed=seed)
    model = model.with_site(site)
    _, out = process_log(model, to_scans(log, model.n_beams))
    truth = log.truth_poses
    rows = []
    for t in range(log.n_scans):
        mask = np.asarray(out.det_mask[t])
        if not mask.any():
            continue
        det = np.asarray(out.det_pose[t], np.float64)[mask]
        sensor = np.asarray(out.sensor_pose[t], np.float64)
        for i in np.flatnonzero(~np.isnan(truth[t, :, 0])):
            gap = np.hypot(*(det[:, :2] - truth[t, i, :2]).T)
            j = int(np.argmin(gap))
            if gap[j] > RADIUS:
                continue
            x, y, th = truth[t, i]
            bearing = wrap(np.arctan2(sensor[1] - det[j, 1], sensor[0] - det[j, 0]) - det[j, 2])
            rows.append((*frame_error(det[j], truth[t, i], 1), bearing, np.hypot(*(sensor[:2] - det[j, :2])),
                         hash((round(x, 4), round(y, 4), round(th, 4), i))))
    a = np.asarray(rows, np.float64).reshape(-1, 6)
    right = np.abs(a[:, 2]) <= WRONG_SIDE
    return {"err": a[right, :3], "bearing": a[right, 3], "range": a[right, 4], "view": a[right, 5],
            "wrong": int((~right).sum()), "n": len(a), "name": f"{name}:{seed}"}


def fourier(bearing, order: int):
    cols = [np.ones_like(bearing)]
    for k in range(1, order + 1):
        cols += [np.cos(k * bearing), np.sin(k * bearing)]
    return np.stack(cols, axis=1)


def bins(d) -> np.ndarray:
    b = ((d["bearing"] + np.pi) / (2 * np.pi) * BEARINGS).astype(int) % BEARINGS
    return np.digitize(d["range"], RANGE_EDGES) * BEARINGS + b


def calibrations(fit: dict) -> dict:
    """name → function of a scene's detections giving the predicted error [n, 3]."""
    out = {"none": lambda d: np.zeros_like(d["err"]), "constant": None}
    mean = fit["err"].mean(axis=0)
    out["constant"] = lambda d, m=mean: np.broadcast_to(m, d["err"].shape)
    for order in (1, 2, 3):
        coef = np.linalg.lstsq(fourier(fit["bearing"], order), fit["err"], rcond=None)[0]
        out[f"bearing, order {order}"] = lambda d, c=coef, k=order: fourier(d["bearing"], k) @ c
    k = bins(fit)
    table = np.zeros((BEARINGS * (len(RANGE_EDGES) + 1), 3))
    for b in range(table.shape[0]):
        if np.sum(k == b) >= 10:
            table[b] = fit["err"][k == b].mean(axis=0)
    out["bearing × range table"] = lambda d, tab=table: tab[bins(d)]
    return out


def rms(e: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(e**2, axis=0)) if len(e) else np.full(3, np.nan)


def fmt(r) -> str:
    return f"{1e3 * r[0]:.1f} / {1e3 * r[1]:.1f} / {np.degrees(r[2]):.2f}"


def views(d: dict, min_scans: int = 5) -> "tuple[np.ndarray, np.ndarray] | None":
    """RMS of the views' mean errors and RMS within the views, over views of at least ``min_scans``."""
    ids, inv, counts = np.unique(d["view"], return_inverse=True, return_counts=True)
    keep = counts[inv] >= min_scans
    if not keep.any():
        return None
    e, inv = d["err"][keep], inv[keep]
    means = np.stack([np.bincount(inv, e[:, c], minlength=len(ids)) for c in range(3)], 1) / np.maximum(
        np.bincount(inv, minlength=len(ids)), 1)[:, None]
    used = np.bincount(inv, minlength=len(ids)) > 0
    return rms(means[used]), rms(e - means[inv])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=None, help="model file (default: the shipped demo model)")
    ap.add_argument("--fit", default="spl-eval:2001", help="calibration scene SCENARIO:SEED")
    ap.add_argument("--check", nargs="+", default=["spl-eval:2002", "spl-eval:2003", "spl-trajectory:7"],
                    help="scenes the calibration is applied to")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    model = load_model(args.model or demo_model_path())
    scenes = []
    for spec in [args.fit, *args.check]:
        name, seed = spec.rsplit(":", 1)
        scenes.append(detections(model, name, int(seed)))
    cal = calibrations(scenes[0])
    print(f"model {args.model or 'demo'}; calibrated on {scenes[0]['name']} ({len(scenes[0]['err'])} detections); "
          "RMS ahead / left [mm] / heading [°]\n")
    print("| calibration | " + " | ".join(s["name"] + (" (fit)" if k == 0 else "") for k, s in enumerate(scenes)) + " |")
    print("|---|" + "---|" * len(scenes))
    for label, f in cal.items():
        print(f"| {label} | " + " | ".join(fmt(rms(s["err"] - f(s))) for s in scenes) + " |")
    print("\n| scene | detections | wrong side (> 30°) | mean ahead / left [mm] / heading [°] | views | "
          "view bias RMS | noise within views RMS |")
    print("|---|---|---|---|---|---|---|")
    for s in scenes:
        m = s["err"].mean(axis=0)
        v = views(s)
        nv = len(np.unique(s["view"]))
        print(f"| {s['name']} | {s['n']} | {s['wrong']} | {1e3 * m[0]:+.1f} / {1e3 * m[1]:+.1f} / {np.degrees(m[2]):+.2f} "
              f"| {nv} | {fmt(v[0]) if v else '–'} | {fmt(v[1]) if v else '–'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
