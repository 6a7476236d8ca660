"""Scan logs that other programs wrote, read into a :class:`~gtsjax.io.logs.ScanLog`, so that every
command that takes a ``.npz`` log (``replay``, ``convert``, ``info``) also takes them.

Formats, and how each one is found (:func:`detect_format`):

=============  ==========================================================  ===============================
format         what                                                        recognised by
=============  ==========================================================  ===============================
``npz``        the spec's scan log (:func:`~gtsjax.io.logs.load_log`)      ``.npz``, or nothing else fits
``ros1``       ROS 1 bag, ``sensor_msgs/LaserScan`` on one topic           ``.bag`` or ``#ROSBAG`` magic
``ros2``       ROS 2 bag (sqlite3 or MCAP), the same message               a directory with metadata.yaml
``carmen``     CARMEN log: ``ROBOTLASER1`` or ``FLASER`` lines             ``.log``/``.clf`` (``.gz`` too)
``breezyslam`` BreezySLAM's URG-04LX text log (``exp1.dat``)               ``.dat``
=============  ==========================================================  ===============================

Every reader parses the whole input before it returns, so a bad file never leaves anything behind;
what is wrong with it is one :class:`InputError` naming the file and the line or message. The result
is validated against the spec, so it always saves (:func:`~gtsjax.io.logs.save_log`) and loads back.
Each imported log carries a one-line ``source`` key (kept as an extra key of the format) that says
where its scans, angles and stamps came from, and what was repaired: real logs' stamps step back
now and then, which the format forbids (see :data:`MAX_STAMP_STEP_BACK`).
"""

import contextlib
import dataclasses
import gzip
import math
import os
import tempfile
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..core.scan import Beams
from ..errors import InputError, InputWarning
from ..sensors import URG_04LX
from .logs import DEFAULT_RANGE_MIN, ScanLog, load_log

FORMATS = ("npz", "ros1", "ros2", "carmen", "breezyslam")
LASERSCAN = "sensor_msgs/msg/LaserScan"
_CARMEN_SUFFIXES = (".log", ".clf", ".carmen")

Progress = Callable[[int, int], None]


def detect_format(path: str | os.PathLike) -> str:
    """Which of :data:`FORMATS` ``path`` holds: by extension first, then by its first bytes. Anything
    unrecognised is ``npz``, so that :func:`load_log` gives its own one-line verdict on it."""
    path = Path(path)
    if path.is_dir():
        return "ros2" if (path / "metadata.yaml").is_file() else "npz"
    name = path.name.lower()
    if name == "metadata.yaml" or path.suffix.lower() in (".db3", ".mcap"):
        return "ros2" if (path.parent / "metadata.yaml").is_file() else "npz"
    if name.endswith(".gz"):
        name = name[:-3]
    suffix = Path(name).suffix
    if suffix == ".npz":
        return "npz"
    if suffix == ".bag":
        return "ros1"
    if suffix in _CARMEN_SUFFIXES:
        return "carmen"
    if suffix == ".dat":
        return "breezyslam"
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return "npz"
    if head.startswith(b"#ROSBAG"):
        return "ros1"
    if head.startswith(b"\x1f\x8b") and _gzip_looks_like_carmen(path):
        return "carmen"
    return "npz"


def import_log(path: str | os.PathLike, *, topic: str | None = None, progress: Progress | None = None) -> ScanLog:
    """Read any supported log (see :data:`FORMATS`) as a validated :class:`ScanLog`.

    ``topic`` picks the LaserScan topic of a ROS bag and is an error for any other format (it would
    otherwise be silently ignored). ``progress(done, total)`` is called now and then while a bag is read.
    """
    path = Path(path)
    fmt = detect_format(path)
    if topic is not None and fmt not in ("ros1", "ros2"):
        raise InputError(path, f"a topic ({topic}) applies to ROS bags only; this is {_FORMAT_NAMES[fmt]}")
    if fmt == "npz":
        if path.is_dir():
            raise InputError(path, "is a directory without a metadata.yaml: neither a ROS 2 bag nor a scan log")
        if path.suffix.lower() in (".db3", ".mcap") and path.is_file():
            raise InputError(path, "is a ROS 2 bag's storage file without the bag's metadata.yaml beside it; give the "
                                   "bag's folder, as ros2 bag record writes it")
        return load_log(path)
    if fmt in ("ros1", "ros2"):
        return read_rosbag(path, topic=topic, progress=progress)
    if fmt == "carmen":
        return read_carmen(path)
    return read_breezyslam(path)


