"""Several lasers on a full-size SPL field: one scene, one log per laser.

Today's SPL field is 9 × 6 m inside a carpet of 10.4 × 7.4 m; the goals' posts (0.10 m) stand on the
goal lines, their centres 0.80 m either side of the middle; four thin poles beside the side lines
(:data:`SIDE_POLES`) give each laser landmarks within its reach. A match puts up to 14 robots on it and a
referee walks about. :func:`simulate_match` lays out such a scene, 2 or 4 lasers on tripods 0.5 m
outside the side lines looking in, robots walking in their own parts of the field (so that they do
not collide, but cross each other's lines of sight all the time) and a referee walking its length;
it renders what each laser sees, at its own scan times (the lasers are not synchronised: laser
``k`` of ``K`` scans ``k / K`` of a period after the first), into one labelled log per laser, and
writes the site with a ``sensors`` list (each pose the true one off by a few cm and degrees, as a
user's tape measure gives it).

Scenario names: ``spl-match-N`` (N lasers, URG-04LX), ``spl-match-N-utm`` (UTM-30LX),
``spl-match-N-mixed`` (the first laser and every other one a URG-04LX, the rest UTM-30LX: two
scanner models on one field, each served by its own trained model); options: the number of robots,
seconds, a referee or not.

Where a laser reports intensity (``-utm``, ``-mixed``) the robots wear reflective tags by default
(:mod:`gtsjax.sim.tagging`; in a mixed match on the robots whatever the laser, the URG-04LX simply
reporting no intensity), their cells sized for the farthest field corner from a UTM-30LX; the site
says who wears which code (``tags``) and every log each robot's name (``truth_names``).
"""

import dataclasses
import math
import re

import numpy as np

from ..errors import InputError
from ..io.logs import ScanLog
from ..io.site import Landmark, Site, SiteSensor
from ..sensors import URG_04LX, UTM_30LX, SensorModel
from .scenarios import T0, lissajous, path_poses, walking_legs
from .scene import Circle, Mover, MovingCircle, Scene, box, render, robot_shape, walls
from .tagging import robot_tags, wants_tags

FIELD = (0.0, 0.0, 9.0, 6.0)
GOAL_POSTS = [("post", 0.0, 2.2, 0.05), ("post", 0.0, 3.8, 0.05), ("post", 9.0, 2.2, 0.05), ("post", 9.0, 3.8, 0.05)]
# The goals' posts stand 4.5 m and more from a laser beside the middle of a side line, at the edge of
# a URG-04LX's reach (5.6 m), where a 0.10 m post spans three beams: too few to be recognised
# reliably, and too few in view for the map transformation. So the site adds thin poles (as a team
# can put up anywhere beside the carpet) 0.35 m outside each side line, a third of the way in from
# each end, within 3.5 m of the lasers on their side.
SIDE_POLES = [("post", 1.5, 6.35, 0.05), ("post", 7.5, 6.35, 0.05), ("post", 1.5, -0.35, 0.05),
              ("post", 7.5, -0.35, 0.05)]
LANDMARKS = GOAL_POSTS + SIDE_POLES
TRIPOD_OFFSET_M = 0.5  # how far outside the side line a tripod stands
PENALTY_S = (3.0, 8.0)  # how long a picked-up robot is off the field (uniform; SPL's 45 s shortened to fit a short log)


def laser_poses(n: int) -> list[tuple[str, tuple[float, float, float]]]:
    """Where the tripods stand: 2 lasers in the middle of the two side lines facing each other; 4 at a
    quarter and three quarters of each side line."""
    x0, y0, x1, y1 = FIELD
    north, south = y1 + TRIPOD_OFFSET_M, y0 - TRIPOD_OFFSET_M
    if n == 1:
        return [("north", (4.5, north, -math.pi / 2))]
    if n == 2:
        return [("north", (4.5, north, -math.pi / 2)), ("south", (4.5, south, math.pi / 2))]
    if n == 4:
        return [("north-west", (2.25, north, -math.pi / 2)), ("north-east", (6.75, north, -math.pi / 2)),
                ("south-west", (2.25, south, math.pi / 2)), ("south-east", (6.75, south, math.pi / 2))]
    raise InputError("spl-match", f"{n} lasers: 1, 2 or 4")


