"""``gtsjax enrol --site SITE.json --model MODEL --robot NAME (--log LOG | --port PORT [--seconds 20])``:
read the band a robot wears from a log of it alone in view (or from the live sensor, recorded first), match
it against the known codes and store the robot's code and offset in the site file
(:mod:`gtsjax.tags.enrol`). The site file is never lost: it is written whole to a temporary file then
renamed over, the previous one kept as ``SITE.json.bak`` (or written to ``--out``), every other entry as
it was."""

import json
import os
import shutil
import tempfile
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from ..errors import InputError
from ..io.atomic import atomic_write
from ._app import app
from ._common import check_out_file, distinct_paths


def _designed(path: Path | None) -> dict | None:
    """``gtsjax tags``'s ``tags.json``: the band's geometry and each robot's designed code."""
    if path is None:
        return None
    if not path.exists():
        raise InputError(path, "no such file")
    try:
        doc = json.loads(path.read_text())
        robots = {str(r["name"]): str(r["code"]) for r in doc["robots"]}
        return {"cells": int(doc["cells"]), "perimeter_m": float(doc["perimeter_m"]),
                "range_m": None if doc.get("range_m") is None else float(doc["range_m"]), "robots": robots}
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(path, f"not a tags.json of gtsjax tags ({type(err).__name__}: {err})") from None