_FORMAT_NAMES = {
    "npz": "a .npz scan log",
    "ros1": "a ROS 1 bag",
    "ros2": "a ROS 2 bag",
    "carmen": "a CARMEN log",
    "breezyslam": "a BreezySLAM text log",
}


def format_name(path: str | os.PathLike) -> str:
    """``"a ROS 1 bag"``, ``"a CARMEN log"``, …: what :func:`import_log` will take ``path`` for."""
    return _FORMAT_NAMES[detect_format(path)]


# Real logs have stamps that step back now and then (4 scans of the Intel Research Lab log, by up to
# 0.86 s: its scans were written out of time order). The format needs non-decreasing stamps; a small
# step back is logging jitter, so such a stamp is raised to the one before it (the scan keeps its
# place in the file, with no time elapsed since the previous scan) and the repair is reported in the
# log's ``source``. A larger step back (a clock reset, logs concatenated) is an error.
MAX_STAMP_STEP_BACK = 2.0


def _monotonic(stamps: np.ndarray, name: Callable[[int], str], where) -> tuple[np.ndarray, str]:
    """``stamps`` made non-decreasing as described at :data:`MAX_STAMP_STEP_BACK`, and a note saying what
    was repaired (empty if nothing was); ``name(j)`` names scan ``j`` in an error."""
    if not np.all(np.isfinite(stamps)):
        j = int(np.flatnonzero(~np.isfinite(stamps))[0])
        raise InputError(where, f"{name(j)}: stamp {stamps[j]} is not finite")
    prev = np.maximum.accumulate(stamps)
    back = np.concatenate([[0.0], prev[:-1] - stamps[1:]])
    if np.any(back > MAX_STAMP_STEP_BACK):
        j = int(np.flatnonzero(back > MAX_STAMP_STEP_BACK)[0])
        raise InputError(where, f"{name(j)}: stamp {stamps[j]!r} is {back[j]:.3f} s earlier than the scans "
                                f"before it (more than the {MAX_STAMP_STEP_BACK:g} s of jitter gtsjax repairs)")
    n = int(np.sum(back > 0))
    if n == 0:
        return stamps, ""
    return prev, f"; {n} stamp(s) that stepped back (by up to {back.max():.3f} s) raised to the previous one"


# --------------------------------------------------------------------------------------------- ROS bags


def read_rosbag(path: str | os.PathLike, *, topic: str | None = None, progress: Progress | None = None) -> ScanLog:
    """``sensor_msgs/LaserScan`` messages of one topic of a ROS 1 bag (a ``.bag`` file) or a ROS 2 bag
    (its directory, or the metadata.yaml / .db3 / .mcap in it), read with ``rosbags.highlevel.AnyReader``.

    Topic: ``topic`` if given (a leading ``/`` may be added or left out: ROS 1 bags often store
    ``scan`` where users type ``/scan``); otherwise the bag's only LaserScan topic. Stamps: the message
    header stamps; if any of them is 0 (some tools write messages without one), the bag's record
    times for all of them, since mixing the two clocks would give nonsense intervals. Ranges are kept
    as float32 with non-finite values (no return in ROS) as they are; intensities are kept when the
    messages carry one per beam (non-finite ones become 0). A scanner that turns clockwise
    (``angle_increment < 0``) has its beams reversed, which leaves every beam's direction unchanged.
    All messages must share one geometry (beams, angles, range window); the first that does not is
    an error naming its index.
    """
    with _open_bag(path) as (reader, where, label):
        return _read_rosbag(reader, where, label, topic, progress)


