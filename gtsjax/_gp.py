"""Gaussian-process regression (paper section 3b, eqs 3-7): squared-exponential ARD kernel, type-II
maximum likelihood with optimistix, exact and bounded-cost (DTC) prediction.

Conventions, decided here and used throughout:

- **Inputs are standardised inside** :func:`fit` (per-feature mean and standard deviation over the
  valid training rows; a constant feature gets scale 1, so it becomes an all-zero column and never a
  NaN). Every kernel below works on standardised inputs; :meth:`GP.predict` standardises test inputs
  with the stored statistics.
- **Targets are centred** (the paper's "subtract the mean of {y_i}, add it to any test output").
- **Hyperparameters live in log space**: ``log_lengthscale`` (per feature, ``W_dd = exp(-2 log l_d)``),
  ``log_signal_var`` (log sigma_f^2) and ``log_noise_var`` (log sigma_n^2). The noise actually used is
  ``sigma_n^2 + jitter * sigma_f^2`` with ``jitter = 1e-8`` by default: the floor that keeps the
  Cholesky factor from failing on duplicate points or a vanishing noise estimate.
- **Padding**: every array-level function takes a ``mask`` over training rows. Padded rows have their
  inputs and targets replaced by zeros (double ``where``), their kernel rows/columns replaced by the
  identity, and they are left out of the point count, so the log marginal likelihood and its gradient
  equal those of the unpadded problem and stay finite for any padded values.
- **Cost**: past ``max_points`` valid rows (default 3000) :func:`fit` keeps a seeded random subsample,
  which caps the exact predictor at O(N) per test point for the mean and O(N^2) for the variance.
  :meth:`GP.sparse` gives a DTC (deterministic training conditional) predictor on M inducing points
  chosen from the training inputs by greedy pivoted Cholesky in the fitted kernel's own metric: O(M)
  per test point for the mean and O(M^2) for the variance. With M = N it reproduces the exact GP.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .errors import InputError

DEFAULT_JITTER = 1e-8
_LOG_2PI = math.log(2.0 * math.pi)


class GPFitError(RuntimeError):
    """Every restart of the hyperparameter optimisation failed (non-finite or not converged)."""


class Hyperparameters(eqx.Module):
    """Log-space hyperparameters ``h = (W, sigma_f^2, sigma_n^2)`` of eqs 3-5.

    ``W_dd = exp(-2 log_lengthscale_d)``: the ARD length scale ``l_d`` is ``W_dd^{-1/2}`` and maps one
    to one onto scikit-learn's ``RBF(length_scale=l)``.
    """

    log_lengthscale: Float[Array, " features"]
    log_signal_var: Float[Array, ""]
    log_noise_var: Float[Array, ""]

    @property
    def lengthscale(self) -> Float[Array, " features"]:
        return jnp.exp(self.log_lengthscale)

    @property
    def w(self) -> Float[Array, " features"]:
        """Diagonal of eq 3's W."""
        return jnp.exp(-2.0 * self.log_lengthscale)

    @property
    def signal_var(self) -> Float[Array, ""]:
        return jnp.exp(self.log_signal_var)

    @property
    def noise_var(self) -> Float[Array, ""]:
        return jnp.exp(self.log_noise_var)


def _cast(tree, dtype):
    return jtu.tree_map(
        lambda a: a.astype(dtype) if eqx.is_array(a) and jnp.issubdtype(a.dtype, jnp.floating) else a, tree
    )


def _effective_noise(params: Hyperparameters, jitter) -> Float[Array, ""]:
    """sigma_n^2 plus the relative jitter floor (``jitter`` * sigma_f^2)."""
    return params.noise_var + jitter * params.signal_var


# --------------------------------------------------------------------------------------------- kernel


def kernel(params: Hyperparameters, x1: Float[Array, " features"], x2: Float[Array, " features"]) -> Float[Array, ""]:
    """Eq 3 for one pair: ``sigma_f^2 exp(-1/2 sum_d W_dd (x1_d - x2_d)^2)``.

    No square root is taken, so the gradient is finite at ``x1 == x2``.
    """
    d = x1 - x2
    return jnp.exp(params.log_signal_var - 0.5 * jnp.sum(params.w * d * d))


def gram(
    params: Hyperparameters, x1: Float[Array, "n features"], x2: Float[Array, "m features"]
) -> Float[Array, "n m"]:
    """``K(X1, X2)`` (eq 6's component-wise definition): :func:`kernel` vmapped over both sets."""
    return jax.vmap(lambda a: jax.vmap(lambda b: kernel(params, a, b))(x2))(x1)


def _safe_rows(x, y, mask):
    """Double ``where``, first half: padded rows read as zeros before any arithmetic touches them."""
    x = jnp.where(mask[:, None], x, jnp.zeros((), x.dtype))
    y = jnp.where(mask, y, jnp.zeros((), y.dtype))
    return x, y


