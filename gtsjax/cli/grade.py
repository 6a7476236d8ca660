"""``gtsjax grade GTD.csv --robot NAME=POSES ...``: each robot's own localisation graded against the
ground truth: which tracks were it, its clock and frame, its errors; a table, Markdown and JSON, and a
figure per robot."""

import math
import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from ._app import app, fail
from ._checks import check_length_units, check_stamp_units
from ._common import VIEW_HELP, VIEW_SAVE_HELP, check_out_dir, check_out_file, file_stem, serve_view

ROBOT_HELP = ("A robot's own poses, NAME=POSES: a TUM or CSV (stamp,x,y,theta) file, a ROS bag topic BAG:TOPIC "
              "(PoseWithCovarianceStamped, PoseStamped, Odometry), or BAG:/tf:CHILD_FRAME. Once per robot.")
FRAME_HELP = ("NAME=field|mirrored|fit: the frame a robot's poses are in. field (the default): the site's; "
              "mirrored: the field turned half a turn about its centre (the other team's frame; the centre from "
              "--site's bounds); fit: a rigid transform fitted and reported (never done unasked: a map turned or "
              "moved is itself a finding).")
OFFSET_HELP = "NAME=SECONDS: the robot's clock minus the laptop's, given instead of estimated."


def _pairs(values: list[str], option: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for v in values:
        name, sep, rest = v.partition("=")
        if not sep or not name or not rest:
            raise fail(option, f"{v!r} is not NAME=VALUE")
        if name in out:
            raise fail(option, f"robot {name} given twice")
        out[name] = rest
    return out


@app.command("grade")
def grade_cmd(
    gtd: Path = typer.Argument(..., help="Ground-truth CSV (from replay or run)."),
    robot: list[str] = typer.Option(..., "--robot", help=ROBOT_HELP),
    site: Path | None = typer.Option(None, "--site", help="Site file: the field's bounds (figures, the centre a "
                                                          "mirrored frame turns about) and landmarks."),
    out_dir: Path | None = typer.Option(None, "--out-dir", help="Where to write grade.md, grade.json and NAME.png "
                                                                "(default: <GTD name>-grade/ next to the CSV)."),
    frame: list[str] = typer.Option([], "--frame", help=FRAME_HELP),
    offset: list[str] = typer.Option([], "--offset", help=OFFSET_HELP),
    max_offset: float = typer.Option(5.0, "--max-offset", min=0.1, max=600.0,
                                     help="The largest clock offset searched (s), either way."),
    classes: list[str] = typer.Option([], "--class", help="Grade against tracks of this class only (default: all)."),
    figures: bool = typer.Option(True, "--figures/--no-figures", help="A PNG per robot."),
    view: str | None = typer.Option(None, "--view", metavar="[web]", help=VIEW_HELP),
    view_save: Path | None = typer.Option(None, "--view-save", help=VIEW_SAVE_HELP),
):
    """Grade each robot's own localisation against the ground truth: identity by association, clock and
    frame alignment, position and heading errors, time lost, recoveries."""
    from ..grade import FRAMES, RobotSpec, grade
    from ..grade.report import COLUMNS, markdown, table_rows, write_json
    from ..io.beliefs import read_beliefs_source
    from ..io.gtd import read_gtd
    from ..io.site import load_site

    console = Console(stderr=True, soft_wrap=True)
    robots = _pairs(robot, "--robot")
    frames = _pairs(frame, "--frame")
    offsets = _pairs(offset, "--offset")
    for option, given in (("--frame", frames), ("--offset", offsets)):
        for name in given:
            if name not in robots:
                raise fail(option, f"robot {name} has no --robot {name}=POSES")
    for name, kind in frames.items():
        if kind not in FRAMES:
            raise fail("--frame", f"{name}={kind}: the frame is one of {', '.join(FRAMES)}")
    fixed = {}
    for name, v in offsets.items():
        try:
            fixed[name] = float(v)
        except ValueError:
            raise fail("--offset", f"{name}={v}: the offset is a number of seconds") from None
        if not math.isfinite(fixed[name]):
            raise fail("--offset", f"{name}={v}: the offset is a number of seconds")
    out_dir = gtd.with_name(gtd.stem + "-grade") if out_dir is None else out_dir
    t_start = time.perf_counter()
    rows = read_gtd(gtd)
    site_obj = load_site(site) if site is not None else None
    centre = (0.0, 0.0)
    if site_obj is not None and site_obj.bounds is not None:
        x0, y0, x1, y1 = site_obj.bounds
        centre = ((x0 + x1) / 2.0, (y0 + y1) / 2.0)
    elif "mirrored" in frames.values():
        console.print("note: no site with bounds, so a mirrored frame is turned about the origin (give --site for the "
                      "field's centre)", markup=False)
    if classes:
        known = sorted({r.cls for r in rows})
        missing = [c for c in classes if c not in known]
        if missing:
            raise fail(gtd, f"has no rows of class {', '.join(missing)} (its classes: {', '.join(known) or 'none'})")
    if not [r for r in rows if not classes or r.cls in classes]:
        raise fail(gtd, "has no track rows: nothing to grade against")
    specs = [RobotSpec(read_beliefs_source(src, name), frames.get(name, "field"), fixed.get(name))
             for name, src in robots.items()]
    # Inputs in the wrong unit are refused before grading, with the factor (graded, a clock in ms or a
    # CSV in mm read as a robot in a frame of its own); a belief's positions in mm are refused as it is read.
    bounds = site_obj.bounds if site_obj is not None else None
    check_length_units(gtd, np.array([[r.x, r.y] for r in rows]), bounds)
    stamps = np.array([r.stamp for r in rows])
    for name, spec in zip(robots, specs, strict=True):
        check_stamp_units(f"--robot {name}={robots[name]}", spec.beliefs.stamps, (stamps.min(), stamps.max()),
                          max_offset, what=f"the ground truth's ({gtd.name})")
    check_out_dir(out_dir)
    if view_save is not None:
        check_out_file(view_save, "--view-save")
    grades = grade(rows, specs, centre=centre, max_offset=max_offset, classes=set(classes) or None)
    t0 = min(r.stamp for r in rows)
    meta = {"gtd": str(gtd), "t0": t0, "max_offset_s": max_offset, "centre": list(centre)}
    (out_dir / "grade.md").write_text(markdown(grades, meta))
    write_json(grades, out_dir / "grade.json", meta)
    written = [out_dir / "grade.md", out_dir / "grade.json"]
    if figures:
        import matplotlib.pyplot as plt

        from ..viz import grade_figure

        for g in grades:
            fig = grade_figure(site_obj, g, t0, title=f"{g.name}: belief against the ground truth")
            path = out_dir / f"{file_stem(g.name, 'robot')}.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            written.append(path)
    table = Table(title=f"{len(grades)} robot{'s' if len(grades) != 1 else ''} graded against {gtd.name}")
    for col in COLUMNS:
        table.add_column(col, overflow="fold")
    for r in table_rows(grades):
        table.add_row(*r)
    Console(width=200).print(table)
    shown = None
    if view is not None or view_save is not None:
        from ..viewer import grade_view

        shown = grade_view(grades, site_obj, t0, mode=view, save=view_save)
        shown.close()
        if shown.url is not None:
            console.print(f"view: {shown.url}", soft_wrap=True)
    for g in grades:
        if g.hint:
            console.print(f"warning: {g.name}: {g.hint}", markup=False, highlight=False)
    console.print(f"graded in {time.perf_counter() - t_start:.1f} s -> {', '.join(str(p) for p in written[:3])}"
                  f"{' …' if len(written) > 3 else ''}", markup=False, highlight=False)
    if view_save is not None:
        console.print(f"view recorded to {view_save}", markup=False, highlight=False)
    serve_view(shown, console)
