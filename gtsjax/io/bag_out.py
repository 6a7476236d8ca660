"""The ground truth as a ROS 2 bag (MCAP storage), beside a robot's own bags.

``--out-bag DIR`` on ``replay`` and ``run`` writes, with rosbags' writer (``StoragePlugin.MCAP``), for
one laser or several:

* ``/scan`` (``sensor_msgs/msg/LaserScan``, frame ``laser``) with one laser; with several lasers of a
  site, ``/NAME/scan`` per laser, frame ``NAME`` (the laser's name in the site, any character a ROS
  name cannot hold written ``_``): each scan as the sensor gave it, ``scan_time`` the scanner's period
  and ``time_increment`` the time from one beam to the next (a Hokuyo turns once per scan, so the
  period over its steps per revolution, as ``urg_node`` writes it); for a scanner gtsjax does not
  know, the median interval of the log's stamps and its share of a revolution per beam;
* ``/tf`` (``tf2_msgs/msg/TFMessage``), with each scan: ``field`` → the laser (its pose in O as
  that scan's map transformation places it) and ``field`` → ``CLASS_ID`` for every confirmed track
  (``robot_3``), so that RViz and Foxglove draw each robot's frame and ``evo_traj bag2 DIR
  /tf:field.robot_3`` reads a track's trajectory;
* ``/gtsjax/tracks`` (``geometry_msgs/msg/PoseArray``, frame ``field``): every confirmed track of the
  scan, in the GTD CSV's row order (by id); an array carries no ids, hence the next two;
* ``/gtsjax/markers`` (``visualization_msgs/msg/MarkerArray``, frame ``field``): a ``DELETEALL``
  marker (the tracks of the scan before are gone), then per track an ``ARROW`` at its pose with
  ``ns`` its class and ``id`` its track id, in the track's colour, and a ``TEXT_VIEW_FACING`` label
  ``CLASS ID`` (``ns`` ``CLASS/label``, same id), as leg_tracker and spencer's trackers draw theirs;
* ``/gtsjax/track_odom`` (``nav_msgs/msg/Odometry``): one message per track per scan on this one
  topic, ``header.frame_id`` ``field`` (the frame the pose is in) and ``child_frame_id`` the track's
  ``CLASS_ID`` (which robot), the pose with its covariance. Not a ``PoseWithCovarianceStamped`` with
  the robot in its frame id: tools read a header's frame as the frame the pose is expressed in, and
  would draw the pose relative to the robot itself. The covariance (6 × 6, row-major, x y z roll
  pitch yaw) holds the tracker's x, y and yaw variances on the diagonal, the x–y covariance at (x, y)
  and (y, x), and :data:`UNOBSERVED_VAR` on z, roll and pitch, which a 2-D ground truth does not
  observe (0 would claim them known exactly: ``robot_localization`` and other consumers that fuse or
  gate on the whole matrix take a large variance as "not measured"); the twist is not estimated
  here: zero, with :data:`UNOBSERVED_VAR` on its diagonal.

``ros2 bag play DIR`` republishes them, Foxglove opens the ``.mcap`` in ``DIR``, and every message is
stamped (header and bag time) with the scan's stamp, converted exactly (:func:`stamp_ns`: the float64
stamp's own value to the nanosecond, not a float product that is off by up to 128 ns at today's
epoch), so that a robot's bag and this one line up. The folder is written as the messages come;
``close`` writes its ``metadata.yaml``.
"""

import dataclasses
import math
import re
from fractions import Fraction
from pathlib import Path

import numpy as np

from ..core.scan import Beams
from ..errors import InputError
from .gtd import TrackRow

FIELD_FRAME = "field"
LASER = "laser"  # the frame of the one laser of a one-laser run
SCAN_TOPIC = "/scan"
TRACKS_TOPIC = "/gtsjax/tracks"
MARKERS_TOPIC = "/gtsjax/markers"
ODOM_TOPIC = "/gtsjax/track_odom"
# The variance (m², rad²) of what a 2-D ground truth does not observe: z, roll, pitch, the twist.
UNOBSERVED_VAR = 1e6
ARROW_LENGTH = 0.3  # metres: a track's marker
# Tracks' colours by id (RGB 0–255), the Rerun view's (:mod:`gtsjax.viewer`), so that both agree.
TRACK_COLOURS = ((230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180), (70, 240, 240),
                 (240, 50, 230), (128, 128, 0), (0, 128, 128), (170, 110, 40))


def track_colour(track_id: int) -> tuple[int, int, int]:
    """A track's colour (RGB 0–255) in the bag's markers and the Rerun view."""
    return TRACK_COLOURS[int(track_id) % len(TRACK_COLOURS)]


