"""The simulator against hand-computed geometry, and its files against the spec read with numpy+json."""

import json
import math

import jax
import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.sensors import URG_04LX, UTM_30LX
from gtsjax.sim import SCENARIOS, Effects, Scene, render, simulate
from gtsjax.sim.scene import Circle, Polygon, box, cast

EXACT = Effects(noise=False, dropout=0.0, grazing_cos=0.0)


def expected_circle_ranges(angles, sensor, cx, cy, r):
    """Closed form, beam by beam: distance from the sensor to a circle along each beam, or inf."""
    out = []
    sx, sy, sth = sensor
    for a in angles:
        d = np.array([math.cos(sth + a), math.sin(sth + a)])
        w = np.array([cx - sx, cy - sy])
        b = d @ w
        disc = b * b - (w @ w - r * r)
        out.append(b - math.sqrt(disc) if disc >= 0 and b - math.sqrt(disc) > 0 else math.inf)
    return np.array(out)


def test_circle_ranges_exact_and_with_noise():
    sensor = np.array([[3.0, 4.0, -math.pi / 2]])
    scene = Scene(circles=[Circle(2.5, 2.0, 0.05)])
    r, _, _ = cast(scene, URG_04LX, sensor)
    exp = expected_circle_ranges(URG_04LX.angles, sensor[0], 2.5, 2.0, 0.05)
    hit = np.isfinite(exp)
    assert 5 <= hit.sum() <= 20
    np.testing.assert_array_equal(np.isfinite(r[0]), hit)
    np.testing.assert_allclose(r[0][hit], exp[hit], atol=1e-9)
    # With the URG-04LX noise (0.3 % at 2.06 m: 6.2 mm), 1 mm quantisation, no dropouts: within 4 σ,
    # multiples of 1 mm.
    rng = np.random.default_rng(0)
    noisy, inten = render(scene, URG_04LX, np.repeat(sensor, 50, 0), rng=rng,
                          effects=Effects(dropout=0.0, grazing_cos=0.0))
    assert inten is None  # the URG-04LX reports no intensity
    err = noisy[:, hit] - exp[hit]
    sigma = 0.003 * math.hypot(0.5, 2.0)
    assert np.all(np.abs(err) < 4 * sigma + 0.0005)
    assert abs(err.mean()) < 0.1 * sigma and 0.85 * sigma < err.std() < 1.15 * sigma
    np.testing.assert_allclose(noisy * 1000, np.round(noisy * 1000), atol=1e-3)
    assert np.all(noisy[:, ~hit] == 0)  # nothing else in the scene: no return


def test_pitch_stretches_forward_range_by_one_over_cos():
    wall = Polygon(np.array([[5.0, -3.0], [5.0, 3.0]]), np.array([0.5, 0.5]))
    scene = Scene(polygons=[wall])
    sensor = np.array([[0.0, 0.0, 0.0]])
    front = URG_04LX.afrt - URG_04LX.amin
    for pitch_deg in (0.0, 2.0, 5.0):
        tilt = np.array([[0.0, math.radians(pitch_deg)]])
        r, _, _ = cast(scene, URG_04LX, sensor, tilt)
        assert r[0, front] == pytest.approx(5.0 / math.cos(math.radians(pitch_deg)), abs=1e-9)
    # A roll leaves the forward beam alone but stretches the beam at 90°.
    r, _, _ = cast(Scene(polygons=[Polygon(np.array([[-3.0, 2.0], [3.0, 2.0]]), np.array([0.5, 0.5]))]), URG_04LX,
                   sensor, np.array([[math.radians(4.0), 0.0]]))
    left = int(np.argmin(np.abs(URG_04LX.angles - math.pi / 2)))
    a = URG_04LX.angles[left]
    assert r[0, left] == pytest.approx(2.0 / (math.cos(math.radians(4.0)) * math.sin(a)), rel=1e-9)


