"""Stage e: the variance calibration of the pose regressors and pose regression on the best candidates."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax import gp
from gtsjax.core.e_pose import PoseRegressor, regress, regress_one_class
from gtsjax.train.calibrate import calibrate
from tests._utils import assert_allclose


def _regressor(rng):
    x = rng.uniform(-2, 2, (80, 2))
    th = 0.8 * x[:, 0]
    noise = 0.03 * rng.normal(size=(4, len(x)))  # noisy targets: predictive variances well above rounding
    fits = [gp.fit(x, t + e, key=jax.random.key(i), restarts=1)
            for i, (t, e) in enumerate(zip([0.1 * x[:, 0], 0.05 * x[:, 1], np.sin(th), np.cos(th)], noise, strict=True))]
    return PoseRegressor(*[f.sparse(80, 20).astype(jnp.float32) for f in fits]), x


def test_calibration_recovers_a_known_variance_factor_despite_misreads():
    rng = np.random.default_rng(0)
    reg, _ = _regressor(rng)
    xs = rng.uniform(-2, 2, (4000, 2)).astype(np.float32)
    rel, var = map(np.asarray, regress_one_class(reg, jnp.asarray(xs)))
    factor = np.array([4.0, 0.25, 9.0])
    target = rel + rng.normal(size=rel.shape) * np.sqrt(factor * var)
    misread = rng.uniform(size=len(xs)) < 0.1  # a side of the robot seen as another: heading off by π
    target[misread, 2] += np.pi
    cal = calibrate(reg, xs, target)
    np.testing.assert_allclose(np.asarray(cal.var_scale), factor, rtol=0.08)
    _, var_cal = regress_one_class(cal, jnp.asarray(xs[:50]))
    expected = np.minimum(var[:50] * np.asarray(cal.var_scale), [np.inf, np.inf, np.pi**2 / 3])
    np.testing.assert_allclose(np.asarray(var_cal), expected, rtol=1e-2)  # float32 DTC variance: rounding


def test_only_the_best_candidates_of_a_mobile_class_get_a_pose():
    rng = np.random.default_rng(1)
    reg, _ = _regressor(rng)
    n = 12
    xs = jnp.asarray(rng.uniform(-2, 2, (n, 2)), jnp.float32)
    cls = jnp.asarray([1] * 10 + [0, 1], jnp.int32)
    ok = jnp.asarray([True] * 9 + [False, True, True])
    scores = jnp.asarray(np.column_stack([np.zeros(n), rng.uniform(0.5, 1, n)]), jnp.float32)
    rel, var, posed = regress((None, reg), xs, cls, ok, scores, max_objects=4, max_landmarks=4)
    rel, var, posed = map(np.asarray, (rel, var, posed))
    eligible = np.flatnonzero(np.asarray(ok & (cls == 1)))
    best = eligible[np.argsort(-np.asarray(scores)[eligible, 1])[:4]]
    assert set(np.flatnonzero(posed)) == set(best.tolist())
    ref_rel, ref_var = map(np.asarray, regress_one_class(reg, xs[best]))
    assert_allclose(rel[best], ref_rel)
    np.testing.assert_allclose(var[best], ref_var, rtol=1e-5, atol=1e-9)
    assert np.all(rel[~posed] == 0) and np.all(var[~posed] == 0)


def test_bucketed_regression_equals_regression_of_every_slot():
    """However many candidates a scan holds (none, one, a bucket's worth, one past it, all), the
    bucketed pose regression gives the poses that regressing every slot gives, and zeros elsewhere."""
    from gtsjax.core.buckets import sizes

    assert sizes(8) == (1, 2, 4, 8) and sizes(14) == (1, 2, 4, 8, 14) and sizes(1) == (1,)
    rng = np.random.default_rng(2)
    reg, _ = _regressor(rng)
    n = 16
    xs = jnp.asarray(rng.uniform(-2, 2, (n, 2)), jnp.float32)
    scores = jnp.asarray(np.column_stack([np.zeros(n), rng.uniform(0.5, 1, n)]), jnp.float32)
    cls = jnp.ones(n, jnp.int32)
    f = jax.jit(lambda ok, bucket: regress((None, reg), xs, cls, ok, scores, 8, 8, bucket), static_argnums=1)
    for present in (0, 1, 2, 3, 4, 5, 8, 12):
        ok = jnp.asarray(np.arange(n) < present)
        a = [np.asarray(v) for v in f(ok, True)]
        b = [np.asarray(v) for v in f(ok, False)]
        np.testing.assert_array_equal(a[2], b[2])
        # float32 matrix products of another shape round differently (the kernel's |a|² + |b|² − 2a·b)
        np.testing.assert_allclose(a[0], b[0], rtol=1e-3, atol=1e-5)
        np.testing.assert_allclose(a[1], b[1], rtol=5e-3, atol=1e-7)  # the DTC variance: a difference of sums
        assert a[2].sum() == min(present, 8)


@pytest.mark.parametrize("groups", [((0, 1, 2, 3),), ((0, 1), (2, 3))])
def test_shared_kernel_rows_pose_as_the_separate_gps_do(groups):
    """A class's pose GPs fitted in groups of one kernel (``PoseRegressor.shared``: one kernel row per
    candidate and group) give the poses and variances of the same GPs held one by one (``outputs()``,
    the layout of models trained before), through stage e's regression of the best candidates."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-2, 2, (80, 2))
    th = 0.8 * x[:, 0]
    y = np.stack([0.1 * x[:, 0], 0.05 * x[:, 1], np.sin(th), np.cos(th)], 1) + 0.03 * rng.normal(size=(80, 4))
    shared = tuple(gp.SharedSparseGP.build(gp.fit_shared(x, y[:, list(g)], key=jax.random.key(i), restarts=1), 80, 20)
                   for i, g in enumerate(groups))
    one = PoseRegressor(shared=tuple(g.astype(jnp.float32) for g in shared),
                        var_scale=jnp.asarray([2.0, 3.0, 4.0], jnp.float32))
    apart = PoseRegressor(*one.outputs(), var_scale=one.var_scale)
    assert one.has_heading and apart.has_heading and apart.shared is None
    assert one.n_kernel_rows == len(groups) and apart.n_kernel_rows == 4
    xs = jnp.asarray(rng.uniform(-2, 2, (10, 2)), jnp.float32)
    a, b = regress_one_class(one, xs), regress_one_class(apart, xs)
    # Each float32 form against the float64 one (the two round differently, each about 5e-5 off: the
    # exact mean's weights run to 1e2, and float32 sums of their products cancel).
    want = regress_one_class(eqx.tree_at(lambda r: r.shared, one, shared), xs.astype(jnp.float64))
    for got in (a, b):
        np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), atol=3e-4)
        # the DTC variance is σf² less a sum plus a sum: in float32 the heading's is good to about 1 %
        np.testing.assert_allclose(np.asarray(got[1]), np.asarray(want[1]), rtol=2e-2, atol=1e-8)
    scores = jnp.asarray(np.column_stack([np.zeros(10), rng.uniform(0.5, 1, 10)]), jnp.float32)
    ok, cls = jnp.ones(10, bool), jnp.ones(10, jnp.int32)
    ra = regress((None, one), xs, cls, ok, scores, 4, 4)
    rb = regress((None, apart), xs, cls, ok, scores, 4, 4)
    np.testing.assert_array_equal(np.asarray(ra[2]), np.asarray(rb[2]))
    np.testing.assert_allclose(np.asarray(ra[0]), np.asarray(rb[0]), atol=6e-4)


