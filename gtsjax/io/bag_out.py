"""The ground truth as a ROS 2 bag (MCAP storage), beside a robot's own bags (issue 19).

``--out-bag DIR`` on ``replay`` and ``run`` writes, with rosbags' writer (``StoragePlugin.MCAP``):

* ``/scan`` (``sensor_msgs/msg/LaserScan``, frame ``laser``, or the laser's name with several): each
  scan as the sensor gave it;
* ``/tf`` (``tf2_msgs/msg/TFMessage``): ``field`` → laser, the laser's pose in O as that scan's map
  transformation places it;
* ``/gtsjax/tracks`` (``geometry_msgs/msg/PoseArray``, frame ``field``): every confirmed track of the
  scan, in the GTD CSV's row order (by id);
* ``/gtsjax/<class>_<id>`` (``geometry_msgs/msg/PoseWithCovarianceStamped``, frame ``field``): each
  track on its own topic, with its variances on the covariance's x, y and yaw diagonal.

``ros2 bag play DIR`` republishes them, Foxglove opens the ``.mcap`` in ``DIR``, and every message is
stamped (header and bag time) with the scan's stamp, so that a robot's bag and this one line up. The
folder is written as the messages come; ``close`` writes its ``metadata.yaml``.
"""

import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from .gtd import TrackRow

FIELD_FRAME = "field"
SCAN_TOPIC = "/scan"
TRACKS_TOPIC = "/gtsjax/tracks"


def track_topic(cls: str, track_id: int) -> str:
    """The topic of one track's poses."""
    return f"/gtsjax/{cls}_{track_id}"


def check_bag_dir(path: Path) -> None:
    """The bag folder is made by the writer: it must not exist yet, and its parent must be a folder
    that can be written (checked before any work)."""
    if path.exists():
        raise InputError(path, "already exists; --out-bag names a new folder for the ROS 2 bag")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(parent, f"is a file, not a folder, so --out-bag {path} cannot be written")


class BagOut:
    """A ROS 2 bag of one run's scans, laser poses and tracks, written as they come."""

    def __init__(self, path: Path, *, angle_min: float, angle_increment: float, range_min: float,
                 range_max: float, scan_time: float = 0.0):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        check_bag_dir(Path(path))
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.path = Path(path)
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.geometry = (float(angle_min), float(angle_increment), float(range_min), float(range_max), float(scan_time))
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

    def _header(self, stamp: float, frame: str):
        T = self.ts.types
        sec = math.floor(stamp)
        nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)
        return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](int(sec), nanosec), frame)

    def _pose(self, x: float, y: float, theta: float):
        T = self.ts.types
        return T["geometry_msgs/msg/Pose"](T["geometry_msgs/msg/Point"](float(x), float(y), 0.0),
                                           T["geometry_msgs/msg/Quaternion"](0.0, 0.0, math.sin(theta / 2),
                                                                             math.cos(theta / 2)))

    def write(self, stamp: float, ranges, intensities, rows: "list[TrackRow]", sensor_pose=None,
              laser: str = "laser") -> None:
        """One scan: its ranges (metres; NaN, 0 or out of range: no return, written as ``inf``), the
        laser's pose in O (``None``: no ``/tf``), its confirmed tracks (the GTD rows)."""
        T = self.ts.types
        ns = int(round(stamp * 1e9))
        a0, da, rmin, rmax, scan_time = self.geometry
        r = np.asarray(ranges, np.float32)
        r = np.where(np.isfinite(r) & (r >= rmin) & (r <= rmax) & (r > 0), r, np.float32(np.inf)).astype(np.float32)
        inten = (np.zeros(0, np.float32) if intensities is None else np.asarray(intensities, np.float32))
        self._put(SCAN_TOPIC if laser == "laser" else f"/{laser}/scan",
                  T["sensor_msgs/msg/LaserScan"](self._header(stamp, laser), a0, a0 + da * (r.size - 1), da,
                                                 0.0, scan_time, rmin, rmax, r, inten), ns)
        if sensor_pose is not None:
            x, y, th = (float(v) for v in sensor_pose)
            q = self._pose(x, y, th).orientation
            tf = T["geometry_msgs/msg/TransformStamped"](
                self._header(stamp, FIELD_FRAME), laser,
                T["geometry_msgs/msg/Transform"](T["geometry_msgs/msg/Vector3"](x, y, 0.0), q))
            self._put("/tf", T["tf2_msgs/msg/TFMessage"]([tf]), ns)
        self._put(TRACKS_TOPIC, T["geometry_msgs/msg/PoseArray"](
            self._header(stamp, FIELD_FRAME), [self._pose(r_.x, r_.y, r_.theta) for r_ in rows]), ns)
        for row in rows:
            cov = np.zeros(36, np.float64)
            cov[0], cov[7], cov[35] = row.var_x, row.var_y, row.var_theta
            self._put(track_topic(row.cls, row.track_id), T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                self._header(stamp, FIELD_FRAME),
                T["geometry_msgs/msg/PoseWithCovariance"](self._pose(row.x, row.y, row.theta), cov)), ns)

    def close(self) -> None:
        self.writer.close()
