"""Measure the per-beam range noise of a real scanner from a logged scan file, by range.

    python scripts/measure_range_noise.py [LOG] [--window 9]

Default LOG: the real URG-04LX log in ``shared/data/logs/breezyslam_exp1.dat`` (756 scans of an
indoor run). Where a short run of consecutive beams falls on one flat surface seen nearly face on,
the points lie on a line up to noise: fit the line (total least squares over ``--window`` beams),
and the residuals' standard deviation along the beam is the scanner's per-beam noise
(repeatability) at that range. Windows that span a corner, graze a surface or hold a dropout are
skipped. The median over windows is reported per range bin, with the model the simulator uses.

Why it matters: the URG-04LX data sheet quotes an *accuracy* of ±10 mm up to 1 m and ±1 % beyond.
Accuracy bounds the systematic error too (it depends on the target's colour and material, and
drifts while the sensor warms up; Kneip et al., ICRA 2009), which a model trained on the real robot
with the real landmarks largely absorbs. The random error from one scan to the next is several times
smaller, and that is what the simulator must draw per beam. Results on the default log: 2 mm below
1 m, 3.5 mm at 1.5-2 m, 6-7 mm at 2.5-4 m.
"""

import argparse
from pathlib import Path

import numpy as np

from gtsjax.io.importers import import_log
from gtsjax.sensors import MODELS

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "logs" / "breezyslam_exp1.dat"
BINS = [(0.2, 0.6), (0.6, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 3.0), (3.0, 3.5), (3.5, 4.0), (4.0, 5.0)]


def window_noise(ranges: np.ndarray, angles: np.ndarray, window: int, stride: int = 3):
    """``(mean range, noise sd along the beam)`` of every flat, near face-on window of ``window``
    consecutive valid beams in a stack of scans ``[T, N]``."""
    out = []
    for r in ranges:
        for s in range(0, r.size - window, stride):
            w = r[s : s + window].astype(np.float64)
            if np.any(~np.isfinite(w)) or np.any(w < 0.1) or np.any(w > 5.0):
                continue
            a = angles[s : s + window]
            p = np.column_stack([w * np.cos(a), w * np.sin(a)])
            p -= p.mean(axis=0)
            _, sv, vt = np.linalg.svd(p, full_matrices=False)
            normal = vt[1]
            beam = np.array([np.cos(a.mean()), np.sin(a.mean())])
            face_on = abs(normal @ beam)
            if face_on < 0.8 or sv[0] / np.sqrt(window) > 0.2:  # grazing, or a span too long to be flat
                continue
            resid = p @ normal
            out.append((w.mean(), np.sqrt(np.sum(resid**2) / (window - 2)) / face_on))
    return np.asarray(out).reshape(-1, 2)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", nargs="?", default=str(DEFAULT))
    ap.add_argument("--window", type=int, default=9)
    args = ap.parse_args()
    log = import_log(args.log)
    angles = log.angle_min + log.angle_increment * np.arange(log.n_beams)
    res = window_noise(log.ranges, angles, args.window)
    model = MODELS.get(log.sensor_model or "")
    print(f"{args.log}: {log.n_scans} scans, {len(res)} flat windows of {args.window} beams")
    print("range [m]   windows   median sd [mm]   quartiles [mm]" + ("   simulator σ [mm]" if model else ""))
    for lo, hi in BINS:
        sel = (res[:, 0] >= lo) & (res[:, 0] < hi)
        if sel.sum() < 20:
            continue
        sd = res[sel, 1] * 1000
        line = f"{lo:3.1f}-{hi:3.1f}   {sel.sum():7d}   {np.median(sd):14.1f}   {np.percentile(sd, 25):5.1f}-{np.percentile(sd, 75):5.1f}"
        if model:
            line += f"   {1000 * float(model.noise.std(np.array((lo + hi) / 2))):16.1f}"
        print(line)


if __name__ == "__main__":
    main()
