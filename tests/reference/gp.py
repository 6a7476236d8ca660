"""One of the model's GPs carried into scikit-learn (``ConstantKernel × RBF`` with the model's
hyperparameters, ``optimizer=None``), for stages d and e.

**How a model GP is carried over.** An exact :class:`gtsjax.gp.GP` stores its standardised training
inputs and centred targets: a ``GaussianProcessRegressor`` is fitted on those with ``alpha`` equal to
the GP's effective noise ``σn² + jitter σf²``, which reproduces its mean and variance. A
:class:`gtsjax.gp.SparseGP` (the DTC predictor the shipped models hold) stores only its ``M``
inducing inputs ``Z``, the weights ``w`` of its mean ``k_Z(x)ᵀ w``, ``L_m⁻¹`` (``K_ZZ + a I = L_m
L_mᵀ``, ``a = jitter σf²``) and ``L_b⁻¹ L_m⁻¹``. Its mean is scikit-learn's kernel between the input
and ``Z`` times ``w`` (a GPR fitted on ``Z`` with ``alpha = a`` and targets ``(K_ZZ + a I) w`` has
``alpha_ = w`` and predicts the same, at the price of a Cholesky factorisation of the 6 000 inducing
points of a shipped pose GP: 6 s each, for nothing the product does not check). Its variance
``σf² − k_Zᵀ (K_ZZ + a I)⁻¹ k_Z`` over the variance's inducing points is a GPR's fitted on those with
``alpha = a``, to which the third term of the DTC variance, ``‖L_b⁻¹ L_m⁻¹ k_Z‖²``, is added from the
stored matrix (``a`` is recovered as the stored effective noise minus ``σn²``).
"""

import warnings

import numpy as np
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel


