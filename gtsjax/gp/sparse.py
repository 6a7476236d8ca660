"""Bounded-cost GP prediction: the DTC (deterministic training conditional) predictor the shipped
models hold, on M inducing points chosen from an exact GP's training inputs.

**Cost**: :meth:`gtsjax.gp.GP.sparse` picks the M inducing points by greedy pivoted Cholesky in the
fitted kernel's own metric: O(M) per test point for the mean and O(M^2) for the variance, whatever
the training-set size. With M = N it reproduces the exact GP.
"""

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Bool, Float, Int

from ..precision import exact_products
from .kernel import Hyperparameters, _cast, _effective_noise, _masked_gram, _standardise, gram, gram_matmul, kernel

if TYPE_CHECKING:
    from .exact import GP


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

    @exact_products
    def predict(
        self, xs: Float[Array, "tests features"], *, include_noise: bool = False
    ) -> tuple[Float[Array, " tests"], Float[Array, " tests"]]:
        """DTC predictive mean (plus target mean) and variance (clipped at 0)."""
        return _predict_sparse(self, xs, include_noise)

    @exact_products
    def predict_mean(self, xs: Float[Array, "tests features"]) -> Float[Array, " tests"]:
        """The DTC predictive mean alone (eq 7's counterpart), for callers that do not need the
        variance (the classifier). Not jitted: it runs inside the step's jit."""
        dt = self.z.dtype
        xs = _standardise(xs.astype(dt), self.x_mean, self.x_scale)
        ks = jnp.where(self.z_mask[None, :], gram_matmul(self.params, xs, self.z), jnp.zeros((), dt))
        return ks @ self.weights + self.y_mean

    def astype(self, dtype) -> "SparseGP":
        return _cast(self, dtype)


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


def _stacked(gps):
    """The GPs as one ``SparseGP`` whose leaves carry a leading GP axis, or ``None`` where their shapes
    differ. Concrete leaves (a model closed over by a jit) are stacked on the host, so the stack is one
    constant of the compiled program rather than a copy it makes at every call."""
    import numpy as np

    leaves = [jax.tree.leaves(g) for g in gps]
    if any(type(g) not in (SparseGP, SharedSparseGP) or type(g) is not type(gps[0]) for g in gps) or any(
            [a.shape for a in ls] != [a.shape for a in leaves[0]] for ls in leaves[1:]):
        return None

    def stack(*a):
        if any(isinstance(x, jax.core.Tracer) for x in a):
            return jnp.stack(a)
        return jnp.asarray(np.stack([np.asarray(x) for x in a]))
    return jax.tree.map(stack, *gps)


@exact_products
def predict_many(gps, xs: Float[Array, "tests features"], *, include_noise: bool = False, mean_only: bool = False):
    """Every GP of ``gps`` on the same test inputs: means ``[outputs, tests]`` (and, unless
    ``mean_only``, variances ``[outputs, tests]``), a row per GP, or per output of a
    :class:`SharedSparseGP`, in order. GPs of one shape run as one batched computation (``vmap`` over
    the stacked GPs: each kernel of the prediction once for all of them, not once per GP: the
    classifier's three score GPs, a class's pose GPs or groups); others one after the other."""
    one = (lambda g: (g.predict_mean(xs),)) if mean_only else (lambda g: g.predict(xs, include_noise=include_noise))
    st = _stacked(gps)
    if st is not None:
        outs = jax.vmap(one)(st)
    else:
        outs = tuple(jnp.concatenate([a.reshape(-1, a.shape[-1]) for a in o]) for o in zip(*map(one, gps), strict=True))
    return tuple(o.reshape(-1, o.shape[-1]) for o in outs)


