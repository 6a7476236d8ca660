"""Fitting a GP: type-II maximum likelihood (paper section 3b, eq 4: maximise eq 5 over the
hyperparameters) with Optimistix's BFGS, several starts, and a clamp on the log length scales.

Conventions:

- **Inputs are standardised inside** :func:`fit` (per-feature mean and standard deviation over the
  valid training rows; a constant feature gets scale 1, so it becomes an all-zero column and never a
  NaN); **targets are centred**. The returned :class:`~gtsjax.gp.GP` stores both statistics.
- **Cost**: past ``max_points`` valid rows (default 3000) :func:`fit` keeps a seeded random subsample,
  which caps the exact predictor at O(N) per test point for the mean and O(N^2) for the variance
  (:meth:`~gtsjax.gp.GP.sparse` for a smaller cap).
- **Host side of the library**: :func:`fit` picks rows by value (NumPy, not jittable); the
  optimisation and the factorisation inside are jitted, in float64.
"""

import dataclasses
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, PRNGKeyArray

from ..precision import exact_products
from .errors import GPArgumentError, GPFitError
from .exact import GP, _condition
from .kernel import DEFAULT_JITTER, Hyperparameters, log_marginal_likelihood

# ------------------------------------------------------------------------------ one start (jitted)


class _SharedHyperparameters(eqx.Module):
    """The hyperparameters :func:`fit_shared` optimises: length scales shared by ``k`` outputs, a signal
    and a noise variance per output (log space, as :class:`~gtsjax.gp.Hyperparameters`)."""

    log_lengthscale: Float[Array, " features"]
    log_signal_var: Float[Array, " outputs"]
    log_noise_var: Float[Array, " outputs"]


def _neg_lml_per_point(params, args):
    """-LML/N of eq 5; for targets ``y`` [N, k] (a shared kernel, :func:`fit_shared`) the sum of the
    outputs' LMLs, each under the shared length scales and its own signal and noise variance, over
    N times the number of informative outputs (``weight`` 1; a constant output has weight 0)."""
    x, y, mask, jitter, weight = args
    n_valid = jnp.maximum(jnp.sum(mask), 1).astype(y.dtype)
    if y.ndim == 1:
        return -log_marginal_likelihood(params, x, y, mask, jitter=jitter) / n_valid

    def one(log_sf, log_sn, yk):
        return log_marginal_likelihood(Hyperparameters(params.log_lengthscale, log_sf, log_sn), x, yk, mask,
                                       jitter=jitter)

    lml = jax.vmap(one, in_axes=(0, 0, 1))(params.log_signal_var, params.log_noise_var, y)
    return -jnp.sum(weight * lml) / (n_valid * jnp.maximum(jnp.sum(weight), 1))


# Upper end of the log length scale (standardised units) that each start is clamped to; scikit-learn's
# default bound (1e5).
LOG_LENGTHSCALE_CLAMP = math.log(1e5)


def _clamp(params: "Hyperparameters | _SharedHyperparameters") -> "Hyperparameters | _SharedHyperparameters":
    ls = jnp.minimum(params.log_lengthscale, jnp.asarray(LOG_LENGTHSCALE_CLAMP, params.log_lengthscale.dtype))
    return type(params)(ls, params.log_signal_var, params.log_noise_var)


# How much looser the convergence test on the hyperparameters is than on the objective. optimistix's
# Cauchy test needs both the objective and every parameter to stop moving; an irrelevant feature's log
# length scale keeps drifting along a flat direction long after the likelihood has converged (at
# N = 2000 this more than doubled the number of BFGS steps). With rtol = 1e-6, a log length scale
# moving by less than about 1e-3 (0.1 % of the length scale) no longer holds the fit open.
_PARAM_TOL_FACTOR = 1e3


def _convergence_norm(tree) -> Float[Array, ""]:
    scale = 1.0 / _PARAM_TOL_FACTOR if isinstance(tree, (Hyperparameters, _SharedHyperparameters)) else 1.0
    return optx.max_norm(tree) * scale


