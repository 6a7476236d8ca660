"""Crash-safe recording of raw scans: an append-only journal while recording, a scan log at the end.

Why a journal: a ``.npz`` is a zip archive written whole, so a recording kept only in memory is
lost to a crash, a ``kill -9`` or a pulled power cable. :class:`Recorder` appends every scan to
``RAW.npz.journal`` next to the target as one fixed-size binary record, written with a single
``write()`` (so ``kill -9`` loses nothing already appended: the data sits in the kernel's page
cache) and ``fsync``'d at least every ``sync_interval`` seconds (so a power cut loses at most the
last second). On a clean :meth:`Recorder.close` the journal becomes ``RAW.npz`` in the scan-log
format of ``shared/spec/formats.md`` (written atomically, a block at a time: :func:`journal_to_log`) and
the journal is removed.

After a crash, turn the journal into a scan log with one command::

    python -m gtsjax.io.record RAW.npz.journal RAW.npz

(:func:`recover`; ``gtsjax recover RAW.npz.journal`` calls the same function). A torn last record
is cut off, and a record whose CRC fails is skipped and counted.

Journal layout (little-endian): ``b"GTSJRNL1"``, ``uint32`` header length, a JSON header
(``n_beams``, ``angle_min``, ``angle_increment``, ``range_min``, ``range_max``, ``sensor_model``,
``intensities``), then records of ``float64 stamp, float32 ranges[n_beams], [float32
intensities[n_beams]], uint32 crc32`` (the CRC covers the bytes of the record before it).
"""

import json
import math
import os
import struct
import sys
import threading
import time
import warnings
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError, InputWarning
from ..sensors import SensorModel
from .logs import DEFAULT_RANGE_MAX, DEFAULT_RANGE_MIN, ScanLog, _validate, load_log

MAGIC = b"GTSJRNL1"
JOURNAL_SUFFIX = ".journal"


def journal_path(path: "str | os.PathLike") -> Path:
    """Where the journal of a recording to ``path`` lives."""
    p = Path(path)
    return p.with_name(p.name + JOURNAL_SUFFIX)


def _record_dtype(n_beams: int, intensities: bool) -> np.dtype:
    fields = [("stamp", "<f8"), ("ranges", "<f4", (n_beams,))]
    if intensities:
        fields.append(("intensities", "<f4", (n_beams,)))
    fields.append(("crc", "<u4"))
    return np.dtype(fields)