def _scene_statics() -> Scene:
    # The goals' posts, the hall's walls 1.5 m beyond the carpet, the teams' benches behind the goals.
    return Scene(circles=[Circle(x, y, r, 0.8) for _, x, y, r in LANDMARKS],
                 polygons=walls(-2.2, -2.2, 11.2, 8.2) + [box(-1.6, 0.5, -1.2, 2.0), box(10.2, 4.0, 10.6, 5.5)])


@dataclasses.dataclass(frozen=True)
class Match:
    """What a match scenario is made of, before rendering: robots' poses on a fine time grid."""

    lasers: list[tuple[str, tuple[float, float, float]]]
    sensors: list[SensorModel]  # each laser's scanner
    dt: float  # the fine grid's step (the fastest laser's period / number of lasers)
    robots: np.ndarray  # [n_fine, M, 3]
    legs: list[np.ndarray]  # the referee's two legs, [n_fine, 2] each
    rows: list[np.ndarray]  # each laser's scans as rows of the fine grid

    @property
    def sensor(self) -> SensorModel:
        """The first laser's scanner (every laser's, but in a mixed match)."""
        return self.sensors[0]


def plan_match(n_lasers: int, sensor: "SensorModel | list[SensorModel]", n_robots: int = 10, seconds: float = 60.0,
               referee: bool = True, seed: int = 0, penalties: int = 0) -> Match:
    """Robots walking Lissajous paths in their own cells of the field (a grid of cells, one robot
    each; at 0.1–0.4 m/s, as :func:`~gtsjax.sim.scenarios.path_poses`), the referee walking the
    field's length and back, all on a time grid ``K`` times finer than the fastest laser's period.
    ``sensor``: every laser's scanner, or one per laser. Laser ``k`` scans every ``period / dt``
    rows of the grid from row ``k``.

    ``penalties``: so many times in the match a robot is picked up, as a referee takes a penalised
    one off the field, and put down again :data:`PENALTY_S` later where its path has gone on to (up
    to a metre or two from where it was lifted): absent from the scene (and its truth NaN) in between.
    Each picks a robot and a start at random (after the first 2 s, ending before the last 2 s; a robot
    picked twice at overlapping times is out for the union). Drawn from a generator of their own:
    without them a match is the one it always was."""
    if not 1 <= n_robots <= 14:
        raise InputError("spl-match", f"{n_robots} robots: 1 to 14")
    rng = np.random.default_rng(seed)
    lasers = laser_poses(n_lasers)
    sensors = list(sensor) if isinstance(sensor, (list, tuple)) else [sensor] * len(lasers)
    K = len(lasers)
    dt = min(s.period for s in sensors) / K
    scan_rows = [np.arange(int(round(seconds / s.period))) * int(round(s.period / dt)) + k
                 for k, s in enumerate(sensors)]
    n_fine = max(int(r[-1]) + 1 for r in scan_rows)
    x0, y0, x1, y1 = FIELD
    cols = int(math.ceil(n_robots / 2)) if n_robots > 1 else 1
    rows = 2 if n_robots > 1 else 1
    cw, ch = (x1 - x0 - 0.6) / cols, (y1 - y0 - 0.6) / rows
    cells = [(x0 + 0.3 + (i + 0.5) * cw, y0 + 0.3 + (j + 0.5) * ch) for j in range(rows) for i in range(cols)]
    order = rng.permutation(len(cells))[:n_robots]
    robots = []
    for k in order:
        cx, cy = cells[k]
        ax, ay = rng.uniform(0.30, 0.40) * cw, rng.uniform(0.28, 0.36) * ch
        robots.append(path_poses(lissajous(cx, cy, ax, ay, rng.uniform(0, 2 * np.pi)), n_fine, dt, rng))
    legs = walking_legs((x0 + 0.5, y0 + 0.8), (x1 - 0.5, y1 - 1.0), n_fine, dt, speed=1.0, rng=rng) if referee else []
    poses = np.stack(robots, 1)
    if penalties:
        lo_s, hi_s = PENALTY_S
        if seconds < 4.0 + hi_s:
            raise InputError("--penalties", f"a {seconds:g} s match has no room for a penalty of up to {hi_s:g} s "
                                            f"(at least {4.0 + hi_s:g} s)")
        prng = np.random.default_rng([seed, 3])
        for _ in range(penalties):
            m, dur = int(prng.integers(n_robots)), prng.uniform(lo_s, hi_s)
            start = prng.uniform(2.0, seconds - 2.0 - dur)
            poses[int(round(start / dt)):int(round((start + dur) / dt)), m] = np.nan
    return Match(lasers, sensors, dt, poses, legs, scan_rows)