class _ArmijoToRounding(optx.BacktrackingArmijo):
    """Optimistix's backtracking Armijo search, except that a step whose objective differs from the last
    accepted one by no more than rounding (``_ROUNDING`` times its size) is accepted too.

    Why: BFGS stops only on an accepted step that moved little in both the objective and the
    parameters. At an optimum, or on a plateau (a signal variance collapsing under the noise), the
    steps shrink until the objective no longer changes at all; plain Armijo then demands a decrease
    that a change of zero cannot give, rejects every step, and the loop runs to ``max_steps``. Which
    start met this was down to rounding: the same starts run one at a time stopped, vmapped together
    (a batched product rounds differently) three of four ran to 1 000 steps."""

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        y_diff = jtu.tree_map(lambda a, b: a - b, y_eval, y)
        predicted = f_info.compute_grad_dot(y_diff)
        f_old = f_info.as_min()
        f_diff = f_eval_info.as_min() - f_old
        rounding = jnp.asarray(_ROUNDING, f_old.dtype) * jnp.maximum(jnp.abs(f_old), jnp.ones((), f_old.dtype))
        armijo = (f_diff <= self.slope * predicted) & (predicted <= 0)
        accept = first_step | armijo | (jnp.abs(f_diff) <= rounding)
        step_size = jnp.where(accept, self.step_init, self.decrease_factor * state.step_size)
        return step_size, accept, optx.RESULTS.successful, type(state)(step_size=step_size)


# A change of the objective (-LML/N, order 1) that is rounding: 64 ulps of float64.
_ROUNDING = 64 * float(np.finfo(np.float64).eps)


class _BFGS(optx.BFGS):
    """Optimistix BFGS that also stops at a first-order optimum: once every component of the
    objective's gradient at the last accepted point is at most ``gtol``.

    Why: its Cauchy test needs the objective and every parameter to stop moving, and a length scale
    drifting along a flat direction keeps the fit open after it has converged. On the benchmark's
    data sets (``benchmarks/bench_gp.py``: N = 100–600, d = 3–23) starts were within 0.001 nats of
    their final LML after 53–74 % of their steps; with ``gtol`` = 1e-6 on ∇(−LML/N) every set ends at
    the same LML (to 0.001 nats), a start taking up to 71 % fewer steps (none fewer where the Cauchy
    test stopped it first)."""

    gtol: float

    def __init__(self, rtol: float, atol: float, gtol: float, norm):
        super().__init__(rtol=rtol, atol=atol, norm=norm)
        self.gtol = gtol

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        stationary = (state.num_accepted_steps > 0) & (optx.max_norm(state.f_info.grad) <= self.gtol)
        return done | stationary, result


def _solver(rtol: float, atol: float, gtol: float) -> optx.AbstractMinimiser:
    """:class:`_BFGS` with the convergence norm above and the search of :class:`_ArmijoToRounding`."""
    bfgs = _BFGS(rtol, atol, gtol, _convergence_norm)
    return eqx.tree_at(lambda s: s.search, bfgs, _ArmijoToRounding())


def _stage(params0, x, y, mask, jitter, weight, rtol: float, atol: float, gtol: float, max_steps: int):
    """Maximise eq 5 (eq 4) from one start, its log length scales clamped at ``LOG_LENGTHSCALE_CLAMP``:
    Optimistix BFGS on -LML/N. Returns the optimum, its objective (inf if BFGS did not succeed or the
    objective is not finite) and the number of steps. The objective is -LML/N so that BFGS's unit
    first step and the tolerances do not depend on the training-set size."""
    solver = _solver(rtol, atol, gtol)
    args = (x, y, mask, jitter, weight)
    sol = optx.minimise(_neg_lml_per_point, solver, _clamp(_params(*params0)), args, max_steps=max_steps,
                        throw=False)
    ok = sol.result == optx.RESULTS.successful
    nll = _neg_lml_per_point(sol.value, args)
    nll = jnp.where(ok & jnp.isfinite(nll), nll, jnp.asarray(jnp.inf, y.dtype))
    return _fields(sol.value), nll, sol.stats["num_steps"]


