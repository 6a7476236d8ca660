"""``gtsjax convert INPUT --out LOG.npz [--topic T]``: a ROS bag, CARMEN log or BreezySLAM text log (or
a ``.npz`` log, re-validated) to the spec's ``.npz`` scan log; and :func:`load_input`, which every
command that reads scans uses, so they all take the same inputs."""

from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from ..io.importers import detect_format, format_name, import_log
from ..io.logs import save_log
from ._app import app

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
                  console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task("read", total=None)
        return import_log(path, topic=topic, progress=lambda n, total: bar.update(task, completed=n, total=total))


def describe(log) -> str:
    """One line: scans × beams, duration and rate, field of view, share of returns, intensities."""
    dur = float(log.stamps[-1] - log.stamps[0])
    rate = (log.n_scans - 1) / dur if dur > 0 else float("nan")
    return (f"{log.n_scans} scans × {log.n_beams} beams, {dur:.1f} s ({rate:.1f} Hz), "
            f"sensor {log.sensor_model or 'unknown'}, fov {np.degrees(log.angle_increment * (log.n_beams - 1)):.1f}°, "
            f"{100 * log.valid().mean():.0f}% returns, intensities {'yes' if log.intensities is not None else 'no'}")


def source_of(log) -> str | None:
    """The importer's one-line ``source`` note, if the log has one."""
    src = log.extra.get("source")
    return None if src is None else str(src)


@app.command()
def convert(
    input: Path = typer.Argument(..., help=INPUT_HELP),
    out: Path = typer.Option(..., "--out", help="Scan log (.npz) to write."),
    topic: str | None = typer.Option(None, "--topic", help=TOPIC_HELP),
):
    """Convert a ROS bag, CARMEN or BreezySLAM log to the .npz scan log every command reads."""
    console = Console(stderr=True, soft_wrap=True)
    log = load_input(input, topic, console)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
    save_log(log, out)
    console.print(f"{input} ({format_name(input)}): {describe(log)}")
    if (src := source_of(log)) is not None:
        console.print(f"  source: {src}")
    console.print(f"wrote {out}")
