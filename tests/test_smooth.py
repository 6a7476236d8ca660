"""The fixed-interval smoother (``gtsjax.core.smooth``) against a NumPy RTS loop written here and
filterpy's ``rts_smoother``, on a constant-velocity track simulated and filtered in NumPy (float64),
its headings measured wrapped and crossing ±π: the sequential and the associative smoother give the
reference's smoothed means and covariances, segment by segment, in float64 and (looser) in float32."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

# filterpy is a test dependency (pyproject's ``test`` extra): imported, not skipped without it.
from filterpy.kalman import rts_smoother

from gtsjax.core.g_types import TrackerParams
from gtsjax.core.geometry import wrap
from gtsjax.core.smooth import rts_associative, rts_sequential, smooth_tracks
from tests._utils import assert_allclose

R = np.diag([0.03**2, 0.03**2, 0.08**2])
SMOOTHERS = {"sequential": rts_sequential, "associative": rts_associative}


def _params(cv: bool = True) -> TrackerParams:
    return TrackerParams.default(jnp.array([False, True]), constant_velocity=cv)


def _model(dt: float, params: TrackerParams):
    """``F``, ``Q`` in NumPy float64, written out from the motion model's definition (the tuning's
    float32 noise densities read exactly)."""
    qp, qt = float(params.q_pos), float(params.q_theta)
    q = np.array([qp, qp, qt])
    if bool(params.constant_velocity):
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        Q = np.block([[np.diag(q * dt**3 / 3), np.diag(q * dt**2 / 2)], [np.diag(q * dt**2 / 2), np.diag(q * dt)]])
    else:
        F = np.eye(6)
        Q = np.zeros((6, 6))
        Q[:3, :3] = np.diag(q * dt)
    return F, Q


def _simulate(T: int, params: TrackerParams, *, omega: float = 1.5, seed: int = 0):
    """A robot driven by the model's own process noise (unwrapped truth), irregular ``dt`` (``dt[0]``
    NaN: unused), and its wrapped pose measurements."""
    rng = np.random.default_rng(seed)
    dt = rng.uniform(0.07, 0.13, T)
    dt[0] = np.nan
    x = np.array([0.5, -1.0, 3.0, 0.3, -0.2, omega])
    truth = np.empty((T, 6))
    truth[0] = x
    cv_params = _params(True)  # the truth moves with velocity whatever model filters it
    for t in range(1, T):
        F, Q = _model(dt[t], cv_params)
        x = F @ x + rng.multivariate_normal(np.zeros(6), Q)
        truth[t] = x
    z = truth[:, :3] + rng.multivariate_normal(np.zeros(3), R, T)
    z[:, 2] = wrap(z[:, 2])
    return truth, dt, z


def _filter(z, dt, params: TrackerParams):
    """The forward EKF of one life in NumPy: heading innovation and state heading wrapped, Joseph
    form. Returns the filtered means and covariances."""
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    m = np.concatenate([z[0], np.zeros(3)])
    P = np.diag([R[0, 0], R[1, 1], R[2, 2], 0.25, 0.25, 4.0])
    ms, Ps = [m.copy()], [P.copy()]
    for t in range(1, len(z)):
        F, Q = _model(dt[t], params)
        m = F @ m
        m[2] = wrap(m[2])
        P = F @ P @ F.T + Q
        nu = z[t] - m[:3]
        nu[2] = wrap(nu[2])
        S = P[:3, :3] + R
        K = P[:, :3] @ np.linalg.inv(S)
        m = m + K @ nu
        m[2] = wrap(m[2])
        A = np.eye(6) - K @ H
        P = A @ P @ A.T + K @ R @ K.T
        P = 0.5 * (P + P.T)
        ms.append(m.copy())
        Ps.append(P.copy())
    return np.array(ms), np.array(Ps)


def _unwrap(theta):
    """A segment's headings made continuous by successive wrapped differences."""
    return theta[0] + np.concatenate([[0.0], np.cumsum(wrap(np.diff(theta)))])


