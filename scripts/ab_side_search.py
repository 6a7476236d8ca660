"""A/B, interleaved in one process: the step as the live loop calls it (``benchmarks._harness.LiveCall``)
with stage e′ fitting the learnt sides only (the shipped model, calibrated before the search) and
searching every side (the same model with ``Outline.prior_search`` set: 11 fits per robot candidate
instead of 4; issue 38, item 5), on the scans of spl-crossing (three robots) and spl-trajectory (one),
single-threaded XLA as the benchmarks run. Rounds alternate so that the machine's drift falls on both.

    python scripts/ab_side_search.py [--rounds 5] [--calls 400] [--out benchmarks/results-ab-side-search.md]
"""

import argparse
import os
import sys
import time
from pathlib import Path

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false "
                           "intra_op_parallelism_threads=1").strip()

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import _data  # noqa: E402
from benchmarks._harness import LiveCall, ab_machine, emit_report  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--calls", type=int, default=400)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from gtsjax.io.logs import to_scans

    lines = ["# A/B: stage e′ searching every side (issue 38, item 5)", "", f"Machine: {ab_machine()}", "",
             f"{args.rounds} interleaved rounds of {args.calls} calls each, the live loop's step, single-threaded XLA.", "",
             "| scenario | learnt sides only: median / p99 [µs] | searching: median / p99 [µs] | ratio of medians |",
             "|---|---|---|---|"]
    for name, seed in (("spl-crossing", 2003), ("spl-trajectory", 2002)):
        log, site = _data.scenario(name, seed)
        model = _data.demo_model(site)
        search = eqx.tree_at(lambda m: m.outline.prior_search, model, jnp.full(len(model.classes), 0.05, jnp.float32),
                             is_leaf=lambda x: x is None)
        scans = to_scans(log, model.n_beams)
        calls = {"learnt": LiveCall(model, scans), "search": LiveCall(search, scans)}
        for c in calls.values():
            for i in range(20):
                jax.block_until_ready(c(i))
        samples = {k: [] for k in calls}
        for _ in range(args.rounds):
            for k, c in calls.items():
                for i in range(args.calls):
                    t0 = time.perf_counter()
                    jax.block_until_ready(c(i))
                    samples[k].append(1e6 * (time.perf_counter() - t0))
        med = {k: float(np.median(v)) for k, v in samples.items()}
        p99 = {k: float(np.quantile(v, 0.99)) for k, v in samples.items()}
        lines.append(f"| {name}:{seed} | {med['learnt']:.0f} / {p99['learnt']:.0f} | {med['search']:.0f} / "
                     f"{p99['search']:.0f} | {med['search'] / med['learnt']:.2f} |")
    emit_report(lines, args.out)


if __name__ == "__main__":
    main()
