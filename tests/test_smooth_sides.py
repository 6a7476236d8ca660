"""The side re-decision (``gtsjax.core.smooth_sides``) against a NumPy loop written here from its
definition (per slot and hypothesis, the fading sum of the evidence after each scan), on random
hypothesis tables with unused hypotheses, replacements and slots changing track; and on a forward
pass simulated here (the mixture's fading weights, the 3-to-1 switch) that lags a side's return: the
re-decided side returns earlier, and a hypothesis a few degrees from the main one is never chosen."""

import jax.numpy as jnp
import numpy as np

from gtsjax.core.geometry import wrap
from gtsjax.core.smooth_sides import SIDE_RAD, SMOOTH_SIDE_LOG_ODDS, smooth_sides


def reference(sh, sl, main, omega, dt, same, memory, log_odds):
    """The definition, one loop per scan, slot and hypothesis."""
    T, M, S = sh.shape
    fade = np.exp(-dt / memory)
    cont = np.zeros((T, M, S), bool)
    e = np.zeros((T, M, S))
    for t in range(1, T):
        for m in range(M):
            for j in range(S):
                if same[t, m] and np.isfinite(sl[t, m, j]) and np.isfinite(sl[t - 1, m, j]):
                    turned = wrap(sh[t, m, j] - sh[t - 1, m, j] - omega[t - 1, m] * dt[t])
                    if abs(turned) < 0.3:
                        cont[t, m, j] = True
                        e[t, m, j] = sl[t, m, j] - fade[t] * sl[t - 1, m, j]
            if cont[t, m].any():
                e[t, m, cont[t, m]] -= e[t, m, cont[t, m]].max()
    b = np.zeros((T, M, S))
    for t in range(T - 2, -1, -1):
        for m in range(M):
            for j in range(S):
                if cont[t + 1, m, j]:
                    b[t, m, j] = fade[t + 1] * (b[t + 1, m, j] + e[t + 1, m, j])
            gone = ~cont[t + 1, m]
            if cont[t + 1, m].any():
                b[t, m, gone] = b[t, m, cont[t + 1, m]].min()
    choice = main.copy()
    for t in range(T):
        for m in range(M):
            w = np.where(np.isfinite(sl[t, m]), sl[t, m] + b[t, m], -np.inf)
            k, i = int(np.argmax(w)), int(main[t, m])
            if abs(wrap(sh[t, m, k] - sh[t, m, i])) > SIDE_RAD and w[k] - w[i] > log_odds:
                choice[t, m] = k
    return choice, np.where(np.isfinite(sl), sl + b, -np.inf)


def _random_table(rng, T=80, M=3, S=4):
    """Hypotheses turning with a random turn rate, some unused, some replaced, slots changing track."""
    dt = rng.uniform(0.05, 0.15, T)
    omega = rng.normal(0.0, 0.5, (T, M))
    sh = np.zeros((T, M, S))
    sh[0] = rng.uniform(-np.pi, np.pi, (M, S))
    for t in range(1, T):
        sh[t] = wrap(sh[t - 1] + omega[t - 1, :, None] * dt[t] + rng.normal(0, 0.02, (M, S)))
        new = rng.random((M, S)) < 0.03
        sh[t] = np.where(new, rng.uniform(-np.pi, np.pi, (M, S)), sh[t])
    sl = rng.normal(-3.0, 3.0, (T, M, S))
    sl[rng.random((T, M, S)) < 0.1] = -np.inf
    main = np.argmax(sl, axis=-1)
    sl[np.arange(T)[:, None], np.arange(M)[None], main] = 0.0
    live = rng.random((T, M)) < 0.95
    ids = np.cumsum(rng.random((T, M)) < 0.02, axis=0)
    same = np.zeros((T, M), bool)
    same[1:] = live[1:] & live[:-1] & (ids[1:] == ids[:-1])
    return sh, sl, main, omega, dt, same