def test_hidden_edges_are_not_seen():
    square = box(1.8, -0.2, 2.2, 0.2)
    scene = Scene(polygons=[square])
    sensor = np.array([[0.0, 0.0, 0.0]])
    r, _, _ = cast(scene, URG_04LX, sensor)
    hit = np.isfinite(r[0])
    a = URG_04LX.angles[hit]
    x, y = r[0, hit] * np.cos(a), r[0, hit] * np.sin(a)
    # From the origin only the face x = 1.8 is visible; no hit lies on the back face x = 2.2 or
    # on the side faces beyond the front corner.
    np.testing.assert_allclose(x, 1.8, atol=1e-9)
    assert np.all(np.abs(y) <= 0.2 + 1e-9)


def test_a_cast_in_parts_gives_each_scan_the_numbers_of_a_cast_whole(monkeypatch):
    """Scans are cast in parts that fit the CPU's caches (``scene._CAST_ELEMENTS``): every scan's
    ranges, incidences and reflectivities are those of one cast of all of them, bit for bit."""
    import gtsjax.sim.scene as scene_module

    scene = Scene(circles=[Circle(1.0, 0.5, 0.1), Circle(-2.0, 1.0, 0.3)],
                  polygons=[box(1.8, -0.2, 2.2, 0.2), box(-3.0, -3.0, 3.0, 3.0)])
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(-1, 1, 37), rng.uniform(-1, 1, 37), rng.uniform(-np.pi, np.pi, 37)])
    monkeypatch.setattr(scene_module, "_CAST_ELEMENTS", 1 << 40)
    whole = cast(scene, URG_04LX, poses)
    per_scan = URG_04LX.n_beams * (2 + 8)
    monkeypatch.setattr(scene_module, "_CAST_ELEMENTS", 5 * per_scan)  # parts of 5 scans, the last of 2
    parts = cast(scene, URG_04LX, poses)
    for a, b in zip(whole, parts, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.isfinite(whole[0]).any()


def test_range_window_and_dropouts():
    scene = Scene(circles=[Circle(0.015, 0.0, 0.005), Circle(7.0, 0.5, 0.3)])  # too close; beyond 5.6 m
    ranges, _ = render(scene, URG_04LX, np.zeros((3, 3)), rng=np.random.default_rng(0), effects=EXACT)
    assert np.all(ranges == 0)
    wall = Polygon(np.array([[2.0, -50.0], [2.0, 50.0]]), np.array([0.5, 0.5]))
    ranges, inten = render(Scene(polygons=[wall]), UTM_30LX, np.zeros((200, 3)), rng=np.random.default_rng(1),
                           effects=Effects(dropout=0.05))
    front = np.abs(UTM_30LX.angles) < 1.0
    lost = np.mean(ranges[:, front] == 0)
    assert 0.04 < lost < 0.06
    assert inten is not None and np.all(inten[ranges > 0] > 0) and np.all(inten[ranges == 0] == 0)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_writes_files_per_the_spec(tmp_path, name):
    log_path, site_path = tmp_path / "log.npz", tmp_path / "site.json"
    assert main(["simulate", name, "--out", str(log_path), "--site", str(site_path), "--scans", "12",
                 "--seed", "3"]) == 0
    # Read with numpy and json only, as another program would.
    with np.load(log_path, allow_pickle=False) as z:
        ranges, stamps = z["ranges"], z["stamps"]
        assert ranges.dtype == np.float32 and ranges.shape[0] == 12 and stamps.dtype == np.float64
        assert np.all(np.diff(stamps) > 0)
        assert z["angle_increment"].shape == () and z["angle_increment"] > 0
        poses, classes = z["truth_poses"], z["truth_classes"]
        assert poses.shape == (12, classes.shape[0], 3) and classes.dtype.kind == "U"
        assert np.all(np.isnan(poses).all(-1) | ~np.isnan(poses).any(-1))  # all-NaN rows or none
        valid = ranges > 0
        assert 0.3 < valid.mean() and np.all(ranges[valid] >= z["range_min"]) and np.all(ranges[valid] <= z["range_max"])
        true_sensor = z["truth_sensor_pose"]
    site = json.loads(site_path.read_text())
    assert len(site["landmarks"]) >= 3 and len(site["sensor_pose"]) == 3
    guess_err = np.hypot(*(np.array(site["sensor_pose"][:2]) - true_sensor[0, :2]))
    assert 0 < guess_err < 0.15  # a rough guess, not the truth


def test_bumped_scenario_moves_the_sensor():
    log, _ = simulate("spl-bumped", seed=0, n_scans=None)
    sp = log.extra["truth_sensor_pose"]
    jump = np.diff(sp, axis=0)
    (i,) = np.nonzero(np.any(np.abs(jump) > 1e-12, axis=1))
    assert len(i) == 1
    assert np.hypot(*jump[i[0], :2]) == pytest.approx(0.03) and abs(jump[i[0], 2]) == pytest.approx(math.radians(2))


def test_seeds_differ_and_repeat():
    a, _ = simulate("spl-trajectory", seed=1, n_scans=20)
    b, _ = simulate("spl-trajectory", seed=1, n_scans=20)
    c, _ = simulate("spl-trajectory", seed=2, n_scans=20)
    np.testing.assert_array_equal(a.ranges, b.ranges)
    assert not np.allclose(a.truth_poses, c.truth_poses)


def test_robot_speed_within_limit():
    log, _ = simulate("spl-trajectory", seed=4)
    p = log.truth_poses[:, 0, :2]
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.diff(log.stamps)
    assert v.max() <= 0.4 + 1e-6 and v.min() >= 0.1 - 1e-6


def test_noise_measurement_recovers_the_simulated_noise():
    """``scripts/measure_range_noise.py``, the measurement the URG-04LX noise model rests on, applied to
    a simulated log of the SPL room recovers the simulator's own σ(r) (to within the bias of a median
    of 9-beam window estimates and the 1 mm quantisation)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "measure_range_noise.py"
    spec = importlib.util.spec_from_file_location("measure_range_noise", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    log, _ = simulate("spl-trajectory", seed=5, n_scans=200)
    angles = log.angle_min + log.angle_increment * np.arange(log.n_beams)
    res = mod.window_noise(log.ranges, angles, 9)
    for lo, hi in [(1.5, 2.5), (2.5, 4.0), (4.0, 5.0)]:
        sel = (res[:, 0] >= lo) & (res[:, 0] < hi)
        assert sel.sum() > 50
        truth = float(np.median(URG_04LX.noise.std(res[sel, 0])))
        assert 0.8 * truth < np.median(res[sel, 1]) < 1.1 * truth, (lo, hi, np.median(res[sel, 1]), truth)


@pytest.mark.parametrize("seed", [1002, 7, 31])
def test_walking_robot_turns_no_faster_than_it_can(seed):
    """A trajectory's heading follows the direction of motion but never turns faster than 1.2 rad/s,
    also where the path doubles back (a robot does not spin round between two scans)."""
    log, _ = simulate("spl-trajectory", seed=seed)
    th = log.truth_poses[:, 0, 2]
    rate = np.abs(np.pi - np.mod(np.pi - np.diff(th), 2 * np.pi)) / np.diff(log.stamps)
    assert rate.max() <= 1.2 + 1e-4  # stamps are epoch seconds: their differences round at 1e-7 s
    xy = log.truth_poses[:, 0, :2]
    motion = np.arctan2(np.diff(xy[:, 1]), np.diff(xy[:, 0]))
    lag = np.abs(np.pi - np.mod(np.pi - (motion - th[:-1]), 2 * np.pi))
    assert np.median(lag) < np.radians(5)  # mostly it faces where it walks


HALL = ["hall-train", "hall-eval", "hall-trajectory"]


def _to_o(pose, xy):
    """Points ``[..., 2]`` of the sensor frame S into O, for a sensor at ``pose`` (x, y, θ)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.stack([pose[0] + c * xy[..., 0] - s * xy[..., 1], pose[1] + s * xy[..., 0] + c * xy[..., 1]], -1)


def _segment_distance(p, a, b):
    """Distance of points ``p [..., 2]`` to the segment from ``a`` to ``b``."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


@pytest.mark.parametrize("name", HALL)
def test_hall_is_clean(name):
    """The clean hall holds the robot, posts and walls and nothing else: every candidate the binary
    filters keep is a post or the robot (its ORS origin within 0.3 m of a site landmark or of the true
    robot) or a piece of wall (every one of its points within 5 σ of the range noise of a wall of the layout: walls
    cut short by a shadow or by the range window), and no wall piece comes within 0.5 m of the field
    (training's margin for background examples). The front end finds every post in most scans and the
    robot in nearly every scan it is on the field."""
    from gtsjax.core.frontend import FrontEndConfig, front_end_batch
    from gtsjax.io import to_scans
    from gtsjax.sim.scenarios import hall_layout

    log, site = simulate(name, seed=5, n_scans=120)
    fe = jax.jit(front_end_batch, static_argnames="windows")(FrontEndConfig(), to_scans(log, URG_04LX.n_beams), windows=True)
    keep, origin = np.asarray(fe.keep), np.asarray(fe.features.origin, np.float64)
    xy, mask = np.asarray(fe.candidates.xy, np.float64), np.asarray(fe.candidates.mask)
    sensor = log.extra["truth_sensor_pose"]
    posts = np.array([(lm.x, lm.y) for lm in site.landmarks])
    wall_ends = [(p.vertices[0], p.vertices[1]) for p in hall_layout().statics.polygons]
    x0, y0, x1, y1 = site.bounds
    robot = log.truth_poses[:, 0, :2]
    post_seen = np.zeros((log.n_scans, len(posts)), bool)
    robot_seen = np.zeros(log.n_scans, bool)
    n_wall = 0
    for t, k in zip(*np.nonzero(keep), strict=True):
        o = _to_o(sensor[t], origin[t, k])
        d_post = np.linalg.norm(posts - o, axis=1)
        d_robot = np.linalg.norm(robot[t] - o) if np.isfinite(robot[t, 0]) else np.inf
        if min(d_post.min(), d_robot) <= 0.3:
            post_seen[t] |= d_post <= 0.15
            robot_seen[t] |= d_robot <= 0.3
            continue
        pts_s = xy[t, k][mask[t, k]]
        pts = _to_o(sensor[t], pts_s)
        off_wall = np.min([_segment_distance(pts, a, b) for a, b in wall_ends], axis=0)
        tol = 5 * URG_04LX.noise.std(np.linalg.norm(pts_s, axis=1)) + 0.001  # 5 σ of range noise, 1 mm steps
        assert np.all(off_wall <= tol), f"scan {t}: a candidate at {o.round(2)} is neither post, robot nor wall"
        assert not (x0 - 0.5 <= o[0] <= x1 + 0.5 and y0 - 0.5 <= o[1] <= y1 + 0.5), f"scan {t}: wall piece at {o}"
        n_wall += 1
    present = np.isfinite(robot[:, 0])
    assert robot_seen[present].mean() >= 0.97
    assert post_seen.mean(axis=0).min() >= 0.8, post_seen.mean(axis=0)
    assert n_wall > 0  # the walls are in the scans (and cut into pieces, as real ones are)


def test_hall_walls_fill_most_of_the_view():
    """"Long walls": in the empty hall, the URG-04LX sees a wall within its range window on about two
    thirds of its beams."""
    from gtsjax.sim.scenarios import hall_layout

    lay = hall_layout()
    r, _, _ = cast(lay.statics, lay.sensor, np.array([lay.sensor_pose]))
    assert np.mean(np.isfinite(r[0]) & (r[0] <= lay.sensor.range_max)) > 0.6
    assert not lay.statics.movers and not lay.statics.moving_circles
    assert all(c.radius < 0.05 for c in lay.statics.circles)  # the posts; nothing else stands in the hall


def test_match_scenario_one_log_per_laser_at_its_own_times(tmp_path):
    """``spl-match-2``: one labelled log per laser, the second laser's scans half a period after the
    first's, the same robots (truth) at each laser's own times, robots kept apart, the site listing
    both lasers (round trip through its file)."""
    from gtsjax.io import load_site, save_site
    from gtsjax.sim.match import FIELD, plan_match, render_match, simulate_match

    logs, site = simulate_match("spl-match-2", seed=3, n_robots=6, seconds=3.0)
    assert list(logs) == ["north", "south"] == [s.name for s in site.sensor_list]
    north, south = logs["north"], logs["south"]
    assert north.n_scans == south.n_scans == 30 and north.sensor_model == "URG-04LX"
    np.testing.assert_allclose(south.stamps - north.stamps, URG_04LX.period / 2, atol=1e-6)  # epoch stamps
    match = plan_match(2, URG_04LX, n_robots=6, seconds=3.0, seed=3)
    np.testing.assert_array_equal(north.truth_poses, match.robots[0::2])
    np.testing.assert_array_equal(south.truth_poses, match.robots[1::2])
    xy = match.robots[..., :2]
    gaps = np.linalg.norm(xy[:, :, None] - xy[:, None], axis=-1) + np.eye(6) * 99
    assert gaps.min() > 0.5  # each robot in its own cell
    x0, y0, x1, y1 = FIELD
    assert np.all((xy[..., 0] > x0) & (xy[..., 0] < x1) & (xy[..., 1] > y0) & (xy[..., 1] < y1))
    save_site(site, tmp_path / "site.json")
    assert load_site(tmp_path / "site.json") == site
    for sen, pose in zip(site.sensor_list, ((4.5, 6.5, -np.pi / 2), (4.5, -0.5, np.pi / 2)), strict=True):
        assert np.hypot(sen.pose[0] - pose[0], sen.pose[1] - pose[1]) < 0.15 and sen.model == "URG-04LX"
    again, _ = render_match(match, seed=3)
    np.testing.assert_array_equal(again["north"].ranges, north.ranges)  # seeded


def test_match_penalties_lift_robots_and_put_them_down_on_their_paths():
    """``--penalties``: a match without them is the one it always was (the same poses to the bit); with
    them, each robot is either on its unpenalised path or absent (NaN, in the logs' truth too), the absences last 3–8 s each (merged where one robot's overlap),
    start after the first 2 s and end before the last 2 s, and a robot put down is where its path has
    gone on to."""
    from gtsjax.errors import InputError
    from gtsjax.sim.match import PENALTY_S, plan_match, render_match

    base = plan_match(2, URG_04LX, n_robots=6, seconds=30.0, seed=4)
    np.testing.assert_array_equal(plan_match(2, URG_04LX, n_robots=6, seconds=30.0, seed=4, penalties=0).robots,
                                  base.robots)
    pen = plan_match(2, URG_04LX, n_robots=6, seconds=30.0, seed=4, penalties=5)
    gone = np.isnan(pen.robots[..., 0])
    assert gone.any() and np.all(np.isnan(pen.robots[gone]))
    np.testing.assert_array_equal(pen.robots[~gone], base.robots[~gone])  # put down on its own path
    t = np.arange(len(pen.robots)) * pen.dt
    spans = 0
    for m in range(6):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], gone[:, m].astype(int), [0]])))
        for a, b in zip(edges[0::2], edges[1::2], strict=True):
            spans += 1
            assert t[a] >= 2.0 - pen.dt and t[b - 1] <= 30.0 - 2.0
            assert PENALTY_S[0] - 2 * pen.dt <= t[b - 1] - t[a] + pen.dt  # at least one penalty's length
    assert 1 <= spans <= 5
    logs, _ = render_match(pen, seed=4)
    north = logs["north"]
    np.testing.assert_array_equal(np.isnan(north.truth_poses[..., 0]), gone[pen.rows[0]])
    with pytest.raises(InputError, match="penalties"):
        plan_match(2, URG_04LX, n_robots=6, seconds=9.0, seed=4, penalties=1)
