"""Identities over time (``gtsjax.core.g_identity``) against a NumPy loop of Bayes' rule (a product of
likelihoods from a uniform start, floored) and a brute-force check of the report: above the threshold,
and no other confirmed track surer of the same identity."""

import jax.numpy as jnp
import numpy as np

from gtsjax.core.g_identity import FLOOR, REPORT_P, report_identities, update_identities


def reference_update(logp, assigned, tag_ll, born):
    out = np.array(logp, float)
    for m in range(out.shape[0]):
        if born[m]:
            out[m] = -np.log(out.shape[1])
        if assigned[m] >= 0:
            out[m] = out[m] + tag_ll[assigned[m]]
        p = np.exp(out[m] - out[m].max())
        post = np.log(p / p.sum())
        post = np.maximum(post, FLOOR)
        out[m] = post - np.log(np.exp(post).sum())
    return out


def test_update_matches_bayes_rule_step_by_step():
    rng = np.random.default_rng(1)
    M, K, n_ids = 6, 5, 4
    logp = np.full((M, n_ids), -np.log(n_ids))
    for _ in range(40):
        assigned = np.where(rng.random(M) < 0.7, rng.integers(0, K, M), -1)
        tag_ll = rng.normal(0, 2, (K, n_ids))
        tag_ll[rng.random(K) < 0.3] = 0.0  # unreadable detections
        born = rng.random(M) < 0.05
        want = reference_update(logp, assigned, tag_ll, born)
        got = np.asarray(update_identities(jnp.asarray(logp, jnp.float32), jnp.asarray(assigned, jnp.int32),
                                           jnp.asarray(tag_ll, jnp.float32), jnp.asarray(born)))
        np.testing.assert_allclose(got, want, atol=2e-4)
        logp = want


def test_reads_of_one_robot_converge_and_the_report_is_exclusive():
    rng = np.random.default_rng(2)
    M, n_ids = 4, 3
    logp = jnp.full((M, n_ids), -np.log(n_ids), jnp.float32)
    truth = np.array([0, 1, 2, 1])  # tracks 1 and 3 both read as robot 1 (one of them a ghost)
    for _ in range(30):
        tag_ll = np.where(np.arange(n_ids)[None] == truth[:, None], 0.0, -1.0) + rng.normal(0, 0.3, (M, n_ids))
        logp = update_identities(logp, jnp.arange(M, dtype=jnp.int32), jnp.asarray(tag_ll, jnp.float32),
                                 jnp.zeros(M, bool))
    p = np.exp(np.asarray(logp))
    confirmed = np.array([True, True, True, True])
    robot = np.asarray(report_identities(logp, jnp.asarray(confirmed)))
    for m in range(M):  # brute force: above the threshold, and no other confirmed track surer of it
        j = int(np.argmax(p[m]))
        surest = max(range(M), key=lambda k: (p[k, j] if confirmed[k] else -1, -k))
        assert robot[m] == (j if p[m, j] > REPORT_P and surest == m else -1)
    assert list(robot[:3]) == [0, 1, 2] and robot[3] == -1
    # An unconfirmed track reports nothing, and its identity is free for the other.
    robot2 = np.asarray(report_identities(logp, jnp.asarray([True, False, True, True])))
    assert robot2[1] == -1 and robot2[3] == (1 if p[3, 1] > REPORT_P else -1)


def test_a_floored_identity_comes_back_after_a_few_clear_reads():
    logp = jnp.full((1, 2), -np.log(2), jnp.float32)
    wrong = jnp.asarray([[0.0, -8.0]], jnp.float32)  # misreads: robot 0, strongly
    for _ in range(5):
        logp = update_identities(logp, jnp.zeros(1, jnp.int32), wrong, jnp.zeros(1, bool))
    assert float(logp[0, 1]) >= FLOOR - 1e-3
    right = jnp.asarray([[-6.0, 0.0]], jnp.float32)
    for _ in range(3):
        logp = update_identities(logp, jnp.zeros(1, jnp.int32), right, jnp.zeros(1, bool))
    assert int(np.argmax(np.asarray(logp)[0])) == 1


def test_tracker_keeps_identities_through_a_crossing_and_a_pick_up():
    """The tracker's wiring (``track_step`` with detections carrying tag reads): two robots cross 0.3 m
    apart and never swap the identities they report; robot 0 is picked up for 2 s and put down 1 m
    away, starts a new track, and reports its identity again by reading, not by place."""
    import jax

    from gtsjax.core.g_track import Detections, TrackerParams, TrackerState, track_step

    params = TrackerParams.default([False, True], rate_hz=10.0)
    step = jax.jit(track_step)
    rng = np.random.default_rng(5)
    n_ids, k = 3, 4
    state = TrackerState.empty(4, ids=n_ids)
    n = 100
    t = np.arange(n) * 0.1
    a = np.stack([1 + 0.4 * t, 1 + 0.2 * t, np.full(n, 0.46)], 1)
    b = np.stack([1.3 + 0.4 * t, 2.2 - 0.2 * t, np.full(n, -0.46)], 1)
    a[60:] += [0.0, 1.0, 0.0]  # put down again 1 m away
    reported = {0: set(), 1: set()}
    back = None
    for i in range(n):
        seen = [(a[i], 0)] * (not 40 <= i < 60) + [(b[i], 1)]
        pose = np.zeros((k, 3), np.float32)
        ll = np.zeros((k, n_ids), np.float32)
        for j, (p, who) in enumerate(seen):
            pose[j] = p + rng.normal(0, [0.01, 0.01, 0.03])
            ll[j] = np.where(np.arange(n_ids) == who, 0.0, -0.6) + rng.normal(0, 0.3, n_ids)
        cov = np.broadcast_to(np.diag(np.asarray([1e-3, 1e-3, 4e-3], np.float32)), (k, 3, 3)).copy()
        det = Detections(jnp.asarray(pose), jnp.asarray(cov), jnp.full(k, 1, jnp.int32),
                         jnp.asarray(np.arange(k) < len(seen)), tag_ll=jnp.asarray(ll))
        state, _ = step(state, det, jnp.asarray(0.1, jnp.float32), params)
        robot = np.asarray(report_identities(state.id_logp, state.live & state.confirmed))
        for s in np.flatnonzero(robot >= 0):
            p = np.asarray(state.mean[s, :2])
            dist = {who: np.linalg.norm(p - q[:2]) for q, who in seen}
            near = min(dist, key=dist.get)
            if dist[near] > 0.3:  # robot 0's track coasting where it was picked up
                continue
            reported[near].add(int(robot[s]))
            if near == 0 and i >= 60 and back is None:
                back = i
    assert reported == {0: {0}, 1: {1}}  # each robot only ever reported as itself
    assert back is not None and back - 60 <= 20  # robot 0 named again within 2 s of being put down