def test_pose_gps_over_one_training_set_read_their_inputs_once():
    """Separate pose GPs each over all of one training set (their inducing rows the same, in each
    GP's own pivot order) as one ``CommonInputsGP``: every output's mean as close to a float64 NumPy
    sum over the GP's own rows as the GP's own float32 prediction is, and its variance that of its own
    ``SparseGP``; and GPs whose inducing rows differ are left apart."""
    from gtsjax.gp.sparse import CommonInputsGP, predict_many

    rng = np.random.default_rng(3)
    reg, x = _regressor(rng)
    gps = reg.outputs()
    assert not all(np.array_equal(np.asarray(g.z), np.asarray(gps[0].z)) for g in gps)  # orders differ
    common = CommonInputsGP.of(gps)
    assert common is not None and common.z.shape == gps[0].z.shape
    xs = jnp.asarray(rng.uniform(-2.5, 2.5, (7, 2)), jnp.float32)
    want_m, want_v = predict_many(gps, xs, include_noise=True)
    got_m, got_v = common.predict(xs, include_noise=True)
    assert_allclose(got_v, want_v, rtol=1e-3, atol=1e-5)  # s − ‖t₁‖² + ‖t₂‖²: float32 cancellation
    assert_allclose(common.predict_mean(xs), got_m, rtol=1e-6, atol=1e-7)
    for j, g in enumerate(gps):  # the mean in float64, over the GP's own rows in its own order
        z = np.asarray(g.z, np.float64)
        xst = (np.asarray(xs, np.float64) - np.asarray(g.x_mean, np.float64)) / np.asarray(g.x_scale, np.float64)
        ell = np.exp(np.asarray(g.params.log_lengthscale, np.float64))
        k = np.exp(float(g.params.log_signal_var)) * np.exp(-0.5 * (((xst[:, None] - z[None]) / ell) ** 2).sum(-1))
        ref = k @ np.asarray(g.weights, np.float64) + float(g.y_mean)
        own = np.abs(np.asarray(want_m[j], np.float64) - ref).max()  # the GP's own float32 rounding
        assert np.abs(np.asarray(got_m[j], np.float64) - ref).max() <= 2 * own + 1e-6
    # The regressor uses it once made, with the same poses and variances to that rounding.
    both = reg.with_common_inputs()
    assert both.common is not None and reg.common is None
    for a, b in zip(regress_one_class(both, xs), regress_one_class(reg, xs), strict=True):
        assert_allclose(a, b, rtol=1e-3, atol=5e-4)
    # Inducing rows that are not one set: left apart.
    fit = gp.fit(x, 0.1 * x[:, 0], key=jax.random.key(9), restarts=1)
    assert CommonInputsGP.of((gps[0], fit.sparse(40, 20).astype(jnp.float32))) is None
    assert PoseRegressor(gps[0], fit.sparse(40, 20).astype(jnp.float32)).with_common_inputs().common is None