def _masked_gram(params, x, mask, noise):
    """``K_X + noise I`` on valid rows, the identity on padded ones (so they add nothing to eq 5)."""
    k = gram(params, x, x)
    both = mask[:, None] & mask[None, :]
    k = jnp.where(both, k, jnp.zeros((), k.dtype))
    diag = jnp.where(mask, noise, jnp.ones((), k.dtype))
    return k + jnp.diag(diag)


def _factor(params, x, y, mask, jitter):
    x, y = _safe_rows(x, y, mask)
    cov = _masked_gram(params, x, mask, _effective_noise(params, jitter))
    chol, _ = jsl.cho_factor(cov, lower=True)
    alpha = jsl.cho_solve((chol, True), y)
    return x, y, chol, alpha


def _lml_forward(params, x, y, mask, jitter):
    _, _, chol, alpha = _factor(params, x, y, mask, jitter)
    n_valid = jnp.sum(mask).astype(y.dtype)
    logdet = jnp.sum(jnp.log(jnp.diagonal(chol)))  # padded diagonal entries are exactly 1
    lml = -0.5 * jnp.dot(y, alpha) - logdet - 0.5 * n_valid * jnp.asarray(_LOG_2PI, y.dtype)
    return lml, (chol, alpha)


@jax.custom_vjp
def _lml(params, x, y, mask, jitter):
    return _lml_forward(params, x, y, mask, jitter)[0]


def _lml_fwd(params, x, y, mask, jitter):
    lml, (chol, alpha) = _lml_forward(params, x, y, mask, jitter)
    return lml, (params, x, mask, jitter, chol, alpha)


def _lml_bwd(res, g):
    """Closed-form gradient of eq 5 (Rasmussen & Williams eq 5.9): d LML = 1/2 tr(Q dK) with
    ``Q = alpha alpha^T - (K+sI)^-1``. ``(K+sI)^-1`` comes from the Cholesky factor (two triangular
    solves); it is needed only here, for the trace, never for the solve of eq 5 itself. This costs
    one O(N^3) solve and O(N^2 d) contractions, several times cheaper than differentiating through
    the factorisation, and never forms the [N, N, d] kernel-derivative tensor."""
    params, x, mask, jitter, chol, alpha = res
    dt = x.dtype
    n = x.shape[0]
    both = mask[:, None] & mask[None, :]
    kf = jnp.where(both, gram(params, x, x), jnp.zeros((), dt))
    kinv = jsl.cho_solve((chol, True), jnp.eye(n, dtype=dt))
    q = alpha[:, None] * alpha[None, :] - kinv
    tr_q = jnp.sum(jnp.where(mask, jnp.diagonal(q), jnp.zeros((), dt)))
    m = q * kf
    r = jnp.sum(m, axis=1)
    w = params.w
    sf2 = params.signal_var
    g_ls = w * (r @ (x * x) - jnp.sum(x * (m @ x), axis=0))
    g_sf = 0.5 * jnp.sum(m) + 0.5 * jitter * sf2 * tr_q
    g_sn = 0.5 * params.noise_var * tr_q
    g_x = -w[None, :] * (x * r[:, None] - m @ x)
    g_y = -alpha
    g_jitter = 0.5 * sf2 * tr_q
    g_params = Hyperparameters(g * g_ls, g * g_sf, g * g_sn)
    return g_params, g * g_x, g * g_y, None, jnp.asarray(g * g_jitter, dtype=jnp.result_type(jitter))


_lml.defvjp(_lml_fwd, _lml_bwd)


def log_marginal_likelihood(
    params: Hyperparameters,
    x: Float[Array, "points features"],
    y: Float[Array, " points"],
    mask: Bool[Array, " points"] | None = None,
    *,
    jitter: float | Float[Array, ""] = DEFAULT_JITTER,
) -> Float[Array, ""]:
    """Eq 5, ``log p(y|X) = -1/2 y^T (K+s I)^-1 y - 1/2 log|K+s I| - (N_t/2) log 2 pi``, through a
    Cholesky factor (never an explicit inverse). ``s = sigma_n^2 + jitter sigma_f^2``.

    Low level: ``x`` and ``y`` are used as given (no standardisation, no centring), so this is the
    function to compare against another implementation with the same raw hyperparameters. Padded
    rows (``mask`` False) are ignored and keep the value and its gradient finite. Differentiable in
    ``params``, ``x`` and ``y`` through a closed-form VJP (see ``_lml_bwd``).
    """
    if mask is None:
        mask = jnp.ones(y.shape, dtype=bool)
    x, y = _safe_rows(x, y, mask)
    return _lml(params, x, y, mask, jnp.asarray(jitter, x.dtype))


