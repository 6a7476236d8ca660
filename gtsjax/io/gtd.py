"""Ground-truth output (``shared/spec/formats.md``): the GTD CSV, per-track TUM trajectories, and
JSON lines for streaming.

CSV header ``stamp,track_id,class,x,y,theta,var_x,var_y,var_theta``; one row per confirmed track per
processed scan, in scan order; ``theta`` wrapped to (−π, π]. The writer flushes every scan, so that
a crash or Ctrl-C loses nothing already processed.

The header is a contract other programs parse, so it stays the default. ``--csv-units`` writes the
optional form :data:`UNITS_HEADER`: the same columns named with their units (``x_m``, ``theta_rad``,
``var_x_m2``, …) and one more, ``cov_xy_m2``, the x–y covariance the marginal variances leave out
(a robot seen end-on from a laser far away has an error ellipse at 45° to the axes, which the
diagonal alone draws as a circle). The reader takes either header, and the spec header followed by
``cov_xy``.

``run --beliefs`` and a model that reads reflective tags append one more optional column, ``robot``,
last after either form: the name of the robot the track is at that scan, empty where none yet. A
tag's reading (:mod:`gtsjax.core.g_identity`) names it where the model reads tags, else the live
association of the robots' own beliefs (:mod:`gtsjax.grade.online`). Without either the file is as
before, byte for byte, so readers of the contract see nothing new unless they ask for it.
"""

import csv
import functools
import io
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

HEADER = ("stamp", "track_id", "class", "x", "y", "theta", "var_x", "var_y", "var_theta")
# The optional form (``--csv-units``): the spec's columns with their units, and the x–y covariance.
UNITS_HEADER = ("stamp_s", "track_id", "class", "x_m", "y_m", "theta_rad", "var_x_m2", "var_y_m2", "var_theta_rad2",
                "cov_xy_m2")
#: The optional last column of ``run --beliefs`` and of models that read tags: the robot's name, empty where unknown.
ROBOT = "robot"
# Headers the reader accepts, with whether they hold ``cov_xy``; each may end in :data:`ROBOT` too.
_BASE = {HEADER: False, HEADER + ("cov_xy",): True, UNITS_HEADER: True, UNITS_HEADER[:-1]: False}
_HEADERS = {**_BASE, **{h + (ROBOT,): c for h, c in _BASE.items()}}


@dataclass(frozen=True)
class TrackRow:
    stamp: float
    track_id: int
    cls: str
    x: float
    y: float
    theta: float
    var_x: float
    var_y: float
    var_theta: float
    cov_xy: float = 0.0  # the x–y covariance; 0 where a CSV without the column was read
    robot: str = ""  # the robot's name from its tag or its beliefs (``run --beliefs``); empty where unknown

    def as_dict(self) -> dict:
        """The row for a JSON line; ``robot`` only where a name is known, so that a run without
        ``--beliefs`` streams what it always did."""
        d = {
            "stamp": self.stamp,
            "track_id": self.track_id,
            "class": self.cls,
            "x": self.x,
            "y": self.y,
            "theta": self.theta,
            "var_x": self.var_x,
            "var_y": self.var_y,
            "var_theta": self.var_theta,
            "cov_xy": self.cov_xy,
        }
        if self.robot:
            d["robot"] = self.robot
        return d


_ROW = "%s,%s,%s,%.6f,%.6f,%.6f,%.6e,%.6e,%.6e\n"  # a GTD row as csv.writer writes the fields below
_ROW_UNITS = _ROW[:-1] + ",%.6e\n"  # and with ``cov_xy``