@contextlib.contextmanager
def _open_bag(path: str | os.PathLike):
    """A ROS bag open in ``rosbags.highlevel.AnyReader``: (reader, the path to name in errors, the bag's
    name for ``source``). A ROS 1 bag found by its magic under another name is read through a link
    with the ``.bag`` suffix AnyReader tells ROS 1 from ROS 2 by; a bag that cannot be opened is one
    :class:`InputError`."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    where = bag = path
    if not path.is_dir() and (path.name == "metadata.yaml" or path.suffix.lower() in (".db3", ".mcap")):
        bag = path.parent
    if not path.exists():
        raise InputError(path, "no such file")
    with tempfile.TemporaryDirectory(prefix="gtsjax-bag-") as tmp:
        if not bag.is_dir() and bag.suffix != ".bag":
            link = Path(tmp) / (bag.name + ".bag")
            link.symlink_to(bag.resolve())
            bag = link
        label = bag.name if bag.is_dir() else where.name
        try:
            reader = AnyReader([bag], default_typestore=get_typestore(Stores.LATEST))
            reader.open()
        except Exception as err:  # rosbags raises its own and builtin errors for damaged bags
            raise InputError(where, f"cannot be read as a ROS bag: {_err_text(err)}") from None
        try:
            yield reader, where, label
        finally:
            reader.close()


@dataclasses.dataclass(frozen=True)
class BagTopic:
    """One topic of a ROS bag as :func:`bag_topics` lists it; a LaserScan topic also has its first
    message's geometry: beams, ``angle_min``, ``angle_increment`` (as the message has it: negative for a
    scanner that turns clockwise), range window, whether it carries intensities."""

    name: str
    msgtype: str
    count: int
    geometry: tuple[int, float, float, float, float, bool] | None = None

    @property
    def is_scan(self) -> bool:
        return self.msgtype == LASERSCAN


def bag_topics(path: str | os.PathLike) -> tuple[str, float, list[BagTopic]]:
    """What a ROS bag holds, without reading its messages (only each LaserScan topic's first, for its
    geometry), so that a user can pick the topic ``--topic`` names: ``"ROS 1 bag"`` or ``"ROS 2 bag"``,
    the seconds between its first and last message, and its topics by name."""
    with _open_bag(path) as (reader, where, _):
        topics = []
        for name, info in sorted(reader.topics.items()):
            geom = None
            if info.msgtype == LASERSCAN and info.msgcount:
                conns = [c for c in reader.connections if c.topic == name]
                try:
                    _, _, raw = next(iter(reader.messages(connections=conns)))
                    msg = reader.deserialize(raw, info.msgtype)
                    geom = (len(msg.ranges), float(msg.angle_min), float(msg.angle_increment), float(msg.range_min),
                            float(msg.range_max), len(msg.intensities) > 0)
                except Exception as err:  # a damaged message: rosbags' own and builtin errors
                    raise InputError(where, f"message 0 on {name} cannot be read: {_err_text(err)}") from None
            topics.append(BagTopic(name, info.msgtype, int(info.msgcount), geom))
        span = reader.duration * 1e-9 if reader.message_count else 0.0
        return ("ROS 2 bag" if reader.is2 else "ROS 1 bag"), span, topics


def _read_rosbag(reader, where: Path, label: str, topic: str | None, progress: Progress | None):
    conns, name = _pick_topic(reader, topic, where)
    total = sum(c.msgcount for c in conns)
    if total == 0:
        raise InputError(where, f"topic {name} has no messages")
    ranges, inten, hdr, rec = [], [], [], []
    geom = None
    with_inten = None
    k = -1
    try:
        for k, (conn, t_rec, raw) in enumerate(reader.messages(connections=conns)):
            msg = reader.deserialize(raw, conn.msgtype)
            r = np.asarray(msg.ranges, dtype=np.float32)
            g = (r.shape[0], float(msg.angle_min), float(msg.angle_increment), float(msg.range_min),
                 float(msg.range_max))
            if geom is None:
                geom = g
                if g[0] == 0:
                    raise InputError(where, f"message 0 on {name} has no ranges")
                if g[2] == 0 or not math.isfinite(g[2]):
                    raise InputError(where, f"message 0 on {name} has angle_increment {g[2]}")
            elif g != geom:
                raise InputError(where, f"message {k} on {name} changes the scan geometry "
                                        f"({_geom_text(geom)} -> {_geom_text(g)}); a log holds one geometry")
            i = np.asarray(msg.intensities, dtype=np.float32)
            has_i = i.shape[0] > 0
            if has_i and i.shape[0] != r.shape[0]:
                raise InputError(where, f"message {k} on {name} has {i.shape[0]} intensities for "
                                        f"{r.shape[0]} ranges")
            if with_inten is None:
                with_inten = has_i
            elif has_i != with_inten:
                raise InputError(where, f"message {k} on {name} {'has' if has_i else 'lacks'} intensities, "
                                        f"unlike the messages before it")
            ranges.append(r)
            if has_i:
                inten.append(i)
            hdr.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
            rec.append(t_rec * 1e-9)
            if progress is not None and (k + 1) % 256 == 0:
                progress(k + 1, total)
    except InputError:
        raise
    except Exception as err:
        raise InputError(where, f"message {k + 1} on {name} cannot be read: {_err_text(err)}") from None
    if progress is not None:
        progress(len(ranges), total)

    hdr_a, rec_a = np.asarray(hdr, np.float64), np.asarray(rec, np.float64)
    if np.any(hdr_a == 0):
        stamps, stamp_src = rec_a, "bag record times (header stamps are 0)"
    else:
        stamps, stamp_src = hdr_a, "message header stamps"
    stamps, note = _monotonic(stamps, lambda j: f"message {j} on {name}", where)
    stamp_src += note
    n, amin, inc, rmin, rmax = geom
    r = np.stack(ranges)
    i = np.stack(inten) if with_inten else None
    if i is not None:
        i = np.where(np.isfinite(i), i, np.float32(0))
        if np.any(i < 0):
            k = int(np.argwhere(i < 0)[0, 0])
            raise InputError(where, f"message {k} on {name} has a negative intensity")
    if inc < 0:
        amin, inc = Beams(amin, inc, n).angle_max, -inc
        r = r[:, ::-1].copy()
        i = None if i is None else i[:, ::-1].copy()
    kind = "ROS 2 bag" if reader.is2 else "ROS 1 bag"
    log = ScanLog(ranges=r, stamps=stamps, angle_min=amin, angle_increment=inc, intensities=i, range_min=rmin,
                  range_max=rmax, sensor_model=None,
                  extra={"source": np.asarray(f"{kind} {label}, topic {name} (sensor_msgs/LaserScan), "
                                              f"stamps: {stamp_src}")})
    return log.validate(where)


def _pick_topic(reader, topic: str | None, where: Path):
    """The connections of the LaserScan topic to read, and its name."""
    topics = reader.topics
    scans = sorted(t for t, info in topics.items() if info.msgtype == LASERSCAN)
    if topic is None:
        if len(scans) == 1:
            name = scans[0]
        elif not scans:
            listed = ", ".join(f"{t} ({info.msgtype})" for t, info in sorted(topics.items())) or "none"
            raise InputError(where, f"no sensor_msgs/LaserScan topic in the bag; its topics: {listed}")
        else:
            raise InputError(where, f"{len(scans)} sensor_msgs/LaserScan topics, pick one with --topic: "
                                    f"{', '.join(scans)}")
    else:
        cands = [topic, "/" + topic.lstrip("/"), topic.lstrip("/")]
        name = next((t for t in cands if t in topics), None)
        if name is None:
            raise InputError(where, f"no topic {topic} in the bag; its LaserScan topics: {', '.join(scans) or 'none'}")
        if topics[name].msgtype != LASERSCAN:
            raise InputError(where, f"topic {name} carries {topics[name].msgtype}, not sensor_msgs/LaserScan; "
                                    f"its LaserScan topics: {', '.join(scans) or 'none'}")
    return [c for c in reader.connections if c.topic == name], name


def _geom_text(g) -> str:
    n, amin, inc, rmin, rmax = g
    return f"{n} beams from {amin:.6g} rad by {inc:.6g} rad, {rmin:g}-{rmax:g} m"


def _err_text(err: BaseException) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if len(text) <= 200 else text[:197] + "..."


# --------------------------------------------------------------------------------------------- CARMEN


# CARMEN's own guesses for FLASER lines, which carry no geometry (carmen_laser_guess_fov and
# carmen_laser_guess_angle_increment in CARMEN's readlog.c): beams from -90 degrees, counter-clockwise,
# at the SICK LMS's resolution for that beam count, the last beam of a 180/360/400-beam scan being
# the one left out; maximum range 80 m.
FLASER_ANGLE_MIN = -math.pi / 2
FLASER_RANGE_MAX = 80.0


def flaser_angle_increment(n_beams: int) -> float:
    """CARMEN's angle step for a FLASER line of ``n_beams`` ranges (radians)."""
    if n_beams in (180, 181):
        return math.pi / 180
    if n_beams in (360, 361):
        return math.pi / 360
    if n_beams in (400, 401):
        return math.pi / 720
    return math.pi / (n_beams - 1)