def _lml_autodiff(params, x, y, mask, jitter):
    """Eq 5 differentiated by JAX through the Cholesky factor: the reference for the closed-form VJP."""
    x, y = _safe_rows(x, y, mask)
    return _lml_forward(params, x, y, mask, jnp.asarray(jitter, x.dtype))[0]


# ------------------------------------------------------------------------------------------ exact GP


def _standardise(x, mean, scale):
    return (x - mean[None, :]) / scale[None, :]


class GP(eqx.Module):
    """A fitted GP regressor (eqs 3-7). Every field is an array; stack GPs of equal padded size with
    ``jax.tree.map(jnp.stack, ...)`` and ``vmap`` their methods.

    ``x`` are the standardised (and possibly padded) training inputs, ``y`` the centred targets,
    ``chol`` the lower Cholesky factor ``L`` of ``K_X + s I`` and ``alpha = (K_X + s I)^-1 y``.
    """

    x: Float[Array, "points features"]
    y: Float[Array, " points"]
    mask: Bool[Array, " points"]
    params: Hyperparameters
    alpha: Float[Array, " points"]
    chol: Float[Array, "points points"]
    y_mean: Float[Array, ""]
    x_mean: Float[Array, " features"]
    x_scale: Float[Array, " features"]
    jitter: Float[Array, ""]

    @property
    def n_points(self) -> int:
        """Padded training-set size (static)."""
        return self.x.shape[0]

    def standardise(self, xs: Float[Array, "tests features"]) -> Float[Array, "tests features"]:
        """Map raw inputs into the standardised space the kernel sees."""
        return _standardise(xs.astype(self.x.dtype), self.x_mean, self.x_scale)

    def predict(
        self, xs: Float[Array, "tests features"], *, include_noise: bool = False
    ) -> tuple[Float[Array, " tests"], Float[Array, " tests"]]:
        """Predictive mean (eq 7, plus the subtracted target mean) and variance
        ``k(x*,x*) - v^T v`` with ``v = L^-1 K*`` (clipped at 0; plus sigma_n^2 if ``include_noise``)."""
        return _predict_exact(self, xs, include_noise)

    def log_marginal_likelihood(self) -> Float[Array, ""]:
        """Eq 5 at the fitted hyperparameters, on the standardised inputs and centred targets."""
        logdet = jnp.sum(jnp.log(jnp.diagonal(self.chol)))
        n_valid = jnp.sum(self.mask).astype(self.y.dtype)
        return -0.5 * jnp.dot(self.y, self.alpha) - logdet - 0.5 * n_valid * jnp.asarray(_LOG_2PI, self.y.dtype)

    def astype(self, dtype) -> "GP":
        """A copy with every floating array cast to ``dtype`` (e.g. float32 for the real-time step).

        The factor is cast, not recomputed, so the float32 mean is as accurate as ``alpha`` allows;
        the float32 variance goes through a float32 triangular solve and is only indicative.
        """
        return _cast(self, dtype)

    def sparse(self, n_inducing: int, n_variance: int | None = None) -> "SparseGP":
        """A DTC predictor on ``n_inducing`` inducing points picked from the training inputs by greedy
        pivoted Cholesky, its variance from the first ``n_variance`` of them (default: all); see
        :class:`SparseGP`. With ``n_inducing`` at least the training-set size the mean is exact.
        Deterministic; no key needed."""
        m = int(min(n_inducing, self.n_points))
        mv = m if n_variance is None else int(min(n_variance, m))
        if m < 1 or mv < 1:
            raise InputError("GP.sparse", f"n_inducing and n_variance must be >= 1, got {n_inducing}, {n_variance}")
        return _build_sparse(self, m, mv)


@eqx.filter_jit
def _predict_exact(gp: GP, xs, include_noise: bool):
    xs = gp.standardise(xs)
    ks = jnp.where(gp.mask[None, :], gram(gp.params, xs, gp.x), jnp.zeros((), gp.x.dtype))  # tests x points
    mean = ks @ gp.alpha + gp.y_mean
    v = jsl.solve_triangular(gp.chol, ks.T, lower=True)
    var = jnp.maximum(gp.params.signal_var - jnp.sum(v * v, axis=0), jnp.zeros((), v.dtype))
    if include_noise:
        var = var + gp.params.noise_var
    return mean, var


@eqx.filter_jit
def _condition(params, x, y, mask, y_mean, x_mean, x_scale, jitter) -> GP:
    x, y, chol, alpha = _factor(params, x, y, mask, jitter)
    return GP(x, y, mask, params, alpha, chol, y_mean, x_mean, x_scale, jitter)