class SharedSparseGP(eqx.Module):
    """The DTC predictors of ``k`` outputs that share one kernel (:func:`gtsjax.gp.fit_shared`: the
    same length scales and training inputs, each output its own signal variance ``s_j`` and noise):
    one kernel row ``r(x*)`` of unit signal variance serves every output's mean and variance.

    With ``K = s_j R`` the DTC mean of output ``j`` (:class:`SparseGP`) is ``r_zᵀ W[:, j]`` with
    ``W[:, j] = s_j w_j``, and its variance ``s_j (1 − ‖P_m r_v‖² + ‖P_b,j r_v‖²)`` with
    ``P_m = √s_j L_m⁻¹`` (the same for every output: ``L_m`` is the factor of ``s_j (R_zz + jitter I)``)
    and ``P_b,j = √s_j L_b,j⁻¹ L_m⁻¹`` (``L_b,j`` depends on the output's noise-to-signal ratio). The
    inducing points are the same for all outputs: greedy pivoted Cholesky picks them by the kernel's
    metric alone, which the outputs share. :meth:`output` gives output ``j`` back as a
    :class:`SparseGP` (same predictions), for code that takes one GP at a time.
    """

    z: Float[Array, "inducing features"]
    z_mask: Bool[Array, " inducing"]
    log_lengthscale: Float[Array, " features"]
    log_signal_var: Float[Array, " outputs"]
    log_noise_var: Float[Array, " outputs"]
    weights: Float[Array, "inducing outputs"]  # s_j w_j: the mean is r_z(x*)ᵀ W[:, j]
    proj_m: Float[Array, "var_inducing var_inducing"]  # √s L_m⁻¹, shared
    proj_b: Float[Array, "outputs var_inducing var_inducing"]  # √s_j L_b,j⁻¹ L_m⁻¹
    y_mean: Float[Array, " outputs"]
    x_mean: Float[Array, " features"]
    x_scale: Float[Array, " features"]
    noise: Float[Array, " outputs"]  # effective noise σn² + jitter σf², as SparseGP.noise

    @property
    def n_outputs(self) -> int:
        return self.weights.shape[1]

    @property
    def n_variance(self) -> int:
        return self.proj_m.shape[0]

    def _row(self, xs):
        """Unit-signal kernel rows ``[inducing, tests]`` of raw inputs ``xs``."""
        dt = self.z.dtype
        unit = Hyperparameters(self.log_lengthscale, jnp.zeros((), dt), jnp.zeros((), dt))
        xs = _standardise(xs.astype(dt), self.x_mean, self.x_scale)
        return jnp.where(self.z_mask[:, None], gram_matmul(unit, self.z, xs), jnp.zeros((), dt))

    @exact_products
    def predict(self, xs: Float[Array, "tests features"], *, include_noise: bool = False
                ) -> tuple[Float[Array, "outputs tests"], Float[Array, "outputs tests"]]:
        """Every output's DTC predictive mean and variance (clipped at 0; plus its σn² if
        ``include_noise``), from one kernel row per test input."""
        r = self._row(xs)
        mean = self.weights.T @ r + self.y_mean[:, None]
        rv = r[: self.n_variance]
        t1 = self.proj_m @ rv
        t2 = jnp.einsum("jab,bt->jat", self.proj_b, rv)
        sv = jnp.exp(self.log_signal_var)[:, None]
        var = sv * (1.0 - jnp.sum(t1 * t1, axis=0)[None, :] + jnp.sum(t2 * t2, axis=1))
        var = jnp.maximum(var, jnp.zeros((), var.dtype))
        if include_noise:
            var = var + jnp.exp(self.log_noise_var)[:, None]
        return mean, var

    @exact_products
    def predict_mean(self, xs: Float[Array, "tests features"]) -> Float[Array, "outputs tests"]:
        """Every output's DTC predictive mean."""
        return self.weights.T @ self._row(xs) + self.y_mean[:, None]

    def astype(self, dtype) -> "SharedSparseGP":
        return _cast(self, dtype)

    def output(self, j: int) -> SparseGP:
        """Output ``j`` as a :class:`SparseGP` with the same predictions."""
        sv = jnp.exp(self.log_signal_var[j])
        params = Hyperparameters(self.log_lengthscale, self.log_signal_var[j], self.log_noise_var[j])
        root = jnp.sqrt(sv)
        return SparseGP(self.z, self.z_mask, params, self.weights[:, j] / sv, self.proj_m / root,
                        self.proj_b[j] / root, self.y_mean[j], self.x_mean, self.x_scale, self.noise[j])

    @staticmethod
    @exact_products
    def build(gps: "tuple[GP, ...]", n_inducing: int, n_variance: int | None = None) -> "SharedSparseGP":
        """The shared predictor of GPs fitted by :func:`gtsjax.gp.fit_shared`, on ``n_inducing``
        inducing points (its variance on the first ``n_variance``) as :meth:`gtsjax.gp.GP.sparse`
        picks them; each output predicts what its own ``gp.sparse(n_inducing, n_variance)`` would.
        The GPs must share their training inputs, mask, input statistics, length scales and jitter."""
        from .errors import GPArgumentError

        g0 = gps[0]
        for g in gps[1:]:
            same = (g.x.shape == g0.x.shape and all(bool(jnp.all(a == b)) for a, b in (
                (g.x, g0.x), (g.mask, g0.mask), (g.x_mean, g0.x_mean), (g.x_scale, g0.x_scale),
                (g.params.log_lengthscale, g0.params.log_lengthscale), (g.jitter, g0.jitter))))
            if not same:
                raise GPArgumentError("SharedSparseGP.build", "the GPs do not share one kernel and training inputs "
                                      "(fit them with gp.fit_shared)")
        m = int(min(n_inducing, g0.n_points))
        mv = m if n_variance is None else int(min(n_variance, m))
        if m < 1 or mv < 1:
            raise GPArgumentError("SharedSparseGP.build",
                                  f"n_inducing and n_variance must be >= 1, got {n_inducing}, {n_variance}")
        return _build_shared(tuple(gps), m, mv)


