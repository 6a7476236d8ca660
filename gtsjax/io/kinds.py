"""What a file is, when it is not what a command expected: one home for the sniffing that ``gtsjax
info`` and every loader share, so that a PNG given as a scan log is called a PNG image whichever
command it is given to, never "not a NumPy .npz archive (ValueError)"."""

import os
import zipfile
from pathlib import Path

#: Other programs' logs that ``gtsjax convert`` (and ``replay``) read, as ``importers.detect_format``
#: names them.
_LOGS = {"ros1": "a ROS 1 bag", "ros2": "a ROS 2 bag", "carmen": "a CARMEN log", "breezyslam": "a BreezySLAM log"}
_MAGIC = ((b"\x89PNG", "a PNG image"), (b"%PDF", "a PDF document"), (b"\xff\xd8\xff", "a JPEG image"),
          (b"GIF8", "a GIF image"), (b"\x1f\x8b", "a gzip-compressed file"), (b"SQLite format 3", "an SQLite database"))


def file_kind(path: str | os.PathLike) -> str | None:
    """``"a PNG image"``, ``"a CSV file"``, ``"a BreezySLAM log"``, ... for a file that is not a zip
    archive (an ``.npz`` is one); ``None`` for a zip archive, a folder, a file that cannot be opened, or
    binary data of no kind known here (the reader's own message then says what is wrong)."""
    from .importers import detect_format  # the importers read logs: imported when asked, not at import

    path = Path(path)
    try:
        if not path.is_file() or zipfile.is_zipfile(path):
            return None
        fmt = detect_format(path)
        if fmt in _LOGS:
            return _LOGS[fmt]
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    if head.startswith(b"PK"):
        return None  # a damaged zip archive: the reader says what it found
    for magic, kind in _MAGIC:
        if head.startswith(magic):
            return kind
    if not head:
        return "an empty file"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as err:
        if err.start < len(head) - 3:  # not just a character cut at the end of the 4 kB
            return None
        text = head[: err.start].decode("utf-8")
    if "\x00" in text:
        return None
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if first.startswith(("{", "[")):
        return "a JSON file"
    return "a CSV file" if "," in first else "a text file"


def not_expected(path: str | os.PathLike, expected: str) -> str | None:
    """The one-line problem of a file of another kind given where ``expected`` was (``"a .npz scan
    log"``), with the way on where there is one; ``None`` where :func:`file_kind` cannot tell."""
    kind = file_kind(path)
    if kind is None:
        return None
    if kind in _LOGS.values() and "scan log" in expected:
        return f"{kind}, not {expected}: convert it first (gtsjax convert {path} --out LOG.npz)"
    return f"{kind}, not {expected}"