def condition(
    params: Hyperparameters,
    x: Float[Array, "points features"],
    y: Float[Array, " points"],
    mask: Bool[Array, " points"] | None = None,
    *,
    jitter: float = DEFAULT_JITTER,
) -> GP:
    """Build a :class:`GP` from given hyperparameters on already-standardised inputs and centred
    targets (identity standardisation, zero target mean). Low level: for tests and for reuse of
    hyperparameters on new data."""
    x = jnp.asarray(x)
    y = jnp.asarray(y, dtype=x.dtype)
    if mask is None:
        mask = jnp.ones(y.shape, dtype=bool)
    d = x.shape[1]
    dt = x.dtype
    return _condition(
        params, x, y, mask, jnp.zeros((), dt), jnp.zeros((d,), dt), jnp.ones((d,), dt), jnp.asarray(jitter, dt)
    )


# ------------------------------------------------------------------------------------------- fitting


def _neg_lml_per_point(params, args):
    x, y, mask, jitter = args
    n_valid = jnp.maximum(jnp.sum(mask), 1).astype(y.dtype)
    return -log_marginal_likelihood(params, x, y, mask, jitter=jitter) / n_valid


# Upper end of the log length scale (standardised units) that each start is clamped to; scikit-learn's
# default bound (1e5).
LOG_LENGTHSCALE_CLAMP = math.log(1e5)


def _clamp(params: Hyperparameters) -> Hyperparameters:
    ls = jnp.minimum(params.log_lengthscale, jnp.asarray(LOG_LENGTHSCALE_CLAMP, params.log_lengthscale.dtype))
    return Hyperparameters(ls, params.log_signal_var, params.log_noise_var)


# How much looser the convergence test on the hyperparameters is than on the objective. optimistix's
# Cauchy test needs both the objective and every parameter to stop moving; an irrelevant feature's log
# length scale keeps drifting along a flat direction long after the likelihood has converged (at
# N = 2000 this more than doubled the number of BFGS steps). With rtol = 1e-6, a log length scale
# moving by less than about 1e-3 (0.1 % of the length scale) no longer holds the fit open.
_PARAM_TOL_FACTOR = 1e3


def _convergence_norm(tree) -> Float[Array, ""]:
    scale = 1.0 / _PARAM_TOL_FACTOR if isinstance(tree, Hyperparameters) else 1.0
    return optx.max_norm(tree) * scale


@eqx.filter_jit
def _optimise(params0, x, y, mask, jitter, rtol, atol, max_steps: int):
    """Maximise eq 5 (eq 4) from one start: BFGS, then, if a log length scale ended past
    ``LOG_LENGTHSCALE_CLAMP``, BFGS again from the optimum with the log length scales clamped there;
    the better successful stage is kept.

    Why two stages: the LML is flat in an irrelevant feature's length scale, BFGS's steps grow along
    flat directions, and a feature that wants a long but finite scale (a near-linear trend, ``log l ~
    8``) is thrown to ``log l ~ 300``, where its gradient underflows and it cannot come back. The
    clamped second start gives it a gradient again (on 20-D data this recovered the 0.1-1 nats by
    which bounded L-BFGS-B, i.e. scikit-learn, was ahead). The objective is -LML/N so that BFGS's unit
    first step and the tolerances do not depend on the training-set size."""
    solver = optx.BFGS(rtol=rtol, atol=atol, norm=_convergence_norm)
    args = (x, y, mask, jitter)
    inf = jnp.asarray(jnp.inf, y.dtype)

    def stage(p):
        sol = optx.minimise(_neg_lml_per_point, solver, _clamp(p), args, max_steps=max_steps, throw=False)
        ok = sol.result == optx.RESULTS.successful
        nll = _neg_lml_per_point(sol.value, args)
        nll = jnp.where(ok & jnp.isfinite(nll), nll, inf)
        return sol.value, nll, sol.stats["num_steps"]

    p1, f1, n1 = stage(params0)
    # The second stage only matters when a length scale ran past the clamp (it is a no-op otherwise,
    # at the cost of a second convergence test's worth of evaluations).
    past = jnp.any(p1.log_lengthscale > jnp.asarray(LOG_LENGTHSCALE_CLAMP, p1.log_lengthscale.dtype))
    p2, f2, n2 = jax.lax.cond(past, stage, lambda p: (p, inf, jnp.zeros_like(n1)), p1)
    second = f2 <= f1
    value = jtu.tree_map(lambda a, b: jnp.where(second, b, a), p1, p2)
    nll = jnp.minimum(f1, f2)
    return value, jnp.isfinite(nll), nll, n1 + n2


