"""GP library (paper section 3b, eqs 3-7) against scikit-learn and against itself (autodiff, padding,
exact vs sparse). Small N throughout: the machine is shared."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

# scikit-learn is a test dependency (pyproject's ``test`` extra): imported, not skipped without it.
import sklearn.gaussian_process as sk_gp  # noqa: E402
import sklearn.gaussian_process.kernels as sk_k  # noqa: E402

from gtsjax import InputError, gp
from gtsjax.gp.kernel import _effective_noise, _lml_forward, _safe_rows
from gtsjax.train import TrainConfig
from gtsjax.train.fit import fit_gp


def _sk_kernel(params: gp.Hyperparameters, noise: float, *, fixed: bool):
    bounds = "fixed" if fixed else (1e-5, 1e5)
    return sk_k.ConstantKernel(float(params.signal_var), bounds) * sk_k.RBF(
        np.asarray(params.lengthscale), bounds
    ) + sk_k.WhiteKernel(noise, bounds)


def _params(d, seed=0):
    rng = np.random.default_rng(seed)
    return gp.Hyperparameters(
        jnp.asarray(rng.uniform(-0.5, 0.8, d)),
        jnp.asarray(rng.uniform(-0.5, 0.5)),
        jnp.asarray(rng.uniform(-4.0, -2.0)),
    )


# --------------------------------------------------------------------------------------- data sets


def _sin1d(rng):
    x = rng.uniform(-3.0, 3.0, (40, 1))
    return x, np.sin(2.0 * x[:, 0]) + 0.05 * rng.normal(size=40)


def _friedman3(rng):
    x = rng.uniform(0.0, 1.0, (60, 3))
    return x, 10.0 * np.sin(np.pi * x[:, 0] * x[:, 1]) + 20.0 * (x[:, 2] - 0.5) ** 2 + 0.5 * rng.normal(size=60)


def _noisy_linear(rng):
    x = rng.normal(size=(50, 3))
    return x, x @ np.array([1.0, -2.0, 0.5]) + 0.3 * rng.normal(size=50)


def _step(rng):
    x = rng.uniform(-2.0, 2.0, (50, 2))
    return x, (np.sum(x * x, axis=1) < 1.5).astype(np.float64)


def _profiles(rng, n=60):
    """Laser-characteristic-like vectors: 16 depth-profile cells of an ellipse seen at heading phi,
    plus width, mean intensity, point count and range (20 features); target cos(phi)."""
    phi = rng.uniform(-np.pi, np.pi, n)
    rng_m = rng.uniform(0.5, 3.5, n)
    cells = np.linspace(-1.0, 1.0, 16)
    half_w = 0.6 + 0.3 * np.abs(np.cos(phi))
    depth = (
        np.sqrt(np.clip(1.0 - (cells[None, :] / half_w[:, None]) ** 2, 0.0, None)) * (0.4 + 0.2 * np.sin(phi))[:, None]
    )
    depth += 0.01 * rng.normal(size=depth.shape)
    extra = np.stack([2.0 * half_w, 0.5 + 0.1 * np.cos(phi), 40.0 / rng_m, rng_m], axis=1)
    return np.concatenate([depth, extra], axis=1), np.cos(phi) + 0.02 * rng.normal(size=n)


DATASETS = {
    "sin1d": _sin1d,
    "friedman3": _friedman3,
    "noisy_linear": _noisy_linear,
    "step": _step,
    "profiles": _profiles,
}


# ------------------------------------------------------------------------------- kernel-level match


@pytest.mark.parametrize("d", [1, 4])
def test_kernel_lml_and_predictions_match_sklearn(d):
    rng = np.random.default_rng(d)
    x = rng.normal(size=(25, d))
    y = np.sin(x[:, 0]) + 0.1 * rng.normal(size=25)
    y = y - y.mean()
    xs = rng.normal(size=(7, d))
    params = _params(d)
    noise = float(params.noise_var)

    k_ours = np.asarray(gp.gram(params, jnp.asarray(x), jnp.asarray(xs)))
    k_sk = (sk_k.ConstantKernel(float(params.signal_var)) * sk_k.RBF(np.asarray(params.lengthscale)))(x, xs)
    np.testing.assert_allclose(k_ours, k_sk, rtol=1e-12, atol=1e-14)

    ours = gp.condition(params, x, y, jitter=0.0)
    lml = float(gp.log_marginal_likelihood(params, jnp.asarray(x), jnp.asarray(y), jitter=0.0))
    reg = sk_gp.GaussianProcessRegressor(_sk_kernel(params, noise, fixed=True), alpha=0.0, optimizer=None).fit(x, y)
    assert abs(lml - reg.log_marginal_likelihood_value_) < 1e-6
    assert abs(float(ours.log_marginal_likelihood()) - reg.log_marginal_likelihood_value_) < 1e-6

    mean, var = ours.predict(jnp.asarray(xs), include_noise=True)
    m_sk, s_sk = reg.predict(xs, return_std=True)
    np.testing.assert_allclose(np.asarray(mean), m_sk, atol=1e-6)
    np.testing.assert_allclose(np.asarray(var), s_sk**2, atol=1e-6)
    _, var_f = ours.predict(jnp.asarray(xs))
    np.testing.assert_allclose(np.asarray(var_f), s_sk**2 - noise, atol=1e-6)


def _lml_autodiff(params, x, y, mask, jitter):
    """Eq 5 differentiated by JAX through the Cholesky factor: the reference for the closed-form VJP."""
    x, y = _safe_rows(x, y, mask)
    return _lml_forward(params, x, y, mask, jnp.asarray(jitter, x.dtype))[0]


def test_closed_form_gradient_matches_autodiff():
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(20, 3)))
    y = jnp.asarray(rng.normal(size=20))
    mask = jnp.asarray(np.arange(20) < 16)
    params = _params(3, seed=1)
    jit_ = jnp.asarray(1e-3)
    g = jax.grad(lambda p, a, b, j: gp.log_marginal_likelihood(p, a, b, mask, jitter=j), argnums=(0, 1, 2, 3))
    g_ref = jax.grad(_lml_autodiff, argnums=(0, 1, 2, 4))
    for a, b in zip(
        jax.tree.leaves(g(params, x, y, jit_)), jax.tree.leaves(g_ref(params, x, y, mask, jit_)), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-10)


# ------------------------------------------------------------------------------- optimum vs sklearn


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
@pytest.mark.parametrize("name", sorted(DATASETS))
def test_fit_optimum_at_least_sklearn(name):
    rng = np.random.default_rng(42)
    x, y = DATASETS[name](rng)
    ours = gp.fit(x, y, key=jax.random.key(0), restarts=3)
    xs, yc = np.asarray(ours.x), np.asarray(ours.y)  # same representation for both: standardised, centred
    np.testing.assert_allclose(yc, y - y.mean(), atol=1e-12)

    d = x.shape[1]
    init = gp.Hyperparameters(jnp.zeros(d), jnp.asarray(0.0), jnp.asarray(np.log(0.1)))
    reg = sk_gp.GaussianProcessRegressor(
        _sk_kernel(init, 0.1, fixed=False), n_restarts_optimizer=2, random_state=0, normalize_y=False
    ).fit(xs, yc)
    lml_ours = float(ours.log_marginal_likelihood())
    lml_sk = float(reg.log_marginal_likelihood_value_)
    print(f"{name}: ours {lml_ours:.6f} sklearn {lml_sk:.6f}")
    assert lml_ours >= lml_sk - 1e-3

    # sklearn evaluates our optimum to the same value: both really are on the same data and model.
    noise = float(_effective_noise(ours.params, ours.jitter))
    theta = _sk_kernel(ours.params, noise, fixed=False).theta
    assert abs(float(reg.log_marginal_likelihood(theta)) - lml_ours) < 1e-4 * max(1.0, abs(lml_ours))


# ------------------------------------------------------------------------------ padding, degeneracy


def _lml_and_grad(params, x, y, mask):
    return jax.value_and_grad(gp.log_marginal_likelihood)(params, x, y, mask)


def test_padding_leaves_lml_and_gradient_unchanged_and_finite():
    rng = np.random.default_rng(5)
    x = rng.normal(size=(12, 3))
    y = rng.normal(size=12)
    params = _params(3, seed=2)
    v0, g0 = _lml_and_grad(params, jnp.asarray(x), jnp.asarray(y), jnp.ones(12, bool))
    xp = np.full((20, 3), np.nan)
    yp = np.full((20,), np.inf)
    xp[:12], yp[:12] = x, y
    mask = jnp.asarray(np.arange(20) < 12)
    v1, g1 = _lml_and_grad(params, jnp.asarray(xp), jnp.asarray(yp), mask)
    assert abs(float(v0 - v1)) < 1e-10
    for a, b in zip(jax.tree.leaves(g0), jax.tree.leaves(g1), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)
    gx = jax.grad(gp.log_marginal_likelihood, argnums=(1, 2))(params, jnp.asarray(xp), jnp.asarray(yp), mask)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(gx))


@pytest.mark.parametrize(
    "case",
    ["duplicates", "constant_column", "one_point", "all_padding_but_one", "tiny_noise"],
)
def test_degenerate_inputs_give_finite_lml_and_gradient(case):
    rng = np.random.default_rng(6)
    params = _params(2, seed=3)
    x = rng.normal(size=(8, 2))
    y = rng.normal(size=8)
    mask = np.ones(8, bool)
    if case == "duplicates":
        x[:] = x[0]
    elif case == "constant_column":
        x[:, 1] = 0.0
    elif case == "one_point":
        x, y, mask = x[:1], y[:1], mask[:1]
    elif case == "all_padding_but_one":
        mask[1:] = False
    elif case == "tiny_noise":
        x[4:] = x[:4]
        params = eqx.tree_at(lambda p: p.log_noise_var, params, jnp.asarray(-60.0))
    v, g = _lml_and_grad(params, jnp.asarray(x), jnp.asarray(y), jnp.asarray(mask))
    assert bool(jnp.isfinite(v))
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(g))


def test_fit_degenerate_data_is_finite():
    rng = np.random.default_rng(7)
    x = rng.normal(size=(15, 3))
    x[:, 1] = 2.5  # constant feature
    y = np.sin(x[:, 0])
    g = gp.fit(x, y, key=jax.random.key(1), restarts=2)
    assert np.all(np.isfinite(np.asarray(g.x)))
    m, v = g.predict(jnp.asarray(x[:4]))
    assert np.all(np.isfinite(np.asarray(m))) and np.all(np.isfinite(np.asarray(v)))
    for xx, yy in [(x[:1], y[:1]), (x, np.full(15, 0.7))]:  # one point; constant target
        g = gp.fit(xx, yy, key=jax.random.key(1), restarts=2)
        m, v = g.predict(jnp.asarray(x[:3]))
        np.testing.assert_allclose(np.asarray(m), yy[0], atol=1e-9)
        assert np.all(np.isfinite(np.asarray(v)))


def test_padded_fit_matches_unpadded_and_compiles_once():
    rng = np.random.default_rng(8)
    x, y = _sin1d(rng)
    a = gp.fit(x, y, key=jax.random.key(2), restarts=1)
    b = gp.fit(x, y, key=jax.random.key(2), restarts=1, pad_to=48)
    assert b.n_points == 48
    assert abs(float(a.log_marginal_likelihood() - b.log_marginal_likelihood())) < 1e-6
    xs = jnp.asarray(rng.uniform(-3, 3, (5, 1)))
    for u, w in zip(a.predict(xs), b.predict(xs), strict=True):
        np.testing.assert_allclose(np.asarray(u), np.asarray(w), rtol=1e-5, atol=1e-7)

    c = gp.fit(x[:30], -y[:30], key=jax.random.key(3), restarts=1, pad_to=48)
    predict = eqx.filter_jit(eqx.debug.assert_max_traces(lambda g, t: g.predict(t), max_traces=1))
    predict(b, xs)
    predict(c, xs + 1.0)  # another GP of the same padded size: no retrace
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), b, c)
    means, _ = eqx.filter_vmap(lambda g: g.predict(xs))(stacked)
    assert means.shape == (2, 5)


# ------------------------------------------------------------------------------ API and behaviour


def test_predict_shapes_float32_copy_and_determinism():
    rng = np.random.default_rng(9)
    x, y = _friedman3(rng)
    g1 = gp.fit(x, y, key=jax.random.key(4), restarts=2)
    g2 = gp.fit(x, y, key=jax.random.key(4), restarts=2)
    for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g2), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    xs = jnp.asarray(rng.uniform(0, 1, (11, 3)))
    mean, var = g1.predict(xs)
    assert mean.shape == (11,) and var.shape == (11,) and mean.dtype == jnp.float64
    assert bool(jnp.all(var >= 0.0))
    _, var_n = g1.predict(xs, include_noise=True)
    np.testing.assert_allclose(np.asarray(var_n - var), float(g1.params.noise_var), rtol=1e-10)

    g32 = g1.astype(jnp.float32)
    assert g32.alpha.dtype == jnp.float32 and g32.mask.dtype == jnp.bool_
    m32, v32 = g32.predict(xs.astype(jnp.float32))
    assert m32.dtype == jnp.float32 and v32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(m32), np.asarray(mean), rtol=1e-3, atol=1e-3 * float(np.std(y)))


def test_subsample_cap():
    rng = np.random.default_rng(10)
    x = rng.uniform(-3, 3, (300, 1))
    y = np.sin(x[:, 0]) + 0.05 * rng.normal(size=300)
    g = gp.fit(x, y, key=jax.random.key(5), restarts=2, max_points=80, screen_points=40)
    assert g.n_points == 80
    m, _ = g.predict(jnp.asarray(x[:20]))
    assert float(jnp.max(jnp.abs(m - jnp.asarray(np.sin(x[:20, 0]))))) < 0.1


def test_fit_on_a_subsample_conditions_on_all_rows():
    """``max_fit_points``: hyperparameters from a subsample, posterior on every row kept. Checked
    against scikit-learn conditioned on all rows with those hyperparameters held fixed, and against a
    fit on the subsample alone (same hyperparameters, which the fit on all rows is not bound to)."""
    rng = np.random.default_rng(12)
    x = rng.uniform(-3, 3, (240, 2))
    y = np.sin(x[:, 0]) * np.cos(0.5 * x[:, 1]) + 0.05 * rng.normal(size=240)
    g = gp.fit(x, y, key=jax.random.key(6), restarts=1, max_fit_points=60)
    assert g.n_points == 240 and int(jnp.sum(g.mask)) == 240
    # scikit-learn on the same standardised inputs and centred targets, kernel fixed at ours.
    xs_all = (x - np.asarray(g.x_mean)) / np.asarray(g.x_scale)
    yc = y - float(g.y_mean)
    noise = float(g.params.noise_var) + float(g.jitter) * float(g.params.signal_var)
    reg = sk_gp.GaussianProcessRegressor(_sk_kernel(g.params, noise, fixed=True), alpha=0.0, optimizer=None)
    reg.fit(xs_all, yc)
    xt = rng.uniform(-3, 3, (30, 2))
    mean, var = g.predict(jnp.asarray(xt), include_noise=True)
    m_sk, s_sk = reg.predict((xt - np.asarray(g.x_mean)) / np.asarray(g.x_scale), return_std=True)
    np.testing.assert_allclose(np.asarray(mean), m_sk + float(g.y_mean), atol=1e-6)
    # scikit-learn counts the whole white noise (ours plus the jitter floor) in its predictive variance.
    np.testing.assert_allclose(np.asarray(var), s_sk**2 - noise + float(g.params.noise_var), atol=1e-6)
    # More rows in the posterior than in the fit predict better than the fit's rows alone would.
    sub = gp.fit(x, y, key=jax.random.key(6), restarts=1, max_points=60)
    truth = np.sin(xt[:, 0]) * np.cos(0.5 * xt[:, 1])
    m_sub, _ = sub.predict(jnp.asarray(xt))
    assert np.sqrt(np.mean((np.asarray(mean) - truth) ** 2)) < np.sqrt(np.mean((np.asarray(m_sub) - truth) ** 2))


def test_sparse_full_rank_matches_exact_and_low_rank_is_close():
    rng = np.random.default_rng(11)
    x = rng.uniform(-3, 3, (60, 2))
    y = np.sin(x[:, 0]) * np.cos(0.5 * x[:, 1]) + 0.05 * rng.normal(size=60)
    g = gp.fit(x, y, key=jax.random.key(6), restarts=2)
    xs = jnp.asarray(rng.uniform(-3, 3, (15, 2)))
    mean, var = g.predict(xs)

    full = g.sparse(60)  # slots whose residual falls below the jitter stay masked: they add nothing
    assert int(jnp.sum(full.z_mask)) >= 50
    m_f, v_f = full.predict(xs)
    np.testing.assert_allclose(np.asarray(m_f), np.asarray(mean), atol=1e-5)
    np.testing.assert_allclose(np.asarray(v_f), np.asarray(var), atol=1e-5)

    low = g.sparse(25)
    assert low.z.shape == (25, 2)
    m_l, v_l = low.predict(xs)
    assert float(jnp.max(jnp.abs(m_l - mean))) < 0.05
    assert float(jnp.max(jnp.abs(v_l - var))) < 0.05 * float(g.params.signal_var)
    m32, _ = low.astype(jnp.float32).predict(xs.astype(jnp.float32))
    assert m32.dtype == jnp.float32


def test_predict_many_equals_each_gp_on_its_own():
    """The stacked prediction of several GPs (one batched computation) gives what each GP predicts on
    its own; GPs of different shapes (inducing counts) are predicted one after the other."""
    from gtsjax.gp.sparse import predict_many

    rng = np.random.default_rng(12)
    x = rng.uniform(-3, 3, (50, 2))
    ys = [np.sin(x[:, 0]), np.cos(x[:, 1]) * x[:, 0], 0.1 * x[:, 1] ** 2]
    gps = [gp.fit(x, y + 0.05 * rng.normal(size=50), key=jax.random.key(i), restarts=1).sparse(20, 8) for i, y in enumerate(ys)]
    xs = jnp.asarray(rng.uniform(-3, 3, (7, 2)))
    for group in (gps, [gps[0], gps[1].astype(jnp.float64), gp.fit(x, ys[2], key=jax.random.key(9), restarts=1).sparse(12, 8)]):
        m, v = jax.jit(lambda xs, group=group: predict_many(group, xs, include_noise=True))(xs)
        (m_only,) = predict_many(group, xs, mean_only=True)
        for i, g in enumerate(group):
            want_m, want_v = g.predict(xs, include_noise=True)
            np.testing.assert_allclose(np.asarray(m[i]), np.asarray(want_m), rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(np.asarray(v[i]), np.asarray(want_v), rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(np.asarray(m_only[i]), np.asarray(g.predict_mean(xs)), rtol=1e-10, atol=1e-10)


def test_all_restarts_failing_raises_clear_error():
    rng = np.random.default_rng(12)
    x, y = _sin1d(rng)
    with pytest.raises(gp.GPFitError, match="all GP hyperparameter restarts failed"):
        gp.fit(x, y, key=jax.random.key(0), restarts=2, max_steps=1)


def test_fit_rejects_bad_input():
    with pytest.raises(gp.GPArgumentError, match="need x"):
        gp.fit(np.zeros((3, 2)), np.zeros(4), key=jax.random.key(0))


def test_bad_gp_arguments_reach_the_user_as_one_line_input_errors():
    """The GP library raises its own error (it is core code); training turns it into the CLI's
    :class:`InputError` with the same message."""
    x, y = np.zeros((3, 2)), np.zeros(3)
    with pytest.raises(gp.GPArgumentError) as err:
        gp.fit(x, y, key=jax.random.key(0), restarts=0)
    assert not isinstance(err.value, InputError)
    assert str(err.value) == "gp.fit: restarts must be >= 1, got 0"
    with pytest.raises(InputError) as err:
        fit_gp(x, y, jax.random.key(0), dataclasses.replace(TrainConfig(), restarts=0), None, "c", 8)
    assert str(err.value) == "gp.fit: restarts must be >= 1, got 0"
    with pytest.raises(InputError) as err:  # constant targets: no optimisation, then the sparse form
        fit_gp(x, y, jax.random.key(0), TrainConfig(restarts=1), None, "c", 0)
    assert str(err.value).startswith("GP.sparse: n_inducing and n_variance must be >= 1, got 0,")


def test_sparse_mean_on_many_points_variance_on_the_first_few():
    """``sparse(M, Mv)``: the mean is DTC on M points (the exact GP's when M covers the training set);
    the variance is DTC on the first Mv pivots, i.e. that of ``sparse(Mv)``."""
    rng = np.random.default_rng(13)
    x = rng.uniform(-3, 3, (70, 3))
    y = np.sin(x[:, 0]) + 0.3 * x[:, 1] * x[:, 2] + 0.05 * rng.normal(size=70)
    g = gp.fit(x, y, key=jax.random.key(7), restarts=2)
    xs = jnp.asarray(rng.uniform(-3, 3, (20, 3)))
    mean, _ = g.predict(xs)

    whole = g.sparse(100, n_variance=12)  # M capped at N = 70: every training point, exact mean
    assert whole.z.shape == (70, 3) and whole.n_variance == 12
    m_w, v_w = whole.predict(xs)
    np.testing.assert_allclose(np.asarray(m_w), np.asarray(mean), atol=1e-8)
    _, v_12 = g.sparse(12).predict(xs)
    np.testing.assert_allclose(np.asarray(v_w), np.asarray(v_12), rtol=1e-8, atol=1e-10)

    part = g.sparse(40, n_variance=12)
    m_p, v_p = part.predict(xs)
    m_40, _ = g.sparse(40).predict(xs)
    np.testing.assert_allclose(np.asarray(m_p), np.asarray(m_40), atol=1e-8)
    np.testing.assert_allclose(np.asarray(v_p), np.asarray(v_12), rtol=1e-8, atol=1e-10)


# ------------------------------------------------------------------------------ one kernel, k outputs


def _lml_numpy(log_ls, sf2, sn2, jitter, x, y):
    """Eq 5 written out in NumPy (pairwise differences, a dense solve and slogdet)."""
    d = (x[:, None, :] - x[None, :, :]) / np.exp(log_ls)
    k = sf2 * np.exp(-0.5 * np.sum(d * d, -1)) + (sn2 + jitter * sf2) * np.eye(len(x))
    _, logdet = np.linalg.slogdet(k)
    return -0.5 * y @ np.linalg.solve(k, y) - 0.5 * logdet - 0.5 * len(x) * np.log(2 * np.pi)


def _three_outputs(rng, n=70):
    x = rng.uniform(-2, 2, (n, 3))
    y = np.stack([np.sin(x[:, 0]) + 0.3 * x[:, 1], 3.0 * np.cos(x[:, 1]) * x[:, 2], 0.2 * x[:, 0] * x[:, 2]], 1)
    return x, y + rng.normal(size=y.shape) * np.array([0.05, 0.3, 0.02])


def test_fit_shared_finds_a_maximum_of_the_summed_lml():
    """The shared fit's GPs share the length scales and differ in signal and noise; at the fitted
    hyperparameters the sum of the outputs' LMLs, computed by plain NumPy, is a maximum: moving any
    one hyperparameter (a shared length scale, an output's signal or noise) lowers it."""
    rng = np.random.default_rng(21)
    x, y = _three_outputs(rng)
    gps = gp.fit_shared(x, y, key=jax.random.key(2), restarts=2)
    assert len(gps) == 3
    ls = np.asarray(gps[0].params.log_lengthscale)
    for g in gps[1:]:
        np.testing.assert_array_equal(np.asarray(g.params.log_lengthscale), ls)
        np.testing.assert_array_equal(np.asarray(g.x), np.asarray(gps[0].x))
    sf = np.array([float(g.params.log_signal_var) for g in gps])
    sn = np.array([float(g.params.log_noise_var) for g in gps])
    assert np.ptp(sn) > 1.0  # the outputs' noise levels differ by e^2 and more: not forced equal
    xs, ys, jit = np.asarray(gps[0].x), [np.asarray(g.y) for g in gps], float(gps[0].jitter)

    def total(ls, sf, sn):
        return sum(_lml_numpy(ls, np.exp(sf[j]), np.exp(sn[j]), jit, xs, ys[j]) for j in range(3))

    best = total(ls, sf, sn)
    for j in range(3):  # each GP's own LML is the NumPy one
        np.testing.assert_allclose(float(gps[j].log_marginal_likelihood()),
                                   _lml_numpy(ls, np.exp(sf[j]), np.exp(sn[j]), jit, xs, ys[j]), rtol=1e-8)
    for vec, i in [(0, i) for i in range(3)] + [(1, j) for j in range(3)] + [(2, j) for j in range(3)]:
        for step in (-0.05, 0.05):
            args = [ls.copy(), sf.copy(), sn.copy()]
            args[vec][i] += step
            assert total(*args) < best + 1e-6 * abs(best), (vec, i, step)


def test_fit_shared_of_one_output_is_fit():
    rng = np.random.default_rng(22)
    x, y = _three_outputs(rng, 50)
    (one,) = gp.fit_shared(x, y[:, :1], key=jax.random.key(3), restarts=2)
    ref = gp.fit(x, y[:, 0], key=jax.random.key(3), restarts=2)
    # a feature the fit finds irrelevant ends on a flat stretch of the LML (log l of about 19, where
    # W = exp(-2 log l) is 1e-17) wherever rounding stops it: compare W there, not log l
    np.testing.assert_allclose(np.asarray(one.params.w), np.asarray(ref.params.w), rtol=1e-6, atol=1e-12)
    same_w = eqx.tree_at(lambda g: g.params.log_lengthscale, one, ref.params.log_lengthscale)
    for a, b in zip(jax.tree.leaves(same_w), jax.tree.leaves(ref), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-9)


def test_shared_sparse_predicts_what_each_outputs_own_predictor_does():
    """One kernel row for all outputs (``SharedSparseGP``) gives each output's own DTC prediction
    (``GP.sparse``), exact means when the inducing points cover the data; ``output(j)`` is output j
    as a ``SparseGP``; GPs fitted one by one are refused."""
    rng = np.random.default_rng(23)
    x, y = _three_outputs(rng, 60)
    gps = gp.fit_shared(x, y, key=jax.random.key(4), restarts=1)
    xs = jnp.asarray(rng.uniform(-2.5, 2.5, (9, 3)))
    for m, mv in ((60, 60), (60, 12), (25, 8)):
        sh = gp.SharedSparseGP.build(gps, m, mv)
        mean, var = jax.jit(lambda v, sh=sh: sh.predict(v, include_noise=True))(xs)
        mean_only = sh.predict_mean(xs)
        for j, g in enumerate(gps):
            want_m, want_v = g.sparse(m, mv).predict(xs, include_noise=True)
            scale = float(g.params.signal_var)
            np.testing.assert_allclose(np.asarray(mean[j]), np.asarray(want_m), atol=1e-8 * scale**0.5)
            np.testing.assert_allclose(np.asarray(mean_only[j]), np.asarray(want_m), atol=1e-8 * scale**0.5)
            np.testing.assert_allclose(np.asarray(var[j]), np.asarray(want_v), rtol=1e-7, atol=1e-10 * scale)
            one_m, one_v = sh.output(j).predict(xs, include_noise=True)
            np.testing.assert_allclose(np.asarray(one_m), np.asarray(want_m), atol=1e-8 * scale**0.5)
            np.testing.assert_allclose(np.asarray(one_v), np.asarray(want_v), rtol=1e-7, atol=1e-10 * scale)
            if m == 60:
                exact_m, _ = g.predict(xs)
                np.testing.assert_allclose(np.asarray(mean[j]), np.asarray(exact_m), atol=1e-7 * scale**0.5)
    m32, v32 = gp.SharedSparseGP.build(gps, 25, 8).astype(jnp.float32).predict(xs.astype(jnp.float32))
    assert m32.dtype == v32.dtype == jnp.float32 and m32.shape == v32.shape == (3, 9)
    apart = [gp.fit(x, y[:, j], key=jax.random.key(j), restarts=1) for j in range(2)]
    with pytest.raises(gp.GPArgumentError, match="share one kernel"):
        gp.SharedSparseGP.build(apart, 20, 8)


def test_starts_vmapped_end_where_they_end_one_by_one(monkeypatch):
    """The starts run as one vmapped BFGS (below ``VMAP_MAX_ROWS`` on a CPU) or one after another: each
    start reaches the same optimum either way, every one within ``max_steps`` (vmapped, a plain
    Armijo search rejected every step at the optimum and ran to the cap), and ``fit`` keeps the same
    GP."""
    import importlib

    fit_module = importlib.import_module("gtsjax.gp.fit")
    x, y = _friedman3(np.random.default_rng(31))
    data = fit_module._standardised(x[:80], y[:80])
    xp, yp, mp = fit_module._padded(data.x, data.y, 80)
    starts = fit_module._initial_params(jax.random.key(5), 4, x.shape[1], data.y_var)
    args = (xp, yp, mp, jnp.asarray(1e-8), jnp.asarray(1.0), 1e-6, 1e-6, 1e-6, 1000)
    p_all, f_all, n_all = fit_module._optimise(starts, *args)
    for i in range(4):
        p_one, f_one, n_one = fit_module._optimise(fit_module._one(fit_module._row(starts, i)), *args)
        assert np.isfinite(float(f_one[0])) and np.isfinite(float(f_all[i]))
        assert int(n_all[i]) < 1000 and int(n_one[0]) < 1000
        np.testing.assert_allclose(float(f_all[i]), float(f_one[0]), rtol=1e-6)
    fits = []
    for rows in (10**6, 0):
        monkeypatch.setattr(fit_module, "VMAP_MAX_ROWS", rows)
        fits.append(gp.fit(x[:80], y[:80], key=jax.random.key(5), restarts=4))
    np.testing.assert_allclose(float(fits[0].log_marginal_likelihood()), float(fits[1].log_marginal_likelihood()),
                               rtol=1e-7)


def test_gradient_stop_ends_where_the_cauchy_test_ends():
    """``gtol``: BFGS stops at a first-order optimum (every gradient component of -LML/N at most
    ``gtol``) instead of waiting for every parameter to stop drifting. Against the same starts run to
    Optimistix's Cauchy test alone (``gtol`` 0): every start ends at the same LML to 0.001 nats, in at
    most as many steps, and its gradient there is at most ``gtol`` or the Cauchy test stopped it."""
    import importlib

    fit_module = importlib.import_module("gtsjax.gp.fit")
    x, y = _friedman3(np.random.default_rng(32))
    n = len(y)
    data = fit_module._standardised(x, y)
    xp, yp, mp = fit_module._padded(data.x, data.y, n)
    starts = fit_module._initial_params(jax.random.key(6), 4, x.shape[1], data.y_var)
    common = (xp, yp, mp, jnp.asarray(1e-8), jnp.asarray(1.0), 1e-6, 1e-6)
    p_g, f_g, n_g = fit_module._optimise(starts, *common, 1e-6, 1000)
    p_c, f_c, n_c = fit_module._optimise(starts, *common, 0.0, 1000)
    np.testing.assert_allclose(np.asarray(f_g) * n, np.asarray(f_c) * n, rtol=0, atol=1e-3)
    assert np.all(np.asarray(n_g) <= np.asarray(n_c)) and np.any(np.asarray(n_g) < np.asarray(n_c))
    grad = jax.grad(fit_module._neg_lml_per_point)
    for i in range(4):
        g = grad(fit_module._row(p_g, i), (xp, yp, mp, jnp.asarray(1e-8), jnp.asarray(1.0)))
        at_optimum = max(float(jnp.max(jnp.abs(a))) for a in jax.tree.leaves(g)) <= 1e-6
        assert at_optimum or int(n_g[i]) == int(n_c[i])
