"""``gtsjax export-tum GTD.csv [--out-dir DIR]``: one TUM trajectory file per track of a ground-truth
CSV, for evo (``evo_traj tum DIR/*.tum``, ``evo_ape tum reference.tum DIR/robot_3.tum``) and the
other tools that read the TUM RGB-D format."""

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from ..io.gtd import read_gtd, tracks_of, write_tum
from ._app import app
from ._common import check_out_dir, file_stem


def tum_name(cls: str, track_id: int) -> str:
    """``<class>_<track id>.tum``, the class reduced to characters safe in a file name."""
    return f"{file_stem(cls, 'track')}_{track_id}.tum"


def export_tum(gtd: Path, out_dir: Path) -> list[tuple[Path, int, str, int, float]]:
    """Write every track of ``gtd`` into ``out_dir``; per file: (path, track id, class, poses, seconds)."""
    tracks = list(tracks_of(read_gtd(gtd)))
    if tracks:
        check_out_dir(out_dir)  # a file in the folder's place is one line, not a traceback
    written = []
    for tid, cls, arr in tracks:
        path = out_dir / tum_name(cls, tid)
        write_tum(path, arr)
        written.append((path, tid, cls, len(arr), float(arr[-1, 0] - arr[0, 0])))
    return written


@app.command("export-tum")
def export_tum_cmd(
    gtd: Path = typer.Argument(..., help="Ground-truth CSV (from replay or run)."),
    out_dir: Path | None = typer.Option(None, "--out-dir", help="Where to write (default: <GTD name>-tum/ next to "
                                                                "the CSV)."),
):
    """Write one TUM trajectory (timestamp x y z qx qy qz qw) per track, for evo and friends."""
    console = Console(stderr=True, soft_wrap=True)
    out_dir = gtd.with_name(gtd.stem + "-tum") if out_dir is None else out_dir
    written = export_tum(gtd, out_dir)
    if not written:
        console.print(f"{gtd} has no track rows; nothing written")
        return
    table = Table(title=f"{len(written)} TUM trajectories in {out_dir}")
    for col in ("file", "track", "class", "poses", "seconds"):
        table.add_column(col)
    for path, tid, cls, n, span in written:
        table.add_row(path.name, str(tid), cls, str(n), f"{span:.1f}")
    console.print(table)
    console.print(f"for example: evo_traj tum {out_dir}/*.tum --plot")
