"""Helpers the commands share: reading any scan input, one-line descriptions, the track summary, the
output checks. Command modules import these, never one another; their models come from
:mod:`gtsjax.drivers.setup`."""

import os
import tempfile
import threading
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from ..errors import InputError
from ..io.importers import detect_format, import_log
from ._app import quiet

#: Threads of :func:`interruptible` left running when the command was stopped: the process ends
#: without waiting for them (:func:`gtsjax.cli.main`).
ABANDONED: list[threading.Thread] = []


def interruptible(work):
    """``work()`` run in a thread of its own while this one waits for it, so that Ctrl-C (and SIGTERM,
    SIGHUP: :func:`gtsjax.cli.main`) stops the command within a fraction of a second: Python delivers a
    signal to the main thread only between its own steps, and a GP fit's optimiser or the tracking
    check runs for minutes inside one compiled call. A thread so stopped is left to the end of the
    process (:data:`ABANDONED`), which ``main`` then ends at once: nothing the work makes is written
    (training writes its model only after ``work`` returns)."""
    box: dict = {}

    def run():
        try:
            box["value"] = work()
        except BaseException as err:  # noqa: BLE001  (handed to the waiting thread, raised there)
            box["error"] = err

    worker = threading.Thread(target=run, name="gtsjax-work", daemon=True)
    worker.start()
    try:
        while worker.is_alive():
            worker.join(0.1)
    except BaseException:
        ABANDONED.append(worker)
        raise
    if "error" in box:
        raise box["error"]
    return box["value"]

INPUT_HELP = ("Scan log: .npz, a ROS 1 bag (.bag), a ROS 2 bag (its directory), a CARMEN log (.log, .log.gz) "
              "or a BreezySLAM URG-04LX text log (.dat).")
TOPIC_HELP = "LaserScan topic of a ROS bag (default: its only one)."


def load_input(path: Path, topic: str | None, console: Console):
    """Any importable log as a :class:`~gtsjax.io.logs.ScanLog`; a bar while a ROS bag is read
    (bags are the one input that can be large and slow to decode), on a terminal only, so that a
    redirected stderr holds nothing but the messages (one line for a bad input)."""
    if detect_format(path) not in ("ros1", "ros2"):
        return import_log(path, topic=topic)
    with Progress(TextColumn(f"reading {path.name}"), BarColumn(), MofNCompleteColumn(), TextColumn("messages"),
                  console=console, transient=True, disable=quiet() or not console.is_terminal) as bar:
        task = bar.add_task("read", total=None)
        return import_log(path, topic=topic, progress=lambda n, total: bar.update(task, completed=n, total=total))


def file_stem(text: str, default: str) -> str:
    """``text`` reduced to characters safe in a file name (``default`` where none are left)."""
    import re

    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-.") or default


def describe(log) -> str:
    """One line: scans × beams, duration and rate, field of view, share of returns, intensities."""
    dur = float(log.stamps[-1] - log.stamps[0])
    rate = (log.n_scans - 1) / dur if dur > 0 else float("nan")
    return (f"{log.n_scans} scans × {log.n_beams} beams, {dur:.1f} s ({rate:.1f} Hz), "
            f"sensor {log.sensor_model or 'unknown'}, fov {np.degrees(log.beams.angle_max - log.angle_min):.1f}°, "
            f"{100 * log.valid().mean():.0f}% returns, intensities {'yes' if log.intensities is not None else 'no'}")


def source_of(log) -> str | None:
    """The importer's one-line ``source`` note, if the log has one."""
    src = log.extra.get("source")
    return None if src is None else str(src)


def track_summary(model, track_ids: dict, unlike: int, off_envelope: int) -> str:
    """One line for ``replay`` and ``run``: the tracks reported per tracked class, and the candidates
    rejected for not looking like any training example of their class (so a user sees why)."""
    tracked = [c for c, t in zip(model.classes, np.asarray(model.tracker.tracked), strict=True) if t]
    per = ", ".join(f"{c} {len(track_ids.get(c, ()))}" for c in tracked)
    return (f"tracks reported: {per}; candidates rejected as unlike any training example of their class: {unlike}, "
            f"outside their class's shape envelope: {off_envelope}")


def print_warnings(console, tally: dict | None, model=None, prefix: str = "") -> list[str]:
    """Print the run's diagnosis (:func:`gtsjax.drivers.diagnose.warnings` of its ``tally``) as one
    ``warning: ...`` line each on ``console`` (stderr); returns the lines. Nothing for a run whose
    counts show no problem, or without a tally."""
    if tally is None:
        return []
    from ..drivers.diagnose import warnings

    lines = [f"warning: {prefix}{w}" for w in warnings(tally, model)]
    for line in lines:
        console.print(line, soft_wrap=True, markup=False, highlight=False)
    return lines


VIEW_HELP = ("Show the run in Rerun: --view opens the native viewer, --view web serves Rerun's web viewer on "
             "127.0.0.1, page and data alike (GTSJAX_VIEW_HOST=0.0.0.0 for other machines; its address printed; no "
             "internet needed). Needs the viewer extra: "
             'pip install "gtsjax\\[viewer]".')  # (an escaped bracket: the help is rich markup)
