"""A/B, interleaved in one process: the shipped model's pose GPs held apart (each its own copy of the
training inputs, ``PoseRegressor.common`` cleared) against their inputs held once
(``gp.sparse.CommonInputsGP``, as a model file loads). Batch replay (vectorised, the default) of a
simulated log, and the live step on URG-04LX frames called back to back and once per 25 ms; rounds
alternate between the two so that the machine's drift falls on both.

    python scripts/ab_pose_inputs.py [--rounds 5] [--out benchmarks/results-ab-pose-inputs.md]
"""

import argparse
import sys
import time
from pathlib import Path

import equinox as eqx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import _data  # noqa: E402
from benchmarks._harness import ab_machine, emit_report  # noqa: E402
from gtsjax.drivers.batch import process_log  # noqa: E402
from gtsjax.drivers.live import warm_up  # noqa: E402
from gtsjax.io import to_scans  # noqa: E402
from gtsjax.sensors import URG_04LX  # noqa: E402


def apart(model):
    """``model`` with every pose regressor's ``common`` cleared: the separate GPs run."""
    none = lambda v: v is None  # noqa: E731
    pose = tuple(None if r is None else eqx.tree_at(lambda r: r.common, r, None, is_leaf=none) for r in model.pose)
    return eqx.tree_at(lambda m: m.pose, model, pose, is_leaf=none)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--scans", type=int, default=512, help="batch replay's log length")
    ap.add_argument("--frames", type=int, default=150, help="live-step frames per round and way of calling")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()

    log, site = _data.scenario("spl-trajectory", 4, args.scans)
    held_once = _data.demo_model(site)
    if not any(r is not None and r.common is not None for r in held_once.pose):
        raise SystemExit("the shipped model's pose GPs do not share their inputs: nothing to compare")
    variants = {"apart": apart(held_once), "once": held_once}
    scans = to_scans(log, held_once.n_beams)
    live_log, live_site = _data.scenario("spl-trajectory", 7, 300)
    frames = [live_log.ranges[i % live_log.n_scans].astype(np.float64) for i in range(args.frames)]
    steps = {k: warm_up(m.with_site(live_site), URG_04LX) for k, m in variants.items()}
    for m in variants.values():
        process_log(m, scans, chunk=256, vectorise=True)  # compile
    rate = {k: [] for k in variants}
    live = {(k, way): [] for k in variants for way in ("back to back", "every 25 ms")}
    dt = np.float32(URG_04LX.period)
    for _ in range(args.rounds):
        for k, m in variants.items():
            t0 = time.perf_counter()
            process_log(m, scans, chunk=256, vectorise=True)
            rate[k].append(args.scans / (time.perf_counter() - t0))
            step, state0 = steps[k]
            for way in ("back to back", "every 25 ms"):
                state = state0
                for i, r in enumerate(frames):
                    t0 = time.perf_counter()
                    state, _, packed = step(state, r, None, dt)
                    np.asarray(packed)
                    if i >= 5:
                        live[(k, way)].append(time.perf_counter() - t0)
                    if way == "every 25 ms":
                        time.sleep(0.025)
    lines = [
        "# Pose GPs' inputs held apart or once: interleaved A/B",
        "",
        f"`python scripts/ab_pose_inputs.py --rounds {args.rounds}`; {ab_machine()}.",
        "",
        "| what | inputs apart | inputs once |",
        "|---|---|---|",
        f"| batch replay, vectorised, {args.scans} scans (median of {args.rounds} rounds) | "
        + " | ".join(f"{np.median(rate[k]):.0f} scans/s" for k in variants) + " |",
    ]
    for way in ("back to back", "every 25 ms"):
        cells = [f"{np.median(live[(k, way)]) * 1e3:.2f} ms (p99 {np.percentile(live[(k, way)], 99) * 1e3:.2f})"
                 for k in variants]
        lines.append(f"| live step, URG-04LX frames, called {way} | " + " | ".join(cells) + " |")
    emit_report(lines, args.out)


if __name__ == "__main__":
    main()
