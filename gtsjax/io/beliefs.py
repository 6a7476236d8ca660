"""A robot's own pose estimates, its *beliefs*: what a team's self-localisation said, read to be graded
against the ground truth (``gtsjax grade``, being built).

Two text formats:

* **TUM** (``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments, as ``export-tum`` writes and
  evo reads): the heading is the quaternion's yaw.
* **CSV** with a header naming at least ``stamp,x,y,theta`` (other columns are left alone), stamps in
  seconds, positions in metres, the heading in radians.

A file is TUM unless its name ends in ``.csv`` or its first line that is not a comment holds a comma.
A robot's clock and units are its own: what is read is checked, and each fault is one line
(:class:`~gtsjax.errors.InputError`) naming the file, the line and what to do. Stamps must increase
(a log whose lines were merged out of order is refused, not sorted: which pose came first is what the
grade is about); every value must be finite; positions beyond :data:`MAX_POSITION_M` are taken for
millimetres and headings beyond :data:`MAX_HEADING_RAD` for degrees, and refused with that hint;
a TUM quaternion must be of unit length (one that is not is a file of another layout).

Or a ROS bag's pose topic, ``BAG:TOPIC`` (:func:`read_beliefs_source`, the form ``grade`` takes), its
poses checked as a file's are.
"""

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .gtd import read_text
from .importers import _err_text, _open_bag, detect_format

#: A position beyond this (m) from the field's origin is no robot's on a field: most likely millimetres.
MAX_POSITION_M = 100.0
#: A heading beyond this (rad; a little over π, for a wrapped one's rounding) is most likely in degrees.
MAX_HEADING_RAD = 2.0 * math.pi
#: How far a TUM quaternion's length may be from 1 (as written with six or nine decimals).
QUATERNION_TOLERANCE = 1e-3
#: The CSV columns read.
CSV_COLUMNS = ("stamp", "x", "y", "theta")
#: The bag message types that carry one pose each, as ``rosbags`` names them (ROS 1's too).
POSE_TYPES = ("geometry_msgs/msg/PoseWithCovarianceStamped", "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")
#: The bag message types of transforms, read for one child frame (``tf/msg/tfMessage``: ROS 1 before Hydro).
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")


@dataclass(frozen=True)
class Beliefs:
    """One robot's poses as it believed them: ``stamps`` (s, increasing, its own clock) and ``poses``
    ``[n, 3]`` (x, y in m, θ in rad wrapped to (−π, π], in its own frame), read from ``source``."""

    name: str
    stamps: np.ndarray
    poses: np.ndarray
    source: str

    @property
    def n(self) -> int:
        return int(self.stamps.size)


def read_beliefs(path: str | os.PathLike, name: str | None = None) -> Beliefs:
    """A belief file (TUM or CSV, see the module) of robot ``name`` (default: the file's stem), checked."""
    path = Path(path)
    text = read_text(path, "is a folder, not a file of a robot's poses",
                     "not a text file: a robot's poses are read as TUM or CSV text")
    lines = [(k, line) for k, line in enumerate(text.splitlines(), start=1) if line.strip()]
    first = next((line for _, line in lines if not line.lstrip().startswith("#")), "")
    is_csv = path.suffix.lower() == ".csv" or "," in first
    stamps, poses = (_read_csv if is_csv else _read_tum)(path, text, lines)
    _check(path, stamps, poses, is_csv)
    return Beliefs(name or path.stem, stamps, _wrapped(poses), str(path))


def _wrapped(poses: np.ndarray) -> np.ndarray:
    poses[:, 2] = np.pi - np.mod(np.pi - poses[:, 2], 2.0 * np.pi)  # to (−π, π]
    return poses


def _read_tum(path: Path, text: str, lines) -> tuple[np.ndarray, np.ndarray]:
    rows, where = [], []
    for k, line in lines:
        if line.lstrip().startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 8:
            raise InputError(path, f"line {k} has {len(fields)} fields; a TUM line has 8 (timestamp tx ty tz qx qy qz "
                                   "qw), or write a CSV with the header stamp,x,y,theta")
        try:
            rows.append([float(v) for v in fields])
        except ValueError:
            raise InputError(path, f"line {k} has a non-numeric field") from None
        where.append(k)
    a = _table(path, rows, where)
    yaw = _yaw(path, a[:, 4:8], where, "line", "(qx qy qz qw)", "not a TUM trajectory")
    return a[:, 0], np.stack([a[:, 1], a[:, 2], yaw], -1)