# Several starts as one optimisation: the starts are a leading axis of the parameters, the data shared.
# One compiled program per (number of starts, data shape); the loop runs until the last start stops,
# the others' states held.
_stages = eqx.filter_jit(eqx.filter_vmap(_stage, in_axes=(0,) + (None,) * 9))


def _optimise(starts, x, y, mask, jitter, weight, rtol: float, atol: float, gtol: float, max_steps: int):
    """Maximise eq 5 (eq 4) from each of ``starts`` (parameters stacked on a leading axis), all in one
    vmapped BFGS (:func:`_stage`); then, for the starts whose log length scales ended past
    ``LOG_LENGTHSCALE_CLAMP``, BFGS again from there with them clamped; the better stage of each
    start is kept. Returns the optima, objectives (inf where a start failed) and step counts, stacked.

    Why two stages: the LML is flat in an irrelevant feature's length scale, BFGS's steps grow along
    flat directions, and a feature that wants a long but finite scale (a near-linear trend, ``log l ~
    8``) is thrown to ``log l ~ 300``, where its gradient underflows and it cannot come back. The
    clamped second start gives it a gradient again (on 20-D data this recovered the 0.1-1 nats by
    which bounded L-BFGS-B, i.e. scikit-learn, was ahead). The host decides whether the second stage
    runs (one look at the first stage's optima), so the program holds one BFGS loop, not two."""
    p1, f1, n1 = _stages(starts, x, y, mask, jitter, weight, rtol, atol, gtol, max_steps)
    clamp = np.asarray(LOG_LENGTHSCALE_CLAMP)
    past = np.any(np.asarray(p1[0]) > clamp, axis=-1)
    if not past.any():
        return p1, f1, n1
    p2, f2, n2 = _stages(p1, x, y, mask, jitter, weight, rtol, atol, gtol, max_steps)
    second = jnp.asarray(past) & (f2 <= f1)
    value = tuple(jnp.where(second.reshape(-1, *([1] * (a.ndim - 1))), b, a) for a, b in zip(p1, p2, strict=True))
    return value, jnp.where(second, f2, f1), n1 + jnp.where(jnp.asarray(past), n2, 0)


def _rng(key, salt: int) -> np.random.Generator:
    """A NumPy generator drawn from ``key`` (row subsamples are chosen on the host: as JAX ops, each new
    count compiled a program of its own)."""
    return np.random.default_rng([int(v) for v in np.asarray(jax.random.key_data(key)).ravel()] + [salt])


def _subsample(key, salt: int, n: int, size: int) -> np.ndarray:
    """``size`` of ``n`` row indices, without replacement, sorted; the same for the same key."""
    return np.sort(_rng(key, salt).choice(n, size, replace=False))


def _initial_params(key, restarts: int, d: int, y_var) -> tuple:
    """Every start's ``(log l, log sigma_f^2, log sigma_n^2)``, stacked on a leading axis of ``restarts``. Start 0: length scales sqrt(d) in
    standardised units (so the summed squared distance is O(1)), sigma_f^2 = var(y), sigma_n^2 =
    var(y)/10. Later starts: log-uniform jitter around that, drawn from ``key`` (on the host: as JAX
    ops they compiled a program of their own per shape). With ``y_var`` [k] (one per output of a
    shared kernel) the signal and noise variances are [restarts, k]."""
    y_var = np.asarray(y_var, np.float64)
    rng = _rng(key, 2)
    jittered = (np.arange(restarts) > 0)[:, None]
    ls = np.full((restarts, d), 0.5 * math.log(max(d, 1))) + jittered * rng.uniform(-1.5, 1.5, (restarts, d))
    shape = (restarts, *y_var.shape)
    jittered = jittered.reshape(restarts, *([1] * y_var.ndim))
    sf = np.log(y_var) + jittered * rng.uniform(-1.0, 1.0, shape)
    sn = np.log(y_var) - math.log(10.0) + jittered * rng.uniform(-4.0, 1.5, shape)
    return jnp.asarray(ls), jnp.asarray(sf), jnp.asarray(sn)


# --------------------------------------------------------------------------- several starts (host)


