"""The GP's kernel and log marginal likelihood (paper section 3b, eqs 3 and 5), with a closed-form VJP.

Conventions, decided here and used throughout the package:

- **Hyperparameters live in log space**: ``log_lengthscale`` (per feature, ``W_dd = exp(-2 log l_d)``),
  ``log_signal_var`` (log sigma_f^2) and ``log_noise_var`` (log sigma_n^2). The noise actually used is
  ``sigma_n^2 + jitter * sigma_f^2`` with ``jitter = 1e-8`` by default: the floor that keeps the
  Cholesky factor from failing on duplicate points or a vanishing noise estimate.
- **Padding**: every array-level function takes a ``mask`` over training rows. Padded rows have their
  inputs and targets replaced by zeros (double ``where``), their kernel rows/columns replaced by the
  identity, and they are left out of the point count, so the log marginal likelihood and its gradient
  equal those of the unpadded problem and stay finite for any padded values.
- Every kernel here works on **standardised inputs** (see :func:`gtsjax.gp.fit`).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import jax.tree_util as jtu
from jaxtyping import Array, Bool, Float

from ..precision import exact_products

DEFAULT_JITTER = 1e-8
_LOG_2PI = math.log(2.0 * math.pi)


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
    """``tree`` with every floating array cast to ``dtype`` (the GPs' ``astype``)."""
    return jtu.tree_map(
        lambda a: a.astype(dtype) if eqx.is_array(a) and jnp.issubdtype(a.dtype, jnp.floating) else a, tree
    )


def _standardise(x, mean, scale):
    return (x - mean[None, :]) / scale[None, :]


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


def gram_matmul(params: Hyperparameters, x1, x2):
    """``K(X1, X2)`` through one matrix product, ``|a|² + |b|² − 2 a·b`` in the ARD metric: the form for
    prediction in the real-time step, where the pairwise-difference form of :func:`gram` costs several
    times more. It rounds differently (cancellation for nearby points, clipped at 0), so fitting and
    the reference tests use :func:`gram`."""
    sw = jnp.sqrt(params.w).astype(x1.dtype)
    a, b = x1 * sw[None, :], x2 * sw[None, :]
    d2 = jnp.sum(a * a, axis=1)[:, None] + jnp.sum(b * b, axis=1)[None, :] - 2.0 * (a @ b.T)
    return params.signal_var.astype(x1.dtype) * jnp.exp(-0.5 * jnp.maximum(d2, jnp.zeros((), x1.dtype)))


def _safe_rows(x, y, mask):
    """Double ``where``, first half: padded rows read as zeros before any arithmetic touches them."""
    x = jnp.where(mask[:, None], x, jnp.zeros((), x.dtype))
    y = jnp.where(mask, y, jnp.zeros((), y.dtype))
    return x, y


def _masked_gram(params, x, mask, noise, form=gram):
    """``K_X + noise I`` on valid rows, the identity on padded ones (so they add nothing to eq 5)."""
    return _with_noise(_masked_kernel(params, x, mask, form), mask, noise)


def _masked_kernel(params, x, mask, form=gram):
    """``K_X`` on valid rows, zero on padded ones, computed by ``form`` (:func:`gram` or
    :func:`gram_matmul`)."""
    both = mask[:, None] & mask[None, :]
    return jnp.where(both, form(params, x, x), jnp.zeros((), x.dtype))


def _with_noise(k, mask, noise):
    diag = jnp.where(mask, noise, jnp.ones((), k.dtype))
    return k + jnp.diag(diag)


def _factor(params, x, y, mask, jitter):
    """The Cholesky factor ``L`` of ``K_X + s I`` and ``alpha = (K_X + s I)^-1 y``, padding made safe;
    also ``K_X`` itself (masked), which the LML's gradient reuses.

    The training Gram matrix is formed as one matrix product (:func:`gram_matmul`): fitting runs in
    float64, where the product form's cancellation (about 1e-16 of ``|a|^2``, standardised inputs)
    is far below the jitter, and the pairwise-difference form materialised an [N, N, d] tensor in
    the fit's compiled gradient (at N = 500, d = 21 the LML and its gradient took 46 ms instead of
    12)."""
    x, y = _safe_rows(x, y, mask)
    k = _masked_kernel(params, x, mask, gram_matmul)
    chol, _ = jsl.cho_factor(_with_noise(k, mask, _effective_noise(params, jitter)), lower=True)
    alpha = jsl.cho_solve((chol, True), y)
    return x, y, k, chol, alpha


# ------------------------------------------------------------------------------ log marginal likelihood


def _lml_forward(params, x, y, mask, jitter):
    _, _, k, chol, alpha = _factor(params, x, y, mask, jitter)
    n_valid = jnp.sum(mask).astype(y.dtype)
    logdet = jnp.sum(jnp.log(jnp.diagonal(chol)))  # padded diagonal entries are exactly 1
    lml = -0.5 * jnp.dot(y, alpha) - logdet - 0.5 * n_valid * jnp.asarray(_LOG_2PI, y.dtype)
    return lml, (k, chol, alpha)


@jax.custom_vjp
def _lml(params, x, y, mask, jitter):
    return _lml_forward(params, x, y, mask, jitter)[0]


def _lml_fwd(params, x, y, mask, jitter):
    lml, (k, chol, alpha) = _lml_forward(params, x, y, mask, jitter)
    return lml, (params, x, mask, jitter, k, chol, alpha)


def _lml_bwd(res, g):
    """Closed-form gradient of eq 5 (Rasmussen & Williams eq 5.9): d LML = 1/2 tr(Q dK) with
    ``Q = alpha alpha^T - (K+sI)^-1``. ``(K+sI)^-1`` comes from the Cholesky factor (two triangular
    solves); it is needed only here, for the trace, never for the solve of eq 5 itself. This costs
    one O(N^3) solve and O(N^2 d) contractions, several times cheaper than differentiating through
    the factorisation, and never forms the [N, N, d] kernel-derivative tensor."""
    params, x, mask, jitter, kf, chol, alpha = res
    dt = x.dtype
    n = x.shape[0]
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


@exact_products
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
