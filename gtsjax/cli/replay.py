"""``gtsjax replay LOG [LOG ...] --site SITE.json --model MODEL --out GTD.csv|FOLDER [--topic T] [--crop-fov]``:
batch re-processing of logged scan files (a ``.npz`` log, or a ROS bag, CARMEN or BreezySLAM log read as
``gtsjax convert`` reads it) through the same jitted pipeline as the live loop. Several logs run side by side, one tracker each
(:func:`~gtsjax.drivers.replay.replay_logs`), into one CSV each in the ``--out`` folder.

The log is checked against the scanner geometry the model was trained on before anything is written
(:func:`~gtsjax.io.logs.fit_to_model`, through :mod:`gtsjax.drivers.setup`): another angular step is refused, and so is a wider field of
view unless ``--crop-fov`` cuts it (and the range window) to the model's."""

import json
import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from ..drivers.replay import replay_log, replay_logs
from ..drivers.setup import MAX_TRACKS_LIMIT, fit_to_model, load, load_for_lasers
from ..errors import InputError
from ..io import load_site
from ..io.bag_out import check_bag_dir
from ..io.importers import detect_format, format_name
from ..io.site import one_sensor
from ._app import CONFIRM_HELP, MAX_TRACKS_HELP, app, quiet
from ._checks import check_memory
from ._common import (
    CSV_UNITS_HELP,
    INPUT_HELP,
    OUT_BAG_HELP,
    TOPIC_HELP,
    VIEW_HELP,
    VIEW_SAVE_HELP,
    check_out_file,
    describe,
    distinct_paths,
    load_input,
    one_model,
    open_view,
    print_warnings,
    serve_view,
    source_of,
    track_summary,
)


