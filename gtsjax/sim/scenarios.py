"""Scenarios: labelled scan logs and their site files, from the paper's SPL experiment, a second
site with another sensor and layout, and a clean hall (robot, posts and walls, nothing else).

Each scenario is a function of a seed that lays out a scene, the sensor's true pose over time and
every labelled object's pose over time; :func:`simulate` renders it into a :class:`ScanLog` (with
``truth_classes``, ``truth_poses`` and the extra key ``truth_sensor_pose``) and a :class:`Site` whose
``sensor_pose`` is the user's rough guess: the true pose off by a few centimetres and degrees.

:func:`recording` makes a training log the way a user records one (:data:`STYLES`: turned on the spot,
held, the old grid, walking, carried in view), of either robot outline (the Nao or a box), at any
scan rate, with clutter at the field's edge if asked; :func:`check_scene` the held-out scenes to check
the model trained on it. Both render through :func:`render_plan`, as :func:`simulate` does.

Where the scanner reports intensity (a UTM-30LX) the robots wear reflective tags by default
(:mod:`gtsjax.sim.tagging`): the site records who wears which code (its ``tags`` entry) and the log
each labelled object's name (``truth_names``); ``tags=False`` renders them bare, as before.
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
from .scene import Circle, Effects, Mover, MovingCircle, Polygon, Scene, box, render, robot_shape, walls
from .tagging import RobotTags, robot_tags, wants_tags

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
    outline: str = "nao"  # the robots' outline (scene.OUTLINES)


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


# ------------------------------------------------------------------------- recording styles
#
# The ways users record a training log : each style a habit, on a site's training grid
# (:func:`_grid_points` at 0.5 × 0.4 m), for either robot outline, at the scanner's rate or another.

SITES: dict[str, Callable[[], Layout]] = {"spl": spl_layout, "lab": lab_layout, "hall": hall_layout}

STYLES: dict[str, str] = {
    "turn": "at each grid point the robot turned on the spot through 16 headings, one scan per heading "
            "(+22.5° a scan, ~5 mm wobble), then carried out of view (~1 s, no truth) to the next point",
    "hold": "put down at each grid point with 8 headings (one per 45° sector, ±1 cm), left 2–3 s each, "
            "carried out of view (~1 s, no truth) between poses",
    "grid": "the training grid as spl-train: 8 headings per point, 3 scans per pose, jumping from one pose "
            "to the next between scans",
    "walk": "the robot walking a Lissajous path at 0.1–0.4 m/s (60 s unless `seconds`)",
    "carried": "poses as 'hold', but carried in view between them, no gap: a straight line at 0.8–1.2 m/s "
               "while the heading turns to the next pose's",
}
"""Recording styles of :func:`recording`, by name."""

CHECK_KINDS: dict[str, str] = {
    "static": "the robot put down at 6 points between the grid's, any heading, 2 s each, 1 s away between",
    "walking": "the robot walking a Lissajous path for 30 s",
}
"""Held-out check scenes of :func:`check_scene`, by name."""

_BUDGET_SCANS = 2000  # what a grid recording aims at without `seconds`
_GAP_S = (0.8, 1.2)  # carried out of view between poses
_HOLD_S = (2.0, 3.0)  # left on the spot
_TURN_HEADINGS = 16
_TURN_WOBBLE = 0.0045  # m: how far a robot turned by hand strays from its spot
_TURN_JITTER = math.radians(1.5)  # about its 22.5° steps
_CARRY_SPEED = (0.8, 1.2)  # m/s
_CARRY_TURN_RATE = 2 * math.pi  # rad/s: at most, while carried
_CARRY_MIN_S = 0.6  # picked up, turned, put down: never quicker
_CLEAR = 0.45  # m: clutter from the rectangle of grid points (robot poses all lie within it)
_WALKER_R = 0.26  # m: a walking person's legs about their path (0.1 + 0.06 beside it, more along)


def _site_layout(site: str, rate_hz: float | None) -> Layout:
    """The site's layout, its sensor running at ``rate_hz`` where given (the same model, its period
    replaced)."""
    if site not in SITES:
        raise InputError(site, f"unknown site; known: {', '.join(SITES)}")
    lay = SITES[site]()
    if rate_hz is not None:
        rpm = float(rate_hz) * 60.0
        if not (math.isfinite(rpm) and rpm >= 1 and abs(rpm - round(rpm)) < 1e-6 * rpm):
            raise InputError(f"rate {rate_hz}", "a scan rate must be positive, a whole number of scans a minute")
        lay = dataclasses.replace(lay, sensor=dataclasses.replace(lay.sensor, scan_rpm=int(round(rpm))))
    return lay


def _training_grid(lay: Layout) -> list[tuple[float, float]]:
    return _grid_points(lay.bounds, 0.5, 0.4, near_sensor=lay.sensor_pose[:2])


def _serpentine(pts) -> list[tuple[float, float]]:
    """Grid points column by column, every other column backwards: each point next to the one before."""
    xs = sorted({round(x, 9) for x, _ in pts})
    out = []
    for i, x in enumerate(xs):
        col = sorted((p for p in pts if round(p[0], 9) == x), key=lambda p: p[1])
        out += col if i % 2 == 0 else col[::-1]
    return out


def _pick(pts, n: int) -> list:
    """``n`` of the points, evenly spread along their order."""
    if n >= len(pts):
        return list(pts)
    return [pts[i] for i in np.unique(np.linspace(0, len(pts) - 1, n).round().astype(int))]


def _absent(n: int) -> np.ndarray:
    return np.full((n, 3), np.nan)


def _gap(rng, period: float) -> np.ndarray:
    return _absent(max(1, round(rng.uniform(*_GAP_S) / period)))


def _join(units: list[np.ndarray], budget: int | None) -> np.ndarray:
    """The units one after another; with a ``budget``, only the whole units that fit (at least one)."""
    if budget is not None:
        total = keep = 0
        for u in units:
            if keep and total + len(u) > budget:
                break
            total += len(u)
            keep += 1
        units = units[:keep]
    return np.concatenate(units)


def turn_poses(points, rng, period: float) -> list[np.ndarray]:
    """Style ``turn``, one unit per point: (after the first) the robot carried out of view for ~1 s,
    then put down near the point (2 cm) and turned on the spot through 16 headings, one scan each, each
    +22.5° (±3°) from the one before, within 4.5 mm of its spot."""
    units = []
    k = np.arange(_TURN_HEADINGS)
    for i, (x, y) in enumerate(points):
        gap = _gap(rng, period) if i else _absent(0)
        spot = np.array([x, y]) + rng.normal(0, 0.02, 2)
        th = rng.uniform(-math.pi, math.pi) + k * 2 * math.pi / _TURN_HEADINGS
        th = th + rng.uniform(-1, 1, k.size) * _TURN_JITTER
        r = _TURN_WOBBLE * np.sqrt(rng.random(k.size))  # consecutive scans at most 9 mm apart
        a = rng.uniform(0, 2 * math.pi, k.size)
        xy = spot + np.column_stack([r * np.cos(a), r * np.sin(a)])
        units.append(np.vstack([gap, np.column_stack([xy, wrap(th)])]))
    return units


def _placements(points, rng, period: float) -> list[tuple[np.ndarray, int]]:
    """Eight poses per point, one heading in each 45° sector, put down within ±1 cm of the point, and
    how many scans each is left (2–3 s)."""
    out = []
    for x, y in points:
        for k in range(8):
            th = -math.pi + k * math.pi / 4 + rng.uniform(-math.pi / 8, math.pi / 8)
            pose = np.array([x + rng.uniform(-0.01, 0.01), y + rng.uniform(-0.01, 0.01), th])
            out.append((pose, math.ceil(rng.uniform(*_HOLD_S) / period - 1e-9)))
    return out


def hold_poses(points, rng, period: float) -> list[np.ndarray]:
    """Style ``hold``, one unit per pose: (after the first) carried out of view for ~1 s, then left
    2–3 s."""
    return [np.vstack([_gap(rng, period) if i else _absent(0), np.repeat(pose[None], n, 0)])
            for i, (pose, n) in enumerate(_placements(points, rng, period))]


def carry(a: np.ndarray, b: np.ndarray, rng, period: float) -> np.ndarray:
    """Carried in view from pose ``a`` to pose ``b``: a straight line at 0.8–1.2 m/s (slower only
    where the heading's turn or the picking up and putting down takes longer), the heading turning
    evenly to ``b``'s; the scans strictly between (``b`` is the next pose's first scan)."""
    d = float(np.hypot(*(b[:2] - a[:2])))
    dth = float(wrap(b[2] - a[2]))
    dur = max(d / rng.uniform(*_CARRY_SPEED), abs(dth) / _CARRY_TURN_RATE, _CARRY_MIN_S)
    f = np.arange(1, math.ceil(dur / period - 1e-9)) * period / dur
    return np.column_stack([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), wrap(a[2] + f * dth)])


def carried_poses(points, rng, period: float) -> list[np.ndarray]:
    """Style ``carried``, one unit per pose: (after the first) carried in view from the pose before,
    then left 2–3 s."""
    units, prev = [], None
    for pose, n in _placements(points, rng, period):
        moving = carry(prev, pose, rng, period) if prev is not None else _absent(0)
        units.append(np.vstack([moving, np.repeat(pose[None], n, 0)]))
        prev = pose
    return units


def _scans_per_point(style: str, rate: float) -> float:
    return {"turn": _TURN_HEADINGS + 1.0 * rate, "hold": 8 * (2.5 + 1.0) * rate,
            "carried": 8 * (2.5 + 0.8) * rate, "grid": 24.0}[style]


def _recording_plan(site: str, style: str, rng, *, rate_hz: float | None = None, clutter: bool = False,
                    outline: str = "nao", seconds: float | None = None, n: int | None = None) -> Plan:
    if style not in STYLES:
        raise InputError(style, f"unknown recording style; known: {', '.join(STYLES)}")
    robot_shape(outline)  # a known outline
    if seconds is not None and not seconds > 0:
        raise InputError(f"seconds {seconds}", "a recording's length must be positive")
    lay = _site_layout(site, rate_hz)
    clutter_rng = rng.spawn(1)[0]  # the room's clutter, whatever the style (the poses' stream unchanged)
    period = lay.sensor.period
    if style == "walk":
        robots = _trajectory(lambda: lay, seconds=60.0 if seconds is None else seconds)(rng, n).robots[:, 0]
    else:
        pts = _training_grid(lay)
        budget = None if seconds is None else max(1, int(round(seconds / period)))
        if style == "grid":
            if budget is not None:
                pts = _pick(pts, max(1, math.ceil(budget / _scans_per_point(style, 1 / period))))
            p = training_poses(pts, rng, 3)
            units = list(p.reshape(-1, 3, 3))
        else:
            need = _scans_per_point(style, 1 / period)
            n_pts = max(2, int(_BUDGET_SCANS // need)) if budget is None else max(2, math.ceil(budget / need))
            pts = _pick(_serpentine(pts), n_pts)
            units = {"turn": turn_poses, "hold": hold_poses, "carried": carried_poses}[style](pts, rng, period)
        robots = _join(units, budget)
    return _dress(lay, robots[:, None, :], clutter_rng if clutter else None, outline)


def _check_points(lay: Layout, rng, k: int = 6) -> list[tuple[float, float]]:
    """``k`` points midway between the training grid's (0.32 m from the nearest), spread over the
    field: one from each of six parts (3 × 2) in turn."""
    g = _training_grid(lay)
    xs, ys = sorted({x for x, _ in g}), sorted({y for _, y in g})
    cells = [(x + 0.25, y + 0.2) for x in xs[:-1] for y in ys[:-1]]
    cells = [c for c in cells if math.dist(c, lay.sensor_pose[:2]) >= 1.0]
    x0, y0, x1, y1 = lay.bounds
    part = [min(2, int(3 * (cx - x0) / (x1 - x0))) * 2 + min(1, int(2 * (cy - y0) / (y1 - y0))) for cx, cy in cells]
    out = []
    for j in rng.permutation(6):
        mine = [c for c, p in zip(cells, part, strict=True) if p == j and c not in out]
        if mine:
            out.append(mine[rng.integers(len(mine))])
    while len(out) < k:
        rest = [c for c in cells if c not in out]
        out.append(rest[rng.integers(len(rest))])
    return out[:k]


def _check_plan(site: str, kind: str, rng, *, rate_hz: float | None = None, outline: str = "nao",
                clutter: bool = False) -> Plan:
    if kind not in CHECK_KINDS:
        raise InputError(kind, f"unknown check scene; known: {', '.join(CHECK_KINDS)}")
    robot_shape(outline)
    lay = _site_layout(site, rate_hz)
    clutter_rng, pose_rng = rng.spawn(2)  # the same room as the recording of this seed, other poses
    period = lay.sensor.period
    if kind == "walking":
        robots = _trajectory(lambda: lay, seconds=30.0)(pose_rng, None).robots[:, 0]
    else:
        hold, gap = round(2.0 / period), round(1.0 / period)
        robots = np.concatenate([np.vstack([_absent(gap), np.repeat([[x, y, pose_rng.uniform(-math.pi, math.pi)]],
                                                                     hold, 0)])
                                 for x, y in _check_points(lay, pose_rng)])
    return _dress(lay, robots[:, None, :], clutter_rng if clutter else None, outline)


def _dress(lay: Layout, robots: np.ndarray, clutter_rng, outline: str) -> Plan:
    """The plan of a static sensor, with the room's clutter where ``clutter_rng`` is given."""
    n = robots.shape[0]
    legs = []
    if clutter_rng is not None:
        lay, legs = add_clutter(lay, clutter_rng, n)
    return Plan(lay, _static_sensor(lay, n), robots, legs, outline=outline)


