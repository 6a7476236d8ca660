"""The grading campaign of docs/grading.md: a simulated match graded against what was put in.

    python scripts/grade_match.py --model match.npz [--seed 2000] [--seconds 60] [--out-dir grade-campaign]

``match.npz`` is the two-laser model docs/several-lasers.md trains (``simulate spl-match-2 --seed 1``,
``train --log north=… --log south=…``). For the held-out seed the script simulates the match with the
robots' beliefs (``simulate spl-match-2 --out-beliefs``: biased, noisy, kidnapped, each on its own clock,
one in the mirrored frame), replays both lasers into a GTD CSV, grades it (the mirrored robot with
``--frame fit``), and compares each figure with the simulation's: identity (each graded row's
nearest true robot), clock offset, APE against the error put in at the same instants (at the true
clock and at the clock found), the fitted frame (over the robot's path in its own frame) and the
kidnaps' recoveries. The same grade against the truth itself as ground truth (rows at the scans'
stamps) tells the grader's errors from the ground truth's. Prints Markdown tables.
"""

import argparse
import dataclasses
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gtsjax.grade import RobotSpec, grade  # noqa: E402
from gtsjax.grade.series import invert, transform  # noqa: E402
from gtsjax.io import load_log  # noqa: E402
from gtsjax.io.beliefs import read_beliefs  # noqa: E402
from gtsjax.io.gtd import TrackRow, read_gtd  # noqa: E402
from gtsjax.sim.beliefs import put_in_error, read_put_in  # noqa: E402


def gtsjax(*args) -> None:
    subprocess.run([sys.executable, "-m", "gtsjax", *map(str, args)], check=True, cwd=ROOT)


def truth_of(d: Path, stem: str):
    logs = [load_log(d / f"{stem}-{name}.npz") for name in ("north", "south")]
    st = np.concatenate([lg.stamps for lg in logs])
    tp = np.concatenate([lg.truth_poses for lg in logs])
    o = np.argsort(st, kind="stable")
    return st[o], tp[o]


def score(g, put, bt, bp, st, tp) -> dict:
    idx = np.clip(np.searchsorted(st, g.errors.t), 0, st.size - 1)
    tru = tp[idx]
    d = np.hypot(tru[..., 0] - g.errors.truth[:, None, 0], tru[..., 1] - g.errors.truth[:, None, 1])
    near = np.nanargmin(np.where(np.isfinite(d), d, np.inf), axis=1) if d.size else np.zeros(0, int)
    out = {"identity": float(np.mean(near == put.truth_index)) if near.size else math.nan,
           "seen": g.summary["seen_share"], "clock_err_ms": 1000 * (g.clock.offset - put.offset),
           "clock_se_ms": 1000 * g.clock.se, "ape_cm": 100 * g.summary["position_m"]["rmse"],
           "net_cm": 100 * g.summary["position_rmse_net_of_gt_m"]}
    for key, clock in (("put_cm", put.offset), ("put_found_cm", g.clock.offset)):
        pe, _ = put_in_error(dataclasses.replace(put, offset=clock), bt, bp, g.errors.t, st, tp)
        out[key] = 100 * math.sqrt(np.nanmean(pe**2))
    if put.frame == "mirrored":
        path = transform(g.errors.truth, invert(put.transform))
        moved = transform(path, g.frame)[:, :2] - transform(path, put.transform)[:, :2]
        out["frame_cm"] = 100 * float(np.max(np.hypot(*moved.T)))
        out["frame_deg"] = math.degrees(abs(math.remainder(g.frame[2] - put.transform[2], 2 * math.pi)))
    rec = []
    for k in put.kidnaps:
        near_j = [j for j in g.jumps if j.lost and abs(j.stamp - k.start) < 0.3]
        rec.append(abs(near_j[0].recovery_s - k.duration) if near_j and math.isfinite(near_j[0].recovery_s) else math.nan)
    out["kidnaps"] = len(put.kidnaps)
    out["recovery_err_s"] = max(rec) if rec else math.nan
    return out


def table(title: str, names, scores) -> str:
    cols = ("identity", "seen", "clock_err_ms", "clock_se_ms", "ape_cm", "net_cm", "put_cm", "put_found_cm",
            "kidnaps", "recovery_err_s")
    lines = [f"**{title}**", "", "| robot | " + " | ".join(cols) + " | frame |", "|---" * (len(cols) + 2) + "|"]
    for n, s in zip(names, scores, strict=True):
        frame = f"{s['frame_cm']:.2f} cm, {s['frame_deg']:.2f}°" if "frame_cm" in s else ""
        lines.append(f"| {n} | " + " | ".join(f"{s[c]:.3f}" if isinstance(s[c], float) else str(s[c]) for c in cols)
                     + f" | {frame} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=2000)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--out-dir", type=Path, default=Path("grade-campaign"))
    a = ap.parse_args()
    d = a.out_dir.resolve()
    d.mkdir(parents=True, exist_ok=True)
    gtsjax("simulate", "spl-match-2", "--seed", a.seed, "--seconds", a.seconds, "--robots", a.robots,
           "--out", d / "held.npz", "--site", d / "site.json", "--out-beliefs", d / "beliefs")
    gtsjax("replay", "--log", f"north={d / 'held-north.npz'}", "--log", f"south={d / 'held-south.npz'}", "--site",
           d / "site.json", "--model", a.model.resolve(), "--out", d / "gtd.csv", "--max-tracks", 14, "--quiet")
    st, tp = truth_of(d, "held")
    puts = read_put_in(d / "beliefs")
    sims = [(p, *(lambda b: (b.stamps, b.poses))(read_beliefs(d / "beliefs" / f"{p.name}.csv"))) for p in puts]
    specs = [RobotSpec(read_beliefs(d / "beliefs" / f"{p.name}.csv"), "fit" if p.frame == "mirrored" else "field")
             for p in puts]
    site = __import__("json").loads((d / "site.json").read_text())
    x0, y0, x1, y1 = site["bounds"]
    centre = ((x0 + x1) / 2, (y0 + y1) / 2)
    rows = read_gtd(d / "gtd.csv")
    t0 = time.perf_counter()
    grades = grade(rows, specs, centre=centre)
    took = time.perf_counter() - t0
    names = [p.name + (" (mirrored, fit)" if p.frame == "mirrored" else "") for p in puts]
    print(table(f"spl-match-2, seed {a.seed}, {a.seconds:g} s, {len(puts)} robots: graded against gtsjax's own ground "
                f"truth ({len(rows)} rows, graded in {took:.1f} s)", names,
                [score(g, *s, st, tp) for g, s in zip(grades, sims, strict=True)]))
    truth_rows = [TrackRow(float(s), m, "robot", *map(float, tp[i, m]), 1e-6, 1e-6, 1e-6)
                  for i, s in enumerate(st) for m in range(tp.shape[1]) if np.all(np.isfinite(tp[i, m]))]
    grades = grade(truth_rows, specs, centre=centre)
    print()
    print(table("the same, graded against the simulation's truth as ground truth (the grader's own errors)", names,
                [score(g, *s, st, tp) for g, s in zip(grades, sims, strict=True)]))


if __name__ == "__main__":
    main()