def _rts_numpy(m, P, dt, params):
    """The RTS loop over one segment (headings unwrapped first, the result wrapped)."""
    m = m.copy()
    m[:, 2] = _unwrap(m[:, 2])
    ms, Ps = m.copy(), P.copy()
    for t in range(len(m) - 2, -1, -1):
        F, Q = _model(dt[t + 1], params)
        P_pred = F @ P[t] @ F.T + Q
        G = P[t] @ F.T @ np.linalg.inv(P_pred)
        ms[t] = m[t] + G @ (ms[t + 1] - F @ m[t])
        Ps[t] = P[t] + G @ (Ps[t + 1] - P_pred) @ G.T
    ms[:, 2] = wrap(ms[:, 2])
    return ms, Ps


def _rts_filterpy(m, P, dt, params):
    """filterpy's ``rts_smoother`` over one segment: its ``Fs[k]``, ``Qs[k]`` take step ``k`` to ``k + 1``."""
    m = m.copy()
    m[:, 2] = _unwrap(m[:, 2])
    models = [_model(dt[t + 1], params) for t in range(len(m) - 1)] + [(np.eye(6), np.zeros((6, 6)))]
    ms, Ps, _, _ = rts_smoother(m, P, [f for f, _ in models], [q for _, q in models])
    ms[:, 2] = wrap(ms[:, 2])
    return ms, Ps


def _two_lives(T=240, gap=(100, 117), params=None, seed=0, omega=1.5):
    """One slot holding two lives: filtered states of ``[0, gap[0])`` and ``[gap[1], T)``, NaN between;
    the truth, ``dt``, ``valid`` and the per-segment references (NumPy loop and filterpy)."""
    params = params or _params()
    truth, dt, z = _simulate(T, params, omega=omega, seed=seed)
    valid = np.ones(T, bool)
    valid[gap[0] : gap[1]] = False
    mean = np.full((T, 6), np.nan)
    cov = np.full((T, 6, 6), np.nan)
    ref_np, ref_fp = mean.copy(), mean.copy()
    ref_np_cov, ref_fp_cov = cov.copy(), cov.copy()
    for a, b in ((0, gap[0]), (gap[1], T)):
        mean[a:b], cov[a:b] = _filter(z[a:b], dt[a:b], params)
        ref_np[a:b], ref_np_cov[a:b] = _rts_numpy(mean[a:b], cov[a:b], dt[a:b], params)
        ref_fp[a:b], ref_fp_cov[a:b] = _rts_filterpy(mean[a:b], cov[a:b], dt[a:b], params)
    return dict(
        truth=truth,
        dt=dt,
        valid=valid,
        mean=mean,
        cov=cov,
        params=params,
        ref=(ref_np, ref_np_cov),
        filterpy=(ref_fp, ref_fp_cov),
    )


def _same_pose(actual, desired, **tol):
    """Means equal, headings compared modulo 2π (two wrapped values either side of ±π are one heading)."""
    actual, desired = np.array(actual, np.float64), np.array(desired, np.float64)
    d = wrap(actual[..., 2] - desired[..., 2])
    np.testing.assert_allclose(d, 0.0, atol=tol.get("atol", 1e-12) + tol.get("rtol", 1e-10) * np.pi)
    actual[..., 2] = desired[..., 2]
    assert_allclose(actual, desired, **tol)


def test_numpy_loop_and_filterpy_agree():
    """The two references are one smoother (the test's own loop checked against filterpy's)."""
    d = _two_lives()
    v = d["valid"]
    _same_pose(d["ref"][0][v], d["filterpy"][0][v])
    assert_allclose(d["ref"][1][v], d["filterpy"][1][v])


@pytest.mark.parametrize("cv", [True, False], ids=["constant-velocity", "inflate-only"])
@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_float64_matches_references(name, cv):
    d = _two_lives(params=_params(cv))
    f = jax.jit(SMOOTHERS[name])
    m, P = f(jnp.asarray(d["mean"]), jnp.asarray(d["cov"]), jnp.asarray(d["dt"]), jnp.asarray(d["valid"]), d["params"])
    assert m.dtype == jnp.float64 and P.dtype == jnp.float64
    v = d["valid"]
    for ref_m, ref_P in (d["ref"], d["filterpy"]):
        _same_pose(m[v], ref_m[v], rtol=1e-9, atol=1e-11)
        assert_allclose(P[v], ref_P[v], rtol=1e-9, atol=1e-13)
    # the steps between the lives come back as they went in (NaN here: nothing leaks out of them)
    assert np.all(np.isnan(np.asarray(m)[~v])) and np.all(np.isnan(np.asarray(P)[~v]))
    assert np.all(np.isfinite(np.asarray(m)[v])) and np.all(np.isfinite(np.asarray(P)[v]))


