"""GP fit and prediction timings against scikit-learn, on laser-profile-like data (d = 21).

    python benchmarks/bench_gp.py [--quick] [--json PATH] [--sizes 500 1000 2000] [--sk-max 2000]

For each training-set size N: gtsjax fit time (first call, which includes compilation, and a second
warmed call with another key), sklearn GaussianProcessRegressor fit time (same kernel family,
n_restarts_optimizer=2, on the same standardised inputs and centred targets), both optima's log
marginal likelihoods, and the predictive pass for 32 test points (exact GP and DTC sparse GP with
M inducing points): median of repeated calls after warm-up, ending in block_until_ready. Wall-clock
numbers depend on the load of the machine; report them with that caveat.
"""

import argparse
import json
import statistics
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from gtsjax import gp  # noqa: E402


def profiles(rng, n, d=21):
    """d features: (d - 5) depth-profile cells of an ellipse seen at heading phi, then width, mean
    intensity, point count, range and a nuisance feature; target cos(phi) plus noise."""
    n_cells = d - 5
    phi = rng.uniform(-np.pi, np.pi, n)
    rng_m = rng.uniform(0.5, 3.5, n)
    cells = np.linspace(-1.0, 1.0, n_cells)
    half_w = 0.6 + 0.3 * np.abs(np.cos(phi))
    depth = np.sqrt(np.clip(1.0 - (cells[None, :] / half_w[:, None]) ** 2, 0.0, None))
    depth = depth * (0.4 + 0.2 * np.sin(phi))[:, None] + 0.01 * rng.normal(size=(n, n_cells))
    extra = np.stack([2.0 * half_w, 0.5 + 0.1 * np.cos(phi), 40.0 / rng_m, rng_m, rng.normal(size=n)], axis=1)
    return np.concatenate([depth, extra], axis=1), np.cos(phi) + 0.05 * rng.normal(size=n)


def median_time(fn, repeats):
    jax.block_until_ready(fn())  # warm-up (compilation)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def sklearn_fit(x, y, restarts):
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    d = x.shape[1]
    kernel = ConstantKernel(1.0, (1e-5, 1e5)) * RBF(np.full(d, np.sqrt(d)), (1e-5, 1e5)) + WhiteKernel(0.1, (1e-5, 1e5))
    reg = GaussianProcessRegressor(kernel, n_restarts_optimizer=restarts, random_state=0, normalize_y=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        t0 = time.perf_counter()
        reg.fit(x, y)
        return time.perf_counter() - t0, float(reg.log_marginal_likelihood_value_)


def run(sizes, sk_max, sk_restarts, n_inducing, repeats):
    rng = np.random.default_rng(0)
    rows = []
    for n in sizes:
        x, y = profiles(rng, n)
        xt, _ = profiles(rng, 32)
        t0 = time.perf_counter()
        g = gp.fit(x, y, key=jax.random.key(0))
        jax.block_until_ready(g)
        t_first = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(gp.fit(x, y, key=jax.random.key(1)))
        t_warm = time.perf_counter() - t0
        lml = float(g.log_marginal_likelihood())

        if n <= sk_max:
            t_sk, lml_sk = sklearn_fit(np.asarray(g.x), np.asarray(g.y), sk_restarts)
        else:
            t_sk, lml_sk = float("nan"), float("nan")

        xt = jnp.asarray(xt)
        sp = g.sparse(n_inducing)
        t_exact = median_time(lambda g=g, xt=xt: g.predict(xt), repeats)
        t_sparse = median_time(lambda sp=sp, xt=xt: sp.predict(xt), repeats)
        m_e, v_e = g.predict(xt)
        m_s, v_s = sp.predict(xt)
        g32 = g.astype(jnp.float32)
        xt32 = xt.astype(jnp.float32)
        t_exact32 = median_time(lambda g32=g32, xt32=xt32: g32.predict(xt32), repeats)
        rows.append(
            dict(
                n=n,
                d=x.shape[1],
                fit_first_s=t_first,
                fit_warm_s=t_warm,
                sk_fit_s=t_sk,
                sk_over_ours=t_sk / t_warm,
                lml=lml,
                lml_sk=lml_sk,
                lml_minus_sk=lml - lml_sk,
                predict32_exact_ms=1e3 * t_exact,
                predict32_exact_f32_ms=1e3 * t_exact32,
                predict32_sparse_ms=1e3 * t_sparse,
                n_inducing=int(min(n_inducing, n)),
                sparse_max_abs_mean_diff=float(jnp.max(jnp.abs(m_s - m_e))),
                sparse_max_abs_var_diff=float(jnp.max(jnp.abs(v_s - v_e))),
            )
        )
        print_row(rows[-1], header=len(rows) == 1)
    return rows


def print_row(r, header):
    cols = [
        ("N", "n", "{:>6d}"),
        ("fit1 s", "fit_first_s", "{:>8.2f}"),
        ("fit s", "fit_warm_s", "{:>8.2f}"),
        ("sk s", "sk_fit_s", "{:>8.2f}"),
        ("sk/ours", "sk_over_ours", "{:>8.2f}"),
        ("LML", "lml", "{:>11.3f}"),
        ("LML sk", "lml_sk", "{:>11.3f}"),
        ("diff", "lml_minus_sk", "{:>9.4f}"),
        ("pred ms", "predict32_exact_ms", "{:>8.3f}"),
        ("f32 ms", "predict32_exact_f32_ms", "{:>8.3f}"),
        ("DTC ms", "predict32_sparse_ms", "{:>8.3f}"),
        ("M", "n_inducing", "{:>5d}"),
        ("|dmean|", "sparse_max_abs_mean_diff", "{:>9.2e}"),
        ("|dvar|", "sparse_max_abs_var_diff", "{:>9.2e}"),
    ]
    if header:
        print(" ".join(f"{h:>{len(f.format(r[k]))}}" for h, k, f in cols))
    print(" ".join(f.format(r[k]) for _, k, f in cols), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N = 200, 500 and fewer repeats")
    ap.add_argument("--sizes", type=int, nargs="+", default=None)
    ap.add_argument("--sk-max", type=int, default=2000, help="skip sklearn above this N")
    ap.add_argument("--sk-restarts", type=int, default=2)
    ap.add_argument("--inducing", type=int, default=256)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args()
    sizes = args.sizes or ([200, 500] if args.quick else [500, 1000, 2000])
    repeats = 5 if args.quick else 20
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}; timings are wall clock on a shared machine")
    rows = run(sizes, args.sk_max, args.sk_restarts, args.inducing, repeats)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