# On a CPU, the most training rows at which the starts run vmapped. A vmapped loop runs until its last
# start stops, so it costs the number of starts times the longest start's steps; one after another
# costs the sum of their steps. Where each evaluation is a few small kernels (N ~ 100) the shared
# per-kernel overhead wins; where it is an O(N^3) factorisation the sum does (at N = 450, d = 17, four
# starts of 258, 256, 242 and 97 steps: vmapped 9.7 s, one after another 8.3 s). On a GPU the starts always
# run vmapped. Either way one program serves every start of a data shape.
VMAP_MAX_ROWS = 200


def _vmapped(n_rows: int) -> bool:
    return n_rows <= VMAP_MAX_ROWS or jax.default_backend() != "cpu"


@dataclasses.dataclass
class _Starts:
    """Runs :func:`_optimise` from given starts under one set of solver settings, and describes every
    failed start in ``failures`` (for :class:`GPFitError`)."""

    jitter: Float[Array, ""]
    weight: Float[Array, "..."]  # per output of a shared kernel: 1 informative, 0 constant (1 for one output)
    rtol: float
    atol: float
    gtol: float
    max_steps: int
    failures: list[str] = dataclasses.field(default_factory=list)

    def run(self, restarts, starts, x, y, mask, label: str) -> list:
        """``(objective, restart, params)`` of the successful ``starts`` (parameters stacked on a leading
        axis, one row per entry of ``restarts``), best first. They run as one vmapped optimisation,
        except on a CPU past ``VMAP_MAX_ROWS`` rows (see there), where they run one after another."""
        if _vmapped(x.shape[0]):
            params, nlls, steps = _optimise(starts, x, y, mask, self.jitter, self.weight, self.rtol, self.atol,
                                            self.gtol, self.max_steps)
        else:
            each = [_optimise(tuple(a[i : i + 1] for a in starts), x, y, mask, self.jitter, self.weight, self.rtol,
                              self.atol, self.gtol, self.max_steps) for i in range(len(restarts))]
            params = tuple(jnp.concatenate(a) for a in zip(*(e[0] for e in each), strict=True))
            nlls, steps = (jnp.concatenate(a) for a in zip(*(e[1:] for e in each), strict=True))
        params = tuple(np.asarray(a) for a in params)
        nlls, steps = np.asarray(nlls), np.asarray(steps)
        done = []
        for i, r in enumerate(restarts):
            if np.isfinite(nlls[i]):
                done.append((float(nlls[i]), int(r), _row(params, i)))
            else:
                self.failures.append(f"{label} restart {r}: not converged to a finite -LML/N after {int(steps[i])} steps")
        done.sort(key=lambda t: (t[0], t[1]))
        return done


def _row(stacked, i: int):
    """Start ``i`` of parameters stacked on a leading axis, as hyperparameters."""
    return _params(*(jnp.asarray(np.asarray(a)[i]) for a in stacked))


def _one(params):
    """One start's hyperparameters as a stack of one."""
    return tuple(jnp.asarray(a)[None] for a in _fields(params))


def _params(log_lengthscale, log_signal_var, log_noise_var) -> "Hyperparameters | _SharedHyperparameters":
    """Hyperparameters of one start from its three arrays; per-output variances make them shared.
    (Starts travel stacked as plain tuples: the modules' annotations describe one start.)"""
    kind = Hyperparameters if jnp.ndim(log_signal_var) == 0 else _SharedHyperparameters
    return kind(log_lengthscale, log_signal_var, log_noise_var)


def _fields(params) -> tuple:
    return params.log_lengthscale, params.log_signal_var, params.log_noise_var


