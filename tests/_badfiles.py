"""Bad file arguments for every command, made here: damaged scan logs, sites, models, ROS bags,
recording journals, ground-truth CSVs and paths (issue 39's fuzz, ``tests/test_cli_fuzz.py``).

:func:`cases` lists them by name, each a :class:`Case`: a command line with placeholders, and how its
bad file is made from the good inputs :func:`write_inputs` writes. Everything is deterministic: the
random damage (bit flips, cut points) comes from a generator seeded by :data:`SEED` and the case's
name, so a case that fails fails again. The bags are written with rosbags' own writers (ROS 1, ROS 2
with SQLite or MCAP storage), the only way here to get bags of several topics."""

import dataclasses
import io
import json
import math
import shutil
import socket
import struct
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gtsjax.cli.demo import demo_model_path

SEED = 39
DEMO_MODEL = demo_model_path()


@dataclasses.dataclass(frozen=True)
class Case:
    """One command line and what it must do.

    ``args`` holds ``{d}`` (the folder of good inputs, :func:`write_inputs`), ``{f}`` (this case's bad
    file, ``file`` in a folder of its own, made by ``make(d, f)``; ``make`` ``None``: nothing is made
    there) and ``{o}`` (an empty folder for outputs). The one error line must hold ``names`` (the
    file or the option at fault), formatted the same way. ``code`` 0 is for an input that is
    acceptable after all, and ``why`` says why; ``root`` False for a case that means nothing to root
    (who reads and writes files whatever their mode); ``xfail`` says why a case still fails, where the
    fix is outside the loaders (the case then fails strictly: it says so once it passes)."""

    args: tuple[str, ...]
    make: Callable[[Path, Path], None] | None = None
    file: str = "bad.npz"
    names: str = "{f}"
    code: int = 2
    why: str = ""
    root: bool = True
    xfail: str = ""


def rng_for(name: str) -> np.random.Generator:
    """The case's own random numbers: the same on every run, different from case to case."""
    return np.random.default_rng([SEED, zlib.crc32(name.encode())])


# ------------------------------------------------------------------------------------------ good inputs


def write_inputs(d: Path) -> None:
    """The good inputs the cases start from: a 5-scan labelled log and its site, the shipped model, a
    ground-truth CSV with rows, a recording journal of 3 scans, and three bags (ROS 1; ROS 2 in SQLite
    with two LaserScan topics and a String topic; ROS 2 in MCAP)."""
    from gtsjax.io import save_log, save_site
    from gtsjax.io.record import Recorder, journal_path
    from gtsjax.sim import simulate

    log, site = simulate("spl-eval", seed=1, n_scans=5)
    save_log(log, d / "log.npz")
    save_site(site, d / "site.json")
    shutil.copyfile(DEMO_MODEL, d / "model.npz")
    rows = [f"{100 + 0.1 * k:.1f},{1 + k % 2},robot,{1 + 0.01 * k},{2.0},{0.1},1e-4,1e-4,1e-3" for k in range(6)]
    (d / "gtd.csv").write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n" + "\n".join(rows) + "\n")
    rec = Recorder(d / "rec.npz", n_beams=8, angle_min=-1.0, angle_increment=0.25)
    for k in range(3):
        rec.append(np.full(8, 1.0 + k, np.float32), 10.0 + 0.1 * k)
    rec.close(keep_journal=True)
    (d / "rec.npz").unlink()
    assert journal_path(d / "rec.npz").exists()
    write_bag(d / "one.bag", "ros1", {"/scan": scans(4, 8)})
    write_bag(d / "two", "sqlite3", {"/front": scans(4, 8), "/rear": scans(3, 6, intensities=True),
                                      "/chatter": 2})
    write_bag(d / "mcap", "mcap", {"/scan": scans(4, 8)})
    (d / "a_folder").mkdir()


def scans(k: int, n: int, *, intensities: bool = False, amin: float = -1.0, inc: float = 0.25,
          rmin: float = 0.05, rmax: float = 10.0, seed: int = 0) -> list[dict]:
    """``k`` LaserScan messages of ``n`` beams as dicts (stamp, rec: seconds; geometry; ranges;
    intensities), 10 Hz."""
    rng = np.random.default_rng(seed)
    return [dict(stamp=100.0 + 0.1 * i, rec=500.0 + 0.1 * i, amin=amin, inc=inc, rmin=rmin, rmax=rmax,
                 ranges=rng.uniform(0.1, 5.0, n).astype(np.float32),
                 intensities=rng.uniform(0, 100, n).astype(np.float32) if intensities else np.zeros(0, np.float32))
            for i in range(k)]


def write_bag(path: Path, kind: str, topics: dict) -> Path:
    """A bag written with rosbags' writers: ``kind`` ``ros1`` (a ``.bag`` file), ``sqlite3`` or ``mcap``
    (a ROS 2 bag's folder). ``topics`` maps a topic to a list of :func:`scans` messages (an empty list:
    a LaserScan topic without messages) or to a number of ``std_msgs/String`` messages."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    scan_t, string_t = ts.types["sensor_msgs/msg/LaserScan"], ts.types["std_msgs/msg/String"]
    header_t, time_t = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr

    def header(stamp):
        sec = int(stamp)
        t = time_t(sec=sec, nanosec=round((stamp - sec) * 1e9))
        return header_t(seq=0, stamp=t, frame_id="laser") if ros1 else header_t(stamp=t, frame_id="laser")

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    with writer as w:
        for topic, msgs in topics.items():
            if isinstance(msgs, int):
                conn = w.add_connection(topic, string_t.__msgtype__, typestore=ts)
                for i in range(msgs):
                    w.write(conn, (600 + i) * 10**9, ser(string_t(data=f"hello {i}"), string_t.__msgtype__))
                continue
            conn = w.add_connection(topic, scan_t.__msgtype__, typestore=ts)
            for m in msgs:
                n = len(m["ranges"])
                msg = scan_t(header=header(m["stamp"]), angle_min=m["amin"], angle_max=m["amin"] + m["inc"] * (n - 1),
                             angle_increment=m["inc"], time_increment=0.0, scan_time=0.1, range_min=m["rmin"],
                             range_max=m["rmax"], ranges=m["ranges"], intensities=m["intensities"])
                w.write(conn, round(m["rec"] * 1e9), ser(msg, scan_t.__msgtype__))
    return path


# ------------------------------------------------------------------------------------------ makers

LOG_KEYS = ("ranges", "stamps", "angle_min", "angle_increment")


def log_dict(d: Path) -> dict:
    with np.load(d / "log.npz") as z:
        return {k: z[k] for k in z.files}


def edited_log(edit: Callable[[dict], None]) -> Callable[[Path, Path], None]:
    """A maker: the good log's arrays, edited, saved with ``np.savez`` (as another program writes one)."""
    def make(d, f):
        z = log_dict(d)
        edit(z)
        np.savez(f, **z)
    return make


