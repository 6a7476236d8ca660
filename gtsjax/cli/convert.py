"""``gtsjax convert INPUT --out LOG.npz [--topic T]``: a ROS bag, CARMEN log or BreezySLAM text log (or
a ``.npz`` log, re-validated) to the spec's ``.npz`` scan log, read by ``_common.load_input`` as every
command that reads scans reads it."""

from pathlib import Path

import typer
from rich.console import Console

from ..io.importers import format_name
from ..io.logs import save_log
from ._app import app
from ._common import INPUT_HELP, TOPIC_HELP, check_out_file, describe, distinct_paths, load_input, source_of


@app.command()
def convert(
    input: Path = typer.Argument(..., help=INPUT_HELP),
    out: Path = typer.Option(..., "--out", help="Scan log (.npz) to write."),
    topic: str | None = typer.Option(None, "--topic", help=TOPIC_HELP),
):
    """Convert a ROS bag, CARMEN or BreezySLAM log to the .npz scan log every command reads."""
    console = Console(stderr=True, soft_wrap=True)
    distinct_paths({"INPUT": input}, {"--out": out})
    check_out_file(out)
    log = load_input(input, topic, console)
    save_log(log, out)
    console.print(f"{input} ({format_name(input)}): {describe(log)}")
    if (src := source_of(log)) is not None:
        console.print(f"  source: {src}")
    console.print(f"wrote {out}")