@app.command("replay")
def replay_cmd(
    logs: list[Path] = typer.Argument(None, help=INPUT_HELP + " Several logs of one scanner run side by side (independent "
                                                "trackers, one compiled program); --out is then a folder."),
    laser_logs: list[str] = typer.Option([], "--log", metavar="NAME=LOG",
                                         help="Several lasers of one field (the site's sensors list): each laser's "
                                              "log, merged by stamp into one track table and one --out CSV."),
    site: Path = typer.Option(..., "--site", help="Site file (.json)."),
    sensor: str | None = typer.Option(None, "--laser", help="With a site of several lasers: the one the scans are "
                                                          "from (its name in the site's sensors list)."),
    models: list[Path] = typer.Option(..., "--model", help="Model file from gtsjax train. With --log, one per scanner "
                                                           "model of the site's lasers (each laser gets the one "
                                                           "trained for the scanner its sensors entry names)."),
    out: Path = typer.Option(..., "--out", help="Ground-truth CSV to write; with several logs, the folder that gets one "
                                                "LOG-NAME.csv per log."),
    sensor_out: Path | None = typer.Option(None, "--sensor-out", help="Also write the estimated sensor pose per scan "
                                                                      "(CSV; with several logs, a folder of "
                                                                      "LOG-NAME.csv)."),
    out_bag: Path | None = typer.Option(None, "--out-bag", help=OUT_BAG_HELP),
    view: str | None = typer.Option(None, "--view", metavar="[web]", help=VIEW_HELP),
    view_save: Path | None = typer.Option(None, "--view-save", help=VIEW_SAVE_HELP),
    chunk: int = typer.Option(256, min=1, help="Scans per compiled chunk."),
    topic: str | None = typer.Option(None, "--topic", help=TOPIC_HELP),
    crop_fov: bool = typer.Option(False, "--crop-fov",
                                  help="Crop a wider field of view to the model's, and its range window."),
    confirm_scans: int | None = typer.Option(None, "--confirm-scans", min=1, help=CONFIRM_HELP),
    max_tracks: int | None = typer.Option(None, "--max-tracks", min=1, max=MAX_TRACKS_LIMIT, help=MAX_TRACKS_HELP),
    step_by_step: bool = typer.Option(False, "--step-by-step",
                                      help="Run each scan's whole step in turn, as the live loop does, instead of perceiving "
                                           "groups of scans at once (faster). Either equals the live loop's rows to float32 "
                                           "round-off, which can tip a near-tie of heading hypotheses."),
    csv_units: bool = typer.Option(False, "--csv-units", help=CSV_UNITS_HELP),
    smooth: bool = typer.Option(False, "--smooth", help="Smooth each track's poses over its whole life, the scans "
                                "after each row as well as before (a fixed-interval RTS smoother over the forward "
                                "pass, which still decides the rows, ids and classes); the rows are written once "
                                "the forward pass is done."),
    summary: Path | None = typer.Option(None, "--summary", help="Write the replay's counters (scans, rows, tracks, "
                                        "the diagnosis of what it reported) as JSON here; with several logs, one "
                                        "object per log."),
):
    """Process logged scan files into ground truth (GTD CSV); with --log NAME=LOG per laser, several
    lasers of one field into one."""
    console = Console(stderr=True)
    distinct_paths({"LOG": logs, "--log": [s.partition("=")[2] for s in laser_logs or []], "--site": site,
                    "--model": models},
                   {"--out": out, "--sensor-out": sensor_out, "--out-bag": out_bag, "--view-save": view_save,
                    "--summary": summary})
    if laser_logs:
        if logs or sensor is not None or step_by_step:
            raise InputError("replay", "--log NAME=LOG (several lasers) takes no positional logs, --laser or "
                                       "--step-by-step")
        if summary is not None:
            check_out_file(summary, "--summary")
        if out_bag is not None:
            check_bag_dir(out_bag)
        _replay_lasers(laser_logs, site, models, out, chunk, topic, crop_fov, confirm_scans, console, sensor_out,
                       max_tracks, summary, csv_units=csv_units, out_bag=out_bag, view=view, view_save=view_save,
                       smooth=smooth)
        return
    if not logs:
        raise InputError("replay", "give a log (or --log NAME=LOG per laser of a site with several)")
    model = one_model(models)
    for given, option in ((out_bag, "--out-bag"), (view, "--view"), (view_save, "--view-save"),
                          (True if smooth else None, "--smooth")):
        if given is not None and len(logs) > 1:
            raise InputError(option, "takes one log (several logs side by side write one CSV each)")
    if out_bag is not None:
        check_bag_dir(out_bag)
    if summary is not None:
        check_out_file(summary, "--summary")
    m = load(model, one_sensor(load_site(site), sensor, site), where=str(site), confirm_scans=confirm_scans,
             max_tracks=max_tracks)
    outs, sensor_outs = _outputs(logs, out, sensor_out)
    scan_logs = [_load_fitted(log, topic, m, crop_fov, console) for log in logs]
    if smooth:
        _check_smooth_memory(m, scan_logs[0].n_scans, f"{logs[0]}'s")
    shown = open_view(m, view, view_save, console)
    t0 = time.perf_counter()
    total = sum(lg.n_scans for lg in scan_logs)
    with Progress(TextColumn("replay"), BarColumn(), MofNCompleteColumn(), TextColumn("scans"),
                  TimeRemainingColumn(), console=console, transient=True, disable=quiet()) as bar:
        task = bar.add_task("replay", total=total)

        def done(n: int) -> None:
            bar.update(task, completed=n)

        if len(scan_logs) == 1:
            results = [replay_log(scan_logs[0], m, outs[0], chunk=chunk, sensor_out=sensor_outs[0],
                                  vectorise=not step_by_step, progress=done, out_bag=out_bag, view=shown,
                                  csv_units=csv_units, smooth=smooth)]
        else:
            results = replay_logs(scan_logs, m, outs, chunk=chunk, sensor_outs=sensor_outs, vectorise=not step_by_step,
                                  progress=done, csv_units=csv_units)
    dt = time.perf_counter() - t0
    if len(results) > 1:
        console.print(f"{len(results)} logs, {total} scans in {dt:.1f} s ({total / max(dt, 1e-9):.0f} scans/s, "
                      "compilation included)")
    for log, o, totals in zip(logs, outs, results, strict=True):
        head = (f"{totals['scans']} scans in {dt:.1f} s ({totals['scans'] / max(dt, 1e-9):.0f} scans/s, "
                "compilation included)" if len(results) == 1 else f"{log.name}: {totals['scans']} scans")
        console.print(f"{head}: {totals['rows']} track rows written to {o}; "
                      f"{totals['degraded']} scans without a new map transformation, "
                      f"{totals['n_overflow']} segments over the candidate limit, {totals['n_too_long']} over-long segments")
        console.print(track_summary(m, totals["track_ids"], totals["unlike"], totals["off_envelope"]), soft_wrap=True)
    for log, totals in zip(logs, results, strict=True):
        print_warnings(console, totals["diagnosis"], m, prefix="" if len(results) == 1 else f"{log.name}: ")
    if summary is not None:
        docs = {_name(log): _summary_doc(totals) for log, totals in zip(logs, results, strict=True)}
        doc = next(iter(docs.values())) if len(docs) == 1 else {"logs": docs}
        summary.write_text(json.dumps(doc) + "\n")
    if view_save is not None:
        console.print(f"view recorded to {view_save}")
    serve_view(shown, console)


