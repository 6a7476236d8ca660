"""Scenarios: labelled scan logs and their site files, from the paper's SPL experiment, a second
site with another sensor and layout, and a clean hall (robot, posts and walls, nothing else).

Each scenario is a function of a seed that lays out a scene, the sensor's true pose over time and
every labelled object's pose over time; :func:`simulate` renders it into a :class:`ScanLog` (with
``truth_classes``, ``truth_poses`` and the extra key ``truth_sensor_pose``) and a :class:`Site` whose
``sensor_pose`` is the user's rough guess: the true pose off by a few centimetres and degrees.
"""

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from ..core.geometry import wrap
from ..errors import InputError
from ..io.logs import ScanLog
from ..io.site import Landmark, Site
from ..sensors import URG_04LX, UTM_30LX, SensorModel, get_model
from .scene import Circle, Effects, Mover, MovingCircle, Scene, box, render, robot_shape, walls

T0 = 1_700_000_000.0  # stamps start here (epoch seconds: they need float64, as real logs do)


@dataclasses.dataclass
class Layout:
    """A site: landmarks, the true sensor pose, field bounds and the static scene around them."""

    landmarks: list[tuple[str, float, float, float]]  # class, x, y, radius
    sensor_pose: tuple[float, float, float]
    bounds: tuple[float, float, float, float]
    statics: Scene
    sensor: SensorModel


def spl_layout() -> Layout:
    """The paper's SPL field: 6 × 4 m, origin at a corner, 0.10 m posts at the goal mouths, the laser on
    the side line at (3, 4) looking into the field; a room around it, a box and a chair outside."""
    posts = [("post", 0.0, 1.3, 0.05), ("post", 0.0, 2.7, 0.05), ("post", 6.0, 1.3, 0.05), ("post", 6.0, 2.7, 0.05)]
    scene = Scene(
        circles=[Circle(x, y, r, 0.8) for _, x, y, r in posts]
        + [Circle(6.5 + dx, 0.3 + dy, 0.015, 0.4) for dx in (0, 0.4) for dy in (0, 0.4)],  # a chair's legs
        polygons=walls(-1.0, -1.2, 7.0, 5.0) + [box(-0.75, 3.2, -0.4, 3.7)],
    )
    return Layout(posts, (3.0, 4.0, -math.pi / 2), (0.0, 0.0, 6.0, 4.0), scene, URG_04LX)


def lab_layout() -> Layout:
    """A second site: an 8 × 5 m lab, a UTM-30LX in a corner, four pillars of 0.16 m diameter."""
    pillars = [("pillar", 7.6, 0.6, 0.08), ("pillar", 7.7, 4.4, 0.08), ("pillar", 2.6, 4.7, 0.08),
               ("pillar", 4.6, 0.2, 0.08)]
    scene = Scene(
        circles=[Circle(x, y, r, 0.7) for _, x, y, r in pillars],
        polygons=walls(-0.6, -0.6, 8.6, 5.6) + [box(3.6, 5.0, 5.2, 5.5, 0.3), box(8.0, 1.8, 8.5, 2.6, 0.6)],
    )
    return Layout(pillars, (0.3, 0.3, math.atan2(4.2, 7.4)), (1.0, 0.8, 7.2, 4.4), scene, UTM_30LX)


def hall_layout() -> Layout:
    """A clean hall: the 6 × 4 m field in an 8.8 × 6.3 m hall, a URG-04LX 0.5 m behind the middle of
    a side line looking into the field, five thin posts (4.5 cm radius) just outside the field, not on
    one line, and nothing else: no boxes, no chairs, no people.

    The walls are long and close enough to be in the scans: within the URG-04LX's 5.6 m on two thirds
    of its beams (the side walls, 1.4 m beside the field, from y ≈ 0.9 m up to the edges of the field
    of view; the back wall behind the laser; the far wall, 5.5 m away, straight ahead). The posts stand
    1 m or more in front of the walls, so that segmentation always breaks between them, and within
    4.5 m of the laser, where a 9 cm post still spans three beams. Where a wall leaves the range window,
    or a shadow of the robot or a post cuts it, a short piece of wall is a candidate, as with real
    walls; those lie 1 m or more outside the field. Everything else the front end keeps is a post or
    the robot (``tests/test_sim.py``).
    """
    posts = [("post", -0.3, 1.4, 0.045), ("post", -0.35, 3.2, 0.045), ("post", 6.3, 1.8, 0.045),
             ("post", 6.35, 3.3, 0.045), ("post", 6.4, 4.3, 0.045)]
    scene = Scene(circles=[Circle(x, y, r, 0.8) for _, x, y, r in posts], polygons=walls(-1.4, -1.0, 7.4, 5.3))
    return Layout(posts, (3.0, 4.5, -math.pi / 2), (0.0, 0.0, 6.0, 4.0), scene, URG_04LX)


