"""The rows' variance floor (issue 55, lever 6): the least position and heading variance which, added to
every reported row's, puts 95 % of training's held-out rows inside their 95 % ellipse (the position's;
the heading's measured and listed, not added) (``train.calibrate.variance_floor``), learnt within
bounds and listed with its evidence, added to the
rows by ``TrackerParams.widened`` (in the step against the reference in ``tests/test_reference.py``,
in the smoothers in ``tests/test_smoothing.py`` and ``tests/test_smooth_lag.py``). Checked against
a bisection on NumPy's linear solve and fresh draws of the same errors."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.core.g_types import TrackerParams
from gtsjax.train.calibrate import (
    FLOOR_RANGE_MM,
    MIN_FLOOR_ROWS,
    _with_offset,
    needed_floors,
    variance_floor,
    within_95,
)

CHI2_2, CHI2_1 = 5.991464547107979, 3.841458820694124


def _rows(rng, n, sd_xy, sd_th, reported_sd_xy, reported_sd_th):
    """``[n, 8]`` rows: errors of the given spreads, reported variances of the given (smaller) ones,
    a random x–y correlation and true heading."""
    vx = (reported_sd_xy * rng.uniform(0.5, 1.5, n)) ** 2
    vy = (reported_sd_xy * rng.uniform(0.5, 1.5, n)) ** 2
    cxy = rng.uniform(-0.8, 0.8, n) * np.sqrt(vx * vy)
    vth = (reported_sd_th * rng.uniform(0.5, 1.5, n)) ** 2
    return np.column_stack([rng.normal(0, sd_xy, n), rng.normal(0, sd_xy, n), rng.normal(0, sd_th, n), vx, vy, cxy,
                            vth, rng.uniform(-math.pi, math.pi, n)])


def _bisected(row) -> tuple[float, float]:
    """The least floor for one row by bisection on the normalised squared errors, NumPy's solve."""
    dx, dy, eth, vx, vy, cxy, vth, _ = row
    d = np.array([dx, dy])

    def nees(f):
        return float(d @ np.linalg.solve(np.array([[vx + f, cxy], [cxy, vy + f]]), d))

    pos = 0.0
    if nees(0.0) > CHI2_2:
        lo, hi = 0.0, 1.0
        for _ in range(200):
            lo, hi = ((lo + hi) / 2, hi) if nees((lo + hi) / 2) > CHI2_2 else (lo, (lo + hi) / 2)
        pos = hi
    return pos, max(eth**2 / CHI2_1 - vth, 0.0)


def test_needed_floors_equal_a_bisection():
    rows = _rows(np.random.default_rng(1), 300, 0.02, 0.05, 0.01, 0.03)
    got = needed_floors(rows)
    want = np.array([_bisected(r) for r in rows])
    assert 0.2 < np.mean(got[:, 0] > 0) < 0.9 and 0.2 < np.mean(got[:, 1] > 0) < 0.9  # both kinds of row
    np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-15)


def test_the_floor_covers_95_percent_of_fresh_rows_and_leaves_misreads_out():
    """Rows whose reported variances are a quarter of their errors' spread: the learnt position floor
    puts 95 % of the training rows' positions inside, and about 95 % of a fresh draw of the same
    errors (not 100 %: it is not a bound on every row); a few rows read on the wrong side change
    nothing. The heading's floor is measured and listed, not added."""
    rng = np.random.default_rng(2)
    rows = _rows(rng, 2000, 0.015, math.radians(2.0), 0.0075, math.radians(1.0))
    misread = rows[:40].copy()
    misread[:, 2] = math.radians(150.0)
    floors, table, warnings = variance_floor({"robot": np.concatenate([rows, misread])}, ("post", "robot"))
    assert not warnings and np.all(floors[0] == 0)
    plain, plain_table, _ = variance_floor({"robot": rows}, ("post", "robot"))
    np.testing.assert_array_equal(floors, plain)
    assert table == plain_table
    f = floors[1].astype(np.float64)
    assert f[0] > 0 and f[1] == 0
    assert 0.95 <= within_95(rows, f)[0] < 0.952  # the 95th percentile: just enough
    assert within_95(rows)[0] < 0.8  # before: too sure
    fresh = within_95(_rows(rng, 4000, 0.015, math.radians(2.0), 0.0075, math.radians(1.0)), f)[0]
    assert 0.93 <= fresh <= 0.97, fresh  # the band for a calibrated ground truth
    assert [r["parameter"] for r in table] == ["row position sd floor", "row heading sd floor"]
    assert [r["source"] for r in table] == ["learnt", "measured"]
    need_th = np.quantile(np.maximum(rows[:, 2] ** 2 / CHI2_1 - rows[:, 6], 0), 0.95, method="higher")
    np.testing.assert_allclose([r["value"] for r in table], [1e3 * math.sqrt(f[0]), math.degrees(math.sqrt(need_th))],
                               atol=0.006)
    assert "2000 held-out rows (right side only)" in table[0]["evidence"] and "95.0 % after" in table[0]["evidence"]
    assert "not added" in table[1]["evidence"]