def _check_smooth_memory(model, n_scans: int, whose: str) -> None:
    """``--smooth`` holds the forward pass's states for the whole log before it smooths: refused before
    any work where they would not fit in the memory the machine has."""
    from ..drivers.smoothing import memory_needed

    check_memory("--smooth", memory_needed(model, n_scans), f"smoothing {whose} {n_scans} scans",
                 "replay without --smooth (the forward pass's rows, a scan at a time), or on a machine with "
                 "more memory")


def _summary_doc(totals: dict) -> dict:
    """A log's totals as JSON: tracks reported per class counted (not their ids)."""
    doc = {k: v for k, v in totals.items() if k != "track_ids"}
    doc["tracks"] = {c: len(ids) for c, ids in sorted(totals["track_ids"].items())}
    return doc


def _outputs(logs: list[Path], out: Path, sensor_out: Path | None) -> tuple[list[Path], list[Path | None]]:
    """Where each log's CSV (and sensor CSV) goes: ``out`` itself for one log; for several, one
    ``NAME.csv`` per log in the folders ``out`` (and ``sensor_out``), created if missing. Checked
    before any log is read, so that a bad place costs nothing."""
    if len(logs) == 1:
        check_out_file(out)
        if sensor_out is not None:
            check_out_file(sensor_out, "--sensor-out")
        return [out], [sensor_out]
    names = [_name(log) for log in logs]
    if len(set(names)) < len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise InputError(out, f"two logs would both write {dup}.csv; give logs with different names")
    folders = [out] + ([sensor_out] if sensor_out is not None else [])
    for folder in folders:
        if folder.exists() and not folder.is_dir():
            raise InputError(folder, "is a file; with several logs --out and --sensor-out name folders")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(folder, f"cannot create the folder ({err.strerror})") from None
    return ([out / f"{n}.csv" for n in names],
            [None if sensor_out is None else sensor_out / f"{n}.csv" for n in names])


def _name(log: Path) -> str:
    """A log's name without its format's suffixes (``run1.log.gz`` → ``run1``)."""
    name = log.name.rstrip("/")
    for suffix in (".gz", ".npz", ".bag", ".log", ".dat", ".mcap", ".db3"):
        name = name.removesuffix(suffix)
    return name or log.name