def _initial_params(key, restart: int, d: int, y_var, dtype) -> Hyperparameters:
    """Restart 0: length scales sqrt(d) in standardised units (so the summed squared distance is O(1)),
    sigma_f^2 = var(y), sigma_n^2 = var(y)/10. Later restarts: log-uniform jitter around that."""
    base_ls = jnp.full((d,), 0.5 * math.log(max(d, 1)), dtype)
    base_sf = jnp.log(y_var)
    base_sn = jnp.log(y_var) - jnp.asarray(math.log(10.0), dtype)
    if restart == 0:
        return Hyperparameters(base_ls, base_sf, base_sn)
    k1, k2, k3 = jax.random.split(jax.random.fold_in(key, restart), 3)
    ls = base_ls + jax.random.uniform(k1, (d,), dtype, -1.5, 1.5)
    sf = base_sf + jax.random.uniform(k2, (), dtype, -1.0, 1.0)
    sn = base_sn + jax.random.uniform(k3, (), dtype, -4.0, 1.5)
    return Hyperparameters(ls, sf, sn)


def _run_starts(starts, x, y, mask, jitter, rtol, atol, max_steps, failures, label):
    """Run :func:`_optimise` from each start; return ``(objective, restart, params)`` of the successful
    ones, best first; failures are described in ``failures``."""
    done = []
    for r, p0 in starts:
        p, ok, nll, steps = _optimise(p0, x, y, mask, jitter, rtol, atol, max_steps)
        nll = float(nll)
        if bool(ok) and np.isfinite(nll):
            done.append((nll, r, p))
        else:
            failures.append(f"{label} restart {r}: converged={bool(ok)} -LML/N={nll:.6g} after {int(steps)} steps")
    done.sort(key=lambda t: (t[0], t[1]))
    return done


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
    max_steps: int = 1000,
) -> GP:
    """Fit a GP regressor by maximising eq 5 (eq 4) over log-space hyperparameters; float64.

    - ``x`` [N, d], ``y`` [N]; ``mask`` [N] (optional) marks valid rows; rows with a non-finite value
      are dropped too.
    - ``key``: jax PRNG key for the subsamples and the random restarts. Same key, same GP.
    - ``restarts``: number of starts (the first a fixed default, the rest random around it, drawn
      from ``key``). Each start runs :class:`optimistix.BFGS` (``throw=False``) and then again from
      its optimum with the log length scales clamped at log 1e5 (see ``_optimise``). A start whose
      ``sol.result`` is not successful or whose objective is not finite is skipped; the best
      remaining one is kept. If all fail, :class:`GPFitError` is raised, naming each failure.
    - ``max_points``: above this many valid rows, a seeded random subsample of ``max_points`` rows is
      used (cost cap: fit O(max_points^3); exact prediction O(max_points) per test point for the mean,
      O(max_points^2) for the variance; :meth:`GP.sparse` for a smaller cap).
    - ``max_fit_points``: with more rows kept than this, the hyperparameters are fitted on a seeded
      random subsample of this many, and the GP is then conditioned on all the rows kept: the exact
      posterior under those hyperparameters. Each likelihood evaluation then costs
      O(max_fit_points^3) and the conditioning one O(N^3) factorisation, so a GP can predict from
      several times the examples its fit could afford (the hyperparameters, a few dozen numbers, are
      well determined by a few thousand examples; the posterior mean gains from every one).
    - ``screen_points``: with more valid rows than this and ``restarts > 1``, the restarts run on a
      seeded subsample of ``screen_points`` rows; on all rows, the default start is then refined from
      scratch, and the best random start (warm, from its subset optimum) only if it beat the default
      on the subset. More restarts therefore never end below one.
    - ``pad_to``: pad the training set to this fixed size (masked) so that GPs fitted on different
      data share shapes (one compilation; stackable). Must be >= the number of rows kept.
    - ``rtol``/``atol``/``max_steps``: :class:`optimistix.BFGS` tolerances on -LML/N and step cap.

    Constant targets (including N = 1) carry no information on the hyperparameters and make eq 5
    unbounded; the default start is then kept without optimisation (the GP predicts the constant).

    Requires ``jax_enable_x64``. Host-side entry point (not jittable: it picks rows by value); the
    optimisation and the factorisation inside are jitted.
    """
    if not jax.config.read("jax_enable_x64"):
        raise InputError("gp.fit", "GP fitting runs in float64: enable jax_enable_x64")
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or y.ndim != 1 or x.shape[0] != y.shape[0]:
        raise InputError("gp.fit", f"need x [N, d] and y [N], got {x.shape} and {y.shape}")
    if restarts < 1:
        raise InputError("gp.fit", f"restarts must be >= 1, got {restarts}")
    if max_fit_points is not None and max_fit_points < 1:
        raise InputError("gp.fit", f"max_fit_points must be >= 1, got {max_fit_points}")
    valid = np.ones(y.shape, bool) if mask is None else np.asarray(mask, bool).copy()
    valid &= np.isfinite(y) & np.all(np.isfinite(x), axis=1)
    rows = np.flatnonzero(valid)
    if rows.size == 0:
        raise InputError("gp.fit", "no valid (finite, unmasked) training rows")
    key_sub, key_init, key_screen = jax.random.split(key, 3)
    if rows.size > max_points:
        pick = np.asarray(jax.random.choice(key_sub, rows.size, (max_points,), replace=False))
        rows = np.sort(rows[pick])
    x, y = x[rows], y[rows]
    n, d = x.shape
    size = n if pad_to is None else int(pad_to)
    if size < n:
        raise InputError("gp.fit", f"pad_to={pad_to} is smaller than the {n} rows kept")

    x_mean = x.mean(axis=0)
    x_std = x.std(axis=0)
    x_scale = np.where(x_std > 1e-12 * np.maximum(np.abs(x_mean), 1.0), x_std, 1.0)
    y_mean = y.mean()
    xs = (x - x_mean) / x_scale
    yc = y - y_mean
    y_var = float(yc.var())
    constant = not y_var > (1e-12 * max(1.0, abs(y_mean))) ** 2
    y_var = 1.0 if constant else y_var

    xp = np.zeros((size, d))
    yp = np.zeros((size,))
    mp = np.zeros((size,), bool)
    xp[:n], yp[:n], mp[:n] = xs, yc, True
    xj, yj, mj = jnp.asarray(xp), jnp.asarray(yp), jnp.asarray(mp)
    jit_ = jnp.asarray(jitter, jnp.float64)
    y_var_j = jnp.asarray(y_var, jnp.float64)
    starts = [(r, _initial_params(key_init, r, d, y_var_j, jnp.float64)) for r in range(restarts)]
    # The rows the hyperparameters are fitted on (all, unless max_fit_points is smaller).
    xf, yf, mf, nf = xj, yj, mj, n
    if max_fit_points is not None and n > max_fit_points:
        sub = np.sort(np.asarray(jax.random.choice(jax.random.fold_in(key_sub, 1), n, (max_fit_points,),
                                                   replace=False)))
        xs, yc = xs[sub], yc[sub] - yc[sub].mean()  # screening below subsamples from these too
        nf = int(max_fit_points)
        xf, yf, mf = jnp.asarray(xs), jnp.asarray(yc), jnp.ones((nf,), bool)

    failures: list[str] = []
    if constant:
        best = starts[0][1]
    else:
        if restarts > 1 and nf > screen_points:
            pick = np.sort(np.asarray(jax.random.choice(key_screen, nf, (screen_points,), replace=False)))
            ys = yc[pick] - yc[pick].mean()
            screened = _run_starts(
                starts,
                jnp.asarray(xs[pick]),
                jnp.asarray(ys),
                jnp.ones((screen_points,), bool),
                jit_,
                rtol,
                atol,
                max_steps,
                failures,
                "screening",
            )
            # The default start is refined from scratch on all rows (a warm start from a subset's
            # optimum can settle in a basin that is worse on all the data); a random start only if
            # screening found it better than the default on the subset.
            sub_default = next((f for f, r, _ in screened if r == 0), np.inf)
            better = [(r, p) for f, r, p in screened if r != 0 and f < sub_default]
            done = _run_starts(starts[:1] + better[:1], xf, yf, mf, jit_, rtol, atol, max_steps, failures,
                               "refining")
            for r, p in better[1:] if not done else []:
                done = _run_starts([(r, p)], xf, yf, mf, jit_, rtol, atol, max_steps, failures, "refining")
                if done:
                    break
        else:
            done = _run_starts(starts, xf, yf, mf, jit_, rtol, atol, max_steps, failures, "full")
        if not done:
            raise GPFitError("all GP hyperparameter restarts failed: " + "; ".join(failures))
        best = done[0][2]
    return _condition(best, xj, yj, mj, jnp.asarray(y_mean), jnp.asarray(x_mean), jnp.asarray(x_scale), jit_)


