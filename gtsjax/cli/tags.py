"""``gtsjax tags --robots N --perimeter M --range R [--scanner S]``: reflective tag codes for N robots
(:mod:`gtsjax.tags.codes`), printed, and each robot's band to print and cut (:mod:`gtsjax.tags.band`),
with ``tags.json`` listing the design for the site and enrolment."""

import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from ..errors import InputError
from ..io.atomic import atomic_write
from ._app import app
from ._checks import check_length
from ._common import check_out_dir, file_stem

#: The longest band around a robot, metres: a Nao's is about 0.8, the largest RoboCup robots' some 3.
MAX_PERIMETER_M = 5.0
#: The tallest band, metres: a few centimetres around the laser's plane.
MAX_HEIGHT_M = 0.5


def _names(names: str | None, n: int) -> list[str]:
    if names is None:
        return [f"robot{k + 1}" for k in range(n)]
    out = [s.strip() for s in names.split(",")]
    if len(out) != n or not all(out) or len(set(out)) != n:
        raise InputError("--names", f"needs {n} distinct, non-empty names separated by commas (one per robot), "
                                    f"got {len(out)}")
    return out


def plan(robots: int, perimeter: float, max_range: float, scanner: str):
    """The design for these arguments: (scanner model, cells, cell length in metres, the design)."""
    from ..sensors import get_model
    from ..tags.codes import cells_for, design

    model = get_model(scanner)
    if not model.has_intensity:
        raise InputError(scanner, "reports no intensity, so it cannot read reflective tags; with it, robots get "
                                  "their identities from their own localisation (gtsjax grade, run --beliefs)")
    if not 0.0 < max_range <= model.range_max:
        raise InputError("--range", f"must be above 0 and at most the {model.name}'s {model.range_max:g} m, got "
                                    f"{max_range:g}")
    cells = cells_for(perimeter, max_range, model.angle_increment)
    return model, cells, perimeter / max(cells, 1), design(robots, cells)


def advice(robots: int, perimeter: float, max_range: float, beam: float, distance: int) -> str | None:
    """Where one misread cell turns one robot's code into another's (distance 1), what band would
    give distance 2: the shortest perimeter at this range, or the longest range at this perimeter."""
    if distance >= 2 or robots < 2:
        return None
    from ..tags.codes import MAX_CELLS, MIN_BEAMS, design

    for n in range(2, MAX_CELLS + 1):
        try:
            ok = design(robots, n).distance >= 2
        except InputError:
            ok = False
        if ok:
            cell = MIN_BEAMS * max_range * beam
            return (f"distance 1: one misread cell makes one robot's code another's (identity then rests on "
                    f"several reads); distance 2 needs {n} cells: a band of {n * cell:.2f} m at {max_range:g} m, or "
                    f"this band read from at most {perimeter / (n * MIN_BEAMS * beam):.1f} m")
    return None


@app.command("tags")
def tags_cmd(
    robots: int = typer.Option(..., "--robots", min=1, help="How many robots to tag."),
    perimeter: float = typer.Option(..., "--perimeter", help="Length of the band around a robot at the laser's "
                                                             "height, metres (a Nao: about 0.8)."),
    max_range: float = typer.Option(..., "--range", help="The farthest a laser sees a robot from, metres (the "
                                                         "field's far corner)."),
    scanner: str = typer.Option("UTM-30LX", "--scanner", help="The scanner that reads the tags (one with "
                                                              "intensity: UTM-30LX, UST-10LX)."),
    height: float = typer.Option(0.03, "--height", help="The band's height, metres: a few centimetres around the "
                                                        "laser's plane, so that a tilted robot stays in it."),
    names: str | None = typer.Option(None, "--names", help="The robots' names, separated by commas (default "
                                                           "robot1, robot2, ...)."),
    out_dir: Path = typer.Option(Path("tags"), "--out-dir", help="Where to write the bands (one SVG per robot, "
                                                                 "bands.pdf with all) and tags.json."),
):
    """Design reflective tag codes, one per robot, and write each robot's band to print and cut."""
    from ..tags.band import band_svg, bands_pdf

    console = Console(stderr=True, soft_wrap=True)
    check_length("--perimeter", perimeter, 0.0, MAX_PERIMETER_M, "band length around a robot")
    check_length("--height", height, 0.0, MAX_HEIGHT_M, "band height")
    who = _names(names, robots)
    model, cells, cell_m, d = plan(robots, perimeter, max_range, scanner)
    check_out_dir(out_dir)
    beam = model.angle_increment
    table = Table(title=f"{robots} tag codes: {cells} cells of {100 * cell_m:.1f} cm, each {cell_m / (max_range * beam):.1f} "
                        f"beams of the {model.name} at {max_range:g} m; distance {d.distance} between robots")
    for col in ("robot", "code (cell 0 first)", "tape cells", "band"):
        table.add_column(col)
    files = []
    pdf = out_dir / "bands.pdf"
    try:  # all of the bands and tags.json, or (stopped, or failing) none of them
        for name, code, s in zip(who, d.codes, d.strings(), strict=True):
            svg = out_dir / f"{file_stem(name, 'robot')}.svg"
            files.append(svg)
            band_svg(svg, name, code, perimeter, height)
            table.add_row(name, s, str(int(code.sum())), str(svg))
        files.append(pdf)
        pages = bands_pdf(pdf, who, d.codes, perimeter, height)
        _write_spec(out_dir / "tags.json", model, perimeter, height, max_range, cells, cell_m, beam, d, who)
    except BaseException:
        for f in files:
            f.unlink(missing_ok=True)
        raise
    print(table.title)
    for name, s in zip(who, d.strings(), strict=True):
        print(f"{name}\t{s}")
    console.print(table)
    console.print(f"wrote {len(files)} SVG bands, {pdf} ({pages} A4 pages at 1:1) and {out_dir / 'tags.json'}")
    console.print("cell 0 starts at the robot's front right corner and the band runs counter-clockwise seen from "
                  "above; grey cells are tape. Print at 100 % and check the millimetre scale.")
    hint = advice(robots, perimeter, max_range, beam, d.distance)
    if hint:
        console.print(f"[yellow]warning:[/yellow] {hint}")


def _write_spec(path: Path, model, perimeter: float, height: float, max_range: float, cells: int, cell_m: float,
                beam: float, d, who: list[str]) -> None:
    """tags.json: the band's geometry and each robot's code, as ``gtsjax enrol --codes`` reads it."""
    spec = {
        "scanner": model.name, "perimeter_m": perimeter, "height_m": height, "range_m": max_range,
        "cells": cells, "cell_m": cell_m, "beams_per_cell_at_range": cell_m / (max_range * beam),
        "distance": d.distance, "self_distance": d.self_distance,
        "robots": [{"name": n, "code": s} for n, s in zip(who, d.strings(), strict=True)],
    }
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(json.dumps(spec, indent=2) + "\n")