def setting(key: str, value) -> Callable[[dict], None]:
    def edit(z):
        z[key] = value
    return edit


def dropping(*keys: str) -> Callable[[dict], None]:
    def edit(z):
        for k in keys:
            z.pop(k)
    return edit


def changing(key: str, fn) -> Callable[[dict], None]:
    def edit(z):
        z[key] = fn(z[key])
    return edit


def cut(source: str, fraction: float | None = None, keep: int | None = None) -> Callable[[Path, Path], None]:
    """A maker: ``source`` (in the good inputs) cut short, at ``fraction`` of its size or after ``keep`` bytes."""
    def make(d, f):
        data = (d / source).read_bytes()
        f.write_bytes(data[: keep if keep is not None else int(len(data) * fraction)])
    return make


def flipped(source: str, n_bits: int, name: str, where: Callable[[bytes], tuple[int, int]] | None = None):
    """A maker: ``source`` with ``n_bits`` bits flipped at random (seeded by the case's ``name``),
    anywhere, or inside the byte range ``where(data)`` returns."""
    def make(d, f):
        data = bytearray((d / source).read_bytes())
        lo, hi = (0, len(data)) if where is None else where(bytes(data))
        rng = rng_for(name)
        for pos in rng.integers(lo, hi, n_bits):
            data[pos] ^= 1 << int(rng.integers(8))
        f.write_bytes(bytes(data))
    return make


def member_data(key: str) -> Callable[[bytes], tuple[int, int]]:
    """The bytes of a zip member's data (after its local header), for :func:`flipped`."""
    def where(data):
        info = zipfile.ZipFile(io.BytesIO(data)).getinfo(key)
        name_len, extra_len = struct.unpack_from("<HH", data, info.header_offset + 26)
        start = info.header_offset + 30 + name_len + extra_len
        return start, start + info.compress_size
    return where


def central_directory(data: bytes) -> tuple[int, int]:
    """The bytes of a zip's central directory, for :func:`flipped`."""
    start = data.find(b"PK\x01\x02")
    return start, data.rfind(b"PK\x05\x06")


def raw(content: bytes | str) -> Callable[[Path, Path], None]:
    def make(d, f):
        f.write_bytes(content.encode() if isinstance(content, str) else content)
    return make


def zip_bomb(d: Path, f: Path) -> None:
    """A small zip bomb: the log's ranges as 500 × 2000 zeros (4 MB), deflated to a few kB."""
    z = log_dict(d)
    t = 500
    arrays = {"ranges": np.zeros((t, 2000), np.float32), "stamps": np.arange(t) * 0.1,
              "angle_min": z["angle_min"], "angle_increment": z["angle_increment"]}
    np.savez_compressed(f, **arrays)


def many_members(d: Path, f: Path) -> None:
    """The good log and 2000 tiny extra keys (a zip of many members)."""
    z = log_dict(d)
    z.update({f"extra{i:04d}": np.zeros(1) for i in range(2000)})
    np.savez(f, **z)


def long_npy_header(d: Path, f: Path) -> None:
    """The good log whose ``stamps`` member has an array header of 200 kB (NumPy refuses headers over
    10 kB as unsafe to parse)."""
    z = log_dict(d)
    buf = io.BytesIO()
    h = repr({"descr": "<f8", "fortran_order": False, "shape": z["stamps"].shape, "pad": "x" * 200_000})
    h = h.encode("latin1") + b"\n"
    buf.write(b"\x93NUMPY\x02\x00" + struct.pack("<I", len(h)) + h + z["stamps"].tobytes())
    with zipfile.ZipFile(f, "w") as out:
        for k, v in z.items():
            if k == "stamps":
                out.writestr("stamps.npy", buf.getvalue())
            else:
                b = io.BytesIO()
                np.save(b, v)
                out.writestr(f"{k}.npy", b.getvalue())


def pickled(d: Path, f: Path) -> None:
    z = log_dict(d)
    z["sensor_model"] = np.array([{"evil": 1}], dtype=object)
    np.savez(f, **z)


def socket_file(d: Path, f: Path) -> None:
    """A Unix socket where a file is expected: it exists, is neither a file nor a folder, and cannot
    be opened (ENXIO), as a file without read permission cannot be (and that, root can read)."""
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(f))
    s.close()


def unreadable(source: str) -> Callable[[Path, Path], None]:
    def make(d, f):
        shutil.copyfile(d / source, f)
        f.chmod(0)
    return make


def site_doc(d: Path) -> dict:
    return json.loads((d / "site.json").read_text())


def edited_site(edit: Callable[[dict], object], *, replace: bool = False) -> Callable[[Path, Path], None]:
    """A maker: the good site, edited in place by ``edit`` (with ``replace``, what it returns is the
    document instead), written as JSON (NaN and Infinity as Python's json writes them)."""
    def make(d, f):
        doc = site_doc(d)
        new = edit(doc)
        f.write_text(json.dumps(new if replace else doc))
    return make


def site_text(transform: Callable[[str], str | bytes]) -> Callable[[Path, Path], None]:
    def make(d, f):
        out = transform((d / "site.json").read_text())
        f.write_bytes(out.encode() if isinstance(out, str) else out)
    return make


def model_dict() -> dict:
    with np.load(DEMO_MODEL) as z:
        return {k: z[k] for k in z.files}


def edited_model(edit: Callable[[dict], None]) -> Callable[[Path, Path], None]:
    def make(d, f):
        z = model_dict()
        edit(z)
        np.savez(f, **z)
    return make


def model_header(edit: Callable[[dict], object], *, replace: bool = False) -> Callable[[dict], None]:
    """An edit of a model's JSON header, in place (with ``replace``, what ``edit`` returns is written
    instead: any JSON value, or text)."""
    def fn(z):
        header = json.loads(str(z["gtsjax_model"]))
        new = edit(header)
        new = new if replace else header
        z["gtsjax_model"] = np.asarray(new if isinstance(new, str) else json.dumps(new))
    return fn


