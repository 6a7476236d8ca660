"""Stage g against a closed-form Kalman filter written in NumPy, and the track life cycle."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax._track import Detections, TrackerParams, TrackerState, assign, track_step, wrap

F32 = jnp.float32


def numpy_kf(z_seq, R, dt, q_pos, q_theta, P0_vel, P0_omega):
    """The textbook constant-velocity Kalman filter, float64, explicit matrices, no wrapping."""
    q = np.array([q_pos, q_pos, q_theta])
    F = np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
    Q = np.block([[np.diag(q * dt**3 / 3), np.diag(q * dt**2 / 2)], [np.diag(q * dt**2 / 2), np.diag(q * dt)]])
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    x = np.r_[z_seq[0], 0, 0, 0]
    P = np.zeros((6, 6))
    P[:3, :3] = R
    P[3, 3] = P[4, 4] = P0_vel
    P[5, 5] = P0_omega
    out = [(x.copy(), P.copy())]
    for z in z_seq[1:]:
        x = F @ x
        P = F @ P @ F.T + Q
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (z - H @ x)
        P = (np.eye(6) - K @ H) @ P
        out.append((x.copy(), P.copy()))
    return out


def dets(poses, cls=1, var=(1e-3, 1e-3, 4e-3), k=4):
    """Detections array with the given poses in the first slots."""
    poses = np.asarray(poses, np.float32).reshape(-1, 3)
    n = poses.shape[0]
    pose = np.zeros((k, 3), np.float32)
    pose[:n] = poses
    cov = np.broadcast_to(np.diag(np.asarray(var, np.float32)), (k, 3, 3)).copy()
    mask = np.arange(k) < n
    return Detections(jnp.asarray(pose), jnp.asarray(cov), jnp.full(k, cls, jnp.int32), jnp.asarray(mask))


PARAMS = TrackerParams.default([False, True], rate_hz=10.0)
step = jax.jit(track_step)


def test_ekf_equals_closed_form_kalman_filter():
    rng = np.random.default_rng(0)
    t = np.arange(30) * 0.1
    truth = np.stack([1 + 0.3 * t, 2 - 0.2 * t, 0.5 + 0.1 * t], 1)
    R = np.diag([1e-3, 2e-3, 4e-3])
    z = truth + rng.multivariate_normal(np.zeros(3), R, size=len(t))
    params = TrackerParams.default([False, True], n_confirm=1)
    state = TrackerState.empty(4)
    ref = numpy_kf(z, R, 0.1, 0.5, 2.0, 0.25, 1.0)
    for i in range(len(t)):
        d = dets(z[i], var=np.diag(R))
        state, _ = step(state, d, jnp.asarray(0.1 if i else 0.0, F32), params)
        slot = int(np.flatnonzero(np.asarray(state.live))[0])
        assert int(np.sum(np.asarray(state.live))) == 1
        np.testing.assert_allclose(np.asarray(state.mean[slot]), ref[i][0], rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(np.asarray(state.cov[slot]), ref[i][1], rtol=1e-3, atol=1e-6)


def test_inflate_only_model_keeps_velocity_out():
    params = TrackerParams.default([False, True], constant_velocity=False, n_confirm=1)
    state = TrackerState.empty(2)
    state, _ = step(state, dets([1.0, 1.0, 0.0]), jnp.asarray(0.0, F32), params)
    state, _ = step(state, dets([1.2, 1.0, 0.0]), jnp.asarray(0.1, F32), params)
    s = int(np.argmax(np.asarray(state.live)))
    # F = I: the velocity states are never coupled to the pose, so they stay at zero.
    np.testing.assert_allclose(np.asarray(state.mean[s, 3:]), 0.0, atol=1e-7)
    P = np.asarray(state.cov[s])
    # A scalar KF per axis with P+ = (P + q dt) R / (P + q dt + R).
    p1 = (1e-3 + 0.5 * 0.1) * 1e-3 / (1e-3 + 0.5 * 0.1 + 1e-3)
    np.testing.assert_allclose(P[0, 0], p1, rtol=1e-4)


def test_heading_innovation_is_wrapped():
    params = TrackerParams.default([False, True], n_confirm=1)
    state = TrackerState.empty(2)
    state, _ = step(state, dets([1.0, 1.0, np.pi - 0.02]), jnp.asarray(0.0, F32), params)
    state, _ = step(state, dets([1.0, 1.0, -np.pi + 0.02]), jnp.asarray(0.1, F32), params)
    assert int(np.sum(np.asarray(state.live))) == 1  # same track, not a new one across the ±π cut
    th = float(state.mean[int(np.argmax(np.asarray(state.live))), 2])
    assert abs(wrap(jnp.asarray(th - np.pi))) < 0.03


def test_life_cycle_confirm_delete_and_ids():
    state = TrackerState.empty(3)
    zero = jnp.asarray(0.1, F32)
    seen = []
    for i in range(3):
        state, _ = step(state, dets([1.0 + 0.01 * i, 1.0, 0.0]), zero, PARAMS)
        seen.append(bool(np.any(np.asarray(state.confirmed))))
    assert seen == [False, False, True]  # n_confirm = 3
    tid = int(np.asarray(state.track_id)[np.asarray(state.live)][0])
    assert tid == 0
    # Coast for m_delete - 1 scans: still there; one more miss ends it.
    for _ in range(int(PARAMS.m_delete) - 1):
        state, _ = step(state, dets(np.zeros((0, 3))), zero, PARAMS)
        assert bool(np.any(np.asarray(state.live)))
    state, _ = step(state, dets(np.zeros((0, 3))), zero, PARAMS)
    assert not bool(np.any(np.asarray(state.live)))
    # A new object gets a new id, never a reused one.
    state, _ = step(state, dets([3.0, 1.0, 0.0]), zero, PARAMS)
    assert int(np.asarray(state.track_id)[np.asarray(state.live)][0]) == 1


def test_untracked_class_starts_no_track():
    state, used = step(TrackerState.empty(2), dets([1.0, 1.0, 0.0], cls=0), jnp.asarray(0.1, F32), PARAMS)
    assert not bool(np.any(np.asarray(state.live))) and not bool(np.any(np.asarray(used)))


def test_ids_survive_two_robots_crossing():
    """Two robots on crossing diagonals pass 0.3 m apart (about a body width); each id keeps its robot."""
    rng = np.random.default_rng(1)
    state = TrackerState.empty(4)
    n = 60
    t = np.arange(n) * 0.1
    a = np.stack([1 + 0.4 * t, 1 + 0.2 * t, np.full(n, 0.46)], 1)
    b = np.stack([1.3 + 0.4 * t, 2.2 - 0.2 * t, np.full(n, -0.46)], 1)  # closest near t = 3 s
    ids_a, ids_b = set(), set()
    for i in range(n):
        za = a[i] + rng.normal(0, [0.01, 0.01, 0.03])
        zb = b[i] + rng.normal(0, [0.01, 0.01, 0.03])
        order = [za, zb] if i % 2 else [zb, za]  # detection order must not matter
        state, _ = step(state, dets(order), jnp.asarray(0.1, F32), PARAMS)
        live = np.asarray(state.live & state.confirmed)
        for s in np.flatnonzero(live):
            p = np.asarray(state.mean[s, :2])
            (ids_a if np.linalg.norm(p - a[i, :2]) < np.linalg.norm(p - b[i, :2]) else ids_b).add(
                int(state.track_id[s]))
    assert len(ids_a) == 1 and len(ids_b) == 1 and ids_a != ids_b


@pytest.mark.parametrize("seed", range(5))
def test_assignment_is_one_to_one_and_gated(seed):
    rng = np.random.default_rng(seed)
    cost = rng.uniform(0, 10, (6, 4))
    cost[rng.uniform(size=cost.shape) < 0.3] = np.inf
    det_of_track, has = assign(jnp.asarray(cost))
    det_of_track, has = np.asarray(det_of_track), np.asarray(has)
    chosen = det_of_track[has]
    assert len(set(chosen.tolist())) == len(chosen)
    assert np.all(np.isfinite(cost[chosen, np.flatnonzero(has)]))
    # Greedy: every unassigned track has no finite cost to an unused detection.
    unused = np.setdiff1d(np.arange(6), chosen)
    for j in np.flatnonzero(~has):
        assert not np.any(np.isfinite(cost[unused, j]))
