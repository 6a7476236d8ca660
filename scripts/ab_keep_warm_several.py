"""A/B, interleaved in one process: the several-laser live loop (``drivers.live_several.run_live_several``)
with and without ``keep_warm`` (per laser, a throwaway step and the host's part of a frame on its last
frame shortly before its next is due), two emulated URG-04LX at 10 Hz over ptys on the full-size
field (``spl-match-2``, the shipped model). Latency from a frame's last byte to its GTD row flushed;
rounds alternate so that the machine's drift falls on both.

    python scripts/ab_keep_warm_several.py [--rounds 3] [--seconds 10] [--out benchmarks/results-ab-keep-warm-several.md]
"""

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import ab_machine, emit_report  # noqa: E402
from gtsjax.cli.demo import demo_model_path  # noqa: E402
from gtsjax.drivers.live_several import run_live_several, warm_up_several  # noqa: E402
from gtsjax.drivers.several import site_poses  # noqa: E402
from gtsjax.io.logs import fit_to_model  # noqa: E402
from gtsjax.io.modelfile import load_model  # noqa: E402
from gtsjax.io.serial import Link  # noqa: E402
from gtsjax.io.site import one_sensor  # noqa: E402
from gtsjax.sensors import URG_04LX  # noqa: E402
from gtsjax.sim.emulator import SensorEmulator  # noqa: E402
from gtsjax.sim.match import simulate_match  # noqa: E402


def one_run(logs, model, poses, compiled, seconds: float, keep_warm: bool):
    with tempfile.TemporaryDirectory(prefix="gtsjax-ab-") as tmp, \
            SensorEmulator(URG_04LX, logs["north"]) as north, SensorEmulator(URG_04LX, logs["south"]) as south:
        links = {"north": Link(north.path), "south": Link(south.path)}
        for link in links.values():
            link.start()
        try:
            stats, _, _ = run_live_several(links, model, poses, Path(tmp) / "gtd.csv", compiled=compiled,
                                           duration=seconds, keep_warm=keep_warm)
        finally:
            for link in links.values():
                link.stop()
    return np.asarray(stats.latencies_ms)[10:], stats.warm_ups, stats.frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=10.0, help="length of each run")
    ap.add_argument("--out", type=Path, help="write the Markdown report here too")
    args = ap.parse_args()
    logs, site = simulate_match("spl-match-2", seed=11, n_robots=4, seconds=args.seconds + 5.0, referee=False)
    truth = {n: tuple(map(float, log.extra["truth_sensor_pose"][0])) for n, log in logs.items()}
    site = dataclasses.replace(site, sensors=tuple(dataclasses.replace(s, pose=truth[s.name]) for s in site.sensors))
    model = load_model(demo_model_path()).with_site(one_sensor(site, "north"))
    logs = {n: fit_to_model(log, model, n) for n, log in logs.items()}
    poses = site_poses(site, ["north", "south"])
    compiled = warm_up_several(model, URG_04LX, poses)
    got = {False: [], True: []}
    for _ in range(args.rounds):
        for keep in (False, True):
            got[keep].append(one_run(logs, model, poses, compiled, args.seconds, keep))
    cells = []
    for keep in (False, True):
        lat = np.concatenate([g[0] for g in got[keep]])
        cells.append(f"{np.median(lat):.2f} ms (p99 {np.percentile(lat, 99):.2f}; {lat.size} frames, "
                     f"{sum(g[1] for g in got[keep])} warm-ups for {sum(g[2] for g in got[keep])})")
    lines = ["# The several-laser live loop with and without keep_warm (interleaved A/B)", "",
             f"`python scripts/ab_keep_warm_several.py --rounds {args.rounds} --seconds {args.seconds:g}`; {ab_machine()}. "
             "Frame's last byte read → GTD row flushed, median (p99), two emulators over ptys in the same process; "
             "the first 10 frames of each run left out.", "",
             "| lasers | keep_warm off | keep_warm on |", "|---|---|---|",
             f"| two URG-04LX at 10 Hz (spl-match-2, 4 robots) | {cells[0]} | {cells[1]} |"]
    emit_report(lines, args.out)


if __name__ == "__main__":
    main()