def _screen_then_refine(runs: _Starts, starts, xs, yc, fit_set, screen_points: int, key_screen) -> list:
    """All starts on a seeded subsample of ``screen_points`` of the fit rows ``xs``/``yc``; then, on
    all of them (``fit_set``), the default start from scratch and the best random start, warm, only
    if screening found it better than the default. A warm start from a subset's optimum can settle in
    a basin that is worse on all the data, so the default is never skipped."""
    pick = _subsample(key_screen, 0, xs.shape[0], screen_points)
    ys = yc[pick] - yc[pick].mean(axis=0)
    n_starts = starts[0].shape[0]
    screened = runs.run(range(n_starts), starts, jnp.asarray(xs[pick]), jnp.asarray(ys),
                        jnp.ones((screen_points,), bool), "screening")
    sub_default = next((f for f, r, _ in screened if r == 0), np.inf)
    better = [(r, p) for f, r, p in screened if r != 0 and f < sub_default]
    # one start at a time: one compiled program for the fit set, whatever number of starts is refined
    done = runs.run([0], tuple(a[:1] for a in starts), *fit_set, "refining")
    for r, p in better:
        found = runs.run([r], _one(p), *fit_set, "refining")
        if found:
            return sorted(done + found, key=lambda t: (t[0], t[1]))
    return done


# ------------------------------------------------------------------------------------ data (host)


