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

#: A position beyond this (m) from the field's origin is no robot's on a field: most likely millimetres.
MAX_POSITION_M = 100.0
#: A heading beyond this (rad; a little over π, for a wrapped one's rounding) is most likely in degrees.
MAX_HEADING_RAD = 2.0 * math.pi
#: How far a TUM quaternion's length may be from 1 (as written with six or nine decimals).
QUATERNION_TOLERANCE = 1e-3
#: The CSV columns read.
CSV_COLUMNS = ("stamp", "x", "y", "theta")


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
    poses[:, 2] = np.pi - np.mod(np.pi - poses[:, 2], 2.0 * np.pi)  # to (−π, π]
    return Beliefs(name or path.stem, stamps, poses, str(path))


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
    q = a[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOLERANCE)
    if bad.size:
        raise InputError(path, f"line {where[bad[0]]}: the quaternion (qx qy qz qw) has length {norm[bad[0]]:.4g}, "
                               "not 1: not a TUM trajectory")
    qx, qy, qz, qw = q.T
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return a[:, 0], np.stack([a[:, 1], a[:, 2], yaw], -1)


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


def _table(path: Path, rows: list, where: list[int]) -> np.ndarray:
    """The lines read as one float64 array, checked: some poses, every value finite (``where``: each
    row's line number)."""
    if not rows:
        raise InputError(path, "holds no poses")
    a = np.asarray(rows, np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
    if bad.size:
        raise InputError(path, f"line {where[bad[0]]} has a value that is not a number (NaN or infinite); "
                               f"{bad.size} such line{'s' if bad.size > 1 else ''} in all: leave out the poses the "
                               "robot did not have")
    return a


def _check(path: Path, stamps: np.ndarray, poses: np.ndarray, is_csv: bool) -> None:
    """Stamps that increase, positions in metres and (CSV) headings in radians."""
    step = np.diff(stamps)
    back = np.flatnonzero(step <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(path, f"pose {i + 1} (stamp {float(stamps[i])!r}) is not after the one before "
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
