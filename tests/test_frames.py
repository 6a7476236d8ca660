"""The one geometry module (``gtsjax.core.geometry``): wrap, rotations, ORS ↔ S ↔ O and the bounds test,
each against an obvious second implementation (complex numbers, ``np.linalg``), on NumPy and on JAX
inputs (the same function serves the jitted step and the host)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.core.geometry import (
    affine_heading,
    compose,
    field_to_sensor,
    in_bounds,
    relative,
    rot,
    sensor_pose,
    sensor_to_field,
    wrap,
)

RNG = np.random.default_rng(7)


def test_wrap_half_open_interval_on_numpy_and_jax():
    a = np.array([np.pi, -np.pi, 3 * np.pi, 0.1, -0.1 - 2 * np.pi, 7.0])
    w = wrap(a)
    assert isinstance(w, np.ndarray) and w.dtype == np.float64
    np.testing.assert_allclose(w, [np.pi, np.pi, np.pi, 0.1, -0.1, 7.0 - 2 * np.pi], atol=1e-12)
    wj = wrap(jnp.asarray(a, jnp.float32))
    assert isinstance(wj, jax.Array)
    np.testing.assert_allclose(np.asarray(wj), w, atol=1e-5)
    b = RNG.uniform(-20, 20, 1000)
    np.testing.assert_allclose(np.exp(1j * wrap(b)), np.exp(1j * b), atol=1e-12)  # same angle
    assert np.all((wrap(b) > -np.pi) & (wrap(b) <= np.pi))


def test_rot_is_multiplication_by_a_unit_complex_number():
    th = RNG.uniform(-4, 4, (5, 3))
    p = RNG.normal(size=(5, 3, 2))
    got = np.einsum("...ij,...j->...i", rot(th), p)
    want = (p[..., 0] + 1j * p[..., 1]) * np.exp(1j * th)
    np.testing.assert_allclose(got[..., 0] + 1j * got[..., 1], want, atol=1e-12)


@pytest.mark.parametrize("xp", [np, jnp])
def test_compose_and_relative_are_inverse_and_match_complex_numbers(xp):
    frame = RNG.normal(size=(50, 3)) * [2, 2, 3]
    rel = RNG.normal(size=(50, 3)) * [0.3, 0.3, 2]
    dtype = np.float64 if xp is np else np.float32
    p = compose(xp.asarray(frame, dtype), xp.asarray(rel, dtype))
    z = (frame[:, 0] + 1j * frame[:, 1]) + (rel[:, 0] + 1j * rel[:, 1]) * np.exp(1j * frame[:, 2])
    tol = 1e-12 if xp is np else 2e-5
    np.testing.assert_allclose(np.asarray(p[:, 0]) + 1j * np.asarray(p[:, 1]), z, atol=tol * 10)
    np.testing.assert_allclose(np.asarray(p[:, 2]), frame[:, 2] + rel[:, 2], atol=tol * 10)
    back = np.asarray(relative(xp.asarray(frame, dtype), p))
    np.testing.assert_allclose(back[:, :2], rel[:, :2], atol=tol * 20)
    np.testing.assert_allclose(np.exp(1j * back[:, 2]), np.exp(1j * rel[:, 2]), atol=tol * 20)
    assert np.all(np.abs(back[:, 2]) <= np.pi)
    pts = np.asarray(relative(xp.asarray(frame, dtype), p[:, :2]))  # a point: no heading
    assert pts.shape == (50, 2)


@pytest.mark.parametrize("xp", [np, jnp])
def test_affine_map_and_its_inverse_against_linalg(xp):
    A = np.stack([rot(t) for t in RNG.uniform(-3, 3, 8)]) * RNG.uniform(0.95, 1.05, (8, 1, 1))
    A[:, 0, 1] += 0.02  # a shear, as a tilted scan plane gives
    mu_s, mu_o, p = RNG.normal(size=(8, 2)), RNG.normal(size=(8, 2)), RNG.normal(size=(8, 5, 2))
    dtype = np.float64 if xp is np else np.float32
    args = [xp.asarray(a, dtype) for a in (A[:, None], mu_s[:, None], mu_o[:, None])]
    o = sensor_to_field(*args, xp.asarray(p, dtype))
    want = mu_o[:, None] + np.einsum("tij,tnj->tni", A, p - mu_s[:, None])
    tol = 1e-12 if xp is np else 1e-5
    np.testing.assert_allclose(np.asarray(o), want, atol=tol)
    s = field_to_sensor(*args, xp.asarray(want, dtype))
    np.testing.assert_allclose(np.asarray(s), np.linalg.solve(A[:, None], (want - mu_o[:, None])[..., None])[..., 0]
                               + mu_s[:, None], atol=tol * 10)
    np.testing.assert_allclose(np.asarray(s), p, atol=tol * 10)
    sp = np.asarray(sensor_pose(*(xp.asarray(a, dtype) for a in (A, mu_s, mu_o))))
    np.testing.assert_allclose(sp[:, :2], mu_o - np.einsum("tij,tj->ti", A, mu_s), atol=tol * 10)
    np.testing.assert_allclose(sp[:, 2], np.arctan2(A[:, 1, 0], A[:, 0, 0]), atol=tol)
    np.testing.assert_allclose(np.asarray(affine_heading(xp.asarray(A, dtype))), sp[:, 2], atol=tol)


def test_in_bounds_edges_inside_nan_outside_margin_grows():
    xy = np.array([[1.0, 1.0], [6.6, 1.0], [0.0, 4.0], [np.nan, 1.0], [-0.4, 2.0]])
    b = np.array([0.0, 0.0, 6.0, 4.0])
    np.testing.assert_array_equal(in_bounds(xy, b), [True, False, True, False, False])
    np.testing.assert_array_equal(in_bounds(xy, b, 0.5), [True, False, True, False, True])
    np.testing.assert_array_equal(np.asarray(in_bounds(jnp.asarray(xy), jnp.asarray(b))), in_bounds(xy, b))
