"""Motion as evidence of the heading (issue 55, lever 2): what training learns of a class's heading
against its direction of travel, on labels built here by hand (a robot that walks ahead, one that
crabs at a fixed angle, one that travels any way, one turned on the spot), and the tracker's evidence
from a moving track, each against a second, obvious computation (SciPy's maximum likelihood, a loop
over tracks and hypotheses with SciPy's Bessel function)."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import optimize, special

from gtsjax.core.g_heading import _MOTION_MIN_SPEED, _MOTION_S, motion_evidence
from gtsjax.core.g_track import TrackerParams, TrackerState
from gtsjax.train import bounds as B
from gtsjax.train.motion import fit_von_mises_uniform, motion_heading, travel_offsets
from tests.test_train_limits import _log, turned_on_the_spot


def _mixture_nll(params, d):
    mu, log_kappa, logit_u = params
    kappa, u = math.exp(log_kappa), 1.0 / (1.0 + math.exp(-logit_u))
    vm = np.exp(kappa * np.cos(d - mu)) / (2 * np.pi * special.i0(kappa))
    return -np.sum(np.log((1 - u) * vm + u / (2 * np.pi)))


@pytest.mark.parametrize(("mu", "kappa", "u"), [(0.0, 30.0, 0.2), (2.5, 8.0, 0.05), (-1.0, 200.0, 0.4)])
def test_the_em_fit_is_the_maximum_likelihood(mu, kappa, u):
    rng = np.random.default_rng(3)
    n = 3000
    d = np.where(rng.random(n) < u, rng.uniform(-np.pi, np.pi, n), rng.vonmises(mu, kappa, n))
    got = fit_von_mises_uniform(d)
    ref = optimize.minimize(_mixture_nll, [got[0] + 0.05, math.log(got[1]) + 0.2, math.log(got[2] / (1 - got[2])) - 0.2],
                            args=(d,), method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 4000})
    r_mu, r_kappa, r_u = ref.x[0], math.exp(ref.x[1]), 1 / (1 + math.exp(-ref.x[2]))
    assert _mixture_nll([got[0], math.log(got[1]), math.log(got[2] / (1 - got[2]))], d) <= ref.fun + 0.05
    assert abs(math.remainder(got[0] - r_mu, 2 * math.pi)) < 0.01
    assert got[1] == pytest.approx(r_kappa, rel=0.03) and got[2] == pytest.approx(r_u, abs=0.01)
    assert abs(math.remainder(got[0] - mu, 2 * math.pi)) < 0.05 and got[2] == pytest.approx(u, abs=0.04)


def _walk(offset_deg: float, speed=0.3, period=0.1, seconds=60.0, seed=0, jitter=0.003):
    """A robot walking a circle of 1.5 m radius at ``speed``, its heading the direction of travel plus
    ``offset_deg`` (NaN: a fresh random heading each scan), with label jitter."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, seconds, period)
    a = speed * t / 1.5
    xy = np.column_stack([3 + 1.5 * np.cos(a), 2 + 1.5 * np.sin(a)]) + rng.normal(0, jitter, (t.size, 2))
    travel = a + np.pi / 2
    heading = rng.uniform(-np.pi, np.pi, t.size) if np.isnan(offset_deg) else travel + math.radians(offset_deg)
    return _log(np.column_stack([xy, np.angle(np.exp(1j * heading))]), period)


@pytest.mark.parametrize("offset", [0.0, 35.0, 180.0])
def test_the_offset_of_a_robot_that_walks_at_an_angle_is_learnt(offset):
    log = _walk(offset)
    d = travel_offsets([log], ("robot",), period=0.1)["robot"]
    # A window's chord is parallel to the tangent at its middle; the labels' 3 mm jitter over its 15 cm
    # turns it by about 1.6°.
    err = np.degrees(np.abs(np.angle(np.exp(1j * (d - math.radians(offset))))))
    assert d.size > 400 and np.median(err) < 1.5 and np.quantile(err, 0.95) < 4.0
    table, rows = motion_heading([log], ("background", "robot"), ("robot",), period=0.1)
    assert table[0].tolist() == [0.0, 0.0, 1.0]  # background: no evidence
    assert abs(math.remainder(table[1, 0] - math.radians(offset), 2 * math.pi)) < 0.02
    spread = {r["parameter"]: r for r in rows}[B.MOTION_SPREAD.what]
    assert "warning" not in spread, spread  # a holonomic robot's wide spread is plausible
    assert spread["source"] == "learnt" and spread["value"] == B.MOTION_SPREAD.floor  # steadier than a robot: held
    assert table[1, 1] == pytest.approx(1 / math.radians(B.MOTION_SPREAD.floor) ** 2)
    assert all(r["hard_range"][0] <= r["value"] <= r["hard_range"][1] for r in rows)