@dataclasses.dataclass
class Plan:
    """What a scenario produces before rendering."""

    layout: Layout
    sensor_poses: np.ndarray  # [T, 3] true
    robots: np.ndarray  # [T, M, 3] truth poses (NaN = absent)
    legs: list[np.ndarray] = dataclasses.field(default_factory=list)  # [T, 2] centres of leg circles
    tilt: np.ndarray | None = None  # [T, 2] roll, pitch


# ---------------------------------------------------------------------------------------- motion


def grid_poses(points, rng, scans_per_pose: int, jitter=(0.02, math.radians(3))) -> np.ndarray:
    """A static robot at each point, headings every 45°, ``scans_per_pose`` scans each, each pose
    jittered a little so that no two poses are identical."""
    out = []
    for x, y in points:
        for k in range(8):
            p = np.array([x, y, -math.pi + k * math.pi / 4])
            p[:2] += rng.normal(0, jitter[0], 2)
            p[2] += rng.normal(0, jitter[1])
            out.append(np.repeat(p[None], scans_per_pose, 0))
    return np.concatenate(out)


def training_poses(points, rng, scans_per_pose: int, pos_jitter: float = 0.02) -> np.ndarray:
    """The training grid: at each point eight headings, one drawn uniformly in each 45° sector (so
    that headings between the paper's multiples of 45° are covered too, as a walking robot needs),
    ``scans_per_pose`` scans each."""
    out = []
    for x, y in points:
        for k in range(8):
            th = -math.pi + k * math.pi / 4 + rng.uniform(-math.pi / 8, math.pi / 8)
            p = np.array([x + rng.normal(0, pos_jitter), y + rng.normal(0, pos_jitter), th])
            out.append(np.repeat(p[None], scans_per_pose, 0))
    return np.concatenate(out)


def placed_poses(points, scans_per_pose: int, gap_scans: int) -> np.ndarray:
    """The paper's evaluation as it is done by hand: the robot is put down at each point with each
    heading (every 45°) and left for ``scans_per_pose`` scans, then picked up and carried to the next
    pose, out of the scan plane for ``gap_scans`` scans (NaN rows)."""
    out = []
    for x, y in points:
        for k in range(8):
            out.append(np.full((gap_scans, 3), np.nan))
            out.append(np.repeat(np.array([[x, y, -math.pi + k * math.pi / 4]]), scans_per_pose, 0))
    return np.concatenate(out)


def path_poses(waypoints_fn: Callable[[np.ndarray], np.ndarray], n: int, period: float, rng,
               v_min=0.1, v_max=0.4, max_turn_rate=1.2) -> np.ndarray:
    """Follow a closed curve ``waypoints_fn(u)`` (u in [0, 1)) at a speed varying smoothly between
    ``v_min`` and ``v_max`` m/s, turning towards the direction of motion at most ``max_turn_rate``
    rad/s (a curve may double back on itself, and a robot does not spin round in one scan; a Nao
    walks sideways or backwards meanwhile)."""
    u = np.linspace(0, 1, 4000, endpoint=False)
    pts = waypoints_fn(u)
    seg = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    s_of_u = np.concatenate([[0], np.cumsum(seg)])
    length = s_of_u[-1]
    t = np.arange(n) * period
    phase = rng.uniform(0, 2 * np.pi)
    speed = v_min + (v_max - v_min) * 0.5 * (1 + np.sin(2 * np.pi * t / 17.0 + phase))
    s = np.mod(np.concatenate([[0], np.cumsum(speed[:-1] * period)]) + rng.uniform(0, length), length)
    uu = np.interp(s, s_of_u, np.concatenate([u, [1.0]]))
    p = waypoints_fn(uu)
    p2 = waypoints_fn(np.mod(uu + 1e-3, 1.0))
    motion = np.arctan2(p2[:, 1] - p[:, 1], p2[:, 0] - p[:, 0])
    heading = np.empty(n)
    heading[0] = motion[0]
    step = max_turn_rate * period
    for i in range(1, n):
        turn = np.clip(wrap(motion[i] - heading[i - 1]), -step, step)
        heading[i] = wrap(heading[i - 1] + turn)
    return np.column_stack([p, heading])