@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_float32_matches_references(name):
    """The step's precision: float32 in and out, held to what float32 keeps through the gains' solves."""
    d = _two_lives()
    f = jax.jit(SMOOTHERS[name])
    f32 = jnp.float32
    m, P = f(
        jnp.asarray(d["mean"], f32),
        jnp.asarray(d["cov"], f32),
        jnp.asarray(d["dt"], f32),
        jnp.asarray(d["valid"]),
        d["params"],
    )
    assert m.dtype == f32 and P.dtype == f32
    v = d["valid"]
    ref_m, ref_P = d["ref"]
    _same_pose(m[v], ref_m[v], rtol=1e-4, atol=2e-5)
    scale = np.max(np.abs(ref_P[v]), axis=(-2, -1), keepdims=True)
    np.testing.assert_allclose(np.asarray(P[v], np.float64) / scale, ref_P[v] / scale, atol=2e-4)


def test_sequential_and_associative_agree_in_float32():
    d = _two_lives(T=600, gap=(250, 262), seed=3)
    args = [jnp.asarray(d[k], jnp.float32) for k in ("mean", "cov", "dt")] + [jnp.asarray(d["valid"]), d["params"]]
    ms, Ps = jax.jit(rts_sequential)(*args)
    ma, Pa = jax.jit(rts_associative)(*args)
    v = d["valid"]
    _same_pose(ma[v], ms[v], rtol=1e-4, atol=2e-5)
    scale = np.max(np.abs(np.asarray(Ps[v], np.float64)), axis=(-2, -1), keepdims=True)
    np.testing.assert_allclose(np.asarray(Pa[v], np.float64) / scale, np.asarray(Ps[v], np.float64) / scale, atol=2e-4)


def _rmse(est, truth, valid):
    d = est[valid] - truth[valid]
    return np.sqrt(np.mean(d[:, :2] ** 2)), np.sqrt(np.mean(wrap(d[:, 2]) ** 2))


@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_smoothing_is_closer_to_the_truth(name):
    """A sanity check on the simulation's truth: the smoothed poses are nearer it than the filtered."""
    d = _two_lives(T=400, gap=(180, 190), seed=5)
    m, _ = jax.jit(SMOOTHERS[name])(*(jnp.asarray(d[k]) for k in ("mean", "cov", "dt", "valid")), d["params"])
    pos_f, th_f = _rmse(d["mean"], d["truth"], d["valid"])
    pos_s, th_s = _rmse(np.asarray(m), d["truth"], d["valid"])
    assert pos_s < 0.8 * pos_f and th_s < 0.8 * th_f, (pos_f, pos_s, th_f, th_s)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_heading_spinning_through_pi(name, dtype):
    """A robot turning at 3 rad/s for 60 s: some 25 turns, the wrapped heading crossing ±π each time.
    The smoothed heading follows the truth across every crossing (a smoother of the wrapped values
    would be pulled by 2π at each) and equals the references'."""
    d = _two_lives(T=600, gap=(300, 305), seed=11, omega=3.0)
    v = d["valid"]
    crossings = np.sum(np.abs(np.diff(d["mean"][v][:, 2])) > np.pi)
    assert crossings >= 10
    m, _ = jax.jit(SMOOTHERS[name])(
        *(jnp.asarray(d[k], dtype) for k in ("mean", "cov", "dt")), jnp.asarray(v), d["params"]
    )
    err = wrap(np.asarray(m, np.float64)[v, 2] - d["truth"][v, 2])
    assert np.max(np.abs(err)) < 0.2
    tol = {"rtol": 1e-9, "atol": 1e-11} if dtype == jnp.float64 else {"rtol": 1e-4, "atol": 3e-5}
    _same_pose(m[v], d["ref"][0][v], **tol)
    assert np.all(np.abs(np.asarray(m)[v, 2]) <= np.pi)


