"""``gtsjax info FILE...``: validate scan logs (a ROS bag's topics listed), site files, model files and
ground-truth CSVs and summarise them;
``gtsjax sensors``: the sensor models gtsjax knows."""

from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from ..core.scan import Beams
from ..drivers.setup import load
from ..errors import InputError
from ..io import load_site
from ..io.gtd import HEADER as GTD_HEADER
from ..io.gtd import read_gtd, tracks_of
from ..io.importers import bag_topics, detect_format, format_name
from ..io.kinds import file_kind
from ..io.modelfile import is_model_file, read_header
from ..sensors import MODELS
from ._app import app
from ._common import TOPIC_HELP, describe, load_input, source_of


@app.command()
def info(
    files: list[Path] = typer.Argument(..., help="Scan logs (.npz, or any input gtsjax convert takes; a ROS bag's "
                                                 "topics are listed), site files (.json), model files (.npz) and "
                                                 "ground-truth CSVs to check."),
    topic: str | None = typer.Option(None, "--topic", help=TOPIC_HELP),
):
    """Check scan logs, ROS bags, site files, model files and ground-truth CSVs against their format and
    print what they hold."""
    console = Console(soft_wrap=True)
    for path in files:
        if is_model_file(path):
            for line in describe_model(path):
                console.print(escape(line))
        elif path.suffix.lower() == ".json":
            site = load_site(path)
            console.print(f"{path}: site, {len(site.landmarks)} landmarks", soft_wrap=True)
            table = Table()
            for col in ("class", "x [m]", "y [m]"):
                table.add_column(escape(col))  # units in [] are not Rich markup
            for lm in site.landmarks:
                table.add_row(lm.cls, f"{lm.x:.3f}", f"{lm.y:.3f}")
            console.print(table)
            if site.sensors:
                for sen in site.sensors:
                    x, y, th = sen.pose
                    console.print(f"  sensor {sen.name} ({sen.model or 'any scanner'}): pose guess x={x:.3f} m  "
                                  f"y={y:.3f} m  θ={np.degrees(th):.1f}°")
                console.print(f"  bounds: {site.bounds if site.bounds is not None else 'none'}")
            else:
                x, y, th = site.sensor_pose
                console.print(f"  sensor pose guess: x={x:.3f} m  y={y:.3f} m  θ={np.degrees(th):.1f}°"
                              f"   bounds: {site.bounds if site.bounds is not None else 'none'}")
            if site.tags is not None:
                t = site.tags
                sized = f", sized for {t.range_m:g} m" if t.range_m is not None else ""
                console.print(escape(f"  tags: {len(t.robots)} robots, bands of {t.cells} cells, {t.perimeter_m:.3f} m"
                                     f"{sized}: " + ", ".join(f"{w.name} {w.code}" + (f" (turned {w.offset_cells})"
                                                                                     if w.offset_cells else "")
                                                              for w in t.robots)), soft_wrap=True)
        elif _is_gtd(path):
            for line in describe_gtd(path):
                console.print(escape(line))
        else:
            if detect_format(path) == "npz" and (what := file_kind(path)) is not None:
                if what == "a JSON file":
                    what += " (a site file is read as one when its name ends in .json)"
                raise InputError(path, f"{what}, not a scan log, site file or model file")
            is_bag = detect_format(path) in ("ros1", "ros2")
            if is_bag:
                lines, scans = describe_bag(path)
                for line in lines:
                    console.print(escape(line))
                if topic is None and len(scans) != 1:
                    if not scans:
                        raise InputError(path, "has no sensor_msgs/LaserScan topic (its topics are listed above): "
                                               "no scans to read")
                    console.print(escape(f"  {len(scans)} LaserScan topics: pick one with --topic T, as convert, "
                                         f"replay and train --background-topic take it (gtsjax info {path} --topic "
                                         f"{scans[0]})"))
                    continue
            log = load_input(path, topic if is_bag else None, Console(stderr=True))
            kind = "" if detect_format(path) == "npz" else f" ({format_name(path)})"
            console.print(f"{path}{kind}: {describe(log)}")
            if (src := source_of(log)) is not None:
                console.print(f"  source: {src}")
            if log.labelled:
                present = ~np.isnan(log.truth_poses[..., 0])
                labels = ", ".join(f"{c} ({100 * present[:, m].mean():.0f}% of scans)"
                                   for m, c in enumerate(log.truth_classes))
                console.print(f"  labelled objects: {labels}")
            if extra := sorted(k for k in log.extra if k != "source"):
                console.print(f"  extra keys: {', '.join(extra)}")


def describe_bag(path: Path) -> tuple[list[str], list[str]]:
    """A ROS bag's topics, one line each (type, messages, and a LaserScan topic's geometry), so that a
    user sees which one to pick with ``--topic``; and the names of its LaserScan topics."""
    kind, span, topics = bag_topics(path)
    lines = [f"{path} (a {kind}): {len(topics)} topic{'s' * (len(topics) != 1)}, "
             f"{sum(t.count for t in topics)} messages recorded over {span:.1f} s"]
    for t in topics:
        line = f"  topic {t.name}: {t.msgtype}, {t.count} messages"
        if t.geometry is not None:
            n, amin, inc, rmin, rmax, inten = t.geometry
            last = Beams(amin, inc, n).angle_max
            line += (f", {n} beams from {np.degrees(amin):.1f}° to {np.degrees(last):.1f}° by "
                     f"{np.degrees(inc):.3f}°, returns in [{rmin:g}, {rmax:g}] m, intensities {'yes' if inten else 'no'}")
        lines.append(line)
    return lines, [t.name for t in topics if t.is_scan]


