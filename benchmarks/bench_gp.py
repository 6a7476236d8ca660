"""GP hyperparameter fitting: ``gtsjax.gp.fit`` against scikit-learn's ``GaussianProcessRegressor``
and (where it installs) tinygp, on the same data, for time and log marginal likelihood (LML).

The data are the project's own: GP inputs (characteristic vector, depth, range; d = 23) of robot
candidates from the simulated SPL training grid, with the robot's x̃ in the candidate's ORS as the
target (a pose regressor of stage e). Every library gets the same standardised inputs and centred
targets and the same model, ``σf² exp(−½ Σ_d (x_d − x'_d)² / l_d²) + σn² δ`` (ARD, one length scale
per feature), and the same number of optimiser starts (3: the default start ``l = √d``,
``σf² = var y``, ``σn² = var y / 10``, and two random ones):

* gtsjax: Optimistix BFGS in float64 with a closed-form LML gradient (``gp.fit``, ``restarts=3``);
* scikit-learn: ``ConstantKernel * RBF(ARD) + WhiteKernel`` with L-BFGS-B, ``n_restarts_optimizer=2``;
* tinygp: the same kernel (``transforms.Linear`` on ``ExpSquared``), its ``log_probability``
  differentiated by JAX, jitted, and minimised with SciPy's L-BFGS-B, as jaxopt's ``ScipyMinimize``
  does.

Each optimum's LML is also evaluated by one function (``gtsjax.gp.log_marginal_likelihood``), so the
"equal or better LML" comparison does not depend on each library's bookkeeping. Fit time is wall
clock of the whole fit; gtsjax and tinygp are timed after a first call that compiles (reported
separately as the cold time). The profile: the cost of one LML-and-gradient evaluation in each
library, and how many evaluations the fit time implies.
"""

import json
import math
import os
import subprocess
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from . import _data

SECTION = "gp"


def standardise(x, y):
    """As ``gp.fit`` does: per-feature mean and standard deviation (constant features scale 1), centred y."""
    m, s = x.mean(0), x.std(0)
    s = np.where(s > 1e-12 * np.maximum(np.abs(m), 1.0), s, 1.0)
    return (x - m) / s, y - y.mean()


def starts(d: int, y_var: float, n: int, seed: int = 0) -> list[np.ndarray]:
    """``(log l [d], log σf², log σn²)`` start vectors: the default start, then random ones around it
    (the same distribution as gtsjax's restarts)."""
    rng = np.random.default_rng(seed)
    base = np.concatenate([np.full(d, 0.5 * math.log(d)), [math.log(y_var), math.log(y_var / 10)]])
    out = [base]
    for _ in range(n - 1):
        out.append(base + np.concatenate([rng.uniform(-1.5, 1.5, d), rng.uniform(-1, 1, 1), rng.uniform(-4, 1.5, 1)]))
    return out