def schema_field(*where: str, value) -> Callable[[dict], None]:
    def edit(header):
        node = header["schema"]
        for name in where:
            node = node["fields"][name]
        node["value"] = value
    return model_header(edit)


def leaf(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[dict], None]:
    """An edit of the model's first float leaf of more than three numbers."""
    def edit(z):
        key = next(k for k in sorted(z) if k != "gtsjax_model" and z[k].dtype.kind == "f" and z[k].size > 3)
        z[key] = fn(z[key].copy())
    return edit


def with_flat(i: int, value):
    def fn(a):
        a.flat[i] = value
        return a
    return fn


def deep_schema(depth: int) -> Callable[[dict], str]:
    """The header's text with the classifier's GP tuple ``depth`` tuples deep (as text: Python's json
    neither writes nor reads a document 20 000 deep)."""
    def edit(header):
        header["schema"]["fields"]["classifier"]["fields"]["gps"] = "DEEP"
        return json.dumps(header).replace('"DEEP"', '{"tuple": [' * depth + "]}" * depth)
    return edit


def journal(header: dict | bytes | None = None, records: list[bytes] | None = None, magic: bytes = b"GTSJRNL1",
            length: int | None = None) -> Callable[[Path, Path], None]:
    """A maker: a recording journal (see gtsjax.io.record's layout) from its parts, written here byte
    by byte; ``header`` a dict (as JSON) or raw bytes; ``length`` a header length that lies."""
    def make(d, f):
        head = header if isinstance(header, bytes) else json.dumps(
            header if header is not None else JOURNAL_HEADER).encode()
        f.write_bytes(magic + struct.pack("<I", len(head) if length is None else length) + head
                      + b"".join(records or []))
    return make


JOURNAL_HEADER = {"n_beams": 8, "angle_min": -1.0, "angle_increment": 0.25, "range_min": 0.02, "range_max": 30.0,
                  "sensor_model": None, "intensities": False}


def record(stamp: float, ranges, *, crc_ok: bool = True) -> bytes:
    """One journal record: float64 stamp, float32 ranges, uint32 CRC-32 of the bytes before it."""
    body = struct.pack("<d", stamp) + np.asarray(ranges, "<f4").tobytes()
    return body + struct.pack("<I", zlib.crc32(body) ^ (0 if crc_ok else 1))


def journal_from_good(transform: Callable[[bytes], bytes]) -> Callable[[Path, Path], None]:
    def make(d, f):
        f.write_bytes(transform((d / "rec.npz.journal").read_bytes()))
    return make


GTD_HEAD = "stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n"


def bag_folder(kind: str, topics: dict, then: Callable[[Path], None] | None = None):
    """A maker: a bag written at ``f`` (a ROS 2 bag's folder, or a ``.bag``), then damaged by ``then``."""
    def make(d, f):
        write_bag(f, kind, topics)
        if then is not None:
            then(f)
    return make


def cut_storage(fraction: float) -> Callable[[Path], None]:
    """Cut a ROS 2 bag's storage file (its ``.mcap`` or ``.db3``) short."""
    def then(folder):
        store = next(p for p in folder.iterdir() if p.suffix in (".mcap", ".db3"))
        data = store.read_bytes()
        store.write_bytes(data[: int(len(data) * fraction)])
    return then


def remove_storage(folder: Path) -> None:
    for p in folder.iterdir():
        if p.suffix in (".mcap", ".db3"):
            p.unlink()


def copy_of(source: str) -> Callable[[Path, Path], None]:
    def make(d, f):
        if (d / source).is_dir():
            shutil.copytree(d / source, f)
        else:
            shutil.copyfile(d / source, f)
    return make


def empty_folder(d: Path, f: Path) -> None:
    f.mkdir()


def read_only_folder(d: Path, f: Path) -> None:
    f.mkdir()
    f.chmod(0o555)


# ------------------------------------------------------------------------------------------ the cases

R = ("--site", "{d}/site.json", "--model", "{d}/model.npz")
# A command for a bad scan log in {f}, by the option it takes it as.
LOG_COMMANDS = {
    "info": ("info", "{f}"),
    "convert": ("convert", "{f}", "--out", "{o}/x.npz"),
    "replay": ("replay", "{f}", *R, "--out", "{o}/gtd.csv"),
    "train": ("train", "{f}", "--site", "{d}/site.json", "--out", "{o}/m.npz"),
    "train --background": ("train", "{d}/log.npz", "--site", "{d}/site.json", "--background", "{f}", "--out",
                           "{o}/m.npz"),
    "evaluate": ("evaluate", "--model", "{d}/model.npz", "{f}", "--site", "{d}/site.json", "--out-dir", "{o}/ev"),
    "plot --truth": ("plot", "{d}/gtd.csv", "--site", "{d}/site.json", "--truth", "{f}", "--out", "{o}/p.png"),
}
SITE_COMMANDS = {
    "info": ("info", "{f}"),
    "replay": ("replay", "{d}/log.npz", "--site", "{f}", "--model", "{d}/model.npz", "--out", "{o}/gtd.csv"),
    "train": ("train", "{d}/log.npz", "--site", "{f}", "--out", "{o}/m.npz"),
    "plot": ("plot", "{d}/gtd.csv", "--site", "{f}", "--out", "{o}/p.png"),
    "plot --coverage": ("plot", "--coverage", "{f}", "--out", "{o}/c.png"),
    "run": ("run", "--port", "/dev/null", "--site", "{f}", "--model", "{d}/model.npz", "--out", "{o}/gtd.csv"),
    "evaluate": ("evaluate", "--model", "{d}/model.npz", "{d}/log.npz", "--site", "{f}", "--out-dir", "{o}/ev"),
}
MODEL_COMMANDS = {
    "info": ("info", "{f}"),
    "replay": ("replay", "{d}/log.npz", "--site", "{d}/site.json", "--model", "{f}", "--out", "{o}/gtd.csv"),
    "run": ("run", "--port", "/dev/null", "--site", "{d}/site.json", "--model", "{f}", "--out", "{o}/gtd.csv"),
    "evaluate": ("evaluate", "--model", "{f}", "{d}/log.npz", "--site", "{d}/site.json", "--out-dir", "{o}/ev"),
}
BAG_COMMANDS = {
    "info": ("info", "{f}"),
    "convert": ("convert", "{f}", "--out", "{o}/x.npz"),
    "replay": ("replay", "{f}", *R, "--out", "{o}/gtd.csv"),
}
CSV_COMMANDS = {
    "info": ("info", "{f}"),
    "export-tum": ("export-tum", "{f}", "--out-dir", "{o}/tum"),
    "plot": ("plot", "{f}", "--site", "{d}/site.json", "--out", "{o}/p.png"),
}