def _f(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


_FITTED: dict[tuple[int, ...], tuple[list, "SklearnGP"]] = {}


def sklearn_gp(gp) -> "SklearnGP | SklearnSharedGP":
    """:class:`SklearnGP` of ``gp`` (:class:`SklearnSharedGP` of a shared group), built once per set of
    arrays (an exact GP's GPR is fitted on all its rows; a model changed elsewhere, ``eqx.tree_at`` on
    its tracker, keeps the same GP arrays). Keyed by the identity of the arrays, which the entry keeps
    alive, so a key is never reused by other arrays."""
    import jax

    leaves = jax.tree_util.tree_leaves(gp)
    key = tuple(id(x) for x in leaves)
    hit = _FITTED.get(key)
    if hit is None:
        hit = _FITTED[key] = (leaves, SklearnSharedGP(gp) if hasattr(gp, "proj_b") and gp.proj_b.ndim == 3
                              else SklearnGP(gp))
    return hit[1]


class SklearnGP:
    """One of the model's GPs (exact or DTC) as a fitted scikit-learn ``GaussianProcessRegressor``
    (see the module docstring for how the DTC predictor is carried over)."""

    def __init__(self, gp):
        p = gp.params
        sf2 = float(np.exp(_f(p.log_signal_var)))
        self.noise_var = float(np.exp(_f(p.log_noise_var)))
        with np.errstate(over="ignore"):  # a feature BFGS switched off (log l ~ 1e3): l = inf, as w = 0 in gtsjax
            lengthscale = np.exp(_f(p.log_lengthscale))
        kernel = ConstantKernel(sf2, constant_value_bounds="fixed") * RBF(lengthscale, length_scale_bounds="fixed")
        self.x_mean = _f(gp.x_mean)
        self.x_scale = _f(gp.x_scale)
        self.y_mean = float(gp.y_mean)
        self.kernel = kernel
        if hasattr(gp, "z"):  # SparseGP (DTC): the mean k_Z(x)ᵀ w, the variance a GPR's on the first mv points
            use = np.asarray(gp.z_mask, bool)
            self.z, self.w = _f(gp.z)[use], _f(gp.weights)[use]
            a = max(float(_f(gp.noise)) - self.noise_var, 1e-12 * sf2)
            mv = int(gp.proj_m.shape[0])  # the variance uses the first mv inducing points only
            use_v = np.asarray(gp.z_mask, bool)[:mv]
            self.proj_b = _f(gp.proj_b)[np.ix_(use_v, use_v)]
            zv = _f(gp.z)[:mv][use_v]
            self.var_gpr = GaussianProcessRegressor(
                kernel, alpha=a, optimizer=None, normalize_y=False, copy_X_train=False
            ).fit(zv, np.zeros(len(zv)))
        else:  # exact GP: one GPR on its training rows gives both
            use = np.asarray(gp.mask, bool)
            a = float(np.exp(_f(p.log_noise_var)) + _f(gp.jitter) * sf2)
            self.var_gpr = GaussianProcessRegressor(kernel, alpha=a, optimizer=None, normalize_y=False,
                                                    copy_X_train=False).fit(_f(gp.x)[use], _f(gp.y)[use])
            self.z, self.w, self.proj_b = None, None, None

    def _mean(self, xs: np.ndarray) -> np.ndarray:
        """The centred predictive mean of standardised inputs."""
        if self.z is None:
            return self.var_gpr.predict(xs)
        return self.kernel(xs, self.z) @ self.w

    def _std(self, x: np.ndarray) -> np.ndarray:
        return (x - self.x_mean) / self.x_scale

    def predict_mean(self, x: np.ndarray) -> np.ndarray:
        """Predictive mean (eq. 7) of raw inputs ``x`` [n, d]."""
        return self._mean(self._std(x)) + self.y_mean

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and variance, observation noise included (what pose regression uses)."""
        xs = self._std(x)
        mean = self._mean(xs)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # sklearn warns when it clips a variance of -1e-17 at 0
            _, std = self.var_gpr.predict(xs, return_std=True)
        var = std**2
        if self.proj_b is not None:
            t2 = self.var_gpr.kernel_(xs, self.var_gpr.X_train_) @ self.proj_b.T
            var = var + np.sum(t2 * t2, axis=1)
        return mean + self.y_mean, np.maximum(var, 0.0) + self.noise_var


class SklearnSharedGP:
    """A group of the model's pose GPs that share one kernel (:class:`gtsjax.gp.SharedSparseGP`) in
    scikit-learn: one kernel row per test input for every output, as a careful user would.

    In unit-signal terms (``K_j = s_j R``) every output's mean is ``r_Z(x)ᵀ W[:, j]`` (``R``
    scikit-learn's ``ConstantKernel(1) × RBF``: every mean at once), and the DTC predictor's jitter is
    the same fraction ``a`` of each output's signal, so one unit GPR with ``alpha = a`` serves every
    variance: that of output ``j`` is ``s_j`` times the unit GPR's ``1 − r_vᵀ (R_vv + a I)⁻¹ r_v`` plus ``s_j ‖P_b,j r_v‖²`` (the group's stored unit
    ``P_b``), plus the output's ``σn²``."""

    def __init__(self, g):
        with np.errstate(over="ignore"):
            lengthscale = np.exp(_f(g.log_lengthscale))
        kernel = ConstantKernel(1.0, constant_value_bounds="fixed") * RBF(lengthscale, length_scale_bounds="fixed")
        self.signal = np.exp(_f(g.log_signal_var))
        self.noise_var = np.exp(_f(g.log_noise_var))
        a = max(float(_f(g.noise)[0] - self.noise_var[0]) / float(self.signal[0]), 1e-12)  # the jitter fraction
        self.x_mean, self.x_scale, self.y_mean = _f(g.x_mean), _f(g.x_scale), _f(g.y_mean)
        use = np.asarray(g.z_mask, bool)
        self.kernel, self.z, self.w = kernel, _f(g.z)[use], _f(g.weights)[use]
        mv = int(g.proj_m.shape[0])
        use_v = use[:mv]
        self.proj_b = _f(g.proj_b)[:, use_v][:, :, use_v]
        self.var_gpr = GaussianProcessRegressor(kernel, alpha=a, optimizer=None, normalize_y=False,
                                                copy_X_train=False).fit(_f(g.z)[:mv][use_v], np.zeros(int(use_v.sum())))

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every output's predictive mean and variance (noise included), each [n, k]."""
        xs = (x - self.x_mean) / self.x_scale
        mean = self.kernel(xs, self.z) @ self.w
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, std = self.var_gpr.predict(xs, return_std=True)
        rv = self.var_gpr.kernel_(xs, self.var_gpr.X_train_)
        t2 = np.einsum("jab,nb->nja", self.proj_b, rv)
        var = self.signal[None, :] * (std[:, None] ** 2 + np.sum(t2 * t2, axis=2))
        return mean + self.y_mean[None, :], np.maximum(var, 0.0) + self.noise_var[None, :]
