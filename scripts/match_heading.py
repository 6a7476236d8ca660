"""Where a match's heading error comes from: range, motion, misreads (issue 55).

A match of two lasers (``spl-match-2``, ten robots walking) is replayed with both lasers merged, as
``gtsjax evaluate --scenario spl-match-2:SEED`` scores its "both" row, and every scored row's heading
error is split by

- the robot's distance to the nearer laser (the single scan's limit grows with range:
  ``scripts/range_curve.py``),
- its true speed and turn rate (from the truth over ±0.2 s), and the rows' signed error against the
  turn's direction (a tracker lagging its turns has a negative mean),
- misreads (more than 30° off), and how many of them come while the robot walks (> 0.15 m/s), with
  the heading against the direction of travel: how much motion could tell (lever 2).

    python scripts/match_heading.py [--seed 2000] [--seconds 30] [--model M.npz]

Prints Markdown tables. Default: the shipped model.
"""

import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _args import parser  # noqa: E402  (scripts/_args.py, beside this script)

from gtsjax.cli.demo import demo_model_path  # noqa: E402
from gtsjax.drivers.evaluation import evaluate_outputs  # noqa: E402
from gtsjax.drivers.setup import attach_site, fit_to_model  # noqa: E402
from gtsjax.drivers.several import merge_logs, models_for_lasers, process_several, site_poses  # noqa: E402
from gtsjax.errors import InputError  # noqa: E402
from gtsjax.io.modelfile import load_model  # noqa: E402
from gtsjax.io.site import one_sensor  # noqa: E402
from gtsjax.sim.match import simulate_match  # noqa: E402

WRONG = 30.0  # degrees: a misread
WALKING = 0.15  # m/s
SPAN = 0.2  # s either side for the truth's speed and turn rate


def truth_motion(stamps: np.ndarray, truth: np.ndarray, scans: np.ndarray, objs: np.ndarray):
    """Speed, direction of travel and turn rate of the truth at each (scan, object), from the poses
    ``SPAN`` seconds either side."""
    a = np.searchsorted(stamps, stamps[scans] - SPAN)
    b = np.minimum(np.searchsorted(stamps, stamps[scans] + SPAN), len(stamps) - 1)
    dt = np.where(b > a, stamps[b] - stamps[a], np.nan)
    d = truth[b, objs, :2] - truth[a, objs, :2]
    turn = np.angle(np.exp(1j * (truth[b, objs, 2] - truth[a, objs, 2])))
    return np.hypot(d[:, 0], d[:, 1]) / dt, np.arctan2(d[:, 1], d[:, 0]), turn / dt


def table(title: str, edges, value: np.ndarray, err_deg: np.ndarray) -> None:
    print(f"| {title} | rows | heading RMS [°] | over {WRONG:g}° |\n|---|---|---|---|")
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (value >= lo) & (value < hi)
        if m.any():
            print(f"| {lo:g}–{hi:g} | {m.sum()} | {np.sqrt(np.mean(err_deg[m] ** 2)):.2f} | "
                  f"{100 * np.mean(err_deg[m] > WRONG):.2f} % |")
    print()


def main(argv=None) -> None:
    ap = parser(__doc__)
    ap.add_argument("--seed", type=int, default=2000)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--model", default=None, help="model file (default: the shipped model)")
    args = ap.parse_args(argv)
    for bad, what in ((args.seed < 0, f"--seed must be 0 or more, got {args.seed}"),
                      (args.seconds <= 0, f"--seconds must be positive, got {args.seconds:g}"),
                      (not 1 <= args.robots <= 14, f"--robots must be 1 to 14, got {args.robots}")):
        if bad:
            ap.error(what)
    try:
        model = load_model(args.model or demo_model_path())
    except InputError as e:
        ap.error(str(e))
    jax.config.update("jax_enable_x64", True)
    logs, site = simulate_match("spl-match-2", seed=args.seed, n_robots=args.robots, seconds=args.seconds)
    names = list(logs)
    base = attach_site(model, one_sensor(site, names[0]))
    models, _ = models_for_lasers([base], site, names)
    merged = merge_logs({n: fit_to_model(log, models[0], n) for n, log in logs.items()})
    _, out = process_several((models[0],), merged, site_poses(site, merged.names))
    res = evaluate_outputs(models[0], merged.log, out)
    scans, objs, _, e_th = res["_errors"]
    err = np.degrees(np.abs(e_th))
    signed = np.degrees(e_th)
    truth, stamps = merged.log.truth_poses, merged.log.stamps
    speed, heading_of_travel, turn = truth_motion(stamps, truth, scans, objs)
    lasers = np.array([site.sensor(n).pose[:2] for n in merged.names], float)
    near = np.min(np.linalg.norm(truth[scans, objs, None, :2] - lasers[None], axis=2), axis=1)
    print(f"spl-match-2:{args.seed}, {args.seconds:g} s, {args.robots} robots, both lasers, model "
          f"{args.model or 'demo'}: {len(err)} rows, heading RMSE {res['heading_rmse_deg']:.2f}°\n")
    table("nearer laser [m]", [0, 2, 3, 4, 5, 6, 10], near, err)
    table("speed [m/s]", [0, 0.05, 0.15, 0.3, 10], speed, err)
    table("turn rate [rad/s]", [0, 0.1, 0.3, 0.6, 1.0, 10], np.abs(turn), err)
    fine = err <= WRONG
    turning = fine & (np.abs(turn) > 0.3)
    walking = speed > WALKING
    off = np.degrees(np.abs(np.angle(np.exp(1j * (truth[scans, objs, 2] - heading_of_travel)))))
    wrong = ~fine
    print(f"- Turning rows (over 0.3 rad/s): mean signed error along the turn {np.mean(signed[turning] * np.sign(turn[turning])):+.2f}° "
          "(negative: the rows lag the turn).")
    print(f"- Walking rows: the heading within 20° of the direction of travel in {100 * np.mean(off[walking] < 20):.1f} %, "
          f"median {np.median(off[walking]):.1f}°.")
    if wrong.any():
        print(f"- Rows over {WRONG:g}°: {wrong.sum()} ({100 * wrong.mean():.2f} %), {100 * np.mean(walking[wrong]):.0f} % of "
              f"them walking; RMSE {np.sqrt(np.mean(err[fine] ** 2)):.2f}° without them.")
    else:
        print(f"- No row over {WRONG:g}°.")


if __name__ == "__main__":
    main()
