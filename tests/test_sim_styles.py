"""The simulator's recording styles (issue 38): each training log has the property that defines its
habit, at the rate asked for, of the robot outline asked for, with clutter where asked; and the
scenarios that were there before render exactly as they did."""

import math

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.errors import InputError
from gtsjax.sim import SCENARIOS, check_scene, recording, render, simulate
from gtsjax.sim.scenarios import spl_layout
from gtsjax.sim.scene import NAO_OUTLINE, NAO_REFLECTIVITY, Circle, Mover, Polygon, Scene


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _runs(present):
    """(start, stop) of each run of True."""
    p = np.concatenate([[False], present, [False]]).astype(int)
    d = np.diff(p)
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0], strict=True))


def _points_o(log):
    """Every return of every scan in the field frame: ``[T, N, 2]``, NaN where no return."""
    a = log.angle_min + log.angle_increment * np.arange(log.n_beams)
    sp = log.extra["truth_sensor_pose"]
    r = np.where(log.ranges > 0, log.ranges, np.nan).astype(np.float64)
    th = sp[:, 2:3] + a[None]
    return np.stack([sp[:, 0:1] + r * np.cos(th), sp[:, 1:2] + r * np.sin(th)], -1)


def _in_body(pts, pose):
    """Points ``[K, 2]`` of O in the frame of a robot at ``pose``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = pts - pose[:2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)


def _grid(bounds, sensor_xy):
    """The training grid as the issue describes it: every 0.5 m in x from 0.5 m inside the field, every
    0.4 m in y from 0.4 m inside, not within 0.8 m of the laser."""
    x0, y0, x1, y1 = bounds
    pts = [(x, y) for x in np.arange(x0 + 0.5, x1 - 0.5 + 1e-9, 0.5) for y in np.arange(y0 + 0.4, y1 - 0.4 + 1e-9, 0.4)]
    return np.array([p for p in pts if math.dist(p, sensor_xy) >= 0.8])


def _robot_returns(log, t, radius=0.35):
    pts = _points_o(log)[t]
    pose = log.truth_poses[t, 0]
    near = np.linalg.norm(pts - pose[:2], axis=1) < radius
    return pts[near]


def test_turn_is_one_scan_per_heading_on_the_spot_then_carried_away():
    log, _ = recording("spl", "turn", seed=2, seconds=20.0)
    assert 150 <= log.n_scans <= 200  # whole points within 20 s
    np.testing.assert_allclose(np.diff(log.stamps), 0.1, atol=1e-6)  # URG-04LX: 10 Hz
    truth = log.truth_poses[:, 0]
    present = ~np.isnan(truth[:, 0])
    assert np.all(np.isnan(truth[~present]).all(1))
    runs = _runs(present)
    assert len(runs) >= 5
    for (_, b), (c, _) in zip(runs[:-1], runs[1:], strict=True):
        assert 8 <= c - b <= 12  # carried out of view ~1 s between points
    for a, b in runs:
        p = truth[a:b]
        assert b - a == 16  # one full turn, one scan per heading
        step = _wrap(np.diff(p[:, 2]))
        assert np.all(np.abs(step - math.radians(22.5)) <= math.radians(3.01))
        assert np.all(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1) <= 0.01)  # on the spot
    starts = np.array([truth[a, :2] for a, _ in runs])
    assert np.all(np.linalg.norm(np.diff(starts, axis=0), axis=1) >= 0.3)  # a new point each time
    # Rendered where present, not rendered while carried: no return near where it stood.
    for a, b in runs[:3]:
        assert all(len(_robot_returns(log, t)) >= 5 for t in range(a, b))
        pts = _points_o(log)[b + 2]
        assert np.sum(np.linalg.norm(pts - truth[b - 1, :2], axis=1) < 0.3) == 0


def test_rates_replace_the_scanners_period():
    log, _ = recording("hall", "turn", rate_hz=40.0, seconds=4.0)
    assert log.sensor_model == "URG-04LX" and log.n_beams == 682
    np.testing.assert_allclose(np.diff(log.stamps), 0.025, atol=1e-6)
    gaps = [c - b for (_, b), (c, _) in zip(_runs(~np.isnan(log.truth_poses[:, 0, 0]))[:-1],
                                              _runs(~np.isnan(log.truth_poses[:, 0, 0]))[1:], strict=True)]
    assert gaps and all(32 <= g <= 48 for g in gaps)  # still ~1 s away, now 40 scans
    log, _ = recording("lab", "walk", rate_hz=10.0, seconds=3.0)
    assert log.sensor_model == "UTM-30LX" and log.n_scans == 30 and log.intensities is not None
    np.testing.assert_allclose(np.diff(log.stamps), 0.1, atol=1e-6)
    log, _ = recording("lab", "walk", seconds=1.0)
    np.testing.assert_allclose(np.diff(log.stamps), 0.025, atol=1e-6)  # the UTM-30LX's own 40 Hz
    log, _ = simulate("hall-train-turn-40hz", n_scans=20)
    np.testing.assert_allclose(np.diff(log.stamps), 0.025, atol=1e-6)


def test_hold_leaves_each_pose_two_seconds_or_more_one_heading_per_sector():
    log, _ = recording("spl", "hold", seed=1, seconds=30.0)
    truth = log.truth_poses[:, 0]
    present = ~np.isnan(truth[:, 0])
    runs = _runs(present)
    assert len(runs) >= 7
    for (_, b), (c, _) in zip(runs[:-1], runs[1:], strict=True):
        assert 8 <= c - b <= 12  # carried away ~1 s
    for a, b in runs:
        assert 2.0 - 1e-9 <= (b - a) * 0.1 <= 3.1  # 2–3 s on the spot
        assert np.all(truth[a:b] == truth[a])  # not moving
    first = np.array([truth[a] for a, _ in runs[:8]])
    assert np.all(np.linalg.norm(first[:, :2] - first[0, :2], axis=1) <= 0.03)  # one point, put down ±1 cm
    sectors = np.round((first[:, 2] + np.pi) / (np.pi / 4)).astype(int) % 8  # 45° sectors about -180°, -135°, ...
    assert len(set(sectors)) == 8  # eight headings, one in each sector
    assert np.ptp(np.mod(first[:, 2], np.pi / 4)) > math.radians(5)  # not just multiples of 45°


def test_carried_is_continuous_at_carrying_speed():
    log, _ = recording("spl", "carried", seed=3, seconds=60.0)
    truth = log.truth_poses[:, 0]
    assert not np.isnan(truth).any()  # carried in view: never absent
    v = np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1) / np.diff(log.stamps)
    assert 0.8 <= v.max() <= 1.2 + 1e-6
    moving = np.nonzero(v > 0.5)[0]
    assert len(moving) >= 5  # a carry across the field, not one jump
    turn = np.abs(_wrap(np.diff(truth[:, 2])))
    assert turn.max() < math.radians(90)  # the heading turns on the way, no jump
    # Rendered while carried, too.
    assert all(len(_robot_returns(log, t + 1)) >= 3 for t in moving)
    still = np.all(np.diff(truth, axis=0) == 0, axis=1)
    assert any((b - a) * 0.1 >= 1.9 for a, b in _runs(still))  # poses held as in "hold"


def test_walk_and_grid():
    log, _ = recording("spl", "walk", seed=4, seconds=10.0)
    truth = log.truth_poses[:, 0]
    assert log.n_scans == 100 and not np.isnan(truth).any()
    v = np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1) / np.diff(log.stamps)
    assert v.max() <= 0.45 and v.min() > 0.05
    log, _ = recording("spl", "grid", seed=4, seconds=12.0)
    truth = log.truth_poses[:, 0]
    assert log.n_scans % 3 == 0 and 60 <= log.n_scans <= 120 and not np.isnan(truth).any()
    blocks = truth.reshape(-1, 3, 3)
    assert np.all(blocks == blocks[:, :1])  # three scans per pose
    assert np.all(np.any(blocks[1:, 0] != blocks[:-1, 0], axis=1))  # from one pose to the next between two scans
    jump = np.abs(_wrap(blocks[1:, 0, 2] - blocks[:-1, 0, 2]))
    assert math.radians(30) < np.median(jump) < math.radians(60)  # the next heading, ~45° on


def test_box_outline_is_rendered_and_differs_from_the_nao():
    def body_points(outline):
        log, _ = recording("lab", "hold", seed=5, seconds=12.0, outline=outline, rate_hz=10.0)
        out = []
        for t in np.nonzero(~np.isnan(log.truth_poses[:, 0, 0]))[0][::3]:
            out.append(_in_body(_robot_returns(log, t, radius=0.4), log.truth_poses[t, 0]))
        return np.concatenate(out)

    box = body_points("box")
    assert len(box) > 100
    tol = 0.05  # 5 σ of the UTM-30LX's 1 cm range noise
    assert np.all(np.abs(box[:, 0]) <= 0.18 + tol) and np.all(np.abs(box[:, 1]) <= 0.12 + tol)
    q = np.quantile(np.abs(box), 0.99, axis=0)
    assert q[0] <= 0.18 + 0.025 and q[1] <= 0.12 + 0.025
    # Its faces are where a 0.36 × 0.24 m box has them: most points near one of the four faces.
    on_face = np.minimum(np.abs(np.abs(box[:, 0]) - 0.18), np.abs(np.abs(box[:, 1]) - 0.12)) < 0.03
    assert on_face.mean() > 0.9
    assert np.any(box[:, 0] > 0.135 + 0.02)  # beyond the Nao's half-width (and its front face at 0.06)
    nao = body_points("nao")
    assert np.all(nao[:, 0] <= 0.06 + tol) and np.all(np.abs(nao[:, 1]) <= 0.135 + tol)


def _static_scene_parts(lay):
    """Walls as segments, other objects as (x, y, radius) and boxes, from the layout's statics."""
    walls = [p.vertices for p in lay.statics.polygons if len(p.vertices) == 2]
    boxes = [p.vertices for p in lay.statics.polygons if len(p.vertices) > 2]
    return walls, [(c.x, c.y, c.radius) for c in lay.statics.circles], boxes