def read_carmen(path: str | os.PathLike) -> ScanLog:
    """Front-laser scans of a CARMEN log (plain or gzip), one scan per ``ROBOTLASER1`` line if the log
    has any, otherwise per ``FLASER`` line; every other line (``ODOM``, ``PARAM``, ``RLASER``, ``#``
    comments, …) is skipped. A CARMEN logger that writes both laser lines writes each scan twice, so
    only one kind is taken.

    ``ROBOTLASER1`` lines carry their geometry: beam i at ``start_angle + i * angular_resolution``,
    the maximum range, and remissions (kept as intensities when there is one per beam). ``FLASER``
    lines carry none, and take CARMEN's own convention for them (as CARMEN's readlog.c fills in a
    FLASER message): SICK LMS, first beam at -π/2, 1° steps for 180 or 181 beams (0.5° for 360/361,
    0.25° for 400/401), maximum range 80 m. So a 180-beam scan, as in the Intel Research Lab log,
    covers -90° … +89°: the SICK's 181st beam (+90°) is the one left out, not a stretched 180 beams
    over 180°, which would turn every beam but the first by up to 1°. Stamps: the line's ``ipc``
    timestamp (the time of the scan), not the logger's. The range window starts at the format's
    default minimum (CARMEN logs have none); the SICK reports "no return" as its maximum (81.83 m),
    beyond the 80 m window.
    """
    path = Path(path)
    rows: dict[str, list] = {"ROBOTLASER1": [], "FLASER": []}
    cut = _CutLine(path)
    for lineno, toks in _text_lines(path, cut):
        kind = toks[0]
        if kind not in rows:
            continue
        rows[kind].append((lineno, toks))
    kind = "ROBOTLASER1" if rows["ROBOTLASER1"] else "FLASER"
    lines = rows[kind]
    if not lines:
        raise InputError(path, "no FLASER or ROBOTLASER1 lines: not a CARMEN laser log")
    parse = _parse_robotlaser if kind == "ROBOTLASER1" else _parse_flaser
    ranges, inten, stamps, linenos = [], [], [], []
    geom = None
    geom_line = 0
    for lineno, toks in lines:
        try:
            r, i, stamp, g = parse(path, lineno, toks)
        except InputError as err:
            if not cut.skip(lineno, err):
                raise
            continue
        if geom is None:
            geom, geom_line = g, lineno
        elif g != geom:
            raise InputError(path, f"line {lineno}: {kind} geometry ({_carmen_geom_text(g)}) differs from line "
                                   f"{geom_line}'s ({_carmen_geom_text(geom)}); a log holds one geometry")
        ranges.append(r)
        inten.append(i)
        stamps.append(stamp)
        linenos.append(lineno)
    if geom is None:  # the one laser line was the cut one
        raise InputError(path, f"no complete FLASER or ROBOTLASER1 line (line {cut.lineno} is cut short)")
    n, amin, inc, rmax, has_i = geom
    if not inc > 0:
        raise InputError(path, f"line {geom_line}: angular resolution {inc} must be > 0")
    if not rmax > DEFAULT_RANGE_MIN:
        raise InputError(path, f"line {geom_line}: maximum range {rmax} m is not above {DEFAULT_RANGE_MIN} m")
    stamps, note = _monotonic(np.asarray(stamps, np.float64), lambda j: f"line {linenos[j]}", path)
    conv = "" if kind == "ROBOTLASER1" else f" (CARMEN's FLASER convention: {math.degrees(inc):g}° steps from -90°)"
    log = ScanLog(
        ranges=np.asarray(ranges, dtype=np.float32),
        stamps=stamps,
        angle_min=amin,
        angle_increment=inc,
        intensities=np.asarray(inten, dtype=np.float32) if has_i else None,
        range_min=DEFAULT_RANGE_MIN,
        range_max=rmax,
        sensor_model=None,
        extra={"source": np.asarray(f"CARMEN log {path.name}, {len(ranges)} {kind} lines{conv}, "
                                    f"stamps: ipc timestamps{note}{cut.note}")},
    )
    return log.validate(path)


