"""End-to-end step latency and batch replay throughput (issue 5's targets), with the shipped demo model.

    python benchmarks/bench_step.py [--quick] [--json PATH]

* step: one jitted step per scan (the live loop's call, ``make_step``), median and p99 over scans of the SPL
  field with several robots in view (``spl-crossing``: up to 3 robots; the table has M = 8 slots),
  after warm-up, each call ending in ``block_until_ready``.
* batch: ``process_log`` over a simulated log, scans per second, compilation excluded (a warm-up
  run first), both the bit-exact (``lax.map``) and the vectorised (``vmap``) paths.
Not a test: timings are reported, never asserted.
"""

import argparse
import json
import time

import jax
import numpy as np


def main():
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    from gtsjax._pipeline import init_state, make_step, process_log
    from gtsjax.cli.demo import demo_model_path
    from gtsjax.io import to_scans
    from gtsjax.io.modelfile import load_model
    from gtsjax.sim import simulate

    n = 200 if args.quick else 2000
    log, site = simulate("spl-crossing", seed=3, n_scans=min(n, 220))
    model = load_model(demo_model_path()).with_site(site)
    scans = to_scans(log, model.n_beams)
    state = init_state(model)
    step = make_step(model)
    one = [jax.tree.map(lambda a, i=i: a[i], scans) for i in range(log.n_scans)]
    for s in one[:5]:
        state, out = step(state, s)
    jax.block_until_ready(out)
    times = []
    for k in range(n):
        s = one[k % len(one)]
        t0 = time.perf_counter()
        state, out = step(state, s)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    t = np.asarray(times) * 1e6
    res = {"step_us_median": float(np.median(t)), "step_us_p99": float(np.percentile(t, 99)),
           "max_tracks": model.max_tracks, "beams": model.n_beams, "scans": n}

    big, _ = simulate("spl-trajectory", seed=4, n_scans=600 if args.quick else 3000)
    big_scans = to_scans(big, model.n_beams)
    for vec in (False, True):
        process_log(model, big_scans, chunk=256, vectorise=vec)  # warm-up: compile
        t0 = time.perf_counter()
        _, out = process_log(model, big_scans, chunk=256, vectorise=vec)
        dt = time.perf_counter() - t0
        res[f"batch_scans_per_s_{'vmap' if vec else 'exact'}"] = big.n_scans / dt
    print(f"step (URG-04LX, M={model.max_tracks}): median {res['step_us_median']:.0f} µs, "
          f"p99 {res['step_us_p99']:.0f} µs over {n} scans")
    print(f"batch replay: {res['batch_scans_per_s_exact']:.0f} scans/s (bit-exact with step), "
          f"{res['batch_scans_per_s_vmap']:.0f} scans/s (vmap)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