def _unexplained(log, lay):
    """Per scan, the returns that are neither the robot, a wall nor an object of the layout."""
    walls, circles, boxes = _static_scene_parts(lay)
    pts = _points_o(log)
    out = []
    for t in range(log.n_scans):
        p = pts[t][~np.isnan(pts[t, :, 0])]
        keep = np.ones(len(p), bool)
        if not np.isnan(log.truth_poses[t, 0, 0]):
            keep &= np.linalg.norm(p - log.truth_poses[t, 0, :2], axis=1) > 0.35
        for a, b in walls:
            ab = b - a
            s = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
            keep &= np.linalg.norm(p - (a + s[:, None] * ab), axis=1) > 0.1
        for x, y, r in circles:
            keep &= np.hypot(p[:, 0] - x, p[:, 1] - y) > r + 0.1
        for v in boxes:
            lo, hi = v.min(0) - 0.1, v.max(0) + 0.1
            keep &= ~np.all((p >= lo) & (p <= hi), axis=1)
        out.append(p[keep])
    return out


def test_clutter_is_background_away_from_robot_poses():
    lay = spl_layout()
    clean, _ = recording("spl", "hold", seed=6, seconds=8.0)
    messy, _ = recording("spl", "hold", seed=6, seconds=8.0, clutter=True)
    np.testing.assert_array_equal(clean.truth_poses, messy.truth_poses)  # the same poses, the room differs
    assert sum(len(u) for u in _unexplained(clean, lay)) <= 2  # nothing but the layout and the robot
    extra = _unexplained(messy, lay)
    assert np.mean([len(u) >= 10 for u in extra]) > 0.95  # chairs, a bag, people in every scan
    pts = np.concatenate(extra)
    grid = _grid(lay.bounds, lay.sensor_pose[:2])
    d = np.min(np.linalg.norm(pts[:, None] - grid[None], axis=-1), axis=1)
    assert d.min() >= 0.4  # clear of every training pose: labels stay clean
    x0, y0, x1, y1 = lay.bounds
    near_field = (pts[:, 0] > x0 - 1.1) & (pts[:, 0] < x1 + 1.1) & (pts[:, 1] > y0 - 1.1) & (pts[:, 1] < y1 + 1.1)
    assert near_field.all()
    # Something walks: the clutter's returns are not the same from scan to scan.
    first, last = extra[0], extra[-1]
    moved = np.min(np.linalg.norm(last[:, None] - first[None], axis=-1), axis=1) > 0.1
    assert moved.sum() >= 3