# ----------------------------------------------------------------------------------------- sparse GP


class SparseGP(eqx.Module):
    """DTC (deterministic training conditional; Quinonero-Candela & Rasmussen 2005) predictor on M
    inducing inputs ``z``, a subset of the training inputs, with the variance from the first ``Mv``
    of them.

    With ``Q = K_xz K_zz^-1 K_zx`` replacing ``K_X``, the predictive mean is ``k_z(x*)^T w`` with
    ``w = (s K_zz + K_zx K_xz)^-1 K_zx y`` and the variance
    ``k(x*,x*) - k_z^T K_zz^-1 k_z + s k_z^T (s K_zz + K_zx K_xz)^-1 k_z``: O(M) and O(M^2) per test
    point whatever N. Computed as in SGPR: ``K_zz = L_m L_m^T``, ``A = L_m^-1 K_zx / sqrt(s)``,
    ``I + A A^T = L_b L_b^T``. Why DTC and not SoR: same mean, but DTC keeps the exact prior variance
    ``k(x*,x*)`` far from the data, and with Z = X it equals the exact GP.

    Inducing points are chosen by greedy pivoted Cholesky of ``K_X`` under the fitted kernel (each
    step takes the training point worst explained by those already chosen), i.e. in the ARD metric
    the GP itself uses; selection stops early (masked slots) when the residual falls below the jitter.
    When M covers the whole training set, ``z`` is the training set (pivots first) and ``w`` is the
    exact GP's ``alpha``: the mean is exact.

    Mean and variance are priced differently, O(M) against O(Mv^2) per test point, and the step
    needs the mean to be good (it is the pose) and the variance only to weigh measurements in the
    tracker. So the variance is the DTC variance of the first ``Mv <= M`` inducing points (the
    pivoted-Cholesky order is nested: they are the ``Mv`` points that pivoting alone would pick),
    a coarser approximation that errs on the large side, while the mean uses all ``M``.
    """

    z: Float[Array, "inducing features"]
    z_mask: Bool[Array, " inducing"]
    params: Hyperparameters
    weights: Float[Array, " inducing"]
    proj_m: Float[Array, "var_inducing var_inducing"]  # L_m^-1 of the first Mv points: t1 = L_m^-1 k_z
    proj_b: Float[Array, "var_inducing var_inducing"]  # L_b^-1 L_m^-1, so that t2 = L_b^-1 t1 is a matmul
    y_mean: Float[Array, ""]
    x_mean: Float[Array, " features"]
    x_scale: Float[Array, " features"]
    noise: Float[Array, ""]

    @property
    def n_variance(self) -> int:
        """``Mv``: how many of the inducing points (the first) the variance uses."""
        return self.proj_m.shape[0]

    def predict(
        self, xs: Float[Array, "tests features"], *, include_noise: bool = False
    ) -> tuple[Float[Array, " tests"], Float[Array, " tests"]]:
        """DTC predictive mean (plus target mean) and variance (clipped at 0)."""
        return _predict_sparse(self, xs, include_noise)

    def astype(self, dtype) -> "SparseGP":
        return _cast(self, dtype)


