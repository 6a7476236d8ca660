"""The exact GP regressor: conditioning on training data and prediction (paper section 3b, eqs 6-7).

Conventions:

- **Inputs are standardised** (per-feature mean and standard deviation over the valid training rows,
  computed in :func:`gtsjax.gp.fit`); every kernel works on standardised inputs, and
  :meth:`GP.predict` standardises test inputs with the stored statistics.
- **Targets are centred** (the paper's "subtract the mean of {y_i}, add it to any test output").
- **Cost**: O(N) per test point for the mean and O(N^2) for the variance; :func:`gtsjax.gp.fit` caps N
  (``max_points``), and :meth:`GP.sparse` gives the bounded-cost predictor (:mod:`gtsjax.gp.sparse`).
"""

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, ArrayLike, Bool, Float

from ..precision import exact_products
from .errors import GPArgumentError
from .kernel import _LOG_2PI, DEFAULT_JITTER, Hyperparameters, _cast, _factor, _standardise, gram
from .sparse import SparseGP, _build_sparse


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

    @exact_products
    def predict(
        self, xs: Float[Array, "tests features"], *, include_noise: bool = False
    ) -> tuple[Float[Array, " tests"], Float[Array, " tests"]]:
        """Predictive mean (eq 7, plus the subtracted target mean) and variance
        ``k(x*,x*) - v^T v`` with ``v = L^-1 K*`` (clipped at 0; plus sigma_n^2 if ``include_noise``)."""
        return _predict_exact(self, xs, include_noise)

    @exact_products
    def predict_mean(self, xs: Float[Array, "tests features"]) -> Float[Array, " tests"]:
        """The predictive mean alone (eq 7), for callers that do not need the variance (the
        classifier). Not jitted: it runs inside the step's jit."""
        xs = self.standardise(xs)
        ks = jnp.where(self.mask[None, :], gram(self.params, xs, self.x), jnp.zeros((), self.x.dtype))
        return ks @ self.alpha + self.y_mean

    @exact_products
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

    @exact_products
    def sparse(self, n_inducing: int, n_variance: int | None = None) -> SparseGP:
        """A DTC predictor on ``n_inducing`` inducing points picked from the training inputs by greedy
        pivoted Cholesky, its variance from the first ``n_variance`` of them (default: all); see
        :class:`~gtsjax.gp.SparseGP`. With ``n_inducing`` at least the training-set size the mean is
        exact. Deterministic; no key needed."""
        m = int(min(n_inducing, self.n_points))
        mv = m if n_variance is None else int(min(n_variance, m))
        if m < 1 or mv < 1:
            raise GPArgumentError(
                "GP.sparse", f"n_inducing and n_variance must be >= 1, got {n_inducing}, {n_variance}"
            )
        return _build_sparse(self, m, mv)


def predict_mean(gp: GP | SparseGP, xs: Float[Array, "tests features"]) -> Float[Array, " tests"]:
    """The predictive mean alone of either predictor (see their ``predict_mean``)."""
    return gp.predict_mean(xs)


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
    x, y, _, chol, alpha = _factor(params, x, y, mask, jitter)
    return GP(x, y, mask, params, alpha, chol, y_mean, x_mean, x_scale, jitter)


@exact_products
def condition(
    params: Hyperparameters,
    x: Float[ArrayLike, "points features"],
    y: Float[ArrayLike, " points"],
    mask: Bool[ArrayLike, " points"] | None = None,
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
