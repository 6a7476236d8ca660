"""``gtsjax replay LOG --site SITE.json --model MODEL --out GTD.csv [--topic T] [--crop-fov]``: batch
re-processing of a logged scan file (a ``.npz`` log, or a ROS bag, CARMEN or BreezySLAM log read as
``gtsjax convert`` reads it) through the same jitted pipeline as the live loop.

The log is checked against the scanner geometry the model was trained on before anything is written
(:func:`~gtsjax.io.logs.fit_to_model`): another angular step is refused, and so is a wider field of
view unless ``--crop-fov`` cuts it (and the range window) to the model's."""

import csv
import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from ..io import load_site, to_scans
from ..io.gtd import GTDWriter, rows_from_output, wrap_angle
from ..io.importers import detect_format, format_name
from ..io.logs import fit_to_model
from ..io.modelfile import load_model
from ._app import CONFIRM_HELP, app
from .convert import INPUT_HELP, TOPIC_HELP, describe, load_input, source_of


def replay_log(log, model, out: Path, *, chunk: int = 256, sensor_out: Path | None = None, progress=None):
    """Run ``log`` through ``model`` (site attached) and write the GTD CSV; returns stacked outputs'
    summary counters. The log is moved to the device a block at a time, so memory stays bounded."""
    from .._pipeline import init_state, process_log

    state = init_state(model)
    block = chunk * 16
    totals = {"scans": 0, "rows": 0, "degraded": 0, "overflow": 0, "too_long": 0, "unlike": 0, "off_envelope": 0,
              "track_ids": {}}
    sensor_rows = []
    with GTDWriter(out) as writer:
        for start in range(0, log.n_scans, block):
            part = log.slice(start, start + block)
            scans = to_scans(part, model.n_beams)
            if start > 0:  # dt of the block's first scan is from the previous block's last
                scans = type(scans)(scans.ranges, scans.intensities, scans.valid, scans.angle_min,
                                    scans.angle_increment,
                                    scans.dt.at[0].set(np.float32(log.stamps[start] - log.stamps[start - 1])))
            cb = None if progress is None else (lambda n, s=start: progress(s + n))
            state, out_arrays = process_log(model, scans, chunk=chunk, state=state, callback=cb)
            for i in range(part.n_scans):
                rows = rows_from_output(part.stamps[i], out_arrays.track_id[i], out_arrays.track_class[i],
                                        out_arrays.track_pose[i], out_arrays.track_var[i], out_arrays.track_mask[i],
                                        model.classes)
                writer.write(rows)
                for row in rows:
                    totals["track_ids"].setdefault(row.cls, set()).add(row.track_id)
            if sensor_out is not None:
                tf = out_arrays.transform
                theta = np.arctan2(tf.A[:, 1, 0], tf.A[:, 0, 0])
                origin = tf.mu_o - np.einsum("tij,tj->ti", tf.A, tf.mu_s)
                for i in range(part.n_scans):
                    sensor_rows.append((repr(float(part.stamps[i])), f"{origin[i, 0]:.6f}", f"{origin[i, 1]:.6f}",
                                        f"{float(wrap_angle(theta[i])):.6f}", int(tf.degraded[i]),
                                        int(tf.n_landmarks[i])))
            totals["scans"] += part.n_scans
            totals["degraded"] += int(np.sum(out_arrays.degraded))
            totals["overflow"] += int(np.sum(out_arrays.overflow))
            totals["too_long"] += int(np.sum(out_arrays.too_long))
            totals["unlike"] += int(np.sum(out_arrays.unlike))
            totals["off_envelope"] += int(np.sum(out_arrays.off_envelope))
        totals["rows"] = writer.rows
    if sensor_out is not None:
        with open(sensor_out, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(("stamp", "x", "y", "theta", "degraded", "n_landmarks"))
            w.writerows(sensor_rows)
    return totals


def track_summary(model, track_ids: dict, unlike: int, off_envelope: int) -> str:
    """One line for ``replay`` and ``run``: the tracks reported per tracked class, and the candidates
    rejected for not looking like any training example of their class (so a user sees why)."""
    tracked = [c for c, t in zip(model.classes, np.asarray(model.tracker.tracked), strict=True) if t]
    per = ", ".join(f"{c} {len(track_ids.get(c, ()))}" for c in tracked)
    return (f"tracks reported: {per}; candidates rejected as unlike any training example of their class: {unlike}, "
            f"outside their class's shape envelope: {off_envelope}")


def load_for_run(model_path: Path, site_path: Path, *, sensor_model: str | None):
    site = load_site(site_path)
    model = load_model(model_path, sensor_model=sensor_model)
    return model.with_site(site, where=str(site_path))


@app.command("replay")
def replay_cmd(
    log: Path = typer.Argument(..., help=INPUT_HELP),
    site: Path = typer.Option(..., "--site", help="Site file (.json)."),
    model: Path = typer.Option(..., "--model", help="Model file from gtsjax train."),
    out: Path = typer.Option(..., "--out", help="Ground-truth CSV to write."),
    sensor_out: Path | None = typer.Option(None, "--sensor-out", help="Also write the estimated sensor pose per scan (CSV)."),
    chunk: int = typer.Option(256, min=1, help="Scans per vmapped chunk."),
    topic: str | None = typer.Option(None, "--topic", help=TOPIC_HELP),
    crop_fov: bool = typer.Option(False, "--crop-fov",
                                  help="Crop a wider field of view to the model's, and its range window."),
    confirm_scans: int | None = typer.Option(None, "--confirm-scans", min=1, help=CONFIRM_HELP),
):
    """Process a logged scan file into ground truth (GTD CSV)."""
    console = Console(stderr=True)
    raw = load_input(log, topic, console)
    m = load_for_run(model, site, sensor_model=raw.sensor_model).with_confirmation(confirm_scans)
    scan_log = fit_to_model(raw, m, log, crop=crop_fov, hint="" if crop_fov else "; crop it with --crop-fov")
    if detect_format(log) != "npz":  # what was read from another program's log, once it is known to fit
        console.print(f"{log} ({format_name(log)}): {describe(raw)}", soft_wrap=True)
        if (src := source_of(raw)) is not None:
            console.print(f"  source: {src}", soft_wrap=True)
    if crop_fov:
        last = scan_log.angle_min + (scan_log.n_beams - 1) * scan_log.angle_increment
        console.print(f"cropped to the model's field of view: {scan_log.n_beams} of {raw.n_beams} beams "
                      f"({np.degrees(scan_log.angle_min):.1f}° … {np.degrees(last):.1f}°), returns in "
                      f"[{scan_log.range_min:g}, {scan_log.range_max:g}] m", soft_wrap=True)
    t0 = time.perf_counter()
    with Progress(TextColumn("replay"), BarColumn(), MofNCompleteColumn(), TextColumn("scans"),
                  TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task("replay", total=scan_log.n_scans)
        totals = replay_log(scan_log, m, out, chunk=chunk, sensor_out=sensor_out,
                            progress=lambda n: bar.update(task, completed=n))
    dt = time.perf_counter() - t0
    console.print(f"{totals['scans']} scans in {dt:.1f} s ({totals['scans'] / max(dt, 1e-9):.0f} scans/s, "
                  f"compilation included): {totals['rows']} track rows written to {out}; "
                  f"{totals['degraded']} scans without a new map transformation, "
                  f"{totals['overflow']} segments over the candidate limit, {totals['too_long']} over-long segments")
    console.print(track_summary(m, totals["track_ids"], totals["unlike"], totals["off_envelope"]), soft_wrap=True)