def lissajous(cx, cy, ax, ay, phase):
    return lambda u: np.column_stack([cx + ax * np.sin(2 * np.pi * u), cy + ay * np.sin(4 * np.pi * u + phase)])


def line_poses(a, b, n, period, speed, delay=0.0) -> np.ndarray:
    """From ``a`` to ``b`` at ``speed``, starting after ``delay`` seconds; absent (NaN) before and after."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = np.linalg.norm(b - a)
    t = np.arange(n) * period - delay
    f = t * speed / length
    out = np.full((n, 3), np.nan)
    on = (f >= 0) & (f <= 1)
    out[on, :2] = a + f[on, None] * (b - a)
    out[on, 2] = math.atan2(b[1] - a[1], b[0] - a[0])
    return out


def walking_legs(a, b, n, period, speed=0.9, rng=None) -> list[np.ndarray]:
    """A person walking back and forth between ``a`` and ``b``: two legs (centres per scan) that swing
    ±0.2 m along the direction of walking, 0.1 m either side of the path."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = np.linalg.norm(b - a)
    t = np.arange(n) * period
    s = np.mod(t * speed, 2 * length)
    f = np.where(s <= length, s, 2 * length - s) / length
    body = a + f[:, None] * (b - a)
    d = (b - a) / length
    side = np.array([-d[1], d[0]])
    stride = 2 * np.pi * t * speed / 1.2
    legs = []
    for sign in (1.0, -1.0):
        swing = 0.2 * np.sin(stride) * sign
        legs.append(body + swing[:, None] * d + 0.1 * sign * side)
    return legs


# ------------------------------------------------------------------------------------- scenarios


def _static_sensor(layout: Layout, n: int) -> np.ndarray:
    return np.repeat(np.asarray(layout.sensor_pose, float)[None], n, 0)


def _grid_points(bounds, step_x, step_y, margin=0.5, near_sensor=None, min_sensor_dist=0.8):
    x0, y0, x1, y1 = bounds
    xs = np.arange(x0 + margin, x1 - margin + 1e-9, step_x)
    ys = np.arange(y0 + margin * 0.8, y1 - margin * 0.8 + 1e-9, step_y)
    pts = [(x, y) for x in xs for y in ys]
    if near_sensor is not None:
        pts = [p for p in pts if math.dist(p, near_sensor) >= min_sensor_dist]
    return pts


def _train(layout_fn, spp=3):
    def plan(rng, n):
        lay = layout_fn()
        pts = _grid_points(lay.bounds, 0.5, 0.4, near_sensor=lay.sensor_pose[:2])
        robots = training_poses(pts, rng, spp)[:, None, :]
        return Plan(lay, _static_sensor(lay, len(robots)), robots)
    return plan


def _eval(layout_fn, points, hold_s=3.0, gap_s=1.0):
    def plan(rng, n):
        lay = layout_fn()
        rate = 1.0 / lay.sensor.period
        robots = placed_poses(points, int(round(hold_s * rate)), int(round(gap_s * rate)))[:, None, :]
        return Plan(lay, _static_sensor(lay, len(robots)), robots)
    return plan