def _run(sh, sl, main, omega, dt, same, memory=1.0, log_odds=SMOOTH_SIDE_LOG_ODDS):
    c, w = smooth_sides(jnp.asarray(sh, jnp.float32), jnp.asarray(sl, jnp.float32), jnp.asarray(main, jnp.int32),
                        jnp.asarray(omega, jnp.float32), jnp.asarray(dt, jnp.float32), jnp.asarray(same),
                        jnp.float32(memory), jnp.float32(log_odds))
    return np.asarray(c), np.asarray(w)


def test_matches_the_definition_on_random_tables():
    rng = np.random.default_rng(7)
    changed = 0
    for _ in range(4):
        table = _random_table(rng)
        c, w = _run(*table, log_odds=2.0)
        c_ref, w_ref = reference(*table, memory=1.0, log_odds=2.0)
        fin = np.isfinite(w_ref)
        assert (np.isfinite(w) == fin).all()
        np.testing.assert_allclose(w[fin], w_ref[fin], rtol=1e-4, atol=1e-3)
        # A choice may differ only on a near-tie of float32 against float64.
        assert (c != c_ref).mean() < 0.01
        changed += int((c_ref != table[2]).sum())
    assert changed > 0  # the tables exercised a re-decision


def _forward(ev, dt, memory=1.0, odds=3.0):
    """The forward mixture's weights of two hypotheses (normalised log-weights, fading), and its main
    hypothesis with the 3-to-1 switch."""
    T = ev.shape[0]
    lw = np.log(np.array([0.5, 0.5]))
    out, main = np.zeros((T, 2)), np.zeros(T, int)
    m = 0
    for t in range(T):
        lw = np.exp(-dt[t] / memory) * lw + ev[t]
        lw = lw - np.logaddexp.reduce(lw)
        if lw[1 - m] - lw[m] > np.log(odds):
            m = 1 - m
        out[t], main[t] = lw, m
    return out, main


def test_a_lagging_return_is_re_decided_earlier():
    """Side 0 (heading 0) read for 4 s, then 0.6 s of misreads of side 1 (π), then side 0 again: the
    forward pass switches to side 1 and lags back; the re-decision returns to side 0 earlier, and never
    puts side 1 before the misreads began. (The window is the forward's, two-sided: misreads four times
    as strong as that, 0.6 s of them, would also put the 0.5 s before them on side 1.)"""
    T, dt = 120, np.full(120, 0.1)
    ev = np.zeros((T, 2))
    ev[:, 0] = 1.0
    ev[40:46] = [0.0, 4.0]
    sl, main = _forward(ev, dt)
    assert main[46:].sum() > 0  # the forward pass did hold side 1 after the misreads
    sh = np.zeros((T, 1, 2))
    sh[:, 0, 1] = np.pi
    same = np.ones((T, 1), bool)
    same[0] = False
    c, _ = _run(sh, sl[:, None, :], main[:, None], np.zeros((T, 1)), dt, same)
    fwd_back = 46 + np.argmax(main[46:] == 0)
    sm_back = 46 + np.argmax(c[46:, 0] == 0)
    assert sm_back < fwd_back
    assert (c[:40, 0] == 0).all() and (c[fwd_back:, 0] == 0).all()
    assert (c[:, 0] == 1).sum() < (main == 1).sum()


def test_the_same_side_a_few_degrees_off_is_not_chosen():
    """A hypothesis 5° from the main one with all the future evidence is the same side read apart:
    left to the RTS smoother, not chosen."""
    T, dt = 60, np.full(60, 0.1)
    ev = np.zeros((T, 2))
    ev[:30, 0] = 1.0
    ev[30:, 1] = 3.0
    sl, _ = _forward(ev, dt)
    main = np.zeros(T, int)
    sh = np.zeros((T, 1, 2))
    sh[:, 0, 1] = np.radians(5)
    same = np.ones((T, 1), bool)
    same[0] = False
    c, w = _run(sh, sl[:, None, :], main[:, None], np.zeros((T, 1)), dt, same)
    assert (w[20:30, 0, 1] - w[20:30, 0, 0] > SMOOTH_SIDE_LOG_ODDS).any()  # it would have won as a side
    assert (c == 0).all()
