"""What training learns from a user's labels about motion and the scanner's rate, on labels recorded the
ways users record them (built here by hand, not by the simulator): motion limits only from evidence of
that motion, held to their sanity ranges, and each with where it came from."""

import math

import numpy as np
import pytest

from gtsjax.core.g_track import DEFAULT_MAX_SPEED, DEFAULT_MAX_TURN_RATE
from gtsjax.io.logs import ScanLog
from gtsjax.train import TrainConfig
from gtsjax.train import bounds as B
from gtsjax.train.motion import motion_limits, scan_rate_entry, tracker_limits


def _log(poses, period=0.1, stamps=None, sensor_model=None):
    poses = np.asarray(poses, float)[:, None, :]
    n = len(poses)
    return ScanLog(ranges=np.ones((n, 5), np.float32),
                   stamps=np.arange(n) * period if stamps is None else np.asarray(stamps, float),
                   angle_min=0.0, angle_increment=0.01, truth_classes=np.array(["robot"]), truth_poses=poses,
                   sensor_model=sensor_model)


def turned_on_the_spot(period=0.1, jitter=0.005, seed=0):
    """The recording that broke training: at each grid point 16 headings, one scan each, consecutive
    scans at the scan period; carried 0.5 m to the next point out of view (NaN rows)."""
    rng = np.random.default_rng(seed)
    rows = []
    for x in np.arange(0.5, 5.6, 0.5):
        for y in (1.0, 2.0, 3.0):
            for k in range(16):
                rows.append([x + rng.normal(0, jitter), y + rng.normal(0, jitter), -math.pi + k * math.pi / 8])
            rows += [[np.nan] * 3] * int(round(1.0 / period))
    return _log(rows, period)


@pytest.mark.parametrize("period", [0.1, 0.025])
@pytest.mark.parametrize("jitter", [0.0, 0.005])
def test_a_robot_turned_on_the_spot_teaches_no_speed(period, jitter):
    log = turned_on_the_spot(period, jitter)
    speed, turn, motion, rows = tracker_limits([log], ("background", "robot"), ("robot",), TrainConfig(), period=period)
    assert speed[1] == DEFAULT_MAX_SPEED  # never 0, never the label jitter's speed
    assert motion["robot"]["max_speed_from"] == "default"
    assert "no translation" in motion["robot"]["max_speed_evidence"]
    # The turn on the spot is turning evidence where it is a plausible turn rate (22.5° a scan at 10 Hz,
    # 3.9 rad/s: the limit 1.25 times that); at 40 Hz (15.7 rad/s, turned by hand faster than a robot
    # turns) it is none, and the default stays.
    per_scan = math.radians(22.5) / period
    plausible = per_scan <= B.MAX_TURN_RATE.plausible[1]
    assert turn[1] == pytest.approx(1.25 * per_scan if plausible else DEFAULT_MAX_TURN_RATE, rel=0.02)
    assert motion["robot"]["max_turn_rate_from"] == ("learnt" if plausible else "default")
    assert not any("warning" in r for r in rows)


def test_one_scan_per_pose_at_the_scan_period_is_not_motion():
    """A grid logged one scan per pose, stamped at the scan period: a 0.4 m jump every scan (4 m/s), a
    new heading every scan. No speed or turn rate is learnt from that."""
    rng = np.random.default_rng(1)
    rows = [[x, y, rng.uniform(-math.pi, math.pi)] for x in np.arange(0.5, 5.6, 0.5) for y in np.arange(0.4, 3.7, 0.4)]
    got = motion_limits([_log(rows)], ("robot",))["robot"]
    assert "max_speed" not in got and "max_turn_rate" not in got


def test_walking_sets_the_limits_carried_fast_is_clamped_with_a_warning():
    t = np.arange(0, 20, 0.1)
    walk = np.column_stack([0.3 * t, np.zeros_like(t), np.full_like(t, 0.2)])
    _, _, motion, _ = tracker_limits([_log(walk)], ("robot",), ("robot",), TrainConfig())
    assert motion["robot"]["max_speed"] == pytest.approx(1.25 * 0.3, rel=1e-3)
    assert motion["robot"]["max_speed_from"] == "learnt"
    # A robot labelled while carried slowly: 0.1 m/s gives 0.125, raised to the floor, with a warning.
    slow = np.column_stack([0.1 * t, np.zeros_like(t), np.zeros_like(t)])
    speed, _, motion, rows = tracker_limits([_log(slow)], ("robot",), ("robot",), TrainConfig())
    assert speed[0] == B.MAX_SPEED.floor
    (row,) = [r for r in rows if r["parameter"] == "max speed"]
    assert "raised to 0.3" in row["warning"] and "--max-speed robot=" in row["warning"]


def test_too_little_motion_is_no_evidence():
    t = np.arange(0, 1.2, 0.1)  # 1.2 s of walking: under the 2 s of evidence asked for
    walk = np.column_stack([0.3 * t, np.zeros_like(t), np.zeros_like(t)])
    _, _, motion, _ = tracker_limits([_log(walk)], ("robot",), ("robot",), TrainConfig())
    assert motion["robot"]["max_speed_from"] == "default"
    assert "only" in motion["robot"]["max_speed_evidence"]