def _load_fitted(log: Path, topic: str | None, m, crop_fov: bool, console: Console):
    """A log read, checked against the model's scanner (cropped with ``crop_fov``), described when it
    came from another program's format."""
    raw = load_input(log, topic, console)
    scan_log = fit_to_model(raw, m, log, crop=crop_fov, hint="" if crop_fov else "; crop it with --crop-fov")
    if detect_format(log) != "npz":  # what was read from another program's log, once it is known to fit
        console.print(f"{log} ({format_name(log)}): {describe(raw)}", soft_wrap=True)
        if (src := source_of(raw)) is not None:
            console.print(f"  source: {src}", soft_wrap=True)
    if crop_fov:
        last = scan_log.beams.angle_max
        console.print(f"{log}: cropped to the model's field of view: {scan_log.n_beams} of {raw.n_beams} beams "
                      f"({np.degrees(scan_log.angle_min):.1f}° … {np.degrees(last):.1f}°), returns in "
                      f"[{scan_log.range_min:g}, {scan_log.range_max:g}] m", soft_wrap=True)
    return scan_log


def _replay_lasers(specs: list[str], site_path: Path, model_paths: list[Path], out: Path, chunk: int, topic: str | None,
                   crop_fov: bool, confirm_scans: int | None, console: Console, sensor_out: Path | None,
                   max_tracks: int | None = None, summary: Path | None = None, *, csv_units: bool = False,
                   out_bag: Path | None = None, view: str | None = None, view_save: Path | None = None,
                   smooth: bool = False) -> None:
    """``replay --log NAME=LOG ...``: the lasers' logs merged by stamp into one track table (and the
    bag and the view, each laser's scans under its name)."""
    from ..drivers.several import models_for_lasers, replay_several

    site_obj = load_site(site_path)
    paths: dict[str, Path] = {}
    for spec in specs:
        name, eq, path = spec.partition("=")
        if not eq or not name or not path:
            raise InputError("--log", f"{spec!r} is not NAME=LOG")
        if name in paths:
            raise InputError("--log", f"laser {name!r} given twice")
        if not site_obj.sensors:
            raise InputError(site_path, "has no sensors list; --log NAME=LOG is for a site with several lasers")
        try:
            site_obj.sensor(name)
        except InputError as err:
            raise InputError(site_path, err.problem) from None
        paths[name] = Path(path)
    check_out_file(out)
    if sensor_out is not None:
        check_out_file(sensor_out, "--sensor-out")
    loaded = load_for_lasers(model_paths, site_obj, str(site_path), confirm_scans=confirm_scans, max_tracks=max_tracks)
    models, kinds = models_for_lasers(loaded, site_obj, list(paths))
    logs = {name: _load_fitted(path, topic, models[kinds[i]], crop_fov, console)
            for i, (name, path) in enumerate(paths.items())}
    if smooth:
        _check_smooth_memory(models[0], sum(lg.n_scans for lg in logs.values()), "the lasers'")
    shown = open_view(models[0], view, view_save, console)
    t0 = time.perf_counter()
    total = sum(lg.n_scans for lg in logs.values())
    with Progress(TextColumn("replay"), BarColumn(), MofNCompleteColumn(), TextColumn("scans"),
                  TimeRemainingColumn(), console=console, transient=True, disable=quiet()) as bar:
        task = bar.add_task("replay", total=total)
        totals = replay_several(logs, models, site_obj, out, kinds=kinds, chunk=chunk,
                                progress=lambda n: bar.update(task, completed=n), sensor_out=sensor_out,
                                csv_units=csv_units, out_bag=out_bag, view=shown, smooth=smooth)
    dt = time.perf_counter() - t0
    per = ", ".join(f"{n} {totals['scans_per_laser'][n]} scans ({totals['degraded'][n]} without a new map "
                    "transformation)" for n in logs)
    tracks = ", ".join(f"{c} {k}" for c, k in sorted(totals["tracks"].items())) or "none"
    console.print(f"{len(logs)} lasers, {total} scans in {dt:.1f} s (compilation included): {per}; "
                  f"{totals['rows']} track rows written to {out}; tracks reported: {tracks}", soft_wrap=True)
    print_warnings(console, totals["diagnosis"], models[0])
    if summary is not None:
        summary.write_text(json.dumps(totals) + "\n")
    if view_save is not None:
        console.print(f"view recorded to {view_save}")
    serve_view(shown, console)
