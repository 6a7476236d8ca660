"""Stage e: the variance calibration of the pose regressors and pose regression on the best candidates."""

import jax
import jax.numpy as jnp
import numpy as np

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