def _is_gtd(path: Path) -> bool:
    """Whether ``info`` reads ``path`` as a ground-truth CSV: named ``.csv``, or a file of another name
    whose first line is a header of one (``stamp…,track_id,…``); the GTD reader then says what is
    wrong with it, a header that is not the format's included."""
    if not path.is_file():
        return False  # a folder, a socket: the log reader says what it is
    if path.suffix.lower() == ".csv":
        return True
    if detect_format(path) != "npz":
        return False
    try:
        with open(path, "rb") as f:
            first = f.readline(4096).decode("utf-8", "replace").split(",")
    except OSError:
        return False
    return len(first) > 2 and first[0].strip() in ("stamp", "stamp_s") and first[1].strip() == "track_id"


def describe_gtd(path: Path) -> list[str]:
    """A ground-truth CSV, read as ``plot`` and ``export-tum`` read it, in a few lines: rows, time span,
    tracks per class, and each track's rows and first and last stamp."""
    rows = read_gtd(path)
    with open(path, encoding="utf-8") as f:
        header = f.readline().strip()
    form = "" if header == ",".join(GTD_HEADER) else f" (header {header})"
    if not rows:
        return [f"{path}: ground-truth CSV{form}, no rows (no track was confirmed)"]
    stamps = [r.stamp for r in rows]
    tracks = list(tracks_of(rows))
    first, last = min(stamps), max(stamps)
    plural = lambda n, word: f"{n} {word}{'s' * (n != 1)}"  # noqa: E731
    lines = [f"{path}: ground-truth CSV{form}, {plural(len(rows), 'row')} in {plural(len(set(stamps)), 'scan')}, "
             f"{first:.3f} … {last:.3f} s ({last - first:.1f} s), {plural(len(tracks), 'track')}"]
    per: dict[str, list[int]] = {}
    for tid, cls, _ in tracks:
        per.setdefault(cls, []).append(tid)
    for cls, ids in sorted(per.items()):
        lines.append(f"  {cls}: {plural(len(ids), 'track')}, id{'s' * (len(ids) != 1)} {', '.join(map(str, ids))}")
    for tid, cls, arr in tracks:
        lines.append(f"  track {tid} ({cls}): {plural(len(arr), 'row')}, {arr[0, 0]:.3f} … {arr[-1, 0]:.3f} s")
    return lines


def describe_model(path: Path) -> list[str]:
    """A model file, checked as ``replay`` loads it, in a few lines: scanner, classes, predictors, and
    what its training summary says."""
    model, header = load(path), read_header(path)
    landmark, tracked = np.asarray(model.landmark_mask), np.asarray(model.tracker.tracked)
    roles = [c + (" (landmark)" if lm else " (tracked)" if tr else "")
             for c, lm, tr in zip(model.classes, landmark, tracked, strict=True)]
    fov = (f", {np.degrees(model.angle_min):.1f}° … "
           f"{np.degrees(model.beams.angle_max):.1f}°"
           if np.isfinite(model.angle_min) else "")
    gps = model.classifier.gps
    sizes = sorted({int((gp.z if hasattr(gp, "z") else gp.x).shape[0]) for gp in gps})  # sparse: inducing points
    points = str(sizes[0]) if len(sizes) == 1 else f"{sizes[0]}–{sizes[-1]}"
    def heading(reg) -> str:
        return "x, y" if not reg.has_heading else "x, y, heading" if reg.turns is None else (
            f"x, y, heading modulo {360 // int(reg.turns)}°")

    poses = ", ".join(f"{c} ({heading(reg)}{'; one kernel' if reg.shared is not None else ''})"
                      for c, reg in zip(model.classes, model.pose, strict=True) if reg is not None)
    lines = [
        f"{path}: gtsjax model (format version {header['version']}) for {model.sensor_model}, {model.n_beams} beams"
        f"{fov}, returns in [{model.range_min:g}, {model.range_max:g}] m",
        f"  classes: {', '.join(roles)}",
        f"  classifier: {len(gps)} GPs on {int(gps[0].x_mean.shape[0])} inputs ({points} points each); "
        f"pose regressors: {poses or 'none'}",
        f"  tracker: at most {model.max_tracks} tracks, confirmed after {int(model.tracker.n_confirm)} scans",
    ]
    summary = header.get("summary", {})
    held, scans = summary.get("heldout"), summary.get("scans")
    if isinstance(scans, int):
        lines.append(f"  trained on {scans} scans" + (
            f"; held-out classification accuracy {100 * held['accuracy']:.2f} % on {held['n']} candidates"
            if isinstance(held, dict) and isinstance(held.get("accuracy"), float) and held.get("n") else ""))
    return lines


@app.command()
def sensors():
    """List the sensor models gtsjax knows (as their PP reply would describe them)."""
    table = Table(title="sensor models")
    # The model's name is what a user copies into --scanner: never cut (at 80 columns the others wrap).
    table.add_column("model", no_wrap=True, min_width=max(len(n) for n in MODELS))
    for col in ("beams", "steps", "front", "fov [°]", "range [m]", "rate [Hz]", "intensity", "noise σ"):
        table.add_column(escape(col))  # units in [] are not Rich markup
    for m in MODELS.values():
        n = m.noise
        far = f"{100 * n.frac_far:.2g} %" if n.frac_far else f"{1000 * n.sigma_far:.0f} mm"
        noise = f"{1000 * n.sigma:.0f} mm" + ("" if n.knee == float("inf") else f" ≤ {n.knee:g} m, then {far}")
        table.add_row(m.name, str(m.n_beams), f"{m.amin}–{m.amax}/{m.ares}", str(m.afrt),
                      f"{np.degrees(m.angle_max - m.angle_min):.1f}", f"{m.range_min:g}–{m.range_max:g}",
                      f"{m.rate_hz:g}", "yes" if m.has_intensity else "no", noise)
    Console().print(table)