class Recorder:
    """Append raw scans to a journal as they arrive; ``close()`` writes the scan log.

    Geometry comes from ``model`` (a :class:`~gtsjax.sensors.SensorModel`) or from ``n_beams``,
    ``angle_min``, ``angle_increment`` (and the optional range window and model name). Stamps are
    host seconds (float64); a stamp earlier than the previous one is raised to it (the format needs
    non-decreasing stamps; a reconnect may restart the sensor's clock) and counted in ``clamped``.
    """

    def __init__(
        self,
        path: "str | os.PathLike",
        model: SensorModel | None = None,
        *,
        n_beams: int | None = None,
        angle_min: float | None = None,
        angle_increment: float | None = None,
        range_min: float | None = None,
        range_max: float | None = None,
        sensor_model: str | None = None,
        intensities: bool = False,
        sync_interval: float = 0.5,
    ):
        self.path = Path(path)
        self.journal = journal_path(self.path)
        if model is not None:
            n_beams = model.n_beams if n_beams is None else n_beams
            angle_min = model.angle_min if angle_min is None else angle_min
            angle_increment = model.angle_increment if angle_increment is None else angle_increment
            range_min = model.range_min if range_min is None else range_min
            range_max = model.range_max if range_max is None else range_max
            sensor_model = model.name if sensor_model is None else sensor_model
        if n_beams is None or angle_min is None or angle_increment is None:
            raise InputError(self.path, "a recorder needs a sensor model or n_beams, angle_min and angle_increment")
        if self.journal.exists() and _holds_no_scan(self.journal):
            # An earlier recording stopped before its first scan (or its header) reached the disk:
            # nothing to recover, and it must not block this one.
            warnings.warn(InputWarning(self.journal, "an earlier recording's journal held no scan: removed"),
                          stacklevel=2)
            self.journal.unlink()
        if self.journal.exists():
            raise InputError(
                self.journal,
                "a journal from an earlier recording is here; recover it first "
                f"(gtsjax recover {self.journal} OUT.npz) or remove it",
            )
        self.header = {
            "n_beams": int(n_beams),
            "angle_min": float(angle_min),
            "angle_increment": float(angle_increment),
            "range_min": float(DEFAULT_RANGE_MIN if range_min is None else range_min),
            "range_max": float(DEFAULT_RANGE_MAX if range_max is None else range_max),
            "sensor_model": sensor_model,
            "intensities": bool(intensities),
        }
        self._dtype = _record_dtype(int(n_beams), bool(intensities))
        self.sync_interval = float(sync_interval)
        self.count = 0
        self.clamped = 0
        self._last_stamp = -np.inf
        self._lock = threading.Lock()
        self._dirty = False
        self._syncing = 0
        self._closed = False
        self.journal.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.journal, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644)
        head = json.dumps(self.header).encode()
        self._size = len(MAGIC) + 4 + len(head)
        os.write(self._fd, MAGIC + struct.pack("<I", len(head)) + head)
        os.fsync(self._fd)
        _fsync_dir(self.journal.parent)  # so that the journal's name itself survives a power cut
        self._stop = threading.Event()
        # fsync from a timer as well, so that the guarantee holds when scans pause.
        self._syncer = threading.Thread(target=self._sync_loop, name="gtsjax-recorder-sync", daemon=True)
        self._syncer.start()

    def append(self, ranges_m: np.ndarray, stamp: float, intensities: np.ndarray | None = None) -> None:
        """Append one scan: ranges in metres (0 for no return), host stamp in seconds."""
        rec = np.zeros((), dtype=self._dtype)
        r = np.asarray(ranges_m, dtype=np.float32)
        if r.shape != (self.header["n_beams"],):
            raise InputError(self.path, f"scan has {r.shape} ranges, the recording has {self.header['n_beams']} beams")
        stamp = float(stamp)
        if stamp < self._last_stamp:
            stamp = self._last_stamp
            self.clamped += 1
        self._last_stamp = stamp
        rec["stamp"] = stamp
        rec["ranges"] = r
        if self.header["intensities"]:
            rec["intensities"] = 0.0 if intensities is None else np.asarray(intensities, dtype=np.float32)
        body = rec.tobytes()[:-4]
        rec["crc"] = zlib.crc32(body)
        with self._lock:
            if self._closed:
                raise InputError(self.path, "recorder is closed")
            data = rec.tobytes()
            try:
                done = 0
                while done < len(data):
                    done += os.write(self._fd, data[done:])
            except OSError as err:
                try:
                    os.ftruncate(self._fd, self._size)  # no torn record left behind
                except OSError:
                    pass
                raise InputError(self.journal, f"cannot write ({err.strerror}); the {self.count} scans before are "
                                 f"kept (gtsjax recover {self.journal} when there is room)") from None
            self._size += len(data)
            self.count += 1
            self._dirty = True

    def append_frame(self, frame) -> None:
        """Append a :class:`~gtsjax.io.serial.LinkFrame` (its ``ranges_m``, ``intensities``, ``stamp``)."""
        self.append(frame.ranges_m, frame.stamp, frame.intensities)

    def sync(self) -> None:
        """Force the journal to disk now. The lock is not held while the disk works: an ``fsync`` can
        take tens of milliseconds, and :meth:`append` (the live loop) must not wait for it; a record
        appended meanwhile leaves the journal dirty for the next sync. :meth:`close` stops the syncing
        thread before it closes the file."""
        with self._lock:
            if self._closed or not self._dirty:
                return
            self._dirty = False
            self._syncing += 1
        try:
            os.fsync(self._fd)
        finally:
            with self._lock:
                self._syncing -= 1

    def _sync_loop(self) -> None:
        while not self._stop.wait(self.sync_interval):
            try:
                self.sync()
            except OSError:
                pass

    def close(self, keep_journal: bool = False, write_log: bool = True) -> int | None:
        """Finish: write the scan log to :attr:`path` (atomically, a block of records at a time:
        :func:`journal_to_log`), remove the journal, return the number of scans written.

        With no scan recorded there is nothing to write (a scan log needs at least one scan): the
        journal is removed and ``None`` returned. ``write_log=False`` (after a failed write: the disk
        is full) closes the journal and leaves it for :func:`recover`, returning ``None``.
        """
        if self._closed:
            return None
        self._stop.set()
        self._syncer.join(timeout=2.0)
        while True:  # a sync running in another thread finishes before the file is closed
            with self._lock:
                if self._syncing == 0:
                    break
            time.sleep(0.001)
        with self._lock:
            try:
                os.fsync(self._fd)
            except OSError:
                pass  # the records are in the file; journal_to_log below reads them back
            os.close(self._fd)
            self._closed = True
        if not write_log:
            return None
        if self.count == 0:
            if not keep_journal:
                self.journal.unlink(missing_ok=True)
            return None
        try:
            report = journal_to_log(self.journal, self.path)
        except OSError as err:
            raise InputError(self.path, f"cannot write the scan log ({err.strerror}); its {self.count} scans are "
                             f"kept in {self.journal} (gtsjax recover {self.journal} when there is room)") from None
        if not keep_journal:
            self.journal.unlink(missing_ok=True)
        return report["records"]

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _holds_no_scan(path: Path) -> bool:
    """Whether a journal holds not one whole scan record: empty, a torn header, or a header alone."""
    try:
        size = path.stat().st_size
        if size < len(MAGIC) + 4:
            return True
        n = _open_journal(path)[3]
    except InputError:
        return False  # damaged: the user decides
    return n == 0