def _yaw(path, q: np.ndarray, where: list[int], row: str, names: str, verdict: str) -> np.ndarray:
    """The yaw of each quaternion (x, y, z, w) of ``q`` ``[n, 4]``, each checked to be of unit length
    (one that is not was written in another layout, or is a pose never set)."""
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOLERANCE)
    if bad.size:
        raise InputError(path, f"{row} {where[bad[0]]}: the quaternion {names} has length {norm[bad[0]]:.4g}, "
                               f"not 1: {verdict}")
    qx, qy, qz, qw = q.T
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _read_csv(path: Path, text: str, lines) -> tuple[np.ndarray, np.ndarray]:
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    names = [h.strip().lower() for h in header] if header else []
    missing = [c for c in CSV_COLUMNS if c not in names]
    if missing:
        raise InputError(path, f"the header must name the columns {','.join(CSV_COLUMNS)} (missing "
                               f"{', '.join(missing)}); a TUM file has no commas")
    cols = [names.index(c) for c in CSV_COLUMNS]
    rows, where = [], []
    for k, rec in enumerate(reader, start=2):
        if not rec or not any(f.strip() for f in rec):
            continue
        if len(rec) != len(names):
            raise InputError(path, f"line {k} has {len(rec)} fields, the header {len(names)}")
        try:
            rows.append([float(rec[j]) for j in cols])
        except ValueError:
            raise InputError(path, f"line {k} has a non-numeric stamp, x, y or theta") from None
        where.append(k)
    a = _table(path, rows, where)
    return a[:, 0], a[:, 1:4]


