"""Training the tag reader (``gtsjax.train.tags``): the band's arc table from a learnt outline's
distance field against the polygon's own (``arc_table`` of the simulator's outline), and the intensity
model against scikit-learn's least squares on returns drawn here."""

import numpy as np
from sklearn.linear_model import LinearRegression

from gtsjax.core.e_tags import arc_table
from gtsjax.sim.scene import BOX_OUTLINE, NAO_OUTLINE
from gtsjax.train.outline import distance_field, outline_radii
from gtsjax.train.tags import arc_from_field, fit_intensity


def _edge_points(vertices, n=4000, seed=0):
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, float)
    i = rng.integers(len(v), size=n)
    u = rng.random(n)[:, None]
    return v[i] + u * (np.roll(v, -1, axis=0)[i] - v[i])


def test_arc_from_a_learnt_outline_is_the_polygons():
    for outline in (NAO_OUTLINE, BOX_OUTLINE):
        field, lo, cell = distance_field(outline_radii(_edge_points(outline)))
        got = arc_from_field(field, lo, cell)
        want = arc_table(outline)
        diff = np.abs((got - want + 0.5) % 1.0 - 0.5)
        assert np.median(diff) < 0.01 and diff.max() < 0.04  # the learnt outline's corners are rounded


def test_intensity_model_is_least_squares():
    rng = np.random.default_rng(4)
    n = 3000
    r = rng.uniform(1.0, 9.0, n)
    tape = rng.random(n) < 0.4
    logi = np.where(tape, np.log(15000.0), np.log(3000.0)) - 0.5 * np.log(r) + rng.normal(0, 0.2, n)
    fitted, beta, mt, st, mb, sb = fit_intensity(np.exp(logi), r, tape)
    X = np.stack([tape, ~tape, -np.log(r)], -1).astype(float)
    ref = LinearRegression(fit_intercept=False).fit(X, logi)
    np.testing.assert_allclose(fitted, ref.coef_[2], rtol=1e-6)
    assert beta == fitted  # inside the sanity range
    u = logi + beta * np.log(r)
    np.testing.assert_allclose([mt, st, mb, sb], [u[tape].mean(), u[tape].std(), u[~tape].mean(), u[~tape].std()],
                               rtol=1e-6)
    assert abs(fitted - 0.5) < 0.05