def ros_name(text: str) -> str:
    """``text`` as one token of a ROS name (letters, digits, ``_``; not starting with a digit), for
    topics and frames made of a laser's or a class's name."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", text) or "_"
    return "_" + name if name[0].isdigit() else name


def track_frame(cls: str, track_id: int) -> str:
    """The TF frame (and ``child_frame_id``) of one track: ``CLASS_ID``."""
    return f"{ros_name(cls)}_{int(track_id)}"


def scan_topic(laser: str) -> str:
    """The LaserScan topic of a laser: ``/scan`` for a one-laser run's, ``/NAME/scan`` for a named one."""
    return SCAN_TOPIC if laser == LASER else f"/{ros_name(laser)}/scan"


def stamp_ns(stamp: float) -> int:
    """A float64 stamp (seconds) in integer nanoseconds, from its exact value (rounded half to even):
    ``round(stamp * 1e9)`` rounds the product to float64 first, whose step is 256 ns at today's epoch."""
    return round(Fraction(float(stamp)) * 1_000_000_000)


@dataclasses.dataclass(frozen=True)
class LaserGeometry:
    """What a ``LaserScan`` says of the scanner that took it."""

    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    scan_time: float = 0.0  # seconds per scan (0: unknown)
    time_increment: float = 0.0  # seconds from one beam to the next (0: unknown)

    @classmethod
    def of_sensor(cls, sensor) -> "LaserGeometry":
        """A known scanner (:class:`~gtsjax.sensors.SensorModel`): its period, over its steps per
        revolution from one beam to the next (it turns once per scan)."""
        return cls(float(sensor.angle_min), float(sensor.angle_increment), float(sensor.range_min),
                   float(sensor.range_max), float(sensor.period), float(sensor.period) / sensor.ares)

    @classmethod
    def of_log(cls, log) -> "LaserGeometry":
        """A scan log's geometry; the timing of the scanner it names (``sensor_model``) where gtsjax
        knows it, else the median interval of its stamps per scan and a revolution's share per beam."""
        from ..sensors import MODELS

        known = MODELS.get(log.sensor_model or "")
        if known is not None:
            timing = cls.of_sensor(known)
            scan_time, time_increment = timing.scan_time, timing.time_increment
        else:
            steps = np.diff(np.asarray(log.stamps, np.float64))
            steps = steps[steps > 0]
            scan_time = float(np.median(steps)) if steps.size else 0.0
            time_increment = scan_time * float(log.angle_increment) / (2 * math.pi)
        return cls(float(log.angle_min), float(log.angle_increment), float(log.range_min), float(log.range_max),
                   scan_time, time_increment)


def check_bag_dir(path: Path) -> None:
    """The bag folder is made by the writer: it must not exist yet, and its parent must be a folder
    that can be written (checked before any work)."""
    if path.exists():
        raise InputError(path, "already exists; --out-bag names a new folder for the ROS 2 bag")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(parent, f"is a file, not a folder, so --out-bag {path} cannot be written")


