"""``gtsjax plot GTD.csv --site SITE.json [--truth LOG.npz] [--out PNG]``: a picture of any ground-truth
output: the field, its landmarks and the laser, every track's path (a colour per track, heading
arrows now and then), and, given the labelled log the CSV was made from, the true paths and each
labelled object's position and heading error over time."""

import textwrap
from pathlib import Path

import numpy as np
import typer
from rich.console import Console

from ..core.geometry import wrap
from ..errors import InputError
from ..io import load_log, load_site
from ..io.gtd import TrackRow, read_gtd, tracks_of
from ._app import app
from ._common import check_out_file, distinct_paths


def scan_index(row_stamps: np.ndarray, log_stamps: np.ndarray) -> np.ndarray:
    """For each GTD row, the index of the log's scan with the same stamp, or -1. Replay writes the
    log's stamps exactly; a tolerance of 1 ms (or a quarter of the scan period, if less) allows for
    CSVs that other tools rounded."""
    if len(log_stamps) == 0 or len(row_stamps) == 0:
        return np.full(len(row_stamps), -1)
    dts = np.diff(log_stamps)
    dts = dts[dts > 0]
    tol = min(1e-3, 0.25 * float(np.median(dts))) if dts.size else 1e-3
    hi = np.clip(np.searchsorted(log_stamps, row_stamps), 0, len(log_stamps) - 1)
    lo = np.clip(hi - 1, 0, len(log_stamps) - 1)
    best = np.where(np.abs(log_stamps[lo] - row_stamps) <= np.abs(log_stamps[hi] - row_stamps), lo, hi)
    return np.where(np.abs(log_stamps[best] - row_stamps) <= tol, best, -1)


def truth_errors(rows: list[TrackRow], log, radius: float, where: object):
    """Per labelled object of ``log``: (class, error series over the log's scans) where the series are
    position error [T] and heading error [T], NaN where the object is absent or no track of its class
    is within ``radius`` of it. Each object is matched, independently in every scan, to the nearest
    track of its class (of any class, if the CSV has none of that class)."""
    T, M = log.truth_poses.shape[:2]
    st = np.array([r.stamp for r in rows], dtype=np.float64)
    idx = scan_index(st, log.stamps)
    if rows and not (idx >= 0).any():
        raise InputError(where, f"none of its {T} scan stamps ({log.stamps[0]:.3f} … {log.stamps[-1]:.3f} s) matches "
                                f"a row of the CSV ({st.min():.3f} … {st.max():.3f} s): is it the log the CSV was "
                                "made from?")
    pose = np.array([[r.x, r.y, r.theta] for r in rows], dtype=np.float64).reshape(-1, 3)
    cls = np.array([r.cls for r in rows])
    order = np.argsort(idx, kind="stable")
    starts = np.searchsorted(idx[order], np.arange(T + 1))
    out = []
    for m in range(M):
        c = str(log.truth_classes[m])
        same = cls == c if (cls == c).any() else np.ones(len(rows), bool)
        e_pos = np.full(T, np.nan)
        e_th = np.full(T, np.nan)
        for t in np.flatnonzero(~np.isnan(log.truth_poses[:, m, 0])):
            cand = order[starts[t]:starts[t + 1]]
            cand = cand[same[cand]]
            if cand.size == 0:
                continue
            d = np.linalg.norm(pose[cand, :2] - log.truth_poses[t, m, :2], axis=1)
            j = int(np.argmin(d))
            if d[j] <= radius:
                e_pos[t] = d[j]
                e_th[t] = float(wrap(pose[cand[j], 2] - log.truth_poses[t, m, 2]))
        out.append((c, e_pos, e_th))
    return out


def check_figure(out: Path) -> None:
    """``--out`` of ``plot``: a file matplotlib can write, by its suffix, in a folder that can be written."""
    from matplotlib.figure import Figure

    if out.is_dir():
        check_out_file(out)  # "is a directory", before the suffix's complaint
    formats = Figure().canvas.get_supported_filetypes()
    if out.suffix.lower().lstrip(".") not in formats:
        raise InputError(out, f"--out must name a figure file: {', '.join('.' + f for f in sorted(formats))}")
    check_out_file(out)