# ----------------------------------------------------------------------------------- clutter


def _rect_distance(p: np.ndarray, rect) -> np.ndarray:
    """Distance of points ``[K, 2]`` to a rectangle (0 inside)."""
    x0, y0, x1, y1 = rect
    dx = np.maximum(np.maximum(x0 - p[:, 0], p[:, 0] - x1), 0.0)
    dy = np.maximum(np.maximum(y0 - p[:, 1], p[:, 1] - y1), 0.0)
    return np.hypot(dx, dy)


def _seg_distance(p: np.ndarray, a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


class _Room:
    """Where clutter may stand in a layout: outside the rectangle of training-grid points by
    ``_CLEAR`` (so that every robot pose of a recording, a check scene or a walk keeps clear of it),
    within 1 m of the field, inside the walls, away from the landmarks, the layout's other objects,
    the sensor and its lines of sight to the landmarks, and in the sensor's view and range."""

    def __init__(self, lay: Layout):
        g = np.asarray(_training_grid(lay))
        self.keep_out = (g[:, 0].min(), g[:, 1].min(), g[:, 0].max(), g[:, 1].max())
        self.lay = lay
        walls_xy = np.concatenate([p.vertices for p in lay.statics.polygons if len(p.vertices) == 2] or
                                  [np.array([[-1e3, -1e3], [1e3, 1e3]])])
        self.room = (*walls_xy.min(0), *walls_xy.max(0))
        self.boxes = [(*p.vertices.min(0), *p.vertices.max(0)) for p in lay.statics.polygons if len(p.vertices) > 2]
        self.circles = np.array([(c.x, c.y) for c in lay.statics.circles]).reshape(-1, 2)
        self.landmarks = np.array([(x, y) for _, x, y, _ in lay.landmarks])
        self.taken: list[tuple[np.ndarray, float]] = []

    def ok(self, p: np.ndarray, r: float) -> bool:
        """Whether circles of radius ``r`` at points ``p [K, 2]`` may stand here."""
        lay, model = self.lay, self.lay.sensor
        sx, sy, sth = lay.sensor_pose
        rx0, ry0, rx1, ry1 = self.room
        if np.any(_rect_distance(p, self.keep_out) < _CLEAR + r) or np.any(_rect_distance(p, lay.bounds) > 1.0):
            return False
        if np.any((p[:, 0] - r < rx0 + 0.3) | (p[:, 0] + r > rx1 - 0.3) | (p[:, 1] - r < ry0 + 0.3)
                  | (p[:, 1] + r > ry1 - 0.3)):
            return False
        near = lambda pts, d: pts.size and np.min(np.linalg.norm(p[:, None] - pts[None], axis=-1)) < d + r  # noqa: E731
        if near(self.landmarks, 0.5) or near(self.circles, 0.4):
            return False
        if any(np.any(_rect_distance(p, b) < 0.3 + r) for b in self.boxes):
            return False
        rng_s = np.hypot(p[:, 0] - sx, p[:, 1] - sy)
        bearing = wrap(np.arctan2(p[:, 1] - sy, p[:, 0] - sx) - sth)
        if np.any(rng_s < 1.0 + r) or np.any(rng_s + r > model.range_max - 0.2):
            return False
        if np.any(bearing < model.angle_min + 0.2) or np.any(bearing > model.angle_max - 0.2):
            return False
        if any(np.any(_seg_distance(p, (sx, sy), lm) < 0.25 + r) for lm in self.landmarks):
            return False
        return not any(np.min(np.linalg.norm(p[:, None] - q[None], axis=-1)) < 0.4 + r + rq for q, rq in self.taken)


def _walker_path(room: _Room):
    """The longest stretch, 2 m or more, of a line 0.8 m outside one side of the grid's rectangle
    where a person may walk (6 cm legs swinging 0.2 m along and 0.1 m beside it); None where none."""
    gx0, gy0, gx1, gy1 = room.keep_out
    d = 0.8
    best = None
    for a, b in [((gx0, gy0 - d), (gx1, gy0 - d)), ((gx0, gy1 + d), (gx1, gy1 + d)),
                 ((gx0 - d, gy0), (gx0 - d, gy1)), ((gx1 + d, gy0), (gx1 + d, gy1))]:
        a, b = np.asarray(a), np.asarray(b)
        f = np.linspace(0, 1, max(2, int(np.hypot(*(b - a)) / 0.1) + 1))
        pts = a + f[:, None] * (b - a)
        good = np.array([room.ok(q[None], _WALKER_R) for q in pts])
        i = 0
        while i < len(pts):  # runs of good points
            if not good[i]:
                i += 1
                continue
            j = i
            while j + 1 < len(pts) and good[j + 1]:
                j += 1
            length = float(np.hypot(*(pts[j] - pts[i])))
            if length >= 2.0 and (best is None or length > best[0]):
                best = (length, pts[i], pts[j])
            i = j + 1
    return None if best is None else (best[1], best[2])


def add_clutter(lay: Layout, rng, n: int) -> tuple[Layout, list[np.ndarray]]:
    """Background a model must learn to ignore, at the edge of the field: two chairs (four 1.5 cm
    legs on a 0.4 m square), a bag (a 0.35 × 0.25 m box), a person standing (two 6 cm legs 0.2 m
    apart) and a person walking to and fro along one side (:func:`walking_legs`), each where
    :class:`_Room` allows (an item that finds no place is left out). Returns the layout with the
    static clutter among its statics, and the walking person's legs for ``n`` scans."""
    room = _Room(lay)
    legs: list[np.ndarray] = []
    path = _walker_path(room)
    if path is not None:
        a, b = path
        legs = walking_legs(a, b, n, lay.sensor.period, speed=rng.uniform(0.8, 1.1))
        f = np.linspace(0, 1, 20)
        room.taken.append((a + f[:, None] * (b - a), _WALKER_R))
    circles, polygons = list(lay.statics.circles), list(lay.statics.polygons)
    x0, y0, x1, y1 = lay.bounds
    for item in ("chair", "chair", "bag", "person"):
        for _ in range(400):
            c = np.array([rng.uniform(x0 - 1.0, x1 + 1.0), rng.uniform(y0 - 1.0, y1 + 1.0)])
            a = rng.uniform(0, 2 * math.pi)
            rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            if item == "chair":
                local, r = np.array([[-0.2, -0.2], [0.2, -0.2], [0.2, 0.2], [-0.2, 0.2]]), 0.015
            elif item == "bag":
                local, r = np.array([[-0.175, -0.125], [0.175, -0.125], [0.175, 0.125], [-0.175, 0.125]]), 0.0
            else:
                local, r = np.array([[0.0, -0.1], [0.0, 0.1]]), 0.06
            p = c + local @ rot.T
            if not room.ok(np.vstack([p, c[None]]), r):
                continue
            room.taken.append((np.vstack([p, c[None]]), r))
            if item == "bag":
                polygons.append(Polygon(p, np.full(4, 0.3)))
            else:
                circles += [Circle(float(q[0]), float(q[1]), r, 0.4) for q in p]
            break
    return dataclasses.replace(lay, statics=Scene(circles=circles, polygons=polygons)), legs


def _recorded(site: str, style: str, **kw):
    def plan(rng, n):
        return _recording_plan(site, style, rng, n=n, **kw)
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
    "spl-train-turn": ("the recording that broke training: SPL grid, the robot turned on the spot through "
                       "16 headings, one scan each, carried 1 s out of view between points", _recorded("spl", "turn")),
    "hall-train-turn": ("clean hall: the robot turned on the spot, one scan per 22.5°, carried 1 s out of view "
                        "between grid points", _recorded("hall", "turn")),
    "hall-train-turn-40hz": ("clean hall as hall-train-turn, the URG-04LX at 40 Hz", _recorded("hall", "turn", rate_hz=40.0)),
    "spl-train-carried": ("SPL grid, 2–3 s per pose, carried in view at 0.8–1.2 m/s between poses; chairs, a bag and "
                          "people at the field's edge", _recorded("spl", "carried", clutter=True)),
    "lab-train-box": ("second site: a 0.36 × 0.24 m box robot put down 2–3 s per pose, 1 s away between poses; "
                      "chairs, a bag and people about (UTM-30LX at 10 Hz)",
                      _recorded("lab", "hold", outline="box", clutter=True, rate_hz=10.0)),
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
        plan = _take(plan, np.linspace(0, t - 1, n_scans).round().astype(int))
    return plan


def _take(plan: Plan, idx) -> Plan:
    """The plan's scans ``idx`` (an index array or a slice), all else kept."""
    return dataclasses.replace(plan, sensor_poses=plan.sensor_poses[idx], robots=plan.robots[idx],
                               legs=[leg[idx] for leg in plan.legs], tilt=None if plan.tilt is None else plan.tilt[idx])


def plan_tags(plan: Plan, model: SensorModel) -> RobotTags:
    """The codes the plan's robots wear when seen by ``model`` from the layout's sensor."""
    return robot_tags(plan.robots.shape[1], plan.outline, [(plan.layout.sensor_pose[:2], model)], plan.layout.bounds)


def build_scene(plan: Plan, tags: RobotTags | None = None) -> Scene:
    st = plan.layout.statics
    shape = robot_shape(plan.outline)
    movers = [Mover(shape if tags is None else tags.shape(m), plan.robots[:, m]) for m in range(plan.robots.shape[1])]
    legs = [MovingCircle(0.06, leg) for leg in plan.legs]
    return Scene(circles=list(st.circles), polygons=list(st.polygons), movers=movers, moving_circles=legs)


def render_plan(plan: Plan, *, seed: int = 0, model: SensorModel | None = None, effects: Effects = Effects(),
                tilt_deg: tuple[float, float] = (0.0, 0.0), stream: int = 1,
                tags: bool | None = None) -> tuple[ScanLog, Site]:
    """Render a plan into a labelled log and its site file (with a rough sensor-pose guess): the
    layout's sensor model unless ``model`` is given, stamps from ``T0 + 1000 s × seed`` spaced by its
    period, noise from the seed's stream ``stream``; the robots wearing tags where ``tags`` says
    (:func:`~gtsjax.sim.tagging.wants_tags`: by default where the model reports intensity)."""
    model = plan.layout.sensor if model is None else model
    worn = plan_tags(plan, model) if wants_tags(tags, [model]) else None
    rng = np.random.default_rng([seed, stream])
    t = plan.sensor_poses.shape[0]
    tilt = plan.tilt
    if any(tilt_deg):
        tilt = np.repeat(np.radians(np.asarray(tilt_deg, float))[None], t, 0)
    ranges, inten = render(build_scene(plan, worn), model, plan.sensor_poses, tilt=tilt, rng=rng, effects=effects)
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
        extra={"truth_sensor_pose": plan.sensor_poses.astype(np.float64),
               **({"truth_names": np.asarray(worn.names, np.str_)} if worn is not None else {})},
    )
    guess_rng = np.random.default_rng([seed, 2])
    sx, sy, sth = plan.sensor_poses[0]
    guess = (float(sx + guess_rng.normal(0, 0.03)), float(sy + guess_rng.normal(0, 0.03)),
             float(sth + guess_rng.normal(0, math.radians(1.5))))
    site = Site(tuple(Landmark(c, x, y) for c, x, y, _ in lay.landmarks), guess, lay.bounds,
                tags=None if worn is None else worn.site_entry())
    return log, site