def test_a_class_alike_turned_half_a_turn_reads_its_heading_modulo_pi():
    """Heading GPs on ``(sin 2θ̃, cos 2θ̃)`` (``turns`` 2, a rectangular base): the read is θ̃ modulo π, half
    the angle the same GPs give read as ``(sin θ̃, cos θ̃)``, with a quarter of its variance; it follows the
    true heading modulo π, and calibration does not charge a read for the half-turn it cannot tell."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-2, 2, (80, 2))
    th = 1.4 * x[:, 0]  # headings over ±160°: the same view for θ and θ + π
    noise = 0.03 * rng.normal(size=(4, len(x)))
    fits = [gp.fit(x, t + e, key=jax.random.key(10 + i), restarts=1)
            for i, (t, e) in enumerate(zip([0.1 * x[:, 0], 0.05 * x[:, 1], np.sin(2 * th), np.cos(2 * th)], noise,
                                           strict=True))]
    plain = PoseRegressor(*[f.sparse(80, 20).astype(jnp.float32) for f in fits])
    half = eqx.tree_at(lambda r: r.turns, plain, jnp.asarray(2, jnp.int32), is_leaf=lambda v: v is None)
    xs = rng.uniform(-1.9, 1.9, (400, 2)).astype(np.float32)
    rel_p, var_p = map(np.asarray, regress_one_class(plain, jnp.asarray(xs)))
    rel_h, var_h = map(np.asarray, regress_one_class(half, jnp.asarray(xs)))
    np.testing.assert_allclose(rel_h[:, 2], rel_p[:, 2] / 2, atol=1e-6)
    below = var_p[:, 2] < np.pi**2 / 3 - 1e-6  # the cap (no information) applies after the quarter
    assert below.mean() > 0.9
    np.testing.assert_allclose(var_h[below, 2], var_p[below, 2] / 4, rtol=1e-5)
    np.testing.assert_array_equal(rel_h[:, :2], rel_p[:, :2])
    truth = 1.4 * xs[:, 0]
    off = np.angle(np.exp(2j * (rel_h[:, 2] - truth))) / 2  # modulo π, by hand
    assert np.degrees(np.sqrt(np.mean(off**2))) < 3.0
    # Held-out targets with the truth's heading, a third of them given as the other half-turn: the
    # same calibration either way (modulo π), where a class without the symmetry would be charged for it.
    target = np.stack([0.1 * xs[:, 0], 0.05 * xs[:, 1], truth], -1) + 0.02 * rng.normal(size=(len(xs), 3))
    flipped = target.copy()
    flipped[rng.uniform(size=len(xs)) < 0.33, 2] += np.pi
    np.testing.assert_allclose(np.asarray(calibrate(half, xs, flipped).var_scale),
                               np.asarray(calibrate(half, xs, target).var_scale), rtol=1e-5)