@app.command()
def plot(
    gtd: Path | None = typer.Argument(None, help="Ground-truth CSV (from replay or run)."),
    site: Path | None = typer.Option(None, "--site", help="Site file (.json) the CSV was made with."),
    coverage: Path | None = typer.Option(None, "--coverage", help="Instead of a CSV: a site file, drawn with what "
                                                                  "each of its lasers sees (range and field of view) "
                                                                  "and how many see each spot."),
    scanner: str = typer.Option("URG-04LX", "--scanner", help="With --coverage: the scanner model of a sensor the "
                                                              "site names none for."),
    truth: Path | None = typer.Option(None, "--truth", help="Labelled scan log (.npz) the CSV was made from: adds "
                                                            "the true paths and the error over time."),
    out: Path | None = typer.Option(None, "--out", help="PNG to write (default: the CSV's name with .png)."),
    match_radius: float = typer.Option(0.5, "--match-radius", min=0.0, help="With --truth: a track farther than "
                                                                              "this (m) from an object is no match."),
):
    """Draw a ground-truth CSV on its field: tracks, headings, and with --truth the error over time; or,
    with --coverage SITE.json, which parts of the field each laser sees."""
    from ..viz import trajectory_figure

    console = Console(stderr=True, soft_wrap=True)
    distinct_paths({"GTD": gtd, "--site": site, "--coverage": coverage, "--truth": truth},
                   {"--out": out if out is not None else gtd.with_suffix(".png") if gtd is not None else None})
    if coverage is not None:
        if gtd is not None or site is not None or truth is not None:
            raise InputError("plot", "--coverage SITE.json draws a site alone: give no CSV, --site or --truth")
        plot_coverage(coverage, scanner, out, console)
        return
    if gtd is None or site is None:
        raise InputError("plot", "needs GTD.csv and --site SITE.json (or --coverage SITE.json)")
    out = gtd.with_suffix(".png") if out is None else out
    check_figure(out)
    site_obj = load_site(site)
    rows = read_gtd(gtd)
    tracks, labels = {}, {}
    for tid, cls, arr in tracks_of(rows):
        tracks[tid], labels[tid] = arr, f"track {tid} ({cls})"
    span = (max(r.stamp for r in rows) - min(r.stamp for r in rows)) if rows else 0.0
    title = f"{gtd.name}: {len(tracks)} track{'s' * (len(tracks) != 1)}, {len(rows)} rows over {span:.1f} s"
    true_paths = truth_labels = errors = None
    summary, short = [], []
    if truth is not None:
        log = load_log(truth)
        if not log.labelled:
            raise InputError(truth, "has no truth_poses: --truth needs a labelled log")
        t = log.stamps - log.stamps[0]
        true_paths = [log.truth_poses[:, m] for m in range(log.truth_poses.shape[1])]
        errors, truth_labels = [], []
        for m, (c, e_pos, e_th) in enumerate(truth_errors(rows, log, match_radius, truth)):
            present = ~np.isnan(log.truth_poses[:, m, 0])
            hit = ~np.isnan(e_pos)
            name = f"truth {m} ({c})"
            truth_labels.append(name)
            if hit.any():
                rmse = 100 * np.sqrt(np.mean(e_pos[hit] ** 2))
                head = np.degrees(np.sqrt(np.mean(e_th[hit] ** 2)))
                text = (f"{name}: tracked in {100 * hit.sum() / max(present.sum(), 1):.0f}% of its scans, "
                        f"RMSE {rmse:.1f} cm, {head:.1f}°")
                short.append(f"{name}: {100 * hit.sum() / max(present.sum(), 1):.0f}% tracked, RMSE {rmse:.1f} cm "
                             f"{head:.1f}°")
            else:
                text = f"{name}: never tracked within {match_radius:g} m"
                short.append(f"{name}: not tracked")
            summary.append(text)
            errors.append((name, t, e_pos, e_th))
        title += "\n" + textwrap.fill("; ".join(short), 100)
    fig = trajectory_figure(site_obj, tracks, truth=true_paths, errors=errors, title=title, labels=labels,
                            truth_labels=truth_labels)
    fig.savefig(out, dpi=110)
    for line in summary:
        console.print(line)
    console.print(f"wrote {out} ({len(tracks)} tracks{', with truth' if truth is not None else ''})")


def plot_coverage(path: Path, scanner: str, out: Path | None, console: Console) -> None:
    """``plot --coverage``: the coverage figure, and per laser and overall the share of the field
    (its bounds) seen, printed."""
    from ..sensors import get_model
    from ..viz import coverage_figure, coverage_grid

    out = path.with_name(path.stem + "-coverage.png") if out is None else out
    check_figure(out)
    site_obj = load_site(path)
    try:
        models = [get_model(sen.model or scanner) for sen in site_obj.sensor_list]
    except InputError as err:
        raise InputError("--scanner", err.problem) from None
    _, _, seen = coverage_grid(site_obj, models)
    count = seen.sum(0)
    lines = [f"{sen.name} ({m.name}, {m.range_max:g} m, {np.degrees(m.angle_max - m.angle_min):.0f}°): "
             f"sees {_pct(s.mean())} of the field" for sen, m, s in zip(site_obj.sensor_list, models, seen,
                                                                                strict=True)]
    shares = ", ".join(f"{_pct(np.mean(count >= k))} by {k}+" for k in range(1, len(models) + 1))
    where = "its bounds" if site_obj.bounds is not None else "the landmarks' extent"
    title = f"{path.name}: {len(models)} laser{'s' * (len(models) != 1)}; of {where}: {shares}"
    fig = coverage_figure(site_obj, models, title=title)
    fig.savefig(out, dpi=110)
    for line in lines:
        console.print(line)
    console.print(f"seen {shares} (range and field of view; a robot in front hides what is behind it)")
    console.print(f"wrote {out}")


def _pct(share: float) -> str:
    """A share as a percentage, with a decimal where rounding would claim all or none."""
    p = 100 * float(share)
    return f"{p:.0f}%" if 0.5 <= p <= 99.5 or p in (0.0, 100.0) else f"{p:.1f}%"