def write_site(doc: dict, path: Path, out: Path | None) -> Path:
    """Write the site document atomically (:func:`~gtsjax.io.atomic.atomic_write`: whole or not at all,
    its permissions kept); in place (``out`` None), the previous file kept as ``SITE.json.bak``."""
    target = path if out is None else out
    try:
        if out is None:
            shutil.copy2(path, backup_of(path))
        with atomic_write(target, "w", encoding="utf-8") as f:
            f.write(json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    except OSError as err:
        raise InputError(target, f"cannot be written ({err.strerror or err})") from None
    return target


def backup_of(site: Path) -> Path:
    """Where an in-place enrolment keeps the previous site file."""
    return site.with_name(site.name + ".bak")


@app.command("enrol")
def enrol_cmd(
    site: Path = typer.Option(..., "--site", help="Site file (.json) to add the robot's tag to."),
    model_path: Path = typer.Option(..., "--model", help="Model file from gtsjax train that reads tags."),
    robot: str = typer.Option(..., "--robot", help="The robot's name, as the site and the CSV's robot column name it."),
    log: Path | None = typer.Option(None, "--log", help="A log of the robot alone, walking or turned in view "
                                                        "(about 20 s, every side facing the laser)."),
    port: str | None = typer.Option(None, "--port", help="Record from this live sensor instead of a log."),
    seconds: float = typer.Option(20.0, "--seconds", min=1.0, help="With --port: how long to record."),
    record: Path | None = typer.Option(None, "--record", help="With --port: keep the recording here (.npz)."),
    tags_json: Path | None = typer.Option(None, "--codes", help="tags.json from gtsjax tags: the designed codes "
                                                               "(and the band's cells where the site has none)."),
    out: Path | None = typer.Option(None, "--out", help="Write the site here instead of in place (SITE.json.bak "
                                                        "then keeps the previous one)."),
    replace: bool = typer.Option(False, "--replace", help="Give the robot a code another robot of the site wears, "
                                                          "removing that robot's entry."),
):
    """Read the reflective band a robot wears and store its code and offset in the site file."""
    from ..drivers.setup import fit_to_model, load
    from ..io import load_log, load_site
    from ..io.site import SiteTags, parse_site
    from ..tags import enrol as E

    console = Console(stderr=True, soft_wrap=True)
    if (log is None) == (port is None):
        raise InputError("enrol", "give --log LOG or --port PORT (one of them)")
    if record is not None and port is None:
        raise InputError("--record", "keeps what --port records; with --log there is nothing to record")
    # Before any work: nothing it writes may be one of its inputs, and every output can be written.
    distinct_paths({"--site": site, "--model": model_path, "--log": log, "--codes": tags_json},
                   {"--out": out, "--record": record, "the backup of --site": None if out is not None else backup_of(site)})
    if out is not None:
        check_out_file(out, "--out")
    if record is not None:
        check_out_file(record, "--record")
    if not robot.strip():
        raise InputError("--robot", "must be a non-empty name")
    site_obj = load_site(site)
    raw_doc = json.loads(site.read_bytes().decode("utf-8-sig"))
    designed = _designed(tags_json)
    model = load(model_path)
    if model.tags is None:
        raise InputError(model_path, "reads no tags (trained without tagged robots, or its training report says why): "
                                     "train on logs of robots wearing tags")
    from ..sensors import MODELS

    if model.sensor_model in MODELS and not MODELS[model.sensor_model].has_intensity:
        raise InputError(model_path, f"is for the {model.sensor_model}, which reports no intensity: tags need a "
                                     "scanner that does (UTM-30LX)")
    reader = model.tags  # the reader as trained: attaching a site without tags would drop it
    cells = designed["cells"] if designed else (site_obj.tags.cells if site_obj.tags else int(reader.cells))
    if designed and site_obj.tags and designed["cells"] != site_obj.tags.cells:
        raise InputError(tags_json, f"designs bands of {designed['cells']} cells, the site's are of "
                                    f"{site_obj.tags.cells}")
    if port is not None:
        log = _record(port, model_path, site, seconds, record, console)
    assert log is not None
    m = load(model_path, site_obj, where=str(site))
    scan_log = fit_to_model(load_log(log), m, log)
    if scan_log.intensities is None:
        raise InputError(log, "carries no intensities: tags are read from a scanner that reports them, recorded "
                              "with them")
    out_rows = E.replay_smoothed(m, scan_log)
    read = E.read_log(reader, m, scan_log, out_rows, cells)
    known = [(w.name, w.code) for w in (site_obj.tags.robots if site_obj.tags else ())]
    if designed:
        known += [(n, c) for n, c in designed["robots"].items() if (n, c) not in known]
    known = [(n, c) for n, c in known if len(c) == cells]
    mt = E.match(read, known)
    _print_read(console, read, mt)
    E.check(read, mt, bool(known))
    base = None
    if site_obj.tags is None:
        if designed:
            base = SiteTags(designed["cells"], designed["perimeter_m"], (), designed["range_m"])
        else:
            k = int(out_rows.track_class[out_rows.track_mask].flat[0]) if out_rows.track_mask.any() else 0
            base = SiteTags(cells, round(E.outline_perimeter(m, k), 3), ())
    new_tags, notes = E.enrolled(site_obj.tags, robot, mt, designed=None if designed is None else designed["robots"],
                                 replace=replace, base=base)
    raw_doc["tags"] = new_tags.to_json()
    parse_site(raw_doc, site)  # the written file must load
    written = write_site(raw_doc, site, out)
    how = ("the read code itself (no known codes given), as mounted" if mt.name is None
           else f"{mt.name}'s code" if mt.name != robot else "its own code")
    console.print(f"{robot}: {mt.code}, offset {mt.offset} cells ({how}); {'; '.join(notes)}; wrote {written}"
                  + ("" if out is not None else f" (the previous file kept as {site.name}.bak)"))
    print(f"{robot}\t{mt.code}\t{mt.offset}")


def _print_read(console: Console, read, mt) -> None:
    """The table of cells (outline cell 0 first) and the match."""
    table = Table(title=f"band read over {read.scans} scans: {read.code_string()} (outline cell 0 first, ? undecided)")
    for col in ("cell", "read", "P(tape)", "evidence", "scans", "returns"):
        table.add_column(col, justify="right")
    p, d = read.p_tape, read.decided
    for k in range(read.cells):
        what = ("tape" if p[k] > 0.5 else "body") if d[k] else ("not seen" if read.seen[k] < 5 else "?")
        table.add_row(str(k), what, f"{p[k]:.3f}", f"{read.evidence[k]:+.0f}", str(read.seen[k]), str(read.returns[k]))
    console.print(table)
    console.print(read.turned_note())
    if mt.name is not None:
        console.print(f"best: {mt.code} ({mt.name}) turned {mt.offset} cells; margin {mt.margin:.1f} to the next code"
                      + (f" ({mt.next_code}, {mt.next_name})" if mt.next_code else "")
                      + f", {mt.offset_margin:.1f} to its next rotation")


def _record(port: str, model_path: Path, site: Path, seconds: float, record: Path | None, console: Console) -> Path:
    """Record ``seconds`` of the live sensor to ``record`` (a temporary file if not given) through the
    live run's machinery (``gtsjax run --record``), its rows thrown away."""
    from ._live import track_live

    if record is None:
        record = Path(tempfile.mkdtemp(prefix="gtsjax-enrol-")) / "enrol.npz"
    console.print(f"recording {seconds:g} s from {port}: walk or turn the robot in view")
    track_live(port, model_path, site, Path(os.devnull), record=record, duration=seconds, view=False, console=console)
    return record