def _trajectory(layout_fn, seconds=60.0, legs=False, bump=False):
    def plan(rng, n):
        lay = layout_fn()
        period = lay.sensor.period
        n = n or int(round(seconds / period))
        x0, y0, x1, y1 = lay.bounds
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        ax = rng.uniform(0.30, 0.38) * (x1 - x0)
        ay = rng.uniform(0.28, 0.34) * (y1 - y0)
        robots = path_poses(lissajous(cx, cy, ax, ay, rng.uniform(0, 2 * np.pi)), n, period, rng)[:, None, :]
        sensor = _static_sensor(lay, n)
        if bump:
            a = rng.uniform(0, 2 * np.pi)
            sensor[n // 2:] += [0.03 * math.cos(a), 0.03 * math.sin(a), math.radians(2.0) * rng.choice([-1, 1])]
        leg_paths = []
        if legs:
            leg_paths = walking_legs((x0 + 0.4, y1 - 0.5), (x1 - 0.4, y0 + 0.8), n, period, rng=rng)
        return Plan(lay, sensor, robots, leg_paths)
    return plan


def _crossing(layout_fn, seconds=22.0):
    def plan(rng, n):
        lay = layout_fn()
        period = lay.sensor.period
        n = n or int(round(seconds / period))
        x0, y0, x1, y1 = lay.bounds
        w, h = x1 - x0, y1 - y0
        jit = rng.uniform(-0.1, 0.1, 4)
        a = line_poses((x0 + 0.15 * w, y0 + 0.3 * h + jit[0]), (x0 + 0.85 * w, y0 + 0.7 * h + jit[1]), n, period, 0.3)
        # B crosses A's path 1.5 s after A passes the crossing point, so they meet about 0.45 m apart.
        b = line_poses((x0 + 0.15 * w, y0 + 0.7 * h + jit[2]), (x0 + 0.85 * w, y0 + 0.3 * h + jit[3]), n, period, 0.3,
                       delay=1.5)
        c = line_poses((x0 + 0.9 * w, y0 + 0.15 * h), (x0 + 0.1 * w, y0 + 0.15 * h), n, period, 0.25, delay=3.0)
        robots = np.stack([a, b, c], 1)
        return Plan(lay, _static_sensor(lay, n), robots)
    return plan


SPL_EVAL_POINTS = [(1.0, 1.0), (5.0, 1.0), (2.0, 2.0), (4.0, 2.0), (3.0, 1.0), (1.0, 3.0), (5.0, 3.0), (3.0, 2.5)]
LAB_EVAL_POINTS = [(2.2, 1.5), (6.2, 1.3), (4.1, 3.1), (5.7, 3.6), (3.3, 2.3)]
HALL_EVAL_POINTS = [(1.0, 1.0), (5.0, 1.0), (3.0, 1.5), (1.5, 2.5), (4.5, 2.5), (3.0, 3.2)]

SCENARIOS: dict[str, tuple[str, Callable]] = {
    "spl-train": ("paper's training grid on the SPL field: static robot every 0.5 × 0.4 m, 8 headings (one in "
                  "each 45° sector), 3 scans per pose (URG-04LX)", _train(spl_layout)),
    "spl-eval": ("paper's evaluation: static robot put down at 8 points such as (1, 1) and (5, 1), headings "
                 "every 45°, 3 s per pose, carried away for 1 s between poses", _eval(spl_layout, SPL_EVAL_POINTS)),
    "spl-trajectory": ("a robot walking a Lissajous path at 0.1–0.4 m/s for 60 s", _trajectory(spl_layout)),
    "spl-crossing": ("three robots on crossing straight paths, 22 s", _crossing(spl_layout)),
    "spl-legs": ("a robot walking while a person walks across the field, 60 s", _trajectory(spl_layout, legs=True)),
    "spl-bumped": ("a robot walking; the sensor is bumped by 3 cm and 2° half-way, 40 s",
                   _trajectory(spl_layout, seconds=40.0, bump=True)),
    "lab-train": ("second site: 8 × 5 m lab, UTM-30LX in a corner, pillars; training grid",
                  _train(lab_layout)),
    "lab-eval": ("second site: static robot put down at 5 points, headings every 45°, 3 s per pose, 1 s away "
                 "between poses",
                 _eval(lab_layout, LAB_EVAL_POINTS)),
    "lab-trajectory": ("second site: a robot walking a Lissajous path for 30 s at 40 Hz",
                       _trajectory(lab_layout, seconds=30.0)),
    "hall-train": ("clean hall: the 6 × 4 m field among long walls, five thin posts and nothing else "
                   "(URG-04LX on the side); training grid as spl-train", _train(hall_layout)),
    "hall-eval": ("clean hall: static robot put down at 6 points, headings every 45°, 3 s per pose, 1 s away "
                  "between poses", _eval(hall_layout, HALL_EVAL_POINTS)),
    "hall-trajectory": ("clean hall: a robot walking a Lissajous path at 0.1–0.4 m/s for 60 s",
                        _trajectory(hall_layout)),
}


def scenario_names() -> list[str]:
    return list(SCENARIOS)


def plan_scenario(name: str, *, seed: int = 0, n_scans: int | None = None) -> Plan:
    if name not in SCENARIOS:
        raise InputError(name, f"unknown scenario; known: {', '.join(SCENARIOS)}")
    rng = np.random.default_rng(seed)
    plan = SCENARIOS[name][1](rng, n_scans)
    t = plan.sensor_poses.shape[0]
    if n_scans is not None and n_scans != t:
        if n_scans < 1:
            raise InputError(name, f"scan count must be >= 1, got {n_scans}")
        # Static grids: keep every pose represented; motions were generated at the right length.
        idx = np.linspace(0, t - 1, n_scans).round().astype(int)
        plan = Plan(plan.layout, plan.sensor_poses[idx], plan.robots[idx], [leg[idx] for leg in plan.legs],
                    None if plan.tilt is None else plan.tilt[idx])
    return plan


def build_scene(plan: Plan) -> Scene:
    st = plan.layout.statics
    movers = [Mover(robot_shape(), plan.robots[:, m]) for m in range(plan.robots.shape[1])]
    legs = [MovingCircle(0.06, leg) for leg in plan.legs]
    return Scene(circles=list(st.circles), polygons=list(st.polygons), movers=movers, moving_circles=legs)


def simulate(name: str, *, seed: int = 0, n_scans: int | None = None, sensor: str | None = None,
             effects: Effects = Effects(), tilt_deg: tuple[float, float] = (0.0, 0.0)) -> tuple[ScanLog, Site]:
    """Render scenario ``name`` into a labelled log and its site file (with a rough sensor-pose guess)."""
    plan = plan_scenario(name, seed=seed, n_scans=n_scans)
    model = plan.layout.sensor if sensor is None else get_model(sensor)
    rng = np.random.default_rng([seed, 1])
    t = plan.sensor_poses.shape[0]
    tilt = plan.tilt
    if any(tilt_deg):
        tilt = np.repeat(np.radians(np.asarray(tilt_deg, float))[None], t, 0)
    ranges, inten = render(build_scene(plan), model, plan.sensor_poses, tilt=tilt, rng=rng, effects=effects)
    lay = plan.layout
    log = ScanLog(
        ranges=ranges,
        stamps=T0 + seed * 1000.0 + np.arange(t) * model.period,
        angle_min=model.angle_min,
        angle_increment=model.angle_increment,
        intensities=inten,
        range_min=model.range_min,
        range_max=model.range_max,
        sensor_model=model.name,
        truth_classes=np.array(["robot"] * plan.robots.shape[1]),
        truth_poses=plan.robots.astype(np.float64),
        extra={"truth_sensor_pose": plan.sensor_poses.astype(np.float64)},
    )
    guess_rng = np.random.default_rng([seed, 2])
    sx, sy, sth = plan.sensor_poses[0]
    guess = (float(sx + guess_rng.normal(0, 0.03)), float(sy + guess_rng.normal(0, 0.03)),
             float(sth + guess_rng.normal(0, math.radians(1.5))))
    site = Site(tuple(Landmark(c, x, y) for c, x, y, _ in lay.landmarks), guess, lay.bounds)
    return log, site