@eqx.filter_jit
def _build_shared(gps, m: int, mv: int) -> SharedSparseGP:
    """:class:`SharedSparseGP` of ``gps``: the inducing points picked once (by the first GP's kernel:
    the metric is the same for all), then each output's :func:`_build_sparse` on them."""
    g0 = gps[0]
    tol = g0.jitter * g0.params.signal_var
    n = g0.n_points
    picks = _pivoted_cholesky(g0.params, g0.x, g0.mask, mv if m >= n else m, tol)
    outs = [_build_sparse(g, m, mv, picks) for g in gps]
    sv = jnp.stack([g.params.signal_var for g in gps])
    root = jnp.sqrt(sv)
    return SharedSparseGP(
        outs[0].z, outs[0].z_mask, g0.params.log_lengthscale,
        jnp.stack([g.params.log_signal_var for g in gps]), jnp.stack([g.params.log_noise_var for g in gps]),
        jnp.stack([o.weights for o in outs], 1) * sv[None, :],
        outs[0].proj_m * root[0],
        jnp.stack([o.proj_b for o in outs]) * root[:, None, None],
        jnp.stack([o.y_mean for o in outs]), g0.x_mean, g0.x_scale, jnp.stack([o.noise for o in outs]))


class CommonInputsGP(eqx.Module):
    """Separate GPs (each its own kernel) whose mean runs over one set of inducing inputs: a class's
    pose GPs trained on the same examples, each predicting its exact mean over all of them
    (:meth:`gtsjax.gp.GP.sparse` with M = N puts each GP's own variance pivots first, so their ``z``
    hold the same rows in different orders). Made by :meth:`of` from such :class:`SparseGP` s, it
    predicts what they predict, with ``z`` stored and read once instead of once per GP: output ``j``'s
    kernel row is ``s_j exp(−½(‖x‖²_j + ‖z‖²_j − 2 (W_j x)·z))`` with ``W_j = diag(ℓ_j⁻²)``, so every
    output's products with ``z`` are one matrix product ``[outputs · tests, features] × zᵀ``. Each
    output's variance reads its own ``Mv`` pivots out of its row (``var_index``)."""

    z: Float[Array, "inducing features"]
    z_mask: Bool[Array, " inducing"]
    log_lengthscale: Float[Array, "outputs features"]
    log_signal_var: Float[Array, " outputs"]
    log_noise_var: Float[Array, " outputs"]
    weights: Float[Array, "outputs inducing"]
    var_index: Int[Array, "outputs var_inducing"]  # where output j's variance points lie in z
    proj_m: Float[Array, "outputs var_inducing var_inducing"]
    proj_b: Float[Array, "outputs var_inducing var_inducing"]
    y_mean: Float[Array, " outputs"]
    x_mean: Float[Array, " features"]
    x_scale: Float[Array, " features"]
    noise: Float[Array, " outputs"]

    @property
    def n_outputs(self) -> int:
        return self.weights.shape[0]

    def _rows(self, xs):
        """Every output's kernel rows ``[outputs, tests, inducing]`` of raw inputs ``xs``."""
        dt = self.z.dtype
        xs = _standardise(xs.astype(dt), self.x_mean, self.x_scale)
        w = jnp.exp(-2.0 * self.log_lengthscale)  # [outputs, features]
        wx = w[:, None, :] * xs[None]  # [outputs, tests, features]
        nx = jnp.sum(wx * xs[None], -1)  # [outputs, tests]
        nz = (self.z * self.z) @ w.T  # [inducing, outputs]
        cross = (wx.reshape(-1, wx.shape[-1]) @ self.z.T).reshape(wx.shape[:2] + self.z.shape[:1])
        d2 = nx[:, :, None] + nz.T[:, None, :] - 2.0 * cross
        k = jnp.exp(self.log_signal_var)[:, None, None] * jnp.exp(-0.5 * jnp.maximum(d2, jnp.zeros((), dt)))
        return jnp.where(self.z_mask[None, None, :], k, jnp.zeros((), dt))

    @exact_products
    def predict(self, xs: Float[Array, "tests features"], *, include_noise: bool = False
                ) -> tuple[Float[Array, "outputs tests"], Float[Array, "outputs tests"]]:
        """Every output's DTC predictive mean and variance, as its :class:`SparseGP`'s."""
        k = self._rows(xs)
        mean = jnp.einsum("otm,om->ot", k, self.weights) + self.y_mean[:, None]
        kv = jnp.take_along_axis(k, self.var_index[:, None, :], axis=2)  # [outputs, tests, var_inducing]
        t1 = jnp.einsum("oab,otb->ota", self.proj_m, kv)
        t2 = jnp.einsum("oab,otb->ota", self.proj_b, kv)
        var = jnp.exp(self.log_signal_var)[:, None] - jnp.sum(t1 * t1, -1) + jnp.sum(t2 * t2, -1)
        var = jnp.maximum(var, jnp.zeros((), var.dtype))
        if include_noise:
            var = var + jnp.exp(self.log_noise_var)[:, None]
        return mean, var

    @exact_products
    def predict_mean(self, xs: Float[Array, "tests features"]) -> Float[Array, "outputs tests"]:
        return jnp.einsum("otm,om->ot", self._rows(xs), self.weights) + self.y_mean[:, None]

    def astype(self, dtype) -> "CommonInputsGP":
        return _cast(self, dtype)

    @staticmethod
    def of(gps: "tuple[SparseGP, ...]") -> "CommonInputsGP | None":
        """The GPs as one :class:`CommonInputsGP`, or ``None`` unless they are :class:`SparseGP` s of
        concrete arrays with the same input statistics, every inducing slot used and the same inducing
        rows (in any order). Host-side (NumPy): a model is converted once, when it is loaded."""
        import numpy as np

        if len(gps) < 2 or any(type(g) is not SparseGP for g in gps):
            return None
        leaves = [a for g in gps for a in jax.tree.leaves(g)]
        if any(isinstance(a, jax.core.Tracer) for a in leaves):
            return None
        g0 = gps[0]
        z0 = np.asarray(g0.z)
        mv = gps[0].n_variance
        for g in gps:
            if (g.z.shape != z0.shape or g.n_variance != mv or not np.all(np.asarray(g.z_mask))
                    or not np.array_equal(np.asarray(g.x_mean), np.asarray(g0.x_mean))
                    or not np.array_equal(np.asarray(g.x_scale), np.asarray(g0.x_scale))):
                return None
        order0 = np.lexsort(z0.T[::-1])
        weights, var_index = [], []
        for g in gps:
            z = np.asarray(g.z)
            order = np.lexsort(z.T[::-1])
            if not np.array_equal(z[order], z0[order0]):
                return None
            pos = np.empty(len(z), np.int64)  # pos[i]: where row i of this GP's z lies in z0
            pos[order] = order0
            w = np.empty_like(np.asarray(g.weights))
            w[pos] = np.asarray(g.weights)  # a permutation: rows that are equal may swap, to the same effect
            weights.append(w)
            var_index.append(pos[:mv])
        st = _stacked(gps)  # every GP's own leaves on a leading axis (the same shapes, checked above)
        return CommonInputsGP(
            g0.z, g0.z_mask, st.params.log_lengthscale, st.params.log_signal_var, st.params.log_noise_var,
            jnp.asarray(np.stack(weights)), jnp.asarray(np.stack(var_index).astype(np.int32)), st.proj_m,
            st.proj_b, st.y_mean, g0.x_mean, g0.x_scale, st.noise)