def _spread(label: str, table: dict, commands: dict, file: str, out: dict, *,
            every: tuple[str, ...] = ("info",)) -> None:
    """Each bad file of ``table`` (name -> (maker, code, why)) under the commands of ``every`` and one
    more of ``commands``, in turn (so that each command meets many kinds of damage and the number of
    cases stays what a minute runs). A file acceptable to ``info`` (code 0) goes to ``info``,
    ``convert`` and ``export-tum`` only: any other command would go on to compile and run."""
    others = [c for c in commands if c not in every]
    for i, (name, (make, code, why)) in enumerate(sorted(table.items())):
        if code == 0:
            chosen = [c for c in ("info", "convert", "export-tum") if c in commands]
        else:
            chosen = list(every) + ([others[i % len(others)]] if others else [])
        for c in chosen:
            out[f"{label}: {name} [{c}]"] = Case(commands[c], make, file, code=code, why=why)


def _log_table() -> dict:
    ok = "no return for those beams (the format: 0, negative, non-finite = no return)"
    flips = {f"{n} bits flipped anywhere (seed {s})": (flipped("log.npz", n, f"log{n}-{s}"), 2, "")
             for n, s in ((16, 1), (64, 2), (256, 3))}
    return {
        **{f"cut at {100 * fr:g} %": (cut("log.npz", fr), 2, "") for fr in (0.0, 0.05, 0.5, 0.97)},
        "cut by its last byte": (lambda d, f: f.write_bytes((d / "log.npz").read_bytes()[:-1]), 2, ""),
        "a bit flipped in the ranges' data": (flipped("log.npz", 1, "ranges-bit", member_data("ranges.npy")), 2, ""),
        "a bit flipped in the stamps' data": (flipped("log.npz", 1, "stamps-bit", member_data("stamps.npy")), 2, ""),
        "bits flipped in the central directory": (flipped("log.npz", 8, "cd-bits", central_directory), 2, ""),
        **flips,
        "ranges int32": (edited_log(changing("ranges", lambda a: (1000 * a).astype(np.int32))), 2, ""),
        "ranges float64": (edited_log(changing("ranges", lambda a: a.astype(np.float64))), 0,
                           "float64 ranges hold the float32 values exactly; they are read as float32"),
        "ranges 1-D": (edited_log(changing("ranges", lambda a: a.ravel())), 2, ""),
        "ranges 3-D": (edited_log(changing("ranges", lambda a: a[..., None])), 2, ""),
        "ranges of no beams": (edited_log(changing("ranges", lambda a: a[:, :0])), 2, ""),
        "ranges of no scans": (edited_log(lambda z: z.update(ranges=z["ranges"][:0], stamps=z["stamps"][:0],
                                                             truth_poses=z["truth_poses"][:0])), 2, ""),
        "ranges strings": (edited_log(changing("ranges", lambda a: a.astype(str))), 2, ""),
        "ranges all NaN": (edited_log(changing("ranges", lambda a: np.full_like(a, np.nan))), 0, ok),
        "ranges negative": (edited_log(changing("ranges", lambda a: -a)), 0, ok),
        "ranges +inf": (edited_log(changing("ranges", lambda a: np.full_like(a, np.inf))), 0, ok),
        "stamps int64": (edited_log(changing("stamps", lambda a: a.astype(np.int64))), 2, ""),
        "stamps of another length": (edited_log(changing("stamps", lambda a: a[:-1])), 2, ""),
        "stamps 2-D": (edited_log(changing("stamps", lambda a: a[:, None])), 2, ""),
        "stamps NaN": (edited_log(changing("stamps", lambda a: np.where(np.arange(a.size) == 2, np.nan, a))), 2, ""),
        "stamps +inf": (edited_log(changing("stamps", lambda a: np.where(np.arange(a.size) == 4, np.inf, a))), 2, ""),
        "stamps unsorted": (edited_log(changing("stamps", lambda a: a[::-1].copy())), 2, ""),
        "stamps all equal": (edited_log(changing("stamps", lambda a: np.full_like(a, a[0]))), 0,
                             "the format asks for non-decreasing stamps: equal ones are allowed"),
        "stamps 1e300": (edited_log(changing("stamps", lambda a: a + 1e300)), 0,
                         "the format bounds no stamp, and float64 holds 1e300 (the scans then share one stamp, "
                         "which it allows)"),
        **{f"without '{k}'": (edited_log(dropping(k)), 2, "") for k in LOG_KEYS},
        "truth_poses without truth_classes": (edited_log(dropping("truth_classes")), 2, ""),
        "truth_poses of the wrong shape": (edited_log(changing("truth_poses", lambda a: a[:, :, :2])), 2, ""),
        "truth_poses +inf": (edited_log(changing("truth_poses", lambda a: np.full_like(a, np.inf))), 2, ""),
        "truth_poses partly NaN": (edited_log(changing("truth_poses", lambda a: np.where(
            np.arange(3) == 0, np.nan, a))), 2, ""),
        "truth_classes numbers": (edited_log(changing("truth_classes", lambda a: np.arange(a.size))), 2, ""),
        "angle_min NaN": (edited_log(setting("angle_min", np.float64(np.nan))), 2, ""),
        "angle_min a string": (edited_log(setting("angle_min", np.asarray("-2.0"))), 2, ""),
        "angle_min an array": (edited_log(setting("angle_min", np.zeros(3))), 2, ""),
        "angle_increment 0": (edited_log(setting("angle_increment", np.float64(0.0))), 2, ""),
        "angle_increment negative": (edited_log(changing("angle_increment", lambda a: -a)), 2, ""),
        "angle_increment +inf": (edited_log(setting("angle_increment", np.float64(np.inf))), 2, ""),
        "range window inverted": (edited_log(lambda z: z.update(range_min=np.float64(5.0), range_max=np.float64(1.0))),
                                  2, ""),
        "range_min negative": (edited_log(setting("range_min", np.float64(-1.0))), 2, ""),
        "intensities NaN": (edited_log(lambda z: z.update(intensities=np.full_like(z["ranges"], np.nan))), 2, ""),
        "intensities negative": (edited_log(lambda z: z.update(intensities=-np.ones_like(z["ranges"]))), 2, ""),
        "intensities of another shape": (edited_log(lambda z: z.update(intensities=np.ones((2, 3), np.float32))),
                                         2, ""),
        "sensor_model a number": (edited_log(setting("sensor_model", np.int64(4))), 2, ""),
        "a pickled object": (pickled, 2, ""),
        "an empty archive": (lambda d, f: np.savez(f), 2, ""),
        "a zip bomb (4 MB of zeros in a few kB)": (zip_bomb, 0, "500 scans of 2000 beams of no return is a "
                                                                "valid log; it is read whole, 4 MB"),
        "2000 extra keys": (many_members, 0, "keys the format does not know are kept, as the spec allows"),
        "an array header of 200 kB": (long_npy_header, 2, ""),
        "an empty file": (raw(b""), 2, ""),
        "a PNG image": (raw(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4), 2, ""),
        "binary garbage": (lambda d, f: f.write_bytes(rng_for("garbage").bytes(5000)), 2, ""),
    }