def test_check_scenes():
    log, _ = check_scene("hall", "static", seed=1)
    truth = log.truth_poses[:, 0]
    runs = _runs(~np.isnan(truth[:, 0]))
    assert len(runs) == 6 and runs[0][0] == 10 and log.n_scans == 180  # 1 s away before each, 2 s each
    assert all(b - a == 20 and np.all(truth[a:b] == truth[a]) for a, b in runs)
    poses = np.array([truth[a] for a, _ in runs])
    grid = _grid((0.0, 0.0, 6.0, 4.0), (3.0, 4.5))
    assert np.min(np.linalg.norm(poses[:, None, :2] - grid[None], axis=-1)) > 0.2  # not training poses
    assert np.any(np.abs(_wrap(poses[:, 2] * 4)) > math.radians(8))  # headings off the multiples of 45°
    assert np.ptp(poses[:, 0]) > 2.0 and np.ptp(poses[:, 1]) > 1.0  # spread over the field
    train, _ = recording("hall", "hold", seed=1, seconds=5.0)
    assert not np.array_equal(train.ranges[:20], log.ranges[:20])
    log, _ = check_scene("spl", "walking", seed=2, rate_hz=10.0, outline="box")
    assert log.n_scans == 300 and not np.isnan(log.truth_poses).any()
    v = np.linalg.norm(np.diff(log.truth_poses[:, 0, :2], axis=0), axis=1) / np.diff(log.stamps)
    assert v.max() <= 0.45