def render_match(match: Match, seed: int = 0, tags: bool | None = None) -> tuple[dict[str, ScanLog], Site]:
    """One labelled log per laser (its scans at its own times: laser ``k`` on the fine grid's rows
    ``match.rows[k]``: ``k, k + K, …`` for lasers of one scanner model) and the site with every laser
    in its ``sensors`` list; the robots wearing tags where ``tags`` says
    (:func:`~gtsjax.sim.tagging.wants_tags`: by default where a laser reports intensity)."""
    st = _scene_statics()
    n_robots = match.robots.shape[1]
    worn = (robot_tags(n_robots, "nao", [(pose[:2], m) for (_, pose), m in zip(match.lasers, match.sensors, strict=True)],
                       FIELD) if wants_tags(tags, match.sensors) else None)
    scene = Scene(circles=list(st.circles), polygons=list(st.polygons),
                  movers=[Mover(robot_shape() if worn is None else worn.shape(m), match.robots[:, m])
                          for m in range(n_robots)],
                  moving_circles=[MovingCircle(0.06, leg) for leg in match.legs])
    logs, sensors = {}, []
    guess_rng = np.random.default_rng([seed, 2])
    for k, (name, pose) in enumerate(match.lasers):
        rows = match.rows[k]
        fine_poses = np.repeat(np.asarray(pose, float)[None], match.robots.shape[0], 0)
        # The scene's movers are indexed by the fine grid; render only this laser's rows.
        sub = Scene(circles=scene.circles, polygons=scene.polygons,
                    movers=[Mover(m.shape, m.poses[rows]) for m in scene.movers],
                    moving_circles=[MovingCircle(c.radius, c.centres[rows], c.reflectivity)
                                    for c in scene.moving_circles])
        m = match.sensors[k]
        ranges, inten = render(sub, m, fine_poses[rows], rng=np.random.default_rng([seed, 1, k]))
        logs[name] = ScanLog(
            ranges=ranges, stamps=T0 + seed * 1000.0 + rows * match.dt, angle_min=m.angle_min,
            angle_increment=m.angle_increment, intensities=inten, range_min=m.range_min, range_max=m.range_max,
            sensor_model=m.name, truth_classes=np.array(["robot"] * match.robots.shape[1]),
            truth_poses=match.robots[rows].astype(np.float64),
            extra={"truth_sensor_pose": fine_poses[rows].astype(np.float64),
                   **({"truth_names": np.asarray(worn.names, np.str_)} if worn is not None else {})})
        sx, sy, sth = pose
        guess = (float(sx + guess_rng.normal(0, 0.03)), float(sy + guess_rng.normal(0, 0.03)),
                 float(sth + guess_rng.normal(0, math.radians(1.5))))
        sensors.append(SiteSensor(name, guess, m.name))
    site = Site(tuple(Landmark(c, x, y) for c, x, y, _ in LANDMARKS), sensors[0].pose, FIELD, {}, tuple(sensors),
                None if worn is None else worn.site_entry())
    return logs, site


MATCH_NAME = re.compile(r"^spl-match-(\d)(-utm|-mixed)?$")


def is_match(name: str) -> bool:
    return MATCH_NAME.match(name) is not None


def simulate_match(name: str, *, seed: int = 0, n_robots: int = 10, seconds: float = 60.0,
                   referee: bool = True, tags: bool | None = None, penalties: int = 0) -> tuple[dict[str, ScanLog], Site]:
    """``spl-match-N[-utm|-mixed]``: N lasers (1, 2 or 4), URG-04LX, UTM-30LX or both (alternating:
    the first a URG-04LX), ``n_robots`` walking, picked up and put down ``penalties`` times
    (:func:`plan_match`); ``tags`` as :func:`render_match`."""
    m = MATCH_NAME.match(name)
    if m is None:
        raise InputError(name, "not a match scenario (spl-match-N, spl-match-N-utm or spl-match-N-mixed, N = 1, 2, 4)")
    n = int(m.group(1))
    kind = m.group(2)
    sensor = ([URG_04LX if k % 2 == 0 else UTM_30LX for k in range(n)] if kind == "-mixed"
              else UTM_30LX if kind == "-utm" else URG_04LX)
    match = plan_match(n, sensor, n_robots=n_robots, seconds=seconds, referee=referee, seed=seed, penalties=penalties)
    return render_match(match, seed=seed, tags=tags)