def test_the_floor_needs_rows_and_stops_at_its_bounds():
    rng = np.random.default_rng(3)
    few = _rows(rng, MIN_FLOOR_ROWS - 1, 0.02, 0.05, 0.01, 0.03)
    assert variance_floor({"robot": few}, ("robot",)) == (None, [], [])
    wild = _rows(rng, 200, 0.1, math.radians(1.0), 0.01, math.radians(1.0))  # 10 cm off, said 1 cm
    floors, table, warnings = variance_floor({"robot": wild}, ("robot",))
    assert len(warnings) == 1 and "stop there" in warnings[0]
    np.testing.assert_allclose(floors[0, 0], (FLOOR_RANGE_MM / 1e3) ** 2, rtol=1e-6)
    assert table[0]["value"] == pytest.approx(FLOOR_RANGE_MM)


def test_the_floor_is_at_most_one_detections_error():
    """Rows that err by more than one detection does (a robot turned by hand between two scans, rows
    the recording's habit gives): the floor stops at the detections' own error variance, and says so."""
    rng = np.random.default_rng(6)
    rows = _rows(rng, 500, 0.02, math.radians(3.0), 0.005, math.radians(0.5))
    dets = rng.normal(0, [0.008, 0.006, math.radians(1.0)], (300, 3))
    dets[:10, 2] = math.radians(170.0)  # misread sides: not part of one detection's error
    floors, table, _ = variance_floor({"robot": rows}, ("robot",), detections={"robot": dets})
    right = dets[10:]
    np.testing.assert_allclose(floors[0, 0], (right[:, 0].var(ddof=1) + right[:, 1].var(ddof=1)) / 2, rtol=1e-5)
    assert "held at one detection's error" in table[0]["evidence"]
    free, _, _ = variance_floor({"robot": rows}, ("robot",))
    assert free[0, 0] > floors[0, 0]


def test_rows_with_the_offset_taken_off_are_the_trackers():
    """What the floor is fitted to (rows' errors once ``pose_offset`` comes off) is what the tracker
    reports (``TrackerParams.off`` on the row's pose)."""
    rng = np.random.default_rng(4)
    offset = np.array([0.004, -0.002, math.radians(0.5)])
    truth = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50), rng.uniform(-math.pi, math.pi, 50)])
    rows = _rows(rng, 50, 0.01, 0.02, 0.01, 0.02)
    rows[:, 7] = truth[:, 2]
    pose = truth + rows[:, :3]
    params = TrackerParams(**{**vars(TrackerParams.default([True])), "pose_offset": jnp.asarray(offset[None], jnp.float32)})
    moved = np.asarray(params.off(jnp.zeros(50, jnp.int32), jnp.asarray(pose, jnp.float32)), np.float64)
    got = _with_offset(rows, offset)
    np.testing.assert_allclose(got[:, :2], moved[:, :2] - truth[:, :2], atol=1e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - (moved[:, 2] - truth[:, 2])))), 0.0, atol=1e-5)
    np.testing.assert_array_equal(got[:, 3:], rows[:, 3:])


def test_widened_adds_each_class_floor_and_a_model_file_keeps_it(tmp_path):
    import equinox as eqx

    from gtsjax.cli.demo import demo_model_path
    from gtsjax.io.modelfile import load_model, save_model

    params = TrackerParams.default([False, True])
    var = np.abs(np.random.default_rng(5).normal(size=(4, 3))).astype(np.float32)
    cls = jnp.asarray([1, 0, 1, 0])
    np.testing.assert_array_equal(np.asarray(params.widened(cls, jnp.asarray(var))), var)
    floor = np.array([[0.0, 0.0], [1e-4, 2e-3]], np.float32)
    wide = TrackerParams(**{**vars(params), "var_floor": jnp.asarray(floor)})
    np.testing.assert_allclose(np.asarray(wide.widened(cls, jnp.asarray(var))), var + floor[[1, 0, 1, 0]][:, [0, 0, 1]])
    model = load_model(demo_model_path())
    assert model.tracker.var_floor is None  # the shipped model's file has none
    leaf = np.linspace(0, 1e-3, 2 * len(model.classes), dtype=np.float32).reshape(-1, 2)
    save_model(eqx.tree_at(lambda m: m.tracker.var_floor, model, jnp.asarray(leaf), is_leaf=lambda x: x is None),
               tmp_path / "m.npz")
    np.testing.assert_array_equal(np.asarray(load_model(tmp_path / "m.npz").tracker.var_floor), leaf)