def common_lml(theta: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """LML of hyperparameters ``theta = (log l, log σf², log σn²)`` by gtsjax's eq. 5 (float64)."""
    from gtsjax import gp

    d = x.shape[1]
    p = gp.Hyperparameters(jnp.asarray(theta[:d]), jnp.asarray(theta[d]), jnp.asarray(theta[d + 1]))
    return float(gp.log_marginal_likelihood(p, jnp.asarray(x), jnp.asarray(y)))


def fit_gtsjax(x, y, restarts: int):
    from gtsjax import gp

    g = jax.block_until_ready(gp.fit(x, y, key=jax.random.key(0), restarts=restarts))
    p = g.params
    theta = np.concatenate([np.asarray(p.log_lengthscale), [float(p.log_signal_var), float(p.log_noise_var)]])
    return theta, float(g.log_marginal_likelihood())


def fit_sklearn(xs, yc, restarts: int):
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    d = xs.shape[1]
    v = float(yc.var())
    kernel = ConstantKernel(v, (1e-5, 1e5)) * RBF(np.full(d, math.sqrt(d)), (1e-5, 1e5)) + WhiteKernel(v / 10, (1e-5, 1e5))
    reg = GaussianProcessRegressor(kernel, n_restarts_optimizer=restarts - 1, random_state=0, normalize_y=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        reg.fit(xs, yc)
    k = reg.kernel_
    theta = np.concatenate([np.log(k.k1.k2.length_scale), [math.log(k.k1.k1.constant_value), math.log(k.k2.noise_level)]])
    return theta, float(reg.log_marginal_likelihood_value_), reg


def tinygp_objective(xs, yc):
    """Jitted ``θ ↦ (−LML, ∇)`` of the tinygp model on (xs, yc)."""
    from tinygp import GaussianProcess, kernels, transforms

    d = xs.shape[1]
    x, y = jnp.asarray(xs), jnp.asarray(yc)

    def nll(theta):
        sf2 = jnp.exp(theta[d])
        k = sf2 * transforms.Linear(jnp.exp(-theta[:d]), kernels.ExpSquared())
        return -GaussianProcess(k, x, diag=jnp.exp(theta[d + 1]) + 1e-8 * sf2).log_probability(y)

    return jax.jit(jax.value_and_grad(nll))


def fit_tinygp(obj, xs, yc, restarts: int):
    from scipy.optimize import minimize

    def f(t):
        v, g = obj(jnp.asarray(t))
        return float(v), np.asarray(g, np.float64)

    best, nfev = None, 0
    for t0 in starts(xs.shape[1], float(yc.var()), restarts):
        r = minimize(f, t0, jac=True, method="L-BFGS-B")
        nfev += r.nfev
        if np.isfinite(r.fun) and (best is None or r.fun < best.fun):
            best = r
    return best.x, -float(best.fun), nfev


def _timed(fn, repeats):
    out, value = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        value = fn()
        out.append(time.perf_counter() - t0)
    return np.asarray(out), value


def per_eval_costs(ctx, xs, yc, obj_tiny, reg) -> dict:
    """Seconds for one LML + gradient evaluation in each library, at the default start."""
    from gtsjax import gp

    d = xs.shape[1]
    t0 = starts(d, float(yc.var()), 1)[0]
    x, y = jnp.asarray(xs), jnp.asarray(yc)

    def neg(theta):
        p = gp.Hyperparameters(theta[:d], theta[d], theta[d + 1])
        return -gp.log_marginal_likelihood(p, x, y)

    g = jax.jit(jax.value_and_grad(neg))
    th = jnp.asarray(t0)
    out = {"gtsjax": float(np.median(ctx.time_calls(lambda i: g(th), 20, warmup=2)))}
    if obj_tiny is not None:
        out["tinygp"] = float(np.median(ctx.time_calls(lambda i: obj_tiny(th), 20, warmup=2)))
    if reg is not None:
        sk_theta = reg.kernel_.theta
        out["scikit-learn"] = float(np.median(ctx.time_calls(
            lambda i: reg.log_marginal_likelihood(sk_theta, eval_gradient=True, clone_kernel=False), 20, warmup=2)))
    return out


def compare(ctx, n: int, repeats: int, restarts: int = 3) -> dict:
    """Fit the n-point problem with every library; record times, LMLs and ratios."""
    res = ctx.results
    x, y = _data.gp_problem(n)
    xs, yc = standardise(x, y)
    tag = f"n{n}"
    t_cold, _ = _timed(lambda: fit_gtsjax(x, y, restarts), 1)
    t_g, (th_g, lml_g) = _timed(lambda: fit_gtsjax(x, y, restarts), repeats)
    res.add(f"gp_fit.{tag}.gtsjax", "s", t_g, section=SECTION, label=f"GP fit N={n}, d=23: gtsjax.gp.fit (3 starts)",
            n_train=n, cold_s=float(t_cold[0]))
    t_s, (th_s, lml_s, reg) = _timed(lambda: fit_sklearn(xs, yc, restarts), repeats)
    res.add(f"gp_fit.{tag}.sklearn", "s", t_s, section=SECTION, label=f"GP fit N={n}: scikit-learn GPR (3 starts)",
            n_train=n)
    res.ratio(f"gp_fit.{tag}.sklearn_over_gtsjax", f"gp_fit.{tag}.sklearn", f"gp_fit.{tag}.gtsjax",
              meaning=f"how many times faster gtsjax fits than scikit-learn (N={n}, median)")
    lml = {"gtsjax": {"own": lml_g, "common": common_lml(th_g, xs, yc)},
           "scikit-learn": {"own": lml_s, "common": common_lml(th_s, xs, yc)}}
    obj = None
    if ctx.peer("tinygp"):
        obj = tinygp_objective(xs, yc)
        t_tc, _ = _timed(lambda: fit_tinygp(obj, xs, yc, restarts), 1)
        t_t, (th_t, lml_t, nfev_t) = _timed(lambda: fit_tinygp(obj, xs, yc, restarts), repeats)
        res.add(f"gp_fit.{tag}.tinygp", "s", t_t, section=SECTION,
                label=f"GP fit N={n}: tinygp + SciPy L-BFGS-B (3 starts)", n_train=n, cold_s=float(t_tc[0]))
        res.ratio(f"gp_fit.{tag}.tinygp_over_gtsjax", f"gp_fit.{tag}.tinygp", f"gp_fit.{tag}.gtsjax",
                  meaning=f"how many times faster gtsjax fits than tinygp + L-BFGS-B (N={n}, median)")
        lml["tinygp"] = {"own": lml_t, "common": common_lml(th_t, xs, yc)}
    res.checks[f"gp_lml.{tag}"] = {"n_train": n, "lml": lml,
                                   "gtsjax_minus_sklearn_common": lml["gtsjax"]["common"] - lml["scikit-learn"]["common"]}
    evals = per_eval_costs(ctx, xs, yc, obj, reg)
    fit_times = {"gtsjax": float(np.median(t_g)), "scikit-learn": float(np.median(t_s))}
    if obj is not None:
        fit_times["tinygp"] = float(np.median(t_t))
    res.profiles[f"gp_fit.{tag}"] = {
        "seconds_per_lml_and_gradient": evals,
        # the fit's time in units of one evaluation: the evaluations it made, plus the optimiser's own overhead
        "fit_time_in_evaluations": {k: round(fit_times[k] / v) for k, v in evals.items()},
    }
    if obj is not None:
        res.profiles[f"gp_fit.{tag}"]["tinygp_lbfgsb_evaluations_counted"] = int(nfev_t)
    return lml


# The cold comparison's data sets: every one a new shape (N, d), fitted in this order in one fresh
# process per library, so that each gtsjax fit pays its compilation (issue 16's protocol).
COLD_SETS = ((150, 3), (250, 8), (350, 13), (450, 17), (600, 21))


def cold_problem(n: int, d: int, seed: int):
    """A smooth nonlinear function of ``d`` features with noise (features on different scales, a few
    irrelevant), ``n`` training rows and 50 test rows; not the project's data."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n + 50, d)) * rng.uniform(0.5, 3.0, d)
    w = rng.normal(size=d) / math.sqrt(d)
    f = np.sin(2.0 * x @ w) + 0.3 * x[:, 0] ** 2 / (1.0 + x[:, 0] ** 2) + 0.1 * x[:, -1]
    y = f + 0.1 * rng.normal(size=n + 50)
    return x[:n], y[:n], x[n:]


def _cold_child(lib: str) -> None:
    """In a fresh process: fit and predict every set of ``COLD_SETS`` with ``lib`` (gtsjax: ``gp.fit``
    with 4 starts; scikit-learn: 3 optimiser restarts, i.e. 4 starts), printing one JSON line per set.
    Imports (and, for JAX, the CPU backend's start-up) come before the clock; the persistent
    compilation cache is off."""
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    if lib == "gtsjax":
        from gtsjax import gp

        jax.block_until_ready(jnp.zeros(1) + 1)  # the backend's start-up, not a compilation of ours
    else:
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    for i, (n, d) in enumerate(COLD_SETS):
        x, y, xt = cold_problem(n, d, i)
        t0 = time.perf_counter()
        if lib == "gtsjax":
            g = gp.fit(x, y, key=jax.random.key(0), restarts=4)
            np.asarray(gp.predict_mean(g, jnp.asarray(xt)))
            t = time.perf_counter() - t0
            p = g.params
            theta = np.concatenate([np.asarray(p.log_lengthscale), [float(p.log_signal_var), float(p.log_noise_var)]])
        else:
            xm, xsd = x.mean(0), x.std(0)
            xs, yc = (x - xm) / xsd, y - y.mean()
            v = float(yc.var())
            kernel = ConstantKernel(v, (1e-5, 1e5)) * RBF(np.full(d, math.sqrt(d)), (1e-5, 1e5)) + WhiteKernel(v / 10, (1e-5, 1e5))
            reg = GaussianProcessRegressor(kernel, n_restarts_optimizer=3, random_state=0)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                reg.fit(xs, yc)
            reg.predict((xt - xm) / xsd)
            t = time.perf_counter() - t0
            k = reg.kernel_
            theta = np.concatenate([np.log(k.k1.k2.length_scale), [math.log(k.k1.k1.constant_value), math.log(k.k2.noise_level)]])
        xs, yc = standardise(x, y)
        print(json.dumps({"n": n, "d": d, "seconds": t, "lml": common_lml(theta, xs, yc)}), flush=True)


def cold(ctx) -> None:
    """The cold comparison (``COLD_SETS``), each library in a fresh process of its own."""
    res = ctx.results
    rows = {}
    for lib in ("gtsjax", "sklearn"):
        env = dict(os.environ, JAX_ENABLE_COMPILATION_CACHE="false")
        out = subprocess.run([sys.executable, "-m", "benchmarks.bench_gp", "--cold", lib], capture_output=True,
                             text=True, env=env, check=True, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        rows[lib] = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    sets = []
    for g, s in zip(rows["gtsjax"], rows["sklearn"], strict=True):
        tag = f"n{g['n']}d{g['d']}"
        res.add(f"gp_cold.{tag}.gtsjax", "s", [g["seconds"]], section=SECTION,
                label=f"GP fit + predict, cold, N={g['n']}, d={g['d']}: gtsjax (4 starts)", n_train=g["n"])
        res.add(f"gp_cold.{tag}.sklearn", "s", [s["seconds"]], section=SECTION,
                label=f"GP fit + predict, cold, N={g['n']}, d={g['d']}: scikit-learn (4 starts)", n_train=g["n"])
        res.ratio(f"gp_cold.{tag}.sklearn_over_gtsjax", f"gp_cold.{tag}.sklearn", f"gp_cold.{tag}.gtsjax",
                  meaning=f"cold fit: how many times faster gtsjax is than scikit-learn (N={g['n']}, d={g['d']})")
        sets.append({"n": g["n"], "d": g["d"], "gtsjax_s": g["seconds"], "sklearn_s": s["seconds"],
                     "gtsjax_minus_sklearn_lml": g["lml"] - s["lml"]})
    res.checks["gp_cold"] = {"sets": sets, "protocol": "one fresh process per library, sets in order, "
                             "imports and JAX's backend start-up before the clock, no persistent cache"}


def run(ctx) -> None:
    sizes = [100] if ctx.quick else [100, 300]
    for n in sizes:
        compare(ctx, n, 1 if ctx.quick else 2)
    if not ctx.quick:
        cold(ctx)
    ctx.results.sections[SECTION] = {"data": "robot candidates of simulated spl-train, target x̃ (ORS)",
                                     "features": 23, "starts": 3}


if __name__ == "__main__":
    if sys.argv[1:2] == ["--cold"]:
        _cold_child(sys.argv[2])