class BagOut:
    """A ROS 2 bag of one run's scans, laser poses and tracks, written as they come. ``lasers``: each
    laser's geometry by name; :data:`LASER` alone for a one-laser run (``/scan``, frame ``laser``)."""

    def __init__(self, path: Path, lasers: "dict[str, LaserGeometry]"):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        frames: dict[str, str] = {}
        for name in lasers:
            other = frames.setdefault(ros_name(name), name)
            if other != name:
                raise InputError(path, f"lasers {other!r} and {name!r} would share the bag's frame "
                                       f"{ros_name(name)!r}; name them apart in the site")
        check_bag_dir(Path(path))
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.path = Path(path)
        self.lasers = dict(lasers)
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.writer = Writer(self.path, version=8, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self._conns: dict[str, object] = {}
        self.messages = 0

    def _conn(self, topic: str, msgtype: str):
        if topic not in self._conns:
            self._conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        return self._conns[topic]

    def _put(self, topic: str, msg, ns: int) -> None:
        self.writer.write(self._conn(topic, msg.__msgtype__), ns, self.ts.serialize_cdr(msg, msg.__msgtype__))
        self.messages += 1

    def _header(self, ns: int, frame: str):
        T = self.ts.types
        sec, nanosec = divmod(ns, 1_000_000_000)
        return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](int(sec), int(nanosec)), frame)

    def _pose(self, x: float, y: float, theta: float, z: float = 0.0):
        T = self.ts.types
        return T["geometry_msgs/msg/Pose"](T["geometry_msgs/msg/Point"](float(x), float(y), float(z)),
                                           T["geometry_msgs/msg/Quaternion"](0.0, 0.0, math.sin(theta / 2),
                                                                             math.cos(theta / 2)))

    def _transform(self, header, child: str, x: float, y: float, theta: float):
        T = self.ts.types
        q = self._pose(x, y, theta).orientation
        return T["geometry_msgs/msg/TransformStamped"](
            header, child, T["geometry_msgs/msg/Transform"](T["geometry_msgs/msg/Vector3"](float(x), float(y), 0.0), q))

    def _marker(self, header, ns: str, marker_id: int, kind: int, action: int, pose, scale, rgb, text: str = ""):
        T = self.ts.types
        r, g, b = (c / 255.0 for c in rgb)
        return T["visualization_msgs/msg/Marker"](
            header, ns, int(marker_id), kind, action, pose, T["geometry_msgs/msg/Vector3"](*scale),
            T["std_msgs/msg/ColorRGBA"](r, g, b, 1.0), T["builtin_interfaces/msg/Duration"](0, 0), False, [], [], "",
            T["sensor_msgs/msg/CompressedImage"](header, "", np.zeros(0, np.uint8)), [], text, "",
            T["visualization_msgs/msg/MeshFile"]("", np.zeros(0, np.uint8)), False)

    def write(self, stamp: float, ranges, intensities, rows: "list[TrackRow]", sensor_pose=None,
              laser: str = LASER) -> None:
        """One scan of ``laser``: its ranges (metres; NaN, 0 or out of range: no return, written as
        ``inf``), the laser's pose in O (``None``: no transform of it), its confirmed tracks (the GTD
        rows)."""
        T = self.ts.types
        ns = stamp_ns(stamp)
        g = self.lasers[laser]
        frame = LASER if laser == LASER else ros_name(laser)
        r = np.asarray(ranges, np.float32)
        beams = Beams(g.angle_min, g.angle_increment, r.size, g.range_min, g.range_max)
        r = np.where(beams.valid(r), r, np.float32(np.inf)).astype(np.float32)
        inten = np.zeros(0, np.float32) if intensities is None else np.asarray(intensities, np.float32)
        self._put(scan_topic(laser), T["sensor_msgs/msg/LaserScan"](
            self._header(ns, frame), g.angle_min, beams.angle_max, g.angle_increment,
            g.time_increment, g.scan_time, g.range_min, g.range_max, r, inten), ns)
        field = self._header(ns, FIELD_FRAME)
        tfs = [] if sensor_pose is None else [self._transform(field, frame, *(float(v) for v in sensor_pose))]
        tfs += [self._transform(field, track_frame(row.cls, row.track_id), row.x, row.y, row.theta) for row in rows]
        if tfs:
            self._put("/tf", T["tf2_msgs/msg/TFMessage"](tfs), ns)
        self._put(TRACKS_TOPIC, T["geometry_msgs/msg/PoseArray"](
            field, [self._pose(row.x, row.y, row.theta) for row in rows]), ns)
        M = T["visualization_msgs/msg/Marker"]
        markers = [self._marker(field, "", 0, M.ARROW, M.DELETEALL, self._pose(0, 0, 0), (0.0, 0.0, 0.0), (0, 0, 0))]
        for row in rows:
            rgb = track_colour(row.track_id)
            markers.append(self._marker(field, row.cls, row.track_id, M.ARROW, M.ADD, self._pose(row.x, row.y, row.theta),
                                        (ARROW_LENGTH, 0.05, 0.05), rgb))
            markers.append(self._marker(field, f"{row.cls}/label", row.track_id, M.TEXT_VIEW_FACING, M.ADD,
                                        self._pose(row.x, row.y, 0.0, z=0.3), (0.0, 0.0, 0.15), rgb,
                                        f"{row.cls} {row.track_id}"))
        self._put(MARKERS_TOPIC, T["visualization_msgs/msg/MarkerArray"](markers), ns)
        unobserved = np.diag(np.full(6, UNOBSERVED_VAR)).ravel()
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            T["geometry_msgs/msg/Twist"](T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                                         T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)), unobserved)
        for row in rows:
            cov = np.zeros((6, 6), np.float64)
            cov[0, 0], cov[1, 1], cov[5, 5] = row.var_x, row.var_y, row.var_theta
            cov[0, 1] = cov[1, 0] = row.cov_xy
            cov[2, 2] = cov[3, 3] = cov[4, 4] = UNOBSERVED_VAR
            self._put(ODOM_TOPIC, T["nav_msgs/msg/Odometry"](
                field, track_frame(row.cls, row.track_id),
                T["geometry_msgs/msg/PoseWithCovariance"](self._pose(row.x, row.y, row.theta), cov.ravel()), twist), ns)

    def close(self) -> None:
        self.writer.close()