def test_a_robot_that_travels_any_way_learns_its_travel_says_little():
    table, rows = motion_heading([_walk(np.nan)], ("robot",), ("robot",), period=0.1)
    spread = {r["parameter"]: r for r in rows}[B.MOTION_SPREAD.what]
    assert "warning" not in spread, spread  # a holonomic robot's wide spread is plausible
    # Uniform offsets: a wide spread or almost all of it "other"; either way a weak likelihood.
    mu, kappa, u = table[0] if table is not None else (0.0, 0.0, 1.0)
    loglik = np.log((1 - u) * np.exp(kappa * (np.cos(np.linspace(-np.pi, np.pi, 73)) - 1)) / special.i0e(kappa) + u)
    assert np.ptp(loglik) < 0.5, (spread, table)


def test_a_robot_turned_on_the_spot_gives_no_evidence():
    table, rows = motion_heading([turned_on_the_spot()], ("background", "robot"), ("robot",), period=0.1)
    assert table is None
    (row,) = rows
    assert row["source"] == "default" and "no translation" in row["evidence"]
    assert "warning" not in row, row  # no evidence is no implausible value: training says nothing of it


def _tracks(v, cov_v, heading, class_id):
    m, s = len(v), heading.shape[1]
    state = TrackerState.empty(m, sides=s)
    mean = np.zeros((m, 6), np.float32)
    mean[:, 3:5] = v
    cov = np.tile(np.eye(6, dtype=np.float32), (m, 1, 1))
    cov[:, 3:5, 3:5] = cov_v
    logw = np.where(np.isnan(heading), -np.inf, math.log(1 / s)).astype(np.float32)
    return eqx.tree_at(lambda t: (t.mean, t.cov, t.class_id, t.side_heading, t.side_logw), state,
                       (jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(class_id, jnp.int32),
                        jnp.asarray(np.nan_to_num(heading), jnp.float32), jnp.asarray(logw)))


def test_motion_evidence_equals_a_loop_over_tracks_and_hypotheses():
    rng = np.random.default_rng(5)
    m, s = 7, 4
    v = rng.normal(0, 0.25, (m, 2))
    v[0] = [0.01, 0.02]  # slower than the floor: no evidence
    a = rng.normal(0, 0.05, (m, 2, 2))
    cov_v = a @ np.swapaxes(a, 1, 2) + 1e-4 * np.eye(2)
    heading = rng.uniform(-np.pi, np.pi, (m, s))
    heading[3, 2:] = np.nan  # unused hypotheses
    class_id = np.array([1, 1, 1, 1, 0, 2, 1])
    table = np.array([[0.0, 0.0, 1.0], [0.2, 60.0, 0.1], [math.pi, 5.0, 0.5]])
    params = eqx.tree_at(lambda p: p.motion_heading, TrackerParams.default([False, True, True]),
                         jnp.asarray(table, jnp.float32), is_leaf=lambda x: x is None)
    dt = 0.1
    got = np.asarray(motion_evidence(_tracks(v, cov_v, heading, class_id), params, jnp.float32(dt)))
    want = np.zeros((m, s))
    for i in range(m):
        mu, kappa, u = table[class_id[i]]
        speed = np.hypot(*v[i])
        if speed < _MOTION_MIN_SPEED or kappa == 0:
            continue
        across = np.array([-v[i, 1], v[i, 0]]) / speed
        var_dir = across @ cov_v[i] @ across / speed**2
        k = 1.0 / (1.0 / kappa + var_dir)
        for j in range(s):
            if np.isnan(heading[i, j]):
                continue
            vm = np.exp(k * np.cos(heading[i, j] - math.atan2(v[i, 1], v[i, 0]) - mu)) / (2 * np.pi * special.i0(k))
            want[i, j] = dt / _MOTION_S * math.log((1 - u) * 2 * np.pi * vm + u)
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert np.all(got[0] == 0) and np.all(got[4] == 0)  # too slow; a class that learnt nothing
    without = np.asarray(motion_evidence(_tracks(v, cov_v, heading, class_id), TrackerParams.default([False, True, True]),
                                         jnp.float32(dt)))
    assert np.all(without == 0)
