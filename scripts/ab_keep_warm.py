"""A/B, interleaved in one process: the live loop (``drivers.live.run_live``) with and without
``keep_warm`` (a throwaway step on the last frame shortly before each frame is due), on the emulated
UTM-30LX at 40 Hz over a pty (the benchmarks' live case: the lab scenario and its model) and the
emulated URG-04LX at 10 Hz (the shipped model). Latency from a frame's last byte to its GTD row
flushed; rounds alternate so that the machine's drift falls on both.

    python scripts/ab_keep_warm.py [--rounds 3] [--seconds 10] [--out benchmarks/results-ab-keep-warm.md]
"""

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import _data  # noqa: E402
from benchmarks._harness import ab_machine, emit_report  # noqa: E402
from gtsjax.drivers.live import run_live, warm_up  # noqa: E402
from gtsjax.io.serial import Link  # noqa: E402
from gtsjax.sensors import URG_04LX, UTM_30LX  # noqa: E402
from gtsjax.sim.emulator import SensorEmulator  # noqa: E402


def one_run(sensor, log, model, compiled, seconds: float, keep_warm: bool):
    with tempfile.TemporaryDirectory(prefix="gtsjax-ab-") as tmp, SensorEmulator(sensor, log) as emu:
        link = Link(emu.path, intensity=sensor.has_intensity)
        link.start()
        try:
            stats = run_live(link, model, Path(tmp) / "gtd.csv", duration=seconds, compiled=compiled,
                             with_intensity=sensor.has_intensity, keep_warm=keep_warm)
        finally:
            link.stop()
    return np.asarray(stats.latencies_ms)[10:], stats.warm_ups, stats.frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=10.0, help="length of each run")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()

    ulog, usite = _data.scenario("lab-trajectory", 5, 600)
    log, site = _data.scenario("spl-trajectory", 7, 300)
    cases = [(UTM_30LX, ulog, _data.utm_model(usite)), (URG_04LX, log, _data.demo_model(site))]
    lat: dict = {}
    warm: dict = {}
    for sensor, lg, model in cases:
        compiled = warm_up(model, sensor)
        for _ in range(args.rounds):
            for keep in (False, True):
                t, w, n = one_run(sensor, lg, model, compiled, args.seconds, keep)
                lat.setdefault((sensor.name, keep), []).append(t)
                warm.setdefault((sensor.name, keep), []).append((w, n))

    def cell(key):
        t = np.concatenate(lat[key])
        w = sum(a for a, _ in warm[key])
        n = sum(b for _, b in warm[key])
        return f"{np.median(t):.2f} ms (p99 {np.percentile(t, 99):.2f}; {len(t)} frames, {w} warm-ups for {n})"

    lines = [
        "# The live loop with and without keep_warm (interleaved A/B)",
        "",
        f"`python scripts/ab_keep_warm.py --rounds {args.rounds} --seconds {args.seconds:g}`; {ab_machine()}. "
        "Frame's last byte read → GTD row flushed, median (p99), the emulator "
        "over a pty in the same process (as `python -m benchmarks`' live section); the first 10 frames of each run "
        "left out.",
        "",
        "| sensor | keep_warm off | keep_warm on |",
        "|---|---|---|",
    ]
    for sensor, _, _ in cases:
        lines.append(f"| {sensor.name} at {sensor.rate_hz:g} Hz | {cell((sensor.name, False))} | "
                     f"{cell((sensor.name, True))} |")
    emit_report(lines, args.out)


if __name__ == "__main__":
    main()
