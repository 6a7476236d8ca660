"""The tracker's turn-rate process noise learnt from the labels' motion (``train.motion.turn_rate_noise``):
on labels built here by hand from the tracker's own model of a turning robot (its heading's second
derivative white noise of a known density, sampled finely and integrated), the learnt density is the
one the labels were made with, whatever the labels' own noise and scan rate; still stretches and
placements between them teach nothing; and training puts it in the model with its row."""

import math

import numpy as np
import pytest

from gtsjax.train import bounds as B
from gtsjax.train.motion import turn_rate_noise, turn_second_differences
from tests.test_train_limits import _log, turned_on_the_spot

LIMITS = {"max_speed": {"robot": 1.0}, "max_turn_rate": {"robot": 3.0}}


def _turning_walk(q: float, period: float, seconds: float, noise_deg: float = 0.0, seed: int = 0,
                  settle_s: float = 5.0, sub: int = 50):
    """A robot walking at 0.3 m/s along its heading, whose turn rate is an Ornstein–Uhlenbeck process
    (time constant ``settle_s``, driven by white angular acceleration of density ``q``), integrated in
    ``sub`` steps a scan; labelled every ``period`` s with ``noise_deg`` of heading noise."""
    rng = np.random.default_rng(seed)
    h = period / sub
    n = int(round(seconds / period))
    omega, theta, x, y = 0.0, 0.0, 3.0, 2.0
    rows = []
    for _ in range(n):
        rows.append([x, y, theta])
        for _ in range(sub):
            omega += -omega / settle_s * h + math.sqrt(q * h) * rng.normal()
            theta += omega * h
            x += 0.3 * math.cos(theta) * h
            y += 0.3 * math.sin(theta) * h
    rows = np.asarray(rows)
    rows[:, 2] = np.angle(np.exp(1j * (rows[:, 2] + np.radians(noise_deg) * rng.normal(size=n))))
    return _log(rows, period)


@pytest.mark.parametrize(("q", "period", "noise_deg"), [(0.1, 0.1, 0.0), (0.3, 0.1, 1.0), (0.1, 0.025, 0.5)])
def test_the_density_the_labels_were_made_with_is_learnt(q, period, noise_deg):
    log = _turning_walk(q, period, seconds=400.0, noise_deg=noise_deg)
    got, row = turn_rate_noise([log], ("robot",), period=period, **LIMITS)
    assert row["source"] == "learnt" and row["value"] == pytest.approx(got, rel=1e-3)
    assert got == pytest.approx(q, rel=0.2), (got, q)
    # the second differences themselves, against the model's closed form 2/3 q (L dt)³ + 6 σ²
    d1, d2 = turn_second_differences([log], ("robot",), period=period, **LIMITS)["robot"]
    sigma2 = math.radians(noise_deg) ** 2
    for d, lag in ((d1, 1), (d2, 2)):
        assert np.mean(d**2) == pytest.approx(2 / 3 * q * (lag * period) ** 3 + 6 * sigma2, rel=0.2)


def test_still_stretches_and_placements_teach_nothing():
    """A robot put down at 30 poses for 3 s each (label noise only), moved to the next between two
    scans: no motion, the default, and its reason; the same poses beside a turning walk learn the walk's."""
    rng = np.random.default_rng(2)
    rows = []
    for _ in range(30):
        pose = [rng.uniform(0.5, 5.5), rng.uniform(0.5, 3.5), rng.uniform(-math.pi, math.pi)]
        rows += [[pose[0] + rng.normal(0, 0.003), pose[1] + rng.normal(0, 0.003), pose[2] + rng.normal(0, 0.01)]
                 for _ in range(30)]
    still = _log(rows, 0.1)
    value, row = turn_rate_noise([still], ("robot",), period=0.1, **LIMITS)
    assert row["source"] == "default" and "moving" in row["evidence"] and value == pytest.approx(0.02)
    walk = _turning_walk(0.2, 0.1, seconds=300.0, seed=4)
    alone, _ = turn_rate_noise([walk], ("robot",), period=0.1, **LIMITS)
    both, row = turn_rate_noise([still, walk], ("robot",), period=0.1, **LIMITS)
    assert row["source"] == "learnt" and both == pytest.approx(alone, rel=1e-9)


def test_labels_steadier_than_the_default_are_held_to_it():
    """A robot that never changes its turn rate (turning at a constant 0.5 rad/s, exact labels), and one
    turned on the spot by 22.5° a scan: no turn-rate noise in their labels, held to the floor, the
    tracker's default (no evidence that a robot turns more steadily), and the row says so."""
    t = np.arange(0, 60, 0.1)
    rows = np.column_stack([3 + 1.0 * np.cos(0.5 * t), 2 + 1.0 * np.sin(0.5 * t), np.angle(np.exp(1j * (0.5 * t + np.pi / 2)))])
    value, row = turn_rate_noise([_log(rows, 0.1)], ("robot",), period=0.1, **LIMITS)
    assert value == B.TURN_RATE_NOISE.floor == pytest.approx(0.02) and row["source"] == "learnt"
    assert "held to 0.02" in row["evidence"] and "warning" not in row
    value, row = turn_rate_noise([turned_on_the_spot()], ("robot",), period=0.1, max_speed={"robot": 0.6},
                                 max_turn_rate={"robot": 4.9})
    assert value == pytest.approx(0.02)


def test_training_puts_it_in_the_model_with_its_row(tiny):
    """The tests' small model, trained on the SPL grid (placements) and 15 s of a robot walking past a
    person: its tracker's turn-rate noise is the learnt row's, learnt from the walk alone."""
    from gtsjax.sim import simulate

    (row,) = [r for r in tiny["report"]["learnt"] if r["parameter"] == B.TURN_RATE_NOISE.what]
    assert row["source"] == "learnt" and "robot" in row["evidence"]
    assert float(tiny["model"].tracker.q_theta) == pytest.approx(row["value"], rel=1e-3)
    legs, _ = simulate("spl-legs", seed=12, n_scans=150)
    tracker, i = tiny["model"].tracker, tiny["model"].classes.index("robot")
    alone, _ = turn_rate_noise([legs], ("robot",), period=0.1, max_speed={"robot": float(tracker.max_speed[i])},
                               max_turn_rate={"robot": float(tracker.max_turn_rate[i])})
    assert row["value"] == pytest.approx(alone, rel=1e-3)


def test_a_hands_turns_are_warned_about_and_the_default_kept():
    """A robot carried from pose to pose, turned by 6° a scan for half a second at a time, its turns
    started and stopped within a scan: a turn rate that jumps like a hand's (several rad²/s³), warned
    about, and the tracker's default kept."""
    rng = np.random.default_rng(5)
    rows, x, y, th = [], 1.0, 1.0, 0.0
    for _ in range(40):
        for _ in range(30):  # put down: still
            rows.append([x + rng.normal(0, 0.003), y + rng.normal(0, 0.003), th + rng.normal(0, 0.01)])
        for _ in range(6):  # carried: moved and turned at once
            x, y, th = x + 0.1, y + 0.02, th + math.radians(6)
            rows.append([x, y, th])
        x, y = (1.0, 1.0) if x > 5 else (x, y)
    rows = np.asarray(rows)
    rows[:, 2] = np.angle(np.exp(1j * rows[:, 2]))
    value, row = turn_rate_noise([_log(rows, 0.1)], ("robot",), period=0.1, max_speed={"robot": 1.5},
                                 max_turn_rate={"robot": 3.0})
    assert value == pytest.approx(0.02) and "warning" in row and "by hand" in row["evidence"]
    assert row["warning"].startswith("turn-rate noise learnt as")
