"""``gtsjax replay LOG --site SITE.json --model MODEL --out GTD.csv [--topic T] [--crop-fov]``: batch
re-processing of a logged scan file (a ``.npz`` log, or a ROS bag, CARMEN or BreezySLAM log read as
``gtsjax convert`` reads it) through the same jitted pipeline as the live loop.

The log is checked against the scanner geometry the model was trained on before anything is written
(:func:`~gtsjax.io.logs.fit_to_model`): another angular step is refused, and so is a wider field of
view unless ``--crop-fov`` cuts it (and the range window) to the model's."""

import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from ..drivers.replay import replay_log
from ..io.importers import detect_format, format_name
from ..io.logs import fit_to_model
from ._app import CONFIRM_HELP, app
from ._common import INPUT_HELP, TOPIC_HELP, describe, load_for_run, load_input, source_of, track_summary


@app.command("replay")
def replay_cmd(
    log: Path = typer.Argument(..., help=INPUT_HELP),
    site: Path = typer.Option(..., "--site", help="Site file (.json)."),
    model: Path = typer.Option(..., "--model", help="Model file from gtsjax train."),
    out: Path = typer.Option(..., "--out", help="Ground-truth CSV to write."),
    sensor_out: Path | None = typer.Option(None, "--sensor-out", help="Also write the estimated sensor pose per scan (CSV)."),
    chunk: int = typer.Option(256, min=1, help="Scans per compiled chunk."),
    topic: str | None = typer.Option(None, "--topic", help=TOPIC_HELP),
    crop_fov: bool = typer.Option(False, "--crop-fov",
                                  help="Crop a wider field of view to the model's, and its range window."),
    confirm_scans: int | None = typer.Option(None, "--confirm-scans", min=1, help=CONFIRM_HELP),
    step_by_step: bool = typer.Option(False, "--step-by-step",
                                      help="Run each scan's whole step in turn, as the live loop does (bit for bit), "
                                           "instead of perceiving groups of scans at once (faster; equal to float32 round-off, "
                                           "which can tip a near-tie of heading hypotheses)."),
):
    """Process a logged scan file into ground truth (GTD CSV)."""
    console = Console(stderr=True)
    raw = load_input(log, topic, console)
    m = load_for_run(model, site).with_confirmation(confirm_scans)
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
        totals = replay_log(scan_log, m, out, chunk=chunk, sensor_out=sensor_out, vectorise=not step_by_step,
                            progress=lambda n: bar.update(task, completed=n))
    dt = time.perf_counter() - t0
    console.print(f"{totals['scans']} scans in {dt:.1f} s ({totals['scans'] / max(dt, 1e-9):.0f} scans/s, "
                  f"compilation included): {totals['rows']} track rows written to {out}; "
                  f"{totals['degraded']} scans without a new map transformation, "
                  f"{totals['n_overflow']} segments over the candidate limit, {totals['n_too_long']} over-long segments")
    console.print(track_summary(m, totals["track_ids"], totals["unlike"], totals["off_envelope"]), soft_wrap=True)