def _parse_flaser(path: Path, lineno: int, toks: list[str]):
    """``FLASER n r1 … rn x y θ odom_x odom_y odom_θ ipc_timestamp [host [logger_timestamp]]``."""
    n = _int(path, lineno, toks, 1, "FLASER", "number of readings")
    need = n + 9
    if len(toks) < need or len(toks) > n + 11:
        raise InputError(path, f"line {lineno}: FLASER with {n} readings needs {need} to {n + 11} fields "
                               f"(type, count, ranges, two poses, timestamp, host, logger timestamp), got {len(toks)}")
    r = _floats(path, lineno, toks[2:2 + n], "FLASER", "range")
    stamp = _stamp(path, lineno, toks[n + 8], "FLASER")
    return r, None, stamp, (n, FLASER_ANGLE_MIN, flaser_angle_increment(n), FLASER_RANGE_MAX, False)


def _parse_robotlaser(path: Path, lineno: int, toks: list[str]):
    """``ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r1 … rn
    m e1 … em laser_x laser_y laser_θ robot_x robot_y robot_θ tv rv forward_safety side_safety
    turn_axis timestamp [host [logger_timestamp]]``."""
    if len(toks) < 10:
        raise InputError(path, f"line {lineno}: ROBOTLASER1 has {len(toks)} fields, too few for its header "
                               "(type, start angle, fov, resolution, max range, accuracy, remission mode, count)")
    head = _floats(path, lineno, toks[2:7], "ROBOTLASER1", "header")
    n = _int(path, lineno, toks, 8, "ROBOTLASER1", "number of readings")
    if len(toks) < n + 10:
        raise InputError(path, f"line {lineno}: ROBOTLASER1 with {n} readings has only {len(toks)} fields")
    m = _int(path, lineno, toks, n + 9, "ROBOTLASER1", "number of remissions")
    need = n + m + 22
    if len(toks) < need or len(toks) > n + m + 24:
        raise InputError(path, f"line {lineno}: ROBOTLASER1 with {n} readings and {m} remissions needs {need} to "
                               f"{n + m + 24} fields, got {len(toks)}")
    if m not in (0, n):
        raise InputError(path, f"line {lineno}: ROBOTLASER1 has {m} remissions for {n} readings")
    r = _floats(path, lineno, toks[9:9 + n], "ROBOTLASER1", "range")
    i = _floats(path, lineno, toks[10 + n:10 + n + m], "ROBOTLASER1", "remission") if m else None
    stamp = _stamp(path, lineno, toks[n + m + 21], "ROBOTLASER1")
    start, _fov, res, rmax, _acc = (float(v) for v in head)
    return r, i, stamp, (n, start, res, rmax, m > 0)