@pytest.mark.parametrize("parallel", [True, False])
def test_smooth_tracks_vmaps_over_slots(parallel):
    """Three slots in one program ([T, M] arrays), lives of one step among them: each slot as smoothed
    alone; one compilation."""
    lives = [_two_lives(T=200, gap=g, seed=s) for g, s in (((60, 70), 1), ((1, 3), 2), ((190, 199), 4))]
    stack = {k: jnp.asarray(np.stack([d[k] for d in lives], axis=1), jnp.float32) for k in ("mean", "cov")}
    valid = jnp.asarray(np.stack([d["valid"] for d in lives], axis=1))
    dt = jnp.asarray(lives[0]["dt"], jnp.float32)
    params = lives[0]["params"]
    before = smooth_tracks._cache_size()
    m, P = smooth_tracks(stack["mean"], stack["cov"], dt, valid, params, parallel=parallel)
    m2, _ = smooth_tracks(stack["mean"] + 0.0, stack["cov"], dt, valid, params, parallel=parallel)
    assert smooth_tracks._cache_size() == before + 1
    assert m.shape == stack["mean"].shape and P.shape == stack["cov"].shape
    one = rts_associative if parallel else rts_sequential
    for i in range(len(lives)):
        mi, Pi = jax.jit(one)(stack["mean"][:, i], stack["cov"][:, i], dt, valid[:, i], params)
        assert_allclose(m[:, i], mi, rtol=1e-5, atol=1e-6)
        assert_allclose(P[:, i], Pi, rtol=1e-5, atol=1e-7)
    assert_allclose(m2, m)


@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_a_life_begun_in_the_next_scan_is_cut_from_the_last(name):
    """Two lives back to back in one slot (a track died and another was born in its slot the next scan,
    no empty step between): with ``cut`` at the second's first step, each is smoothed as alone, as the
    references smooth them; without it they would be one segment."""
    d = _two_lives(gap=(100, 117))
    # Close the gap: the second life's states moved to start right after the first's last step.
    keep = d["valid"]
    mean, cov, dt = d["mean"][keep], d["cov"][keep], d["dt"][keep]
    ref_m = d["ref"][0][keep]
    dt = dt.copy()
    dt[100] = d["dt"][117]  # the time from the first life's last step is the next scan's interval
    valid = np.ones(mean.shape[0], bool)
    cut = np.zeros_like(valid)
    cut[100] = True
    f = jax.jit(SMOOTHERS[name])
    m, _ = f(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(dt), jnp.asarray(valid), d["params"], jnp.asarray(cut))
    _same_pose(m, ref_m, rtol=1e-9, atol=1e-11)
    joined, _ = f(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(dt), jnp.asarray(valid), d["params"])
    assert np.max(np.abs(np.asarray(joined)[90:100, :2] - ref_m[90:100, :2])) > 1e-6


@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_extra_variance_widens_that_steps_prediction_as_filterpy_does(name):
    """``extra[t]``: variances added to the prediction into step ``t`` (where the forward pass reset a
    turn rate or a heading): the same as filterpy's smoother given that step's ``Q`` plus them."""
    d = _two_lives(gap=(100, 117))
    keep = np.arange(100)
    mean, cov, dt = d["mean"][keep], d["cov"][keep], d["dt"][keep]
    extra = np.zeros((100, 6))
    extra[40, 5] = 100.0
    extra[70, 2] = 100.0
    extra[70, 5] = 100.0
    m = mean.copy()
    m[:, 2] = _unwrap(m[:, 2])
    models = [_model(dt[t + 1], d["params"]) for t in range(99)] + [(np.eye(6), np.zeros((6, 6)))]
    Qs = [q + np.diag(extra[t + 1]) if t < 99 else q for t, (_, q) in enumerate(models)]
    ref_m, ref_P, _, _ = rts_smoother(m, cov, [f for f, _ in models], Qs)
    ref_m[:, 2] = wrap(ref_m[:, 2])
    f = jax.jit(SMOOTHERS[name])
    got_m, got_P = f(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(dt), jnp.ones(100, bool), d["params"], None,
                     jnp.asarray(extra))
    _same_pose(got_m, ref_m, rtol=1e-9, atol=1e-11)
    assert_allclose(got_P, ref_P, rtol=1e-9, atol=1e-13)
    plain, _ = f(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(dt), jnp.ones(100, bool), d["params"])
    assert np.max(np.abs(np.asarray(plain)[30:40, 5] - ref_m[30:40, 5])) > 1e-6  # the extra did something