def _check_header(header, path: Path) -> None:
    """A journal header holds what a log needs: the beam count, the angles, whether there are
    intensities; anything else (a header edited, or written by something else) is one line."""
    def finite(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if not isinstance(header, dict):
        raise InputError(path, "journal header is damaged (not a JSON object)")
    missing = [k for k in ("n_beams", "angle_min", "angle_increment", "intensities") if k not in header]
    if missing:
        raise InputError(path, f"journal header is missing {', '.join(map(repr, missing))}")
    n = header["n_beams"]
    if not (isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= 1_000_000):
        raise InputError(path, f"journal header's n_beams is {n!r}, expected 1–1000000")
    if not (finite(header["angle_min"]) and finite(header["angle_increment"]) and header["angle_increment"] > 0):
        raise InputError(path, "journal header's angle_min and angle_increment must be finite, the increment positive")
    if not isinstance(header["intensities"], bool):
        raise InputError(path, "journal header's intensities must be true or false")
    for key in ("range_min", "range_max"):
        if key in header and not finite(header[key]):
            raise InputError(path, f"journal header's {key} is {header[key]!r}, expected a finite number (m)")
    if not isinstance(header.get("sensor_model"), str | None):
        raise InputError(path, f"journal header's sensor_model is {header['sensor_model']!r}, expected a name or null")


def read_journal(path: "str | os.PathLike") -> tuple[ScanLog, dict]:
    """The scan log held by a journal, and a report: ``records``, ``torn_bytes``, ``bad_crc``."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise InputError(path, f"cannot read the journal ({err.strerror or err})") from None
    if len(raw) < len(MAGIC) + 4 or raw[: len(MAGIC)] != MAGIC:
        raise InputError(path, "not a gtsjax recording journal (bad magic)")
    (hlen,) = struct.unpack_from("<I", raw, len(MAGIC))
    start = len(MAGIC) + 4 + hlen
    try:
        header = json.loads(raw[len(MAGIC) + 4 : start].decode())
        _check_header(header, path)
        n_beams = int(header["n_beams"])
        has_inten = bool(header["intensities"])
    except InputError:
        raise
    except (ValueError, KeyError, TypeError, UnicodeDecodeError):
        raise InputError(path, "journal header is damaged") from None
    dtype = _record_dtype(n_beams, has_inten)
    body = raw[start:]
    n = len(body) // dtype.itemsize
    torn = len(body) - n * dtype.itemsize
    recs = np.frombuffer(body, dtype=dtype, count=n)
    as_bytes = np.frombuffer(body, dtype=np.uint8, count=n * dtype.itemsize).reshape(n, dtype.itemsize)
    crc_ok = np.array([zlib.crc32(row[:-4].tobytes()) == c for row, c in zip(as_bytes, recs["crc"], strict=True)], bool)
    good = recs[crc_ok] if n else recs
    report = {"records": int(np.count_nonzero(crc_ok)), "torn_bytes": int(torn), "bad_crc": int(n - crc_ok.sum())}
    if good.shape[0] == 0:
        raise InputError(path, "the journal holds no complete scan")
    stamps = np.maximum.accumulate(good["stamp"].astype(np.float64))
    log = ScanLog(
        ranges=np.ascontiguousarray(good["ranges"], dtype=np.float32),
        stamps=stamps,
        angle_min=float(header["angle_min"]),
        angle_increment=float(header["angle_increment"]),
        intensities=np.ascontiguousarray(good["intensities"], dtype=np.float32) if has_inten else None,
        range_min=float(header.get("range_min", DEFAULT_RANGE_MIN)),
        range_max=float(header.get("range_max", DEFAULT_RANGE_MAX)),
        sensor_model=header.get("sensor_model"),
    )
    return log, report


#: Records converted at a time by :func:`journal_to_log`: memory stays bounded by a block whatever the
#: recording's length (an hour of a UTM-30LX with intensities is 1.25 GB of records).
BLOCK_RECORDS = 2048


def _open_journal(path: Path):
    """The journal's header, record dtype, data offset and record count (a torn tail not counted)."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(len(MAGIC) + 4)
            if len(head) < len(MAGIC) + 4 or head[: len(MAGIC)] != MAGIC:
                raise InputError(path, "not a gtsjax recording journal (bad magic)")
            (hlen,) = struct.unpack_from("<I", head, len(MAGIC))
            header_bytes = f.read(hlen)
    except OSError as err:
        raise InputError(path, f"cannot read the journal ({err.strerror or err})") from None
    try:
        header = json.loads(header_bytes.decode())
        _check_header(header, path)
        dtype = _record_dtype(int(header["n_beams"]), bool(header["intensities"]))
    except InputError:
        raise
    except (ValueError, KeyError, TypeError, UnicodeDecodeError):
        raise InputError(path, "journal header is damaged") from None
    start = len(MAGIC) + 4 + hlen
    n = max(size - start, 0) // dtype.itemsize
    torn = max(size - start, 0) - n * dtype.itemsize
    return header, dtype, start, n, torn


def journal_to_log(journal: "str | os.PathLike", out_path: "str | os.PathLike") -> dict:
    """Write the scan log a journal holds to ``out_path`` (an ``.npz`` of the scan-log format, written
    to a temporary name and renamed), a block of records at a time: the journal is memory-mapped and
    each array streamed into the archive, so converting an hour's recording takes a block's memory,
    not the recording's several times over. A torn last record is cut, a record failing its CRC
    skipped. Returns ``records``, ``torn_bytes``, ``bad_crc``, ``out``."""
    import zipfile

    journal, out_path = Path(journal), Path(out_path)
    header, dtype, start, n, torn = _open_journal(journal)
    recs = np.memmap(journal, dtype=dtype, mode="r", offset=start, shape=(n,)) if n else np.zeros(0, dtype)
    good = np.zeros(n, bool)
    for a in range(0, n, BLOCK_RECORDS):
        block = np.asarray(recs[a:a + BLOCK_RECORDS])
        rows = block.view(np.uint8).reshape(len(block), dtype.itemsize)
        good[a:a + len(block)] = [zlib.crc32(r[:-4].tobytes()) == c for r, c in zip(rows, block["crc"], strict=True)]
    idx = np.flatnonzero(good)
    report = {"records": int(idx.size), "torn_bytes": int(torn), "bad_crc": int(n - idx.size), "out": str(out_path)}
    if idx.size == 0:
        raise InputError(journal, "the journal holds no complete scan")
    n_beams, has_inten = int(header["n_beams"]), bool(header["intensities"])
    stamps = np.maximum.accumulate(np.asarray(recs["stamp"][idx], np.float64))
    small = {"stamps": stamps, "angle_min": np.float64(header["angle_min"]),
             "angle_increment": np.float64(header["angle_increment"]),
             "range_min": np.float64(header.get("range_min", DEFAULT_RANGE_MIN)),
             "range_max": np.float64(header.get("range_max", DEFAULT_RANGE_MAX))}
    if header.get("sensor_model") is not None:
        small["sensor_model"] = np.asarray(header["sensor_model"], dtype=np.str_)
    # The format's rules, checked with a stand-in for the ranges of their shape (no memory; the
    # intensities' values are checked block by block as they are written). What breaks one is in the
    # journal: it is the file named.
    _validate({**small, "ranges": np.lib.stride_tricks.as_strided(np.zeros(1, np.float32), (idx.size, n_beams),
                                                                  (0, 0))}, journal)
    _out_folder(out_path)
    tmp = out_path.with_name(out_path.name + ".part")
    try:
        with open(tmp, "wb") as f, zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for field in ("ranges", "intensities") if has_inten else ("ranges",):
                with zf.open(f"{field}.npy", "w", force_zip64=True) as entry:
                    np.lib.format.write_array_header_2_0(entry, {"descr": "<f4", "fortran_order": False,
                                                                 "shape": (int(idx.size), n_beams)})
                    for a in range(0, idx.size, BLOCK_RECORDS):
                        block = np.ascontiguousarray(recs[field][idx[a:a + BLOCK_RECORDS]], dtype="<f4")
                        if field == "intensities" and not (np.all(np.isfinite(block)) and np.all(block >= 0)):
                            raise InputError(journal, "'intensities' must be finite and >= 0")
                        entry.write(block.tobytes())
            for key, value in small.items():
                with zf.open(f"{key}.npy", "w", force_zip64=True) as entry:
                    np.lib.format.write_array(entry, np.asarray(value), allow_pickle=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out_path)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)  # no half-written .part left behind
        except OSError:
            pass
        raise
    finally:
        del recs
    return report


