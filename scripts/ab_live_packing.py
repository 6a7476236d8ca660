"""A/B, interleaved in one process: the live step as it was (the frame's ranges, intensities and
validity made on the host, ``frame_arrays``, and passed as three arrays and ``dt``; the state and
output as the pipeline's arrays, 21 in and 21 + 28 out: ``jit`` of ``step`` and ``pack_tracks``)
against ``drivers.live.LiveStep`` (the frame copied as it came into one buffer, the state and output
packed one buffer per dtype). Frames of the shipped URG-04LX model and of the benchmarks' UTM-30LX
model, called back to back and once per 25 ms (the sensor's period at 40 Hz, the thread asleep
between); rounds alternate between the two ways so that the machine's drift falls on both. Also the
bare cost of a call that passes the state through, both ways.

    python scripts/ab_live_packing.py [--rounds 4] [--out benchmarks/results-ab-live-packing.md]
"""

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import _data  # noqa: E402
from benchmarks._harness import ab_machine, emit_report  # noqa: E402
from gtsjax.core.pipeline import init_state, step  # noqa: E402
from gtsjax.core.scan import Scan  # noqa: E402
from gtsjax.drivers.live import LiveStep, frame_arrays, pack_tracks  # noqa: E402
from gtsjax.sensors import URG_04LX, UTM_30LX  # noqa: E402


def unpacked_step(model, sensor):
    """The live step as it was before packing: the pipeline's state and output as they are."""
    am = jnp.asarray(sensor.angle_min, jnp.float32)
    ai = jnp.asarray(sensor.angle_increment, jnp.float32)

    @jax.jit
    def live_step(state, ranges, intensities, valid, dt):
        state, o = step(model, state, Scan(ranges, intensities, valid, am, ai, jnp.asarray(dt, jnp.float32)))
        return state, o, pack_tracks(o)

    def call(state, ranges_m, intensities, dt):
        return live_step(state, *frame_arrays(ranges_m, intensities, sensor, model.n_beams), dt)

    return call, init_state(model)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--frames", type=int, default=150, help="frames per round and way of calling")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()

    cases = []
    log, site = _data.scenario("spl-trajectory", 7, 300)
    cases.append((URG_04LX, log, _data.demo_model(site)))
    ulog, usite = _data.scenario("lab-trajectory", 5, 200)
    cases.append((UTM_30LX, ulog, _data.utm_model(usite)))
    times: dict = {}
    bare: dict = {}
    for sensor, lg, model in cases:
        frames = [lg.ranges[i % lg.n_scans].astype(np.float64) for i in range(args.frames)]
        packed = LiveStep(model, sensor)
        ways = {"arrays": unpacked_step(model, sensor), "packed": (packed, packed.initial_state())}
        dt = np.float32(sensor.period)
        through = {"arrays": jax.jit(lambda s, r: (s, r[0])), "packed": jax.jit(lambda s, r: (s, r[0]))}
        for k, (f, s0) in ways.items():
            jax.block_until_ready(f(s0, frames[0], None, dt))
            jax.block_until_ready(through[k](s0, frames[0]))
        for _ in range(args.rounds):
            for k, (f, s0) in ways.items():
                for how in ("back to back", "every 25 ms"):
                    state = s0
                    for i, r in enumerate(frames):
                        t0 = time.perf_counter()
                        state, _, rows = f(state, r, None, dt)
                        np.asarray(rows)
                        if i >= 5:
                            times.setdefault((sensor.name, how, k), []).append(time.perf_counter() - t0)
                        if how == "every 25 ms":
                            time.sleep(0.025)
                for _ in range(200):
                    t0 = time.perf_counter()
                    jax.block_until_ready(through[k](s0, frames[0]))
                    bare.setdefault((sensor.name, k), []).append(time.perf_counter() - t0)

    def cell(t):
        return f"{np.median(t) * 1e3:.3f} ms (p99 {np.percentile(t, 99) * 1e3:.3f})"

    lines = [
        "# The live step's frame, state and output: as arrays, or a few buffers (interleaved A/B)",
        "",
        f"`python scripts/ab_live_packing.py --rounds {args.rounds}`; {ab_machine()}. Median (p99) of {args.rounds} × {args.frames - 5} calls each; the call "
        "ends when the GTD rows' array is on the host.",
        "",
        "| what | as before: frame arrays on the host, 21 + 4 arrays in, 21 + 28 + 1 out | LiveStep: 3 + 1 in, 3 + 3 + 1 out |",
        "|---|---|---|",
    ]
    for sensor, _, _ in cases:
        for how in ("back to back", "every 25 ms"):
            lines.append(f"| live step, {sensor.name} frames, called {how} | "
                         + " | ".join(cell(times[(sensor.name, how, k)]) for k in ("arrays", "packed")) + " |")
        lines.append(f"| a call that passes the state through, {sensor.name} | "
                     + " | ".join(cell(bare[(sensor.name, k)]) for k in ("arrays", "packed")) + " |")
    emit_report(lines, args.out)


if __name__ == "__main__":
    main()
