"""A/B: ``gp.fit`` with BFGS's gradient stop (``gtol`` 1e-6, the default) against the Cauchy test alone
(``gtol`` 0, what the fit did before), and scikit-learn, interleaved in one process on the GP
benchmark's data (``benchmarks/bench_gp.py``: N = 100 and 300, d = 23, 3 starts), so that the
machine's drift falls on all three alike. Prints the medians, the ratios and each fit's LML.

``PYTHONPATH=. python scripts/ab_gp_gtol.py [--rounds 5]``
"""

import argparse
import os

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

from benchmarks import _data, bench_gp  # noqa: E402
from gtsjax import gp  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    for n in (100, 300):
        x, y = _data.gp_problem(n)
        xs, yc = bench_gp.standardise(x, y)
        fits = {"gtol 1e-6": 1e-6, "gtol 0 (before)": 0.0}
        times = {k: [] for k in (*fits, "scikit-learn")}
        lml = {}
        def fit(gtol, x=x, y=y):
            return jax.block_until_ready(gp.fit(x, y, key=jax.random.key(0), restarts=3, gtol=gtol))

        for gtol in fits.values():
            fit(gtol)  # compiled before the clock
        for _ in range(args.rounds):
            for k, gtol in fits.items():
                t0 = time.perf_counter()
                g = fit(gtol)
                times[k].append(time.perf_counter() - t0)
                lml[k] = float(g.log_marginal_likelihood())
            t0 = time.perf_counter()
            theta, _, _ = bench_gp.fit_sklearn(xs, yc, 3)
            times["scikit-learn"].append(time.perf_counter() - t0)
            lml["scikit-learn"] = bench_gp.common_lml(theta, xs, yc)
        med = {k: float(np.median(v)) for k, v in times.items()}
        print(f"N = {n}, {args.rounds} rounds interleaved:")
        for k, v in med.items():
            print(f"  {k:16s} median {v:.3f} s   LML {lml[k]:.3f}   scikit-learn / this {med['scikit-learn'] / v:.2f}x")


if __name__ == "__main__":
    main()
