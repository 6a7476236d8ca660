"""Grading (``gtsjax.grade``, issue 41): ``grade()`` on a 10-minute match of 10 robots graded against a
two-laser ground truth (``--quick``: 1 minute). Target: ≤ 30 s on these 2 cores.

The ground truth is built from the simulated match's truth (``plan_match``: 10 robots walking their
cells, two lasers' scans merged at 20 Hz) with 1 cm of noise and each track broken once, so that the
section times the grader, not a replay; the beliefs are ``gtsjax.sim.beliefs``' (30 Hz, their own
clocks, biases, kidnaps, one robot in the mirrored frame, graded with ``fit``). Each run is timed end
to end, from the rows (as ``read_gtd`` returns them) to every robot's errors. Identity is checked
(``checks.grade_identity``: the share of each robot's graded rows that are its own).
"""

import math
import time

import numpy as np

from gtsjax.grade import RobotSpec, grade
from gtsjax.io.beliefs import Beliefs
from gtsjax.io.gtd import TrackRow
from gtsjax.sensors import URG_04LX
from gtsjax.sim.beliefs import simulate_beliefs
from gtsjax.sim.match import FIELD, plan_match

SECTION = "grade"
TARGET_S = 30.0


def _ground_truth(seconds: float, n_robots: int = 10, seed: int = 3):
    match = plan_match(2, URG_04LX, n_robots=n_robots, seconds=seconds, referee=False, seed=seed)
    stamps = 1.7e9 + np.arange(match.robots.shape[0]) * match.dt
    rng = np.random.default_rng(seed)
    rows, who = [], {}
    breaks = rng.uniform(5, seconds - 5, n_robots)
    for i in range(stamps.size):
        t = stamps[i] - stamps[0]
        for m in range(n_robots):
            tid = m if t < breaks[m] else 100 + m
            x, y, th = match.robots[i, m] + rng.normal(0, [0.01, 0.01, 0.02])
            rows.append(TrackRow(float(stamps[i]), tid, "robot", float(x), float(y), math.remainder(th, 2 * math.pi),
                                 1e-4, 1e-4, 4e-4))
            who[(float(stamps[i]), tid)] = m
    return stamps, match.robots, rows, who


def run(ctx) -> None:
    res = ctx.results
    seconds = 60.0 if ctx.quick else 600.0
    stamps, truth, rows, who = _ground_truth(seconds)
    centre = ((FIELD[0] + FIELD[2]) / 2, (FIELD[1] + FIELD[3]) / 2)
    sims = simulate_beliefs(stamps, truth, centre, seed=3)
    specs = [RobotSpec(Beliefs(p.name, t, poses, p.name), "fit" if p.frame == "mirrored" else "field")
             for p, t, poses in sims]
    times, grades = [], None
    for _ in range(2 if ctx.quick else 3):
        t0 = time.perf_counter()
        grades = grade(rows, specs, centre=centre)
        times.append(time.perf_counter() - t0)
    res.add("grade.match_10_robots", "s", times, section=SECTION,
            label=f"grade(): 10 robots against a two-laser ground truth of {seconds / 60:g} min ({len(rows)} rows)",
            rows=len(rows), log_seconds=seconds)
    ident = {}
    for (p, _, _), g in zip(sims, grades, strict=True):
        mine = [who[(float(t), int(i))] for t, i in zip(g.errors.t, g.track_ids, strict=True)]
        ident[p.name] = float(np.mean(np.asarray(mine) == p.truth_index)) if mine else float("nan")
    res.checks["grade_identity"] = {"min_share": min(ident.values()), "per_robot": ident,
                                    "clock_error_ms": {p.name: 1000 * (g.clock.offset - p.offset)
                                                       for (p, _, _), g in zip(sims, grades, strict=True)}}