def _pivoted_cholesky(params, x, mask, m: int, tol):
    """Greedy pivoted Cholesky: indices of ``m`` training rows and whether each slot is used."""
    n = x.shape[0]
    neg_inf = jnp.asarray(-jnp.inf, x.dtype)
    resid0 = jnp.where(mask, jnp.broadcast_to(params.signal_var, (n,)), neg_inf)

    def body(j, carry):
        resid, rows, idx, used = carry
        p = jnp.argmax(resid)
        r = resid[p]
        ok = r > tol
        kp = jnp.where(mask, jax.vmap(lambda b: kernel(params, x[p], b))(x), jnp.zeros((), x.dtype))
        safe_r = jnp.where(ok, r, jnp.ones((), x.dtype))
        row = (kp - rows.T @ rows[:, p]) / jnp.sqrt(safe_r)
        row = jnp.where(ok, row, jnp.zeros((), x.dtype))
        rows = rows.at[j].set(row)
        resid = (resid - row * row).at[p].set(neg_inf)
        return resid, rows, idx.at[j].set(p.astype(jnp.int32)), used.at[j].set(ok)

    init = (resid0, jnp.zeros((m, n), x.dtype), jnp.zeros((m,), jnp.int32), jnp.zeros((m,), bool))
    _, _, idx, used = jax.lax.fori_loop(0, m, body, init)
    return idx, used


@eqx.filter_jit
def _build_sparse(gp: GP, m: int, mv: int) -> SparseGP:
    params = gp.params
    dt = gp.x.dtype
    n = gp.n_points
    tol = gp.jitter * params.signal_var
    if m >= n:
        # Every training point: the variance's pivots first, then the rest in order; the exact mean.
        idx_v, used_v = _pivoted_cholesky(params, gp.x, gp.mask, mv, tol)
        first = jnp.zeros((n,), bool).at[idx_v].set(used_v)
        pos = jnp.zeros((n,), jnp.int32).at[idx_v].set(jnp.arange(mv, dtype=jnp.int32))
        rest = mv + jnp.cumsum(~first, dtype=jnp.int32) - 1
        perm = jnp.argsort(jnp.where(first, pos, rest))
        z_mask = gp.mask[perm]
        z = jnp.where(z_mask[:, None], gp.x[perm], jnp.zeros((), dt))
        weights = jnp.where(z_mask, gp.alpha[perm], jnp.zeros((), dt))
    else:
        idx, z_mask = _pivoted_cholesky(params, gp.x, gp.mask, m, tol)
        z = jnp.where(z_mask[:, None], gp.x[idx], jnp.zeros((), dt))
        weights = _dtc(params, z, z_mask, gp, tol)[0]
    noise = _effective_noise(params, gp.jitter)
    # The variance needs L_m^-1 k_z and L_b^-1 L_m^-1 k_z for every test point. Two triangular solves
    # per call are slow on small matrices (the step's budget is a fraction of a millisecond), so the
    # two triangular inverses are formed once here, in the fit's float64, and prediction is matmuls.
    _, proj_m, proj_b = _dtc(params, z[:mv], z_mask[:mv], gp, tol)
    return SparseGP(z, z_mask, params, weights, proj_m, proj_b, gp.y_mean, gp.x_mean, gp.x_scale, noise)