# ------------------------------------------------------------------------------------------ building


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
def _build_sparse(gp: "GP", m: int, mv: int, picks=None) -> SparseGP:
    """The :class:`SparseGP` of ``gp`` on ``m`` inducing points, its variance on the first ``mv``
    (both already clipped to ``1 <= mv <= m <= N``; :meth:`gtsjax.gp.GP.sparse` is the entry point).
    ``picks``: the pivoted Cholesky's choice (``mv`` points when ``m`` covers the training set, else
    ``m``) where the caller made it already."""
    params = gp.params
    dt = gp.x.dtype
    n = gp.n_points
    tol = gp.jitter * params.signal_var
    if m >= n:
        # Every training point: the variance's pivots first, then the rest in order; the exact mean.
        idx_v, used_v = picks if picks is not None else _pivoted_cholesky(params, gp.x, gp.mask, mv, tol)
        first = jnp.zeros((n,), bool).at[idx_v].set(used_v)
        pos = jnp.zeros((n,), jnp.int32).at[idx_v].set(jnp.arange(mv, dtype=jnp.int32))
        rest = mv + jnp.cumsum(~first, dtype=jnp.int32) - 1
        perm = jnp.argsort(jnp.where(first, pos, rest))
        z_mask = gp.mask[perm]
        z = jnp.where(z_mask[:, None], gp.x[perm], jnp.zeros((), dt))
        weights = jnp.where(z_mask, gp.alpha[perm], jnp.zeros((), dt))
    else:
        idx, z_mask = picks if picks is not None else _pivoted_cholesky(params, gp.x, gp.mask, m, tol)
        z = jnp.where(z_mask[:, None], gp.x[idx], jnp.zeros((), dt))
        weights = _dtc(params, z, z_mask, gp, tol)[0]
    noise = _effective_noise(params, gp.jitter)
    # The variance needs L_m^-1 k_z and L_b^-1 L_m^-1 k_z for every test point. Two triangular solves
    # per call are slow on small matrices (the step's budget is a fraction of a millisecond), so the
    # two triangular inverses are formed once here, in the fit's float64, and prediction is matmuls.
    _, proj_m, proj_b = _dtc(params, z[:mv], z_mask[:mv], gp, tol)
    return SparseGP(z, z_mask, params, weights, proj_m, proj_b, gp.y_mean, gp.x_mean, gp.x_scale, noise)


def _dtc(params, z, z_mask, gp: "GP", tol):
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