def _out_folder(out_path: Path) -> None:
    """The folder of the log :func:`journal_to_log` writes, made if missing (as every command makes its
    outputs' folders), once the journal is known to hold a log: a folder in the log's place, or a
    file in a folder's, is one line."""
    if out_path.is_dir():
        raise InputError(out_path, "is a directory; give the scan log (.npz) to write")
    existing = next((p for p in out_path.parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InputError(existing, f"is a file, not a folder, so {out_path} cannot be written")
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(out_path.parent, f"cannot create the folder ({err.strerror})") from None


def recover(journal: "str | os.PathLike", out_path: "str | os.PathLike | None" = None) -> ScanLog:
    """Turn a journal (possibly with a torn last record) into a valid scan log at ``out_path``.

    ``out_path`` defaults to the journal's name without ``.journal``. The journal is left in place.
    Returns the log, read back (``main``, ``gtsjax recover``, only counts it).
    """
    report = _recover(journal, out_path)
    return load_log(report["out"])


def _recover(journal: "str | os.PathLike", out_path: "str | os.PathLike | None") -> dict:
    journal = Path(journal)
    if out_path is None:
        if not journal.name.endswith(JOURNAL_SUFFIX):
            raise InputError(journal, f"name does not end in {JOURNAL_SUFFIX}; give the output path")
        out_path = journal.with_name(journal.name[: -len(JOURNAL_SUFFIX)])
    try:
        return journal_to_log(journal, out_path)
    except OSError as err:  # a full disk, a folder without write permission
        raise InputError(out_path, f"cannot write the scan log ({err.strerror or err})") from None


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def main(argv: list[str] | None = None) -> int:
    """``python -m gtsjax.io.record JOURNAL [OUT.npz]``: recover a recording; exit 0, or 2 on bad input."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (1, 2) or args[0] in ("-h", "--help"):
        print("usage: python -m gtsjax.io.record RAW.npz.journal [OUT.npz]", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    try:
        report = _recover(args[0], args[1] if len(args) == 2 else None)
    except InputError as err:
        print(f"gtsjax: {err}", file=sys.stderr)
        return 2
    print(
        f"recovered {report['records']} scans to {report['out']} ({report['torn_bytes']} torn bytes cut, "
        f"{report['bad_crc']} damaged records skipped) in {time.monotonic() - t0:.2f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