def _checked(x, y, restarts: int, max_fit_points: int | None, outputs: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``x`` and ``y`` as float64 arrays, once the arguments are known to be usable; ``y`` is [N] when
    ``outputs`` is 1, else [N, k] with k >= 1."""
    if not jax.config.read("jax_enable_x64"):
        raise GPArgumentError(where, "GP fitting runs in float64: enable jax_enable_x64")
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    want = "[N]" if outputs == 1 else "[N, k]"
    if x.ndim != 2 or y.ndim != (1 if outputs == 1 else 2) or x.shape[0] != y.shape[0] or y.size == 0:
        raise GPArgumentError(where, f"need x [N, d] and y {want}, got {x.shape} and {y.shape}")
    if restarts < 1:
        raise GPArgumentError(where, f"restarts must be >= 1, got {restarts}")
    if max_fit_points is not None and max_fit_points < 1:
        raise GPArgumentError(where, f"max_fit_points must be >= 1, got {max_fit_points}")
    return x, y


def _valid_rows(x, y, mask, where: str) -> np.ndarray:
    """Indices of the rows that are unmasked and finite (every output of a row); at least one."""
    valid = np.ones(y.shape[:1], bool) if mask is None else np.asarray(mask, bool).copy()
    valid &= np.all(np.isfinite(y.reshape(len(y), -1)), axis=1) & np.all(np.isfinite(x), axis=1)
    rows = np.flatnonzero(valid)
    if rows.size == 0:
        raise GPArgumentError(where, "no valid (finite, unmasked) training rows")
    return rows


class _Standardised(NamedTuple):
    x: np.ndarray  # standardised inputs
    y: np.ndarray  # centred targets ([N], or [N, k] for a shared kernel)
    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: np.ndarray  # [] or [k]
    y_var: np.ndarray  # [] or [k]; 1 for constant targets
    constant: np.ndarray  # [] or [k]: the targets carry no information on the hyperparameters


def _standardised(x, y) -> _Standardised:
    x_mean = x.mean(axis=0)
    x_std = x.std(axis=0)
    x_scale = np.where(x_std > 1e-12 * np.maximum(np.abs(x_mean), 1.0), x_std, 1.0)
    y_mean = y.mean(axis=0)
    xs = (x - x_mean) / x_scale
    yc = y - y_mean
    y_var = yc.var(axis=0)
    constant = ~(y_var > (1e-12 * np.maximum(1.0, np.abs(y_mean))) ** 2)
    y_var = np.where(constant, 1.0, y_var)
    return _Standardised(xs, yc, x_mean, x_scale, y_mean, y_var, constant)


def _padded(xs, yc, size: int):
    """Inputs, targets and mask padded (masked) to ``size`` rows, on the device."""
    n, d = xs.shape
    xp = np.zeros((size, d))
    yp = np.zeros((size, *yc.shape[1:]))
    mp = np.zeros((size,), bool)
    xp[:n], yp[:n], mp[:n] = xs, yc, True
    return jnp.asarray(xp), jnp.asarray(yp), jnp.asarray(mp)


def _fit_rows(xs, yc, padded, max_fit_points: int | None, key_sub):
    """The rows the hyperparameters are fitted on: all of them (``padded``), unless ``max_fit_points``
    is smaller, then a seeded subsample of that many, its targets centred again. Returns them on the
    host (screening subsamples from these) and on the device."""
    n = xs.shape[0]
    if max_fit_points is None or n <= max_fit_points:
        return xs, yc, padded
    sub = _subsample(key_sub, 1, n, int(max_fit_points))
    xs, yc = xs[sub], yc[sub] - yc[sub].mean(axis=0)
    return xs, yc, (jnp.asarray(xs), jnp.asarray(yc), jnp.ones((int(max_fit_points),), bool))


# ------------------------------------------------------------------------------------------- fit


@exact_products
def fit(
    x,
    y,
    *,
    key: PRNGKeyArray,
    restarts: int = 3,
    max_points: int = 3000,
    max_fit_points: int | None = None,
    screen_points: int = 500,
    mask=None,
    pad_to: int | None = None,
    jitter: float = DEFAULT_JITTER,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    gtol: float = 1e-6,
    max_steps: int = 1000,
) -> GP:
    """Fit a GP regressor by maximising eq 5 (eq 4) over log-space hyperparameters; float64.

    - ``x`` [N, d], ``y`` [N]; ``mask`` [N] (optional) marks valid rows; rows with a non-finite value
      are dropped too.
    - ``key``: jax PRNG key for the subsamples and the random restarts. Same key, same GP.
    - ``restarts``: number of starts (the first a fixed default, the rest random around it, drawn
      from ``key``). The starts run together as one vmapped :class:`optimistix.BFGS` optimisation
      (``throw=False``), and those whose log length scales ran past log 1e5 run again from there,
      clamped (see ``_optimise``). A start that does not succeed or whose objective is not finite is
      skipped; the best remaining one is kept. If all fail, :class:`GPFitError` is raised, naming
      each failure.
    - ``max_points``: above this many valid rows, a seeded random subsample of ``max_points`` rows is
      used (cost cap: fit O(max_points^3); exact prediction O(max_points) per test point for the mean,
      O(max_points^2) for the variance; :meth:`GP.sparse` for a smaller cap).
    - ``max_fit_points``: with more rows kept than this, the hyperparameters are fitted on a seeded
      random subsample of this many, and the GP is then conditioned on all the rows kept: the exact
      posterior under those hyperparameters. Each likelihood evaluation then costs
      O(max_fit_points^3) and the conditioning one O(N^3) factorisation, so a GP can predict from
      several times the examples its fit could afford (the hyperparameters, a few dozen numbers, are
      well determined by a few thousand examples; the posterior mean gains from every one).
    - ``screen_points``: with more valid rows than this and ``restarts > 1``, the starts run on a
      seeded subsample of ``screen_points`` rows; on all rows, the default start is then refined from
      scratch, and the best random start (warm, from its subset optimum) only if it beat the default
      on the subset. More restarts therefore never end below one. (Screening on half the rows at
      every size was tried: 1.6 times faster at N = 300, but on a 450-point, 17-feature problem it
      ended 4.7 nats below running every start on all the rows.)
    - ``pad_to``: pad the training set to this fixed size (masked) so that GPs fitted on different
      data share shapes (one compilation; stackable). Must be >= the number of rows kept.
    - ``rtol``/``atol``/``max_steps``: :class:`optimistix.BFGS` tolerances on -LML/N and step cap.
    - ``gtol``: BFGS also stops once every component of the gradient of -LML/N (in the log
      hyperparameters) is at most this: a first-order optimum (see ``_BFGS``).

    Constant targets (including N = 1) carry no information on the hyperparameters and make eq 5
    unbounded; the default start is then kept without optimisation (the GP predicts the constant).

    Arguments it cannot use (shapes, counts, no valid row, no ``jax_enable_x64``) raise
    :class:`GPArgumentError`.

    Requires ``jax_enable_x64``. Host-side entry point (not jittable: it picks rows by value); the
    optimisation and the factorisation inside are jitted.
    """
    x, y = _checked(x, y, restarts, max_fit_points, 1, "gp.fit")
    best, padded, data, jit_ = _fit_hyperparameters(
        x, y, key, restarts, max_points, max_fit_points, screen_points, mask, pad_to, jitter, rtol, atol, gtol, max_steps,
        "gp.fit")
    y_mean, x_mean, x_scale = (jnp.asarray(a) for a in (data.y_mean, data.x_mean, data.x_scale))
    return _condition(best, *padded, y_mean, x_mean, x_scale, jit_)


@exact_products
def fit_shared(
    x,
    y,
    *,
    key: PRNGKeyArray,
    restarts: int = 3,
    max_points: int = 3000,
    max_fit_points: int | None = None,
    screen_points: int = 500,
    mask=None,
    pad_to: int | None = None,
    jitter: float = DEFAULT_JITTER,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    gtol: float = 1e-6,
    max_steps: int = 1000,
) -> tuple[GP, ...]:
    """Fit ``k`` GP regressors of the same inputs with one shared kernel: one set of ARD length scales,
    each output its own signal and noise variance, maximising the sum of the outputs' LMLs (eq 5)
    with the same BFGS, starts, subsamples and screening as :func:`fit` (whose arguments these are).

    ``y`` is [N, k]. Returns one :class:`GP` per output, each conditioned on its own targets; they
    share ``x``, ``mask``, the input statistics and the length scales, so that one kernel row of a
    test input serves them all (:meth:`gtsjax.gp.SharedSparseGP.build`: a class's four pose GPs in
    one row). Each is an ordinary :class:`GP`: predicting with it alone is predicting with
    that output. Rows with a non-finite target in any output are dropped. An output whose targets are
    constant carries no information on the shared hyperparameters: it is left out of the objective
    and keeps its default start (it predicts its constant).
    """
    x, y = _checked(x, y, restarts, max_fit_points, 2, "gp.fit_shared")
    best, padded, data, jit_ = _fit_hyperparameters(
        x, y, key, restarts, max_points, max_fit_points, screen_points, mask, pad_to, jitter, rtol, atol, gtol, max_steps,
        "gp.fit_shared")
    xp, yp, mp = padded
    x_mean, x_scale = jnp.asarray(data.x_mean), jnp.asarray(data.x_scale)
    return tuple(
        _condition(Hyperparameters(best.log_lengthscale, best.log_signal_var[j], best.log_noise_var[j]), xp, yp[:, j],
                   mp, jnp.asarray(data.y_mean[j]), x_mean, x_scale, jit_)
        for j in range(y.shape[1]))


def _fit_hyperparameters(x, y, key, restarts, max_points, max_fit_points, screen_points, mask, pad_to, jitter, rtol,
                         atol, gtol, max_steps, where: str):
    """The host side of :func:`fit` and :func:`fit_shared` up to the conditioning: rows kept,
    standardised and padded, then the best hyperparameters over the starts. Returns them with the
    padded data, its statistics and the jitter."""
    rows = _valid_rows(x, y, mask, where)
    key_sub, key_init, key_screen = jax.random.split(key, 3)
    if rows.size > max_points:
        rows = rows[_subsample(key_sub, 0, rows.size, max_points)]
    x, y = x[rows], y[rows]
    n, d = x.shape
    size = n if pad_to is None else int(pad_to)
    if size < n:
        raise GPArgumentError(where, f"pad_to={pad_to} is smaller than the {n} rows kept")

    data = _standardised(x, y)
    padded = _padded(data.x, data.y, size)
    jit_ = jnp.asarray(jitter, jnp.float64)
    starts = _initial_params(key_init, restarts, d, data.y_var)
    if np.all(data.constant):
        return _row(starts, 0), padded, data, jit_
    xs, yc, fit_set = _fit_rows(data.x, data.y, padded, max_fit_points, key_sub)
    runs = _Starts(jit_, jnp.asarray(~data.constant, jnp.float64), rtol, atol, gtol, max_steps)
    if restarts > 1 and xs.shape[0] > screen_points:
        done = _screen_then_refine(runs, starts, xs, yc, fit_set, screen_points, key_screen)
    else:
        done = runs.run(range(restarts), starts, *fit_set, "full")
    if not done:
        raise GPFitError("all GP hyperparameter restarts failed: " + "; ".join(runs.failures))
    return done[0][2], padded, data, jit_