def _site_table() -> dict:
    lms = lambda doc: doc["landmarks"]  # noqa: E731
    return {
        "missing landmarks": (edited_site(lambda doc: doc.pop("landmarks")), 2, ""),
        "missing sensor_pose": (edited_site(lambda doc: doc.pop("sensor_pose")), 2, ""),
        "landmarks an object": (edited_site(lambda doc: doc.update(landmarks={"a": 1})), 2, ""),
        "a landmark without x": (edited_site(lambda doc: lms(doc)[1].pop("x")), 2, ""),
        "a landmark x a string": (edited_site(lambda doc: lms(doc)[0].update(x="1.5")), 2, ""),
        "a landmark x true": (edited_site(lambda doc: lms(doc)[0].update(x=True)), 2, ""),
        "a landmark x NaN": (edited_site(lambda doc: lms(doc)[0].update(x=math.nan)), 2, ""),
        "a landmark y Infinity": (edited_site(lambda doc: lms(doc)[2].update(y=math.inf)), 2, ""),
        "a landmark x 1e300": (edited_site(lambda doc: lms(doc)[0].update(x=1e300)), 2, ""),
        "a landmark x 1e400 (beyond a float)": (site_text(lambda t: t.replace('"x": ', '"x": 1e400, "_": ', 1)), 2, ""),
        "a landmark's class empty": (edited_site(lambda doc: lms(doc)[0].update({"class": ""})), 2, ""),
        "a landmark's class a number": (edited_site(lambda doc: lms(doc)[0].update({"class": 7})), 2, ""),
        "a landmark a list": (edited_site(lambda doc: lms(doc).__setitem__(0, [0, 1])), 2, ""),
        "two landmarks": (edited_site(lambda doc: doc.update(landmarks=lms(doc)[:2])), 2, ""),
        "collinear landmarks": (edited_site(lambda doc: doc.update(landmarks=[
            {"class": "post", "x": float(i), "y": 2.0 * i} for i in range(4)])), 2, ""),
        "all landmarks at one point": (edited_site(lambda doc: doc.update(landmarks=[
            {"class": "post", "x": 1.0, "y": 1.0}] * 4)), 2, ""),
        "sensor_pose of two numbers": (edited_site(lambda doc: doc.update(sensor_pose=[1.0, 2.0])), 2, ""),
        "sensor_pose NaN": (edited_site(lambda doc: doc.update(sensor_pose=[1.0, math.nan, 0.0])), 2, ""),
        "sensor_pose a string": (edited_site(lambda doc: doc.update(sensor_pose="1 2 0")), 2, ""),
        "bounds inverted": (edited_site(lambda doc: doc.update(bounds=[5.0, 5.0, 0.0, 0.0])), 2, ""),
        "bounds of three numbers": (edited_site(lambda doc: doc.update(bounds=[0.0, 0.0, 5.0])), 2, ""),
        "bounds 1e9": (edited_site(lambda doc: doc.update(bounds=[0.0, 0.0, 1e9, 1e9])), 2, ""),
        "sensors empty": (edited_site(lambda doc: doc.update(sensors=[])), 2, ""),
        "sensors with one name twice": (edited_site(lambda doc: doc.update(sensors=[
            {"name": "a", "sensor_pose": [0, 0, 0]}, {"name": "a", "sensor_pose": [1, 0, 0]}])), 2, ""),
        "a sensor of an unknown scanner": (edited_site(lambda doc: doc.update(sensors=[
            {"name": "a", "sensor_pose": [0, 0, 0], "model": "LMS-100"}])), 2, ""),
        "a sensor name with '='": (edited_site(lambda doc: doc.update(sensors=[
            {"name": "a=b", "sensor_pose": [0, 0, 0]}])), 2, ""),
        "the top level a list": (edited_site(lambda doc: [doc], replace=True), 2, ""),
        "the top level null": (raw("null"), 2, ""),
        "nested 5000 deep in a landmark": (site_text(lambda t: t.replace('"x": ', '"x": ' + "[" * 5000 + "]" * 5000
                                                                         + ', "_": ', 1)), 2, ""),
        "not UTF-8 (Latin-1)": (site_text(lambda t: t.replace('"post"', '"poteau \u00e9"').encode("latin-1")), 2, ""),
        "UTF-16": (site_text(lambda t: t.encode("utf-16")), 2, ""),
        "a UTF-8 byte-order mark": (site_text(lambda t: "\ufeff" + t), 0,
                                    "Windows editors start UTF-8 files with a byte-order mark; it is not content"),
        "empty": (raw(""), 2, ""),
        "blank": (raw("  \n\t\n"), 2, ""),
        "cut in half": (site_text(lambda t: t[: len(t) // 2]), 2, ""),
        "a trailing comma": (site_text(lambda t: t.rstrip().rstrip("}") + ",}"), 2, ""),
    }


def _model_table() -> dict:
    flips = {f"{n} bits flipped anywhere (seed {s})": (flipped("model.npz", n, f"model{n}-{s}"), 2, "")
             for n, s in ((8, 1), (64, 2))}
    return {
        **{f"cut at {100 * fr:g} %": (cut("model.npz", fr), 2, "") for fr in (0.001, 0.3, 0.99)},
        **flips,
        "a bit flipped in the header's data": (flipped("model.npz", 1, "header-bit", member_data("gtsjax_model.npy")),
                                               2, ""),
        "version 2": (edited_model(model_header(lambda h: h.update(version=2))), 2, ""),
        "version '3' (a string)": (edited_model(model_header(lambda h: h.update(version="3"))), 2, ""),
        "another format name": (edited_model(model_header(lambda h: h.update(format="other"))), 2, ""),
        "a header that is not JSON": (edited_model(model_header(lambda h: "{not json", replace=True)), 2, ""),
        "a header that is a JSON list": (edited_model(model_header(lambda h: [h], replace=True)), 2, ""),
        "a header without its schema": (edited_model(model_header(lambda h: h.pop("schema"))), 2, ""),
        "a header with n_beams 0": (edited_model(model_header(lambda h: h.update(n_beams=0))), 2, ""),
        "a header with n_beams 'many'": (edited_model(model_header(lambda h: h.update(n_beams="many"))), 2, ""),
        "a header's classes not the model's": (edited_model(model_header(lambda h: h.update(classes=["a", "b"]))),
                                               2, ""),
        "a schema 20 000 deep": (edited_model(model_header(deep_schema(20_000), replace=True)), 2, ""),
        "a schema 450 deep": (edited_model(model_header(deep_schema(450), replace=True)), 2, ""),
        "max_tracks 10^9": (edited_model(schema_field("max_tracks", value=10**9)), 2, ""),
        "max_tracks a string": (edited_model(schema_field("max_tracks", value="8")), 2, ""),
        "n_dist 0": (edited_model(schema_field("frontend", "n_dist", value=0)), 2, ""),
        "a leaf +inf": (edited_model(leaf(with_flat(0, np.inf))), 2, ""),
        "a leaf -inf": (edited_model(leaf(with_flat(1, -np.inf))), 2, ""),
        "a leaf float64": (edited_model(leaf(lambda a: a.astype(np.float64))), 2, ""),
        "a leaf of another shape": (edited_model(leaf(lambda a: a.ravel()[:-1])), 2, ""),
        "a leaf missing": (edited_model(lambda z: z.pop("leaf00003")), 2, ""),
        "a leaf pickled": (edited_model(lambda z: z.update(leaf00003=np.array([{"x": 1}], dtype=object))), 2, ""),
    }


def _journal_table() -> dict:
    good = [record(10.0 + 0.1 * k, np.full(8, 1.0 + k)) for k in range(3)]
    h = JOURNAL_HEADER
    return {
        "the header alone": (journal(), 2, ""),
        "the magic alone": (raw(b"GTSJRNL1"), 2, ""),
        "cut in its header": (journal_from_good(lambda b: b[:20]), 2, ""),
        "cut in its second record": (journal_from_good(lambda b: b[: -len(good[0]) - 10]), 0,
                                     "a recording cut by a crash: recover keeps the whole records and cuts the torn one"),
        "a wrong magic": (journal(magic=b"GTSJRNL9", records=good), 2, ""),
        "a header length beyond the file": (journal(records=good, length=2**31), 2, ""),
        "a header that is not JSON": (journal(b"{n_beams: 8", records=good), 2, ""),
        "a header that is a list": (journal(b"[8]", records=good), 2, ""),
        "n_beams 0": (journal({**h, "n_beams": 0}, good), 2, ""),
        "n_beams 10^7": (journal({**h, "n_beams": 10**7}, good), 2, ""),
        "n_beams 8.5": (journal({**h, "n_beams": 8.5}, good), 2, ""),
        "angle_increment negative": (journal({**h, "angle_increment": -0.25}, good), 2, ""),
        "intensities 'yes'": (journal({**h, "intensities": "yes"}, good), 2, ""),
        "range_min a string": (journal({**h, "range_min": "0.02"}, good), 2, ""),
        "range_max NaN": (journal({**h, "range_max": math.nan}, good), 2, ""),
        "a range window inverted": (journal({**h, "range_min": 5.0, "range_max": 1.0}, good), 2, ""),
        "sensor_model a list": (journal({**h, "sensor_model": ["URG-04LX"]}, good), 2, ""),
        "every record failing its CRC": (journal(records=[record(10.0, np.ones(8), crc_ok=False)] * 3), 2, ""),
        "a stamp NaN": (journal(records=[*good[:1], record(math.nan, np.ones(8)), *good[1:]]), 2, ""),
        "an empty file": (raw(b""), 2, ""),
    }


def _csv_table() -> dict:
    row = "100.0,1,robot,1.0,2.0,0.1,1e-4,1e-4,1e-3\n"
    return {
        "empty": (raw(""), 2, ""),
        "the header alone": (raw(GTD_HEAD), 0, "a run that never confirmed a track writes the header alone"),
        "another header": (raw("t,id,cls,x,y,th,vx,vy,vth\n" + row), 2, ""),
        "the header in another order": (raw("track_id,stamp,class,x,y,theta,var_x,var_y,var_theta\n" + row), 2, ""),
        "a row of 8 fields": (raw(GTD_HEAD + row.rsplit(",", 1)[0] + "\n"), 2, ""),
        "a non-numeric x": (raw(GTD_HEAD + row.replace("1.0,2.0", "one,2.0")), 2, ""),
        "a track id 1.5": (raw(GTD_HEAD + row.replace(",1,robot", ",1.5,robot")), 2, ""),
        "a NaN x": (raw(GTD_HEAD + row.replace("1.0,2.0", "nan,2.0")), 2, ""),
        "an x of 1e400": (raw(GTD_HEAD + row.replace("1.0,2.0", "1e400,2.0")), 2, ""),
        "binary garbage": (lambda d, f: f.write_bytes(rng_for("csv garbage").bytes(3000)), 2, ""),
        "UTF-16": (raw((GTD_HEAD + row).encode("utf-16")), 2, ""),
        "an unterminated quote": (raw(GTD_HEAD + row.replace("robot", '"robot')), 2, ""),
    }


def _bag_cases(out: dict) -> None:
    b = BAG_COMMANDS
    laser = {"/scan": scans(4, 8)}
    bags = {
        "an empty folder": ("bagdir", empty_folder, ["info", "convert"], ""),
        "a metadata.yaml without its data": ("bagdir", bag_folder("sqlite3", laser, remove_storage),
                                             ["info", "convert", "replay"], ""),
        "a metadata.yaml of garbage": ("bagdir", lambda d, f: (f.mkdir(), (f / "metadata.yaml").write_text(
            "rosbag2_bagfile_information: [unclosed\n")), ["info", "convert"], ""),
        "an MCAP cut in half": ("bagdir", bag_folder("mcap", laser, cut_storage(0.5)), ["info", "convert"], ""),
        "an MCAP cut at 90 %": ("bagdir", bag_folder("mcap", laser, cut_storage(0.9)), ["convert", "replay"], ""),
        "an SQLite file cut in half": ("bagdir", bag_folder("sqlite3", laser, cut_storage(0.5)), ["info", "convert"],
                                       ""),
        "no LaserScan topic (ROS 2)": ("bagdir", bag_folder("sqlite3", {"/chatter": 3}), ["info", "convert"], ""),
        "no LaserScan topic (ROS 1)": ("x.bag", bag_folder("ros1", {"/chatter": 3}), ["info", "replay"], ""),
        "a LaserScan topic without messages": ("x.bag", bag_folder("ros1", {"/scan": []}), ["info", "convert"], ""),
        "a LaserScan of no beams": ("bagdir", bag_folder("mcap", {"/scan": scans(3, 0)}), ["info", "convert"], ""),
        "a LaserScan of angle_increment 0": ("x.bag", bag_folder("ros1", {"/scan": scans(3, 8, inc=0.0)}),
                                             ["convert"], ""),
        "a ROS 1 bag of garbage": ("x.bag", lambda d, f: f.write_bytes(b"#ROSBAG V2.0\n" + rng_for("bag").bytes(4000)),
                                   ["info", "convert", "replay"], ""),
        "an empty .bag": ("x.bag", raw(b""), ["info", "convert"], ""),
        "a ROS 1 bag cut in half": ("x.bag", lambda d, f: f.write_bytes((d / "one.bag").read_bytes()[:2000]),
                                    ["info", "convert"], ""),
        "ROS 1 magic under another name, then garbage": ("scan.raw", lambda d, f: f.write_bytes(
            b"#ROSBAG V2.0\n" + bytes(300)), ["info", "convert"], ""),
        "an MCAP without its folder's metadata.yaml": ("x.mcap", lambda d, f: shutil.copyfile(
            next((d / "mcap").glob("*.mcap")), f), ["info", "convert"], ""),
    }
    for name, (file, make, commands, why) in bags.items():
        for c in commands:
            out[f"bag: {name} [{c}]"] = Case(b[c], make, file, why=why)
    # Several LaserScan topics: info lists them (that is what it is for); a command that reads scans
    # needs --topic, and a --topic the bag does not have is one line.
    out["bag: two LaserScan topics [info]"] = Case(("info", "{d}/two"), None, names="{d}/two", code=0,
                                                   why="info lists a bag's topics and says how to pick one")
    out["bag: two LaserScan topics [convert]"] = Case(("convert", "{d}/two", "--out", "{o}/x.npz"), None,
                                                      names="{d}/two")
    out["bag: two LaserScan topics, --topic of a String [convert]"] = Case(
        ("convert", "{d}/two", "--out", "{o}/x.npz", "--topic", "/chatter"), None, names="{d}/two")
    out["bag: --topic the bag lacks [info]"] = Case(("info", "{d}/two", "--topic", "/nope"), None, names="{d}/two")
    out["bag: --topic on a .npz log [convert]"] = Case(("convert", "{d}/log.npz", "--out", "{o}/x.npz", "--topic",
                                                        "/scan"), None, names="{d}/log.npz")
    out["bag: --topic picks the one with intensities [convert]"] = Case(
        ("convert", "{d}/two/metadata.yaml", "--out", "{o}/x.npz", "--topic", "rear"), None, names="{d}/two", code=0,
        why="a topic named without its slash, the bag by its metadata.yaml: a 3-scan log of 6 beams")


def _path_cases(out: dict) -> None:
    """Paths: a folder where a file is expected, a file that is not there, one that cannot be opened (a
    socket; and without read permission, for a user other than root), outputs where they cannot go."""
    inputs = {  # command -> (args with {f} the input, what {f} is read as)
        "info": ("info", "{f}"),
        "convert": ("convert", "{f}", "--out", "{o}/x.npz"),
        "replay (log)": LOG_COMMANDS["replay"],
        "replay (site)": SITE_COMMANDS["replay"],
        "replay (model)": MODEL_COMMANDS["replay"],
        "train (log)": LOG_COMMANDS["train"],
        "train (site)": SITE_COMMANDS["train"],
        "evaluate (model)": MODEL_COMMANDS["evaluate"],
        "evaluate (log)": LOG_COMMANDS["evaluate"],
        "plot (csv)": CSV_COMMANDS["plot"],
        "plot (site)": SITE_COMMANDS["plot"],
        "plot --truth": LOG_COMMANDS["plot --truth"],
        "run (site)": SITE_COMMANDS["run"],
        "run (model)": MODEL_COMMANDS["run"],
        "recover": ("recover", "{f}", "{o}/x.npz"),
        "export-tum": CSV_COMMANDS["export-tum"],
    }
    good = {"info": "log.npz", "convert": "log.npz", "replay (log)": "log.npz", "replay (site)": "site.json",
            "replay (model)": "model.npz", "train (log)": "log.npz", "train (site)": "site.json",
            "evaluate (model)": "model.npz", "evaluate (log)": "log.npz", "plot (csv)": "gtd.csv",
            "plot (site)": "site.json", "plot --truth": "log.npz", "run (site)": "site.json",
            "run (model)": "model.npz", "recover": "rec.npz.journal", "export-tum": "gtd.csv"}
    for c, args in inputs.items():
        name = good[c]
        out[f"path: a folder for the {c} input"] = Case(args, empty_folder, name)
        out[f"path: a missing {c} input"] = Case(args, None, name)
        out[f"path: a socket for the {c} input"] = Case(args, socket_file, name)
        out[f"path: an unreadable {c} input"] = Case(args, unreadable(name), name, root=False)
    for name in ("gtd.csv", "site.json", "rec.npz.journal", "one.bag"):
        out[f"path: a socket named {name} [info]"] = Case(("info", "{f}"), socket_file, name)
        out[f"path: a folder named {name} [info]"] = Case(("info", "{f}"), empty_folder, name)
    # A bad input and an output in a folder not yet made: the folder must not be left behind.
    for c, args in (("convert", ("convert", "{f}", "--out", "{o}/new/x.npz")),
                    ("train", ("train", "{f}", "--site", "{d}/site.json", "--out", "{o}/new/m.npz")),
                    ("recover", ("recover", "{f}", "{o}/new/x.npz"))):
        bad = raw(b"GTSJRNL1") if c == "recover" else raw(b"not a log")
        out[f"path: a bad input, {c} into a folder not yet made"] = Case(
            args, bad, "raw.npz.journal" if c == "recover" else "bad.npz")
    # Outputs: a file where a folder must be, a folder where a file must be, a read-only folder; a
    # missing folder is made (the command succeeds).
    outs = {
        "convert --out under a file": (("convert", "{d}/log.npz", "--out", "{d}/site.json/x.npz"), "{d}/site.json"),
        "convert --out a folder": (("convert", "{d}/log.npz", "--out", "{d}/a_folder"), "{d}/a_folder"),
        "replay --out under a file": (("replay", "{d}/log.npz", *R, "--out", "{d}/gtd.csv/o.csv"), "{d}/gtd.csv"),
        "replay --sensor-out a folder": (("replay", "{d}/log.npz", *R, "--out", "{o}/o.csv", "--sensor-out",
                                          "{d}/a_folder"), "{d}/a_folder"),
        "replay --out-bag a file": (("replay", "{d}/log.npz", *R, "--out", "{o}/o.csv", "--out-bag", "{d}/gtd.csv"),
                                    "{d}/gtd.csv"),
        "replay, two logs, --out a file": (("replay", "{d}/log.npz", "{d}/mcap", *R, "--out", "{d}/gtd.csv"),
                                           "{d}/gtd.csv"),
        "train --out a folder": (("train", "{d}/log.npz", "--site", "{d}/site.json", "--out", "{d}/a_folder"),
                                 "{d}/a_folder"),
        "train --report under a file": (("train", "{d}/log.npz", "--site", "{d}/site.json", "--out", "{o}/m.npz",
                                         "--report", "{d}/log.npz/r.json"), "{d}/log.npz"),
        "evaluate --out-dir a file": (("evaluate", "--model", "{d}/model.npz", "{d}/log.npz", "--site",
                                       "{d}/site.json", "--out-dir", "{d}/gtd.csv"), "{d}/gtd.csv"),
        "plot --out a folder": (("plot", "{d}/gtd.csv", "--site", "{d}/site.json", "--out", "{d}/a_folder"),
                                "{d}/a_folder"),
        "plot --out under a file": (("plot", "{d}/gtd.csv", "--site", "{d}/site.json", "--out", "{d}/log.npz/p.png"),
                                    "{d}/log.npz"),
        "simulate --out a folder": (("simulate", "spl-eval", "--scans", "5", "--out", "{d}/a_folder", "--site",
                                     "{o}/s.json"), "{d}/a_folder"),
        "simulate --site under a file": (("simulate", "spl-eval", "--scans", "5", "--out", "{o}/x.npz", "--site",
                                          "{d}/gtd.csv/s.json"), "{d}/gtd.csv"),
        "run --out a folder": (("run", "--port", "/dev/null", *R, "--out", "{d}/a_folder"), "{d}/a_folder"),
        "run --record under a file": (("run", "--port", "/dev/null", *R, "--out", "{o}/o.csv", "--record",
                                       "{d}/site.json/r.npz"), "{d}/site.json"),
        "run --summary a folder": (("run", "--port", "/dev/null", *R, "--out", "{o}/o.csv", "--summary",
                                    "{d}/a_folder"), "{d}/a_folder"),
        "recover OUT a folder": (("recover", "{d}/rec.npz.journal", "{d}/a_folder"), "{d}/a_folder"),
        "recover OUT under a file": (("recover", "{d}/rec.npz.journal", "{d}/log.npz/x.npz"), "{d}/log.npz"),
        "export-tum --out-dir a file": (("export-tum", "{d}/gtd.csv", "--out-dir", "{d}/log.npz"), "{d}/log.npz"),
    }
    for name, (args, names) in outs.items():
        out[f"path: {name}"] = Case(args, None, names=names)
    ro = {
        "convert": ("convert", "{d}/log.npz", "--out", "{f}/x.npz"),
        "simulate": ("simulate", "spl-eval", "--scans", "5", "--out", "{f}/x.npz", "--site", "{o}/s.json"),
        "recover": ("recover", "{d}/rec.npz.journal", "{f}/x.npz"),
        "export-tum": ("export-tum", "{d}/gtd.csv", "--out-dir", "{f}/tum"),
        "run": ("run", "--port", "/dev/null", *R, "--out", "{f}/o.csv"),
    }
    for c, args in ro.items():
        out[f"path: {c} into a read-only folder"] = Case(args, read_only_folder, "ro", root=False)
    fine = {
        "convert": ("convert", "{d}/log.npz", "--out", "{o}/new/deeper/x.npz"),
        "simulate": ("simulate", "spl-eval", "--scans", "5", "--out", "{o}/new/x.npz", "--site", "{o}/other/s.json"),
        "recover": ("recover", "{d}/rec.npz.journal", "{o}/new/x.npz"),
        "export-tum": ("export-tum", "{d}/gtd.csv", "--out-dir", "{o}/new/tum"),
    }
    for c, args in fine.items():
        out[f"path: {c} into a folder not yet made"] = Case(args, None, names="", code=0,
                                                             why="a missing output folder is made, as for every "
                                                                 "command that writes")


def cases() -> dict[str, Case]:
    """Every case, by name."""
    out: dict[str, Case] = {}
    _spread("log", _log_table(), LOG_COMMANDS, "bad.npz", out)
    _spread("site", _site_table(), SITE_COMMANDS, "bad.json", out)
    _spread("model", _model_table(), MODEL_COMMANDS, "bad.npz", out)
    # info takes a model for a model and a log for a log: the mix-ups are the other commands'.
    for c in ("convert", "replay", "evaluate"):
        out[f"log: a model file [{c}]"] = Case(LOG_COMMANDS[c], copy_of("model.npz"))
    for c in ("replay", "run", "evaluate"):
        out[f"model: a scan log [{c}]"] = Case(MODEL_COMMANDS[c], copy_of("log.npz"))
    for name, (make, code, why) in sorted(_journal_table().items()):
        out[f"journal: {name} [recover]"] = Case(("recover", "{f}", "{o}/x.npz"), make, "raw.npz.journal",
                                                 code=code, why=why)
    _spread("csv", _csv_table(), CSV_COMMANDS, "bad.csv", out, every=("info", "export-tum"))
    _bag_cases(out)
    _path_cases(out)
    return out