def _carmen_geom_text(g) -> str:
    n, amin, inc, rmax, has_i = g
    return f"{n} beams from {amin:.6g} rad by {inc:.6g} rad, max {rmax:g} m{', remissions' if has_i else ''}"


def _int(path: Path, lineno: int, toks: list[str], k: int, kind: str, what: str) -> int:
    try:
        v = int(toks[k])
    except (ValueError, IndexError):
        raise InputError(path, f"line {lineno}: {kind} {what} must be an integer, got "
                               f"{toks[k] if k < len(toks) else 'nothing'!r}") from None
    if v <= 0 and what == "number of readings":
        raise InputError(path, f"line {lineno}: {kind} has {v} readings")
    if v < 0:
        raise InputError(path, f"line {lineno}: {kind} {what} is negative ({v})")
    return v


def _floats(path: Path, lineno: int, toks: list[str], kind: str, what: str) -> np.ndarray:
    try:
        return np.array([float(t) for t in toks], dtype=np.float64)
    except ValueError:
        bad = next(t for t in toks if not _is_float(t))
        raise InputError(path, f"line {lineno}: {kind} {what} {bad!r} is not a number") from None


def _stamp(path: Path, lineno: int, tok: str, kind: str) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise InputError(path, f"line {lineno}: {kind} timestamp {tok!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(path, f"line {lineno}: {kind} timestamp {tok!r} is not finite")
    return v


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def _open_text(path: Path):
    with open(path, "rb") as f:
        gz = f.read(2) == b"\x1f\x8b"
    return gzip.open(path, "rt", encoding="utf-8") if gz else open(path, encoding="utf-8")


class _CutLine:
    """The last line of a text log when the file ends in it without a newline, as a crash or a full
    disk leaves a log: if that line does not parse, it is skipped with a warning
    (:class:`~gtsjax.errors.InputWarning`) instead of refusing the whole log. A bad line anywhere
    else, or a last line that ends in a newline, is still an :class:`InputError`."""

    def __init__(self, path: Path):
        self.path, self.lineno, self.skipped = path, 0, False

    def skip(self, lineno: int, err: InputError) -> bool:
        """Whether line ``lineno``, which failed with ``err``, is the cut last line (then warn)."""
        if not self.lineno or lineno != self.lineno:
            return False
        self.skipped = True
        warnings.warn(InputWarning(self.path, f"line {lineno} is cut short (the file ends in it without a newline, "
                                              f"as after a crash) and does not parse ({err.problem}); skipped"),
                      stacklevel=2)
        return True

    @property
    def note(self) -> str:
        return f"; last line {self.lineno} cut short, skipped" if self.skipped else ""


def _text_lines(path: Path, cut: _CutLine | None = None):
    """(line number, whitespace-split tokens) of every non-blank, non-comment line of a text log, plain
    or gzip; a file that is not text, or a damaged gzip stream, is one :class:`InputError`. ``cut``
    is told the number of a last line that has no newline at its end."""
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, "is a directory, not a text log")
    lineno = 0
    try:
        with _open_text(path) as f:
            for lineno, line in enumerate(f, start=1):
                if cut is not None and not line.endswith("\n"):
                    cut.lineno = lineno
                toks = line.split()
                if toks and not toks[0].startswith("#"):
                    yield lineno, toks
    except UnicodeDecodeError:
        raise InputError(path, f"line {lineno + 1}: not text (undecodable bytes); is it a binary file?") from None
    except (EOFError, gzip.BadGzipFile, zlib.error) as err:
        raise InputError(path, f"damaged or truncated gzip stream after line {lineno} "
                               f"({type(err).__name__})") from None
    except OSError as err:  # no permission to read it, a socket, a device that fails
        raise InputError(path, f"cannot be read ({err.strerror or err})") from None