def first_seconds(plan: Plan, seconds: float, model: SensorModel | None = None) -> Plan:
    """The plan's scans up to ``seconds`` after its first (at least one), at the period of ``model`` (the
    layout's scanner unless given): the start of the scenario as it would be rendered whole, where
    ``n_scans`` spreads a static grid's scans over all its poses."""
    period = (plan.layout.sensor if model is None else model).period
    n = max(1, min(plan.sensor_poses.shape[0], int(math.floor(seconds / period + 1e-9)) + 1))
    return _take(plan, np.s_[:n])


def simulate(name: str, *, seed: int = 0, n_scans: int | None = None, sensor: str | None = None,
             effects: Effects = Effects(), tilt_deg: tuple[float, float] = (0.0, 0.0),
             tags: bool | None = None, seconds: float | None = None) -> tuple[ScanLog, Site]:
    """Render scenario ``name`` into a labelled log and its site file (with a rough sensor-pose guess);
    ``tags``: robots wearing reflective tags (``None``: where the scanner reports intensity);
    ``seconds``: only its first seconds (:func:`first_seconds`)."""
    model = None if sensor is None else get_model(sensor)
    plan = plan_scenario(name, seed=seed, n_scans=n_scans)
    if seconds is not None:
        plan = first_seconds(plan, seconds, model)
    return render_plan(plan, seed=seed, model=model, effects=effects, tilt_deg=tilt_deg, tags=tags)