OUT_BAG_HELP = ("Also write a ROS 2 bag (MCAP storage) to this new folder: the scans (sensor_msgs/LaserScan on "
                "/scan, or /NAME/scan per laser of several), /tf (field to each laser and to each track's CLASS_ID "
                "frame), the tracks (/gtsjax/tracks PoseArray, /gtsjax/markers MarkerArray with ids, "
                "/gtsjax/track_odom nav_msgs/Odometry with covariance, child_frame_id CLASS_ID).")
CSV_UNITS_HELP = ("Write the CSV's optional header with units (stamp_s, x_m, theta_rad, var_x_m2, ...) and the x-y "
                  "covariance column cov_xy_m2; gtsjax reads either form.")
VIEW_SAVE_HELP = "Record the view to this .rrd file (Rerun's viewer reopens it); needs the viewer extra."


def open_view(model, mode: str | None, save: Path | None, console):
    """The :class:`~gtsjax.viewer.View` a command's ``--view`` / ``--view-save`` ask for (``None``
    without either); the web viewer's address printed."""
    if mode is None and save is None:
        return None
    from ..viewer import View

    if save is not None:
        check_out_file(save, "--view-save")
    view = View(model, mode=mode, save=save)
    if view.url is not None:
        console.print(f"view: {view.url}", soft_wrap=True)
    return view


def serve_view(view, console) -> None:
    """After a batch command, keep the web viewer's server up until Ctrl-C (the recording stays
    scrubbable in the browser); nothing for the native viewer, which holds its own copy."""
    import time

    if view is None or view.url is None:
        return
    console.print(f"the view stays at {view.url} until Ctrl-C", soft_wrap=True)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass


def one_model(models: list[Path]) -> Path:
    """The one ``--model`` of a command on one laser (several are for lasers of different scanners)."""
    if len(models) != 1:
        raise InputError("--model", f"given {len(models)} times; several models are for a site's lasers of different "
                                    "scanner models (--log NAME=LOG or --port NAME=PORT)")
    return models[0]


def _same_place(a: Path, b: Path) -> bool:
    """Whether two paths name one file or folder: the same path once resolved, or (both existing) one
    file under two names (a link)."""
    try:
        if a.resolve() == b.resolve():
            return True
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def distinct_paths(inputs: dict[str, "Path | list[Path] | None"],
                   outputs: dict[str, "Path | list[Path] | None"]) -> None:
    """Before any work, for every command that writes: no output is one of the command's inputs (the
    input would be replaced by what the command writes) and no two outputs are one file (the second
    would replace the first). Keys are the options as the user wrote them (``--out``, ``LOG``); a
    clash is one line naming both (:class:`InputError`)."""
    def flat(d):
        for option, v in d.items():
            for p in ([] if v is None else v if isinstance(v, list | tuple) else [v]):
                yield option, Path(p)

    ins, outs = list(flat(inputs)), list(flat(outputs))
    for i, (o_opt, o) in enumerate(outs):
        for in_opt, src in ins:
            if _same_place(o, src):
                raise InputError(o, f"is both {o_opt} and the input {in_opt}: writing it would destroy the input; "
                                    f"give {o_opt} another path")
        for o2_opt, o2 in outs[:i]:
            if _same_place(o, o2):
                raise InputError(o, f"is given as both {o2_opt} and {o_opt}: one would overwrite the other; give "
                                    "each its own path")


def check_out_file(path: Path, option: str = "--out") -> None:
    """A file a command will write, checked before any work: a missing folder is created; the path
    being a folder, a file where a folder should be, or a place that cannot be written is one line
    (:class:`InputError`). Nothing is written at ``path`` itself."""
    if path.is_dir():
        raise InputError(path, f"is a directory; {option} takes the file to write")
    parent = path.parent
    existing = next((p for p in (parent, *parent.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InputError(existing, f"is a file, not a folder, so {option} {path} cannot be written")
    _writable_folder(parent)
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError(path, "is not writable")


def check_out_dir(path: Path, option: str = "--out-dir") -> None:
    """A folder a command will write into, checked (and created) before any work: a file in its
    place or in the place of a folder above it, or a folder that cannot be written, is one line."""
    existing = next((p for p in (path, *path.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InputError(existing, f"is a file, not a folder, so {option} {path} cannot be written")
    _writable_folder(path)


# Folders the output checks made for this command (the top one of each), removed again while empty
# when the command fails (:func:`remove_made_folders`): a bad input leaves nothing behind.
_made: list[Path] = []


def _writable_folder(folder: Path) -> None:
    top = next((p for p in reversed((folder, *folder.parents)) if not p.exists()), None)
    if top is not None:
        _made.append(top)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(folder, f"cannot create the folder ({err.strerror})") from None
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise InputError(folder, f"cannot write in this folder ({err.strerror})") from None


def remove_made_folders() -> None:
    """Remove the folders the output checks made for a command that then failed, where nothing was
    written in them (deepest first; a folder holding anything stays)."""
    while _made:
        top = _made.pop()
        for folder in sorted((p for p in (top, *top.rglob("*")) if p.is_dir()), key=lambda p: -len(p.parts)):
            try:
                folder.rmdir()
            except OSError:
                pass


def forget_made_folders() -> None:
    """The command succeeded: the folders made for its outputs stay."""
    _made.clear()