def _gzip_looks_like_carmen(path: Path) -> bool:
    try:
        with gzip.open(path, "rt", encoding="utf-8") as f:
            for _, line in zip(range(200), f, strict=False):
                toks = line.split()
                if toks and toks[0] in ("FLASER", "ROBOTLASER1", "ODOM", "PARAM", "RLASER"):
                    return True
    except (OSError, EOFError, UnicodeDecodeError, zlib.error):
        return False
    return False


# --------------------------------------------------------------------------------------------- BreezySLAM

BREEZY_FIRST_RANGE = 24


def read_breezyslam(path: str | os.PathLike) -> ScanLog:
    """BreezySLAM's URG-04LX log (its ``examples/exp1.dat``): one scan per line, field 0 the timestamp
    in microseconds, fields 1–23 odometry and other data (not used), fields 24–705 the 682 ranges in
    millimetres (0 = no return), and one trailing field, which BreezySLAM's own reader drops.

    The line carries no geometry; the angles are the URG-04LX model's (:data:`gtsjax.sensors.URG_04LX`:
    steps 44–725 of 1024 per turn, step 384 forward), as are the range window and ``sensor_model``,
    so a model trained for that scanner replays the log as it is.
    """
    path = Path(path)
    ranges, stamps, linenos = [], [], []
    cut = _CutLine(path)
    for lineno, toks in _text_lines(path, cut):
        try:
            stamp, r = _parse_breezy(path, lineno, toks)
        except InputError as err:
            if not cut.skip(lineno, err):
                raise
            continue
        ranges.append(r)
        stamps.append(stamp)
        linenos.append(lineno)
    if not ranges:
        raise InputError(path, "no scan lines: not a BreezySLAM text log")
    stamps, note = _monotonic(np.asarray(stamps, dtype=np.float64) / 1e6, lambda j: f"line {linenos[j]}", path)
    log = ScanLog(
        ranges=(np.asarray(ranges, dtype=np.float64) / 1000.0).astype(np.float32),
        stamps=stamps,
        angle_min=URG_04LX.angle_min,
        angle_increment=URG_04LX.angle_increment,
        range_min=URG_04LX.range_min,
        range_max=URG_04LX.range_max,
        sensor_model=URG_04LX.name,
        extra={"source": np.asarray(f"BreezySLAM text log {path.name}, {len(ranges)} lines, URG-04LX angles, "
                                    f"stamps: µs field{note}{cut.note}")},
    )
    return log.validate(path)


def _parse_breezy(path: Path, lineno: int, toks: list[str]) -> tuple[int, np.ndarray]:
    n = URG_04LX.n_beams
    lo, hi = BREEZY_FIRST_RANGE, BREEZY_FIRST_RANGE + n
    if len(toks) not in (hi, hi + 1):
        raise InputError(path, f"line {lineno} has {len(toks)} fields; a BreezySLAM URG-04LX line has {hi + 1} "
                               f"(timestamp in µs, 23 odometry fields, {n} ranges in mm, one trailing field)")
    try:
        stamp = int(toks[0])
    except ValueError:
        raise InputError(path, f"line {lineno}: timestamp {toks[0]!r} is not an integer (µs)") from None
    return stamp, _floats(path, lineno, toks[lo:hi], "BreezySLAM", "range")