def test_set_limits_win_and_are_never_warned_about():
    log = turned_on_the_spot()
    cfg = TrainConfig(max_speed={"robot": 0.01}, max_turn_rate={"robot": 50.0})
    speed, turn, motion, rows = tracker_limits([log], ("robot",), ("robot",), cfg)
    assert (speed[0], turn[0]) == (0.01, 50.0)
    assert motion["robot"]["max_speed_from"] == motion["robot"]["max_turn_rate_from"] == "set"
    assert not any("warning" in r for r in rows)


def test_scan_rate_from_stamps_or_the_scanner_when_the_log_kept_one_scan_a_pose():
    rate, row = scan_rate_entry([_log(np.zeros((50, 3)), period=0.025)])
    assert rate == pytest.approx(40.0) and row["source"] == "learnt"
    # Stamps taken on the host jitter both ways (±20 %), and lost frames lengthen an interval in five:
    # still 10 Hz, not the rate of a low quantile (jitter) nor of the mean (losses).
    rng = np.random.default_rng(4)
    dt = 0.1 * (1 + rng.uniform(-0.2, 0.2, 400)) * np.where(np.arange(400) % 5 == 0, 2, 1)
    assert scan_rate_entry([_log(np.zeros((400, 3)), stamps=np.cumsum(dt))])[0] == pytest.approx(10.0, rel=0.03)
    # One scan kept every 2 s from a URG-04LX (10 Hz): the tracker runs at the scanner's rate.
    sparse = _log(np.zeros((30, 3)), period=2.0, sensor_model="URG-04LX")
    rate, row = scan_rate_entry([sparse])
    assert rate == pytest.approx(10.0) and row["source"] == "default" and "sparser" in row["evidence"]
    assert scan_rate_entry([sparse], 25.0)[0] == 25.0


def test_defaults_are_inside_their_own_ranges():
    for bound, default in ((B.MAX_SPEED, DEFAULT_MAX_SPEED), (B.MAX_TURN_RATE, DEFAULT_MAX_TURN_RATE)):
        assert bound.floor <= bound.plausible[0] <= default <= bound.plausible[1] <= bound.ceiling


# ------------------------------------------------------------------ held-out groups and coverage


def test_a_placement_is_one_held_out_group_and_a_walk_is_cut_by_the_second():
    from gtsjax.train.labels import scan_groups

    period = 0.1
    stay = lambda x, th, n: np.repeat([[x, 1.0, th]], n, 0)  # noqa: E731
    away = np.full((10, 3), np.nan)
    t = np.arange(50) * period
    walk = np.column_stack([1 + 0.3 * t, np.full(50, 2.0), np.zeros(50)])
    poses = np.concatenate([stay(1.0, 0.0, 30), away, stay(1.0, 1.5, 25), stay(2.0, 1.5, 20), walk])
    g = scan_groups(_log(poses, period))
    # Each placement one group however long it stays (3 s, 2.5 s); the jump to the next pose starts one.
    first, second, third = g[:30], g[40:65], g[65:85]
    assert len(set(first)) == len(set(second)) == len(set(third)) == 1
    assert len({first[0], second[0], third[0]}) == 3
    # The absent second is its own block; the 5 s walk (0.3 m/s) is cut into blocks of about one second.
    assert set(g[30:40]).isdisjoint(set(first) | set(second))
    sizes = np.unique(g[85:], return_counts=True)[1]
    assert 4 <= len(sizes) <= 6 and sizes[:-1].min() >= 10


def test_training_says_where_the_labels_leave_the_robot_unseen():
    from gtsjax.io.site import Landmark, Site
    from gtsjax.train.check import coverage

    site = Site(tuple(Landmark("post", x, y) for x, y in ((0, 1.3), (0, 2.7), (6, 1.3))), (3.0, 4.0, -math.pi / 2),
                (0.0, 0.0, 6.0, 4.0))
    # Turned on the spot at every point of a 0.5 m grid: every square, every side; no warning.
    grid = [[x, y, -math.pi + k * math.pi / 8] for x in np.arange(0.25, 6, 0.5) for y in np.arange(0.25, 4, 0.5)
            for k in range(16)]
    rep, lines = coverage([_log(grid)], [site], ("robot",))
    assert lines == [] and rep["robot"]["cells"] == rep["robot"]["of"] == 24
    # Put down at two points only: 2 of 24 squares.
    two = [[x, 1.0, -math.pi + k * math.pi / 4] for x in (1.0, 4.0) for k in range(8) for _ in range(20)]
    rep, lines = coverage([_log(two)], [site], ("robot",))
    assert rep["robot"]["cells"] == 2 and any("2 of the field's 24 squares" in w for w in lines)
    # Everywhere on the field, but always side-on to the laser (heading = bearing + 90°, as a robot walking
    # paths across the laser's view mostly is): one side of eight, and warned so.
    across = [[x, y, math.atan2(y - 4.0, x - 3.0) + math.pi / 2] for x in np.arange(0.25, 6, 0.5)
              for y in np.arange(0.25, 4, 0.5)]
    rep, lines = coverage([_log(across)], [site], ("robot",))
    assert any("sides" in w for w in lines)
    seen = np.asarray(rep["robot"]["side_shares"])
    assert np.sum(seen < 0.05) >= 6 and seen.sum() == pytest.approx(1.0)
    assert lines[0].startswith("robot is seen from")