def test_new_scenarios_listed_and_bad_arguments_refused(capsys):
    for name in ("spl-train-turn", "hall-train-turn", "hall-train-turn-40hz"):
        assert name in SCENARIOS
    assert main(["simulate", "--list"]) == 0
    assert "hall-train-turn" in capsys.readouterr().out
    log, _ = simulate("spl-train-turn", seed=0, n_scans=30)
    assert log.n_scans == 30
    with pytest.raises(InputError):
        recording("field", "turn")
    with pytest.raises(InputError):
        recording("spl", "spin")
    with pytest.raises(InputError):
        recording("spl", "turn", outline="cylinder")
    with pytest.raises(InputError):
        recording("spl", "turn", rate_hz=0.0)
    with pytest.raises(InputError):
        check_scene("spl", "moving")


def test_existing_scenarios_still_render_the_nao_as_before():
    """``spl-train`` as it was made before recording styles: the training grid, eight headings one
    per sector with 2 cm jitter, three scans per pose, the Nao's outline, rendered with the seed's
    noise stream; rebuilt here from the primitives."""
    lay = spl_layout()
    rng = np.random.default_rng(0)
    poses = []
    for x, y in _grid(lay.bounds, lay.sensor_pose[:2]):
        for k in range(8):
            th = -math.pi + k * math.pi / 4 + rng.uniform(-math.pi / 8, math.pi / 8)
            p = [x + rng.normal(0, 0.02), y + rng.normal(0, 0.02), th]
            poses += [p] * 3
    poses = np.array(poses)
    idx = np.linspace(0, len(poses) - 1, 60).round().astype(int)
    poses = poses[idx]
    scene = Scene(circles=list(lay.statics.circles), polygons=list(lay.statics.polygons),
                  movers=[Mover(Polygon(NAO_OUTLINE, NAO_REFLECTIVITY), poses)])
    sensor = np.repeat(np.array([lay.sensor_pose]), len(poses), 0)
    ranges, _ = render(scene, lay.sensor, sensor, rng=np.random.default_rng([0, 1]))
    log, _ = simulate("spl-train", seed=0, n_scans=60)
    np.testing.assert_array_equal(log.truth_poses[:, 0], poses)
    np.testing.assert_array_equal(log.ranges, ranges)
    assert isinstance(lay.statics.circles[0], Circle)