@functools.cache
def _csv_field(text: str) -> str:
    """``text`` as ``csv.writer`` writes it among other fields (quoted where it must be)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([text, "x"])
    return buf.getvalue()[: -len(",x\n")]


def format_rows(rows: list[TrackRow], units: bool = False, robot: bool = False) -> str:
    """The GTD CSV lines of ``rows`` (:class:`GTDWriter`'s text for them), with the ``cov_xy``
    column where ``units`` (the header :data:`UNITS_HEADER`), and the :data:`ROBOT` column last
    where ``robot``."""
    if robot:
        return "".join([f"{format_rows([r], units)[:-1]},{_csv_field(r.robot)}\n" for r in rows])
    if units:
        return "".join([_ROW_UNITS % (repr(r.stamp), r.track_id, _csv_field(r.cls), r.x, r.y, r.theta, r.var_x,
                                      r.var_y, r.var_theta, r.cov_xy) for r in rows])
    return "".join([_ROW % (repr(r.stamp), r.track_id, _csv_field(r.cls), r.x, r.y, r.theta, r.var_x, r.var_y,
                            r.var_theta) for r in rows])


def wrap_angle(a: float) -> float:
    """One angle (a Python float) to (−π, π]: :func:`~gtsjax.core.geometry.wrap`'s arithmetic
    (Python's ``%`` is NumPy's ``mod``), without NumPy."""
    return math.pi - (math.pi - a) % (2.0 * math.pi)


#: The columns of a scan's track table as the live step hands it to the host in one transfer
#: (:func:`gtsjax.drivers.live.pack_tracks`), one row per track slot: the GTD row's fields first
#: (:func:`rows_from_table` reads them), then what the run's diagnosis counts, then the identity the
#: track reports from its tag (an index into the model's ``tag_names``, -1 for none: issue 43).
PACKED = ("track_id", "class", "x", "y", "theta", "var_x", "var_y", "var_theta", "cov_xy", "reported", "live", "hold",
          "speed", "turn_rate", "robot")
#: The packed table's last row, the scan's status, in its first columns: degraded (no new map
#: transformation), objects, candidates unlike their class's examples, candidates outside their
#: class's envelope, the classes detected as a bit field.
STATUS = ("degraded", "n_objects", "unlike", "off_envelope", "detected")
#: Where each column and status field lies.
COLUMN = {c: i for i, c in enumerate(PACKED)}
STATUS_AT = {c: i for i, c in enumerate(STATUS)}
_ID, _CLS, _X, _Y, _TH, _VX, _VY, _VT, _CXY, _REP, _ROB = (
    COLUMN[c] for c in ("track_id", "class", "x", "y", "theta", "var_x", "var_y", "var_theta", "cov_xy", "reported",
                        "robot"))


def rows_from_table(stamp: float, table, class_names, robot_names: "tuple[str, ...]" = ()) -> list[TrackRow]:
    """Rows for one scan from its track slots as lists in the :data:`PACKED` layout (numbers;
    ``reported`` above 0.5 for a reported track), reported tracks only, in id order; with
    ``robot_names`` (a model's ``tag_names``), each row's ``robot`` the name its track reports from its
    tag, where it reports one. Plain Python: the live loop calls it right after the step, where each
    NumPy call costs many times what it does in a tight loop (see
    :func:`gtsjax.drivers.live.rows_from_packed`)."""
    rows = [TrackRow(float(stamp), int(r[_ID]), class_names[int(r[_CLS])], r[_X], r[_Y], wrap_angle(r[_TH]),
                     r[_VX], r[_VY], r[_VT], r[_CXY],
                     robot_names[int(r[_ROB])] if robot_names and r[_ROB] >= 0 else "")
            for r in table if r[_REP] > 0.5]
    rows.sort(key=lambda row: row.track_id)
    return rows


def rows_from_output(stamp: float, track_id, cls_index, pose, var, mask, class_names, cov_xy=None) -> list[TrackRow]:
    """Rows for one scan from the step's fixed-size track arrays (NumPy or JAX), confirmed tracks only
    (:func:`rows_from_table` of the slots laid out as :data:`PACKED`, in float64); ``cov_xy`` 0 where
    not given."""
    pose, var = np.asarray(pose, np.float64), np.asarray(var, np.float64)
    columns = {"track_id": track_id, "class": cls_index, "x": pose[:, 0], "y": pose[:, 1], "theta": pose[:, 2],
               "var_x": var[:, 0], "var_y": var[:, 1], "var_theta": var[:, 2], "reported": mask}
    if cov_xy is not None:
        columns["cov_xy"] = cov_xy
    table = np.zeros((len(mask), len(PACKED)))
    table[:, COLUMN["robot"]] = -1.0
    for name, values in columns.items():
        table[:, COLUMN[name]] = np.asarray(values, np.float64)
    return rows_from_table(stamp, table.tolist(), class_names)


class GTDWriter:
    """Appends rows to a GTD CSV, one ``write`` per scan, so that a crash or Ctrl-C loses nothing
    already processed. A write that fails (a full disk) is undone to the end of the last whole scan,
    so the file never ends in a torn row, and raised as one line (:class:`InputError`) naming the
    file, the error and the rows kept. Use as a context manager."""

    def __init__(self, path: str | os.PathLike, units: bool = False, robot: bool = False):
        self.path, self.units, self.robot = Path(path), units, robot
        if self.path.parent and not self.path.parent.exists():
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._size = 0
        self.rows = 0
        self._append(",".join((UNITS_HEADER if units else HEADER) + ((ROBOT,) if robot else ())) + "\n")

    def _append(self, text: str) -> None:
        data = text.encode()
        done = 0
        try:
            while done < len(data):
                done += os.write(self._fd, data[done:])
        except OSError as err:
            try:
                os.ftruncate(self._fd, self._size)  # freeing the torn part needs no space
            except OSError:
                pass
            raise InputError(self.path, f"cannot write ({err.strerror}); the {self.rows} rows before are kept") from None
        self._size += len(data)

    def write(self, rows: list[TrackRow]) -> None:
        """Append one scan's rows, flushed. The text is what ``csv.writer`` writes for the rows
        (only a class name can need quoting; its field is made by ``csv`` once per name), formatted
        with one ``%`` per row: this runs on the live loop's path right after the step, when every
        line of Python costs several times what it does in a tight loop (a ``csv.writer`` over a
        ``StringIO`` cost many times this)."""
        if not rows:
            return
        self._append(format_rows(rows, self.units, self.robot))
        self.rows += len(rows)

    def close(self) -> None:
        if self._fd < 0:
            return
        fd, self._fd = self._fd, -1
        try:
            os.fsync(fd)
        except OSError:
            pass  # every row is in the file already; the disk failing to sync it is not the rows' loss
        finally:
            os.close(fd)

    def __enter__(self) -> "GTDWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def json_line(rows: list[TrackRow], stamp: float, **extra) -> str:
    """One scan as a JSON line: ``{"stamp": ..., "tracks": [{...}, ...], ...extra}``."""
    return json.dumps({"stamp": stamp, "tracks": [r.as_dict() for r in rows], **extra}, separators=(",", ":"))


def read_text(path: Path, folder: str, binary: str) -> str:
    """A text file's contents, or one line (:class:`InputError`) for a path that is missing, a folder
    (``folder`` says what was expected), not text (``binary``) or unreadable."""
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, folder)
    try:
        return path.read_text()
    except UnicodeDecodeError:
        raise InputError(path, binary) from None
    except OSError as err:  # a socket, a file without read permission
        raise InputError(path, f"cannot be read ({err.strerror or err})") from None


def read_gtd(path: str | os.PathLike) -> list[TrackRow]:
    """Read a GTD CSV back (either header, :data:`HEADER` or :data:`UNITS_HEADER`, and the spec's
    header followed by ``cov_xy``; each with or without a last :data:`ROBOT` column); a file that does
    not follow the format is an :class:`InputError`."""
    path = Path(path)
    text = read_text(path, "is a folder, not a ground-truth CSV", "not a text CSV file")
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    names = None if header is None else tuple(h.strip() for h in header)
    if names not in _HEADERS:
        raise InputError(path, f"header must be {','.join(HEADER)} (or, with units, {','.join(UNITS_HEADER)}; "
                               f"either may end in ,{ROBOT})")
    with_robot = names[-1] == ROBOT
    with_cov = _HEADERS[names]
    n_num = len(names) - 3 - int(with_robot)  # the numeric columns after the class
    rows = []
    for n, rec in enumerate(reader, start=2):
        if not rec:
            continue
        if len(rec) != len(names):
            raise InputError(path, f"line {n} has {len(rec)} fields, expected {len(names)}")
        try:
            vals = [float(rec[0]), int(rec[1]), rec[2]] + [float(v) for v in rec[3:3 + n_num]]
        except ValueError:
            raise InputError(path, f"line {n} has a non-numeric field") from None
        if not all(math.isfinite(v) for v in vals[:2] + vals[3:]):
            raise InputError(path, f"line {n} has a non-finite value")
        if not with_cov:
            vals.append(0.0)
        rows.append(TrackRow(*vals, robot=rec[-1] if with_robot else ""))
    return rows


def tracks_of(rows: list[TrackRow]) -> Iterator[tuple[int, str, np.ndarray]]:
    """Per track: id, class and an array ``[n, 4]`` of (stamp, x, y, theta) in stamp order."""
    by_id: dict[int, list[TrackRow]] = {}
    for r in rows:
        by_id.setdefault(r.track_id, []).append(r)
    for tid in sorted(by_id):
        rs = by_id[tid]
        arr = np.array([[r.stamp, r.x, r.y, r.theta] for r in rs], dtype=np.float64)
        yield tid, rs[0].cls, arr[np.argsort(arr[:, 0], kind="stable")]


def write_tum(path: str | os.PathLike, track: np.ndarray) -> None:
    """One track as a TUM trajectory: ``timestamp tx ty tz qx qy qz qw`` per line, z = 0, the
    heading as a rotation about z."""
    t, x, y, th = track.T
    half = th / 2.0
    lines = [
        f"{ti:.6f} {xi:.6f} {yi:.6f} 0.000000 0.000000 0.000000 {np.sin(h):.9f} {np.cos(h):.9f}"
        for ti, xi, yi, h in zip(t, x, y, half, strict=True)
    ]
    Path(path).write_text("\n".join(lines) + ("\n" if lines else ""))