def _table(path, rows: list, where: list[int], row: str = "line") -> np.ndarray:
    """The lines read as one float64 array, checked: some poses, every value finite (``where``: each
    row's line number, or for a bag its message's index, ``row`` saying which)."""
    if not rows:
        raise InputError(path, "holds no poses")
    a = np.asarray(rows, np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
    if bad.size:
        raise InputError(path, f"{row} {where[bad[0]]} has a value that is not a number (NaN or infinite); "
                               f"{bad.size} such {row}{'s' if bad.size > 1 else ''} in all: leave out the poses the "
                               "robot did not have")
    return a


def _check(path, stamps: np.ndarray, poses: np.ndarray, is_csv: bool, where: list[int] | None = None,
           row: str = "pose") -> None:
    """Stamps that increase, positions in metres and (CSV) headings in radians. A pose out of order is
    named as pose 1, 2, … or, given ``where`` (a bag's), as the ``row`` it came from."""
    step = np.diff(stamps)
    back = np.flatnonzero(step <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(path, f"{row} {where[i] if where is not None else i + 1} (stamp {float(stamps[i])!r}) "
                               "is not after the one before "
                               f"({float(stamps[i - 1])!r}): "
                               "the stamps must increase; write the poses in the order the robot had them")
    far = float(np.max(np.abs(poses[:, :2])))
    if far > MAX_POSITION_M:
        raise InputError(path, f"positions up to {far:.0f} from the origin: in millimetres? gtsjax takes metres "
                               "(divide x and y by 1000)")
    if is_csv:
        turn = float(np.max(np.abs(poses[:, 2])))
        if turn > MAX_HEADING_RAD:
            raise InputError(path, f"headings up to {turn:.0f}: in degrees? gtsjax takes radians (theta in (−π, π])")


# --------------------------------------------------------------------------------------------- ROS bags


def read_beliefs_source(source: str, name: str) -> Beliefs:
    """POSES as the command line gives it: a TUM/CSV file, or a bag topic ``BAG:TOPIC``, or for /tf
    ``BAG:/tf:CHILD_FRAME``.

    BAG is a ROS 1 ``.bag`` file or a ROS 2 bag (its folder, or the ``.mcap`` / ``.db3`` /
    ``metadata.yaml`` in it), opened as ``gtsjax import`` opens one; ``source`` is split at the first
    ``:/`` whose left part exists, since a path may hold colons but a topic starts with ``/`` (a ROS 1
    bag's topic stored without it is found too). TOPIC carries ``geometry_msgs/PoseWithCovarianceStamped``,
    ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``; or it is a ``tf2_msgs/TFMessage`` topic,
    of which the transforms to CHILD (compared without a leading ``/``) are read, their parent frame
    taken for the field's frame (a robot that publishes map -> base_link names base_link). Stamps are
    the header stamps, the robot's own clock, which is what the grade aligns to the ground truth's
    (not the bag's record times: a bag recorded on another machine has another clock). The pose is
    x, y and the orientation's yaw; the poses are checked as a file's are.
    """
    path = Path(source)
    if path.exists():
        if detect_format(path) in ("ros1", "ros2"):
            with _open_bag(path) as (reader, where, _):
                raise InputError(where, f"is a ROS bag: name the topic of the poses as {source}:TOPIC; its pose "
                                        f"topics: {_pose_topics(reader)}")
        return read_beliefs(path, name)
    cuts = [i for i in range(len(source)) if source.startswith(":/", i)]
    cut = next((i for i in cuts if i and Path(source[:i]).exists()), None)
    if cut is None:
        left, _, right = source.rpartition(":")
        if left and Path(left).exists():  # a topic typed without its /
            raise InputError(left, f"a bag's topic starts with /: name it as {left}:/{right}")
        hint = " (a bag's topic is named as BAG:/TOPIC)" if ":" in source and not cuts else ""
        raise InputError(source[:cuts[0]] if cuts else source, "no such file" + hint)
    bag, topic = Path(source[:cut]), source[cut + 1:]
    if detect_format(bag) not in ("ros1", "ros2"):
        raise InputError(bag, f"is not a ROS bag, so {topic} cannot be read from it: BAG:TOPIC takes a ROS 1 .bag "
                              "file or a ROS 2 bag's folder (or its .mcap, .db3 or metadata.yaml)")
    topic, _, child = topic.partition(":")
    with _open_bag(bag) as (reader, where, _):
        stamps, poses, rows = _read_bag_poses(reader, where, topic, child, source)
    _check(source, stamps, poses, False, rows, "message")
    return Beliefs(name or bag.stem, stamps, _wrapped(poses), source)


def _pose_topics(reader) -> str:
    """The bag's topics that poses can be read from, with their types, as one line's list."""
    topics = sorted((t, info.msgtype) for t, info in reader.topics.items() if info.msgtype in POSE_TYPES + TF_TYPES)
    return ", ".join(f"{t} ({m}{': name the child frame as ' + t + ':CHILD' if m in TF_TYPES else ''})"
                     for t, m in topics) or "none"


def _read_bag_poses(reader, where: Path, topic: str, child: str, source: str):
    """(stamps, poses ``[n, 3]``, each pose's message index) of ``topic`` (for a transform topic, the
    transforms to ``child``), checked as a file's lines are; errors past the topic's name name
    ``source``, the bag and topic together."""
    topics = reader.topics
    name = next((t for t in (topic, "/" + topic.lstrip("/"), topic.lstrip("/")) if t in topics), None)
    if name is None:
        raise InputError(where, f"no topic {topic} in the bag; its pose topics: {_pose_topics(reader)}")
    msgtype = topics[name].msgtype
    is_tf = msgtype in TF_TYPES
    if msgtype not in POSE_TYPES + TF_TYPES:
        raise InputError(where, f"topic {name} carries {msgtype}, not a pose: the poses are read from "
                                f"{', '.join(POSE_TYPES)} or, as TOPIC:CHILD, {TF_TYPES[0]}")
    if child and not is_tf:
        raise InputError(where, f"topic {name} carries {msgtype}, not transforms: a child frame (:{child}) "
                                "is named only on a tf2_msgs/msg/TFMessage topic")
    if not topics[name].msgcount:
        raise InputError(where, f"topic {name} has no messages")
    conns = [c for c in reader.connections if c.topic == name]
    want = child.lstrip("/")
    rows, where_k, frames = [], [], set()
    k = 0  # the message being read, for an error
    try:
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if is_tf:
                for tf in msg.transforms:
                    frame = tf.child_frame_id.lstrip("/")
                    frames.add(frame)
                    if frame == want:
                        t, q = tf.transform.translation, tf.transform.rotation
                        rows.append([_stamp(tf.header.stamp), t.x, t.y, q.x, q.y, q.z, q.w])
                        where_k.append(k)
                k += 1
                continue
            pose = msg.pose.pose if msgtype != POSE_TYPES[1] else msg.pose  # the two with covariance nest it
            p, q = pose.position, pose.orientation
            rows.append([_stamp(msg.header.stamp), p.x, p.y, q.x, q.y, q.z, q.w])
            where_k.append(k)
            k += 1
    except Exception as err:  # a damaged message: rosbags' own and builtin errors
        raise InputError(where, f"message {k} on {name} cannot be read: {_err_text(err)}") from None
    if is_tf and not rows:
        seen = sorted(frames)
        listed = ", ".join(seen[:10]) + (f" and {len(seen) - 10} more" if len(seen) > 10 else "") or "none"
        what = f"has no transforms to child frame {want}" if want else f"needs a child frame, as BAG:{name}:CHILD"
        raise InputError(where, f"topic {name} {what}; its child frames: {listed}")
    a = _table(source, rows, where_k, "message")
    yaw = _yaw(source, a[:, 3:7], where_k, "message", "(x y z w)", "not an orientation")
    return a[:, 0], np.stack([a[:, 1], a[:, 2], yaw], -1), where_k


def _stamp(t) -> float:
    """A header stamp in seconds (rosbags names ROS 1's ``nsecs`` ``nanosec`` too; ``nsec`` in case)."""
    return t.sec + 1e-9 * getattr(t, "nanosec", getattr(t, "nsec", 0))