def _dtc(params, z, z_mask, gp: GP, tol):
    """DTC on inducing points ``z`` for the training set of ``gp``: the weights of the mean and the
    two triangular inverses of the variance (see :class:`SparseGP`)."""
    dt = z.dtype
    m = z.shape[0]
    noise = _effective_noise(params, gp.jitter)
    kmm = _masked_gram(params, z, z_mask, tol)
    kmx = jnp.where(z_mask[:, None] & gp.mask[None, :], gram(params, z, gp.x), jnp.zeros((), dt))
    chol_m = jnp.linalg.cholesky(kmm)
    sn = jnp.sqrt(noise)
    a = jsl.solve_triangular(chol_m, kmx, lower=True) / sn
    chol_b = jnp.linalg.cholesky(jnp.eye(m, dtype=dt) + a @ a.T)
    c = jsl.solve_triangular(chol_b, a @ gp.y, lower=True) / sn
    weights = jsl.solve_triangular(chol_m.T, jsl.solve_triangular(chol_b.T, c, lower=False), lower=False)
    eye = jnp.eye(m, dtype=dt)
    proj_m = jsl.solve_triangular(chol_m, eye, lower=True)
    proj_b = jsl.solve_triangular(chol_b, proj_m, lower=True)
    return weights, proj_m, proj_b


def gram_matmul(params: Hyperparameters, x1, x2):
    """``K(X1, X2)`` through one matrix product, ``|a|² + |b|² − 2 a·b`` in the ARD metric: the form for
    prediction in the real-time step, where the pairwise-difference form of :func:`gram` costs several
    times more. It rounds differently (cancellation for nearby points, clipped at 0), so fitting and
    the reference tests use :func:`gram`."""
    sw = jnp.sqrt(params.w).astype(x1.dtype)
    a, b = x1 * sw[None, :], x2 * sw[None, :]
    d2 = jnp.sum(a * a, axis=1)[:, None] + jnp.sum(b * b, axis=1)[None, :] - 2.0 * (a @ b.T)
    return params.signal_var.astype(x1.dtype) * jnp.exp(-0.5 * jnp.maximum(d2, jnp.zeros((), x1.dtype)))


def predict_mean(gp: "GP | SparseGP", xs: Float[Array, "tests features"]) -> Float[Array, " tests"]:
    """The predictive mean alone (eq. 7), for callers that do not need the variance (the classifier)."""
    if isinstance(gp, SparseGP):
        dt = gp.z.dtype
        xs = _standardise(xs.astype(dt), gp.x_mean, gp.x_scale)
        ks = jnp.where(gp.z_mask[None, :], gram_matmul(gp.params, xs, gp.z), jnp.zeros((), dt))
        return ks @ gp.weights + gp.y_mean
    xs = gp.standardise(xs)
    ks = jnp.where(gp.mask[None, :], gram(gp.params, xs, gp.x), jnp.zeros((), gp.x.dtype))
    return ks @ gp.alpha + gp.y_mean


@eqx.filter_jit
def _predict_sparse(sp: SparseGP, xs, include_noise: bool):
    dt = sp.z.dtype
    xs = _standardise(xs.astype(dt), sp.x_mean, sp.x_scale)
    ks = jnp.where(sp.z_mask[:, None], gram_matmul(sp.params, sp.z, xs), jnp.zeros((), dt))  # inducing x tests
    mean = ks.T @ sp.weights + sp.y_mean
    kv = ks[: sp.n_variance]
    t1 = sp.proj_m @ kv
    t2 = sp.proj_b @ kv
    var = sp.params.signal_var - jnp.sum(t1 * t1, axis=0) + jnp.sum(t2 * t2, axis=0)
    var = jnp.maximum(var, jnp.zeros((), dt))
    if include_noise:
        var = var + sp.params.noise_var
    return mean, var