def recording(site: str, style: str, *, seed: int = 0, rate_hz: float | None = None, clutter: bool = False,
              outline: str = "nao", seconds: float | None = None, tags: bool | None = None) -> tuple[ScanLog, Site]:
    """A labelled training log of ``site`` ("spl", "lab", "hall") recorded in ``style`` (:data:`STYLES`),
    of a robot of ``outline`` ("nao", "box", "cart"), the site's scanner at ``rate_hz`` (its own rate unless
    given), with chairs, a bag and people at the field's edge if ``clutter``. Grid styles visit an
    even spread of the training grid's points, as many as make about 2000 scans ("grid": all of them);
    ``seconds`` shortens any style to the whole poses (points for "turn") that fit in it, the
    walk to exactly that long. Returns the log and site file as :func:`simulate` does (``tags`` as there)."""
    plan = _recording_plan(site, style, np.random.default_rng(seed), rate_hz=rate_hz, clutter=clutter,
                           outline=outline, seconds=seconds)
    return render_plan(plan, seed=seed, tags=tags)


def check_scene(site: str, kind: str, *, seed: int = 0, rate_hz: float | None = None, outline: str = "nao",
                clutter: bool = False, tags: bool | None = None) -> tuple[ScanLog, Site]:
    """A held-out scene to check a model trained on :func:`recording`'s log of the same site, outline and
    rate: ``kind`` "static" (the robot put down at 6 points between the training grid's, any heading,
    2 s each, 1 s away before each) or "walking" (a 30 s Lissajous walk). With ``clutter``, the same
    room as the recording of this seed; the poses and the noise are the check's own (``tags`` as in
    :func:`simulate`)."""
    plan = _check_plan(site, kind, np.random.default_rng(seed), rate_hz=rate_hz, outline=outline, clutter=clutter)
    return render_plan(plan, seed=seed, stream=3, tags=tags)
