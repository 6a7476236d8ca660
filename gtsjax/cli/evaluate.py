"""``gtsjax evaluate``: accuracy of a model on labelled logs or simulated scenarios (the paper's
Fig. 5–6 experiment and the moving cases), as a table, Markdown, JSON and an error-map PNG."""

import json
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from ..drivers.setup import MAX_TRACKS_LIMIT
from ._app import CONFIRM_HELP, MAX_TRACKS_HELP, app, fail
from ._checks import MAX_SCENARIO_S, check_length, scenario_spec
from ._common import check_out_dir

# The ground truth as written (confirmed tracks), and the paper's per-sample figures (each scan's
# detections before tracking).
COLUMNS = [("recall", "recall", "{:.1%}"), ("position_rmse_m", "pos RMSE [cm]", "{:.1f}"),
           ("heading_rmse_deg", "heading RMSE [°]", "{:.1f}"), ("heading_median_deg", "heading median [°]", "{:.1f}"),
           ("false_tracks_per_scan", "false tracks/scan", "{:.3f}"), ("id_switches", "id switches", "{}"),
           ("degraded_scans", "degraded scans", "{}"), ("bump_recovered_after_s", "bump recovered [s]", "{:.1f}"),
           ("appear_heading_ok_fraction", "heading ≤ 5° 0.5 s after put down", "{:.0%}")]
DET_COLUMNS = [("det_recall", "detected", "{:.1%}"), ("det_position_rmse_m", "pos RMSE [cm]", "{:.1f}"),
               ("det_heading_rmse_deg", "heading RMSE [°]", "{:.1f}"),
               ("det_heading_median_deg", "heading median [°]", "{:.1f}"),
               ("det_misread_fraction", "heading off > 30°", "{:.1%}"),
               ("occluded_share", "views hidden by robots", "{:.1%}")]
# How well the rows' own variances hold their errors, and the errors' mean in the robot's frame (issue 55).
BAR_COLUMNS = [("position_within_95", "pos in its 95 % ellipse", "{:.1%}"),
               ("heading_within_95", "heading in its 95 % interval", "{:.1%}"),
               ("position_nees", "pos NEES (2 if calibrated)", "{:.2f}"),
               ("heading_nees", "heading NEES (1 if calibrated)", "{:.2f}"),
               ("bias_ahead_m", "bias ahead [mm]", "{:+.1f}"), ("bias_left_m", "bias left [mm]", "{:+.1f}"),
               ("heading_bias_deg", "heading bias [°]", "{:+.2f}"),
               ("view_heading_bias_rms_deg", "still: heading bias of a view, RMS [°]", "{:.1f}"),
               ("view_heading_noise_rms_deg", "still: heading noise in a view, RMS [°]", "{:.1f}")]


def _fmt(key, fmt, v):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return fmt.format(100 * v if key.endswith("position_rmse_m") else 1000 * v if key.startswith("bias_") else v)


def _table(title, columns, results):
    t = Table(title=title)
    t.add_column("data")
    for _, head, _ in columns:
        t.add_column(escape(head), justify="right")  # units in [] are not Rich markup
    for label, res in results.items():
        t.add_row(label, *(_fmt(k, f, res.get(k)) for k, _, f in columns))
    return t


def _markdown(columns, results):
    md = ["| data | " + " | ".join(h for _, h, _ in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for label, res in results.items():
        md.append(f"| {label} | " + " | ".join(_fmt(k, f, res.get(k)) for k, _, f in columns) + " |")
    return md


@app.command("evaluate")
def evaluate_cmd(
    models: list[Path] = typer.Option(..., "--model", help="Model file from gtsjax train; for a match of lasers of "
                                                           "different scanners (spl-match-N-mixed), one per scanner "
                                                           "model."),
    logs: list[Path] = typer.Argument(None, help="Labelled scan logs (.npz); with --site."),
    site: Path | None = typer.Option(None, "--site", help="Site file of the logs."),
    sensor: str | None = typer.Option(None, "--laser", help="With a site of several lasers: the one the scans are "
                                                          "from (its name in the site's sensors list)."),
    scenario: list[str] = typer.Option(None, "--scenario", help="Simulated scenario(s) instead of logs (NAME or NAME:SEED)."),
    out_dir: Path = typer.Option(Path("eval-out"), "--out-dir", help="Where to write results.md, results.json, PNGs."),
    confirm_scans: int | None = typer.Option(None, "--confirm-scans", min=1, help=CONFIRM_HELP),
    max_tracks: int | None = typer.Option(None, "--max-tracks", min=1, max=MAX_TRACKS_LIMIT, help=MAX_TRACKS_HELP),
    robots: int = typer.Option(10, "--robots", min=1, max=14, help="spl-match-* scenarios: robots on the field."),
    seconds: float | None = typer.Option(None, "--seconds", min=1.0,
                                         help="How long: an spl-match-* scenario's length (default 60 s); any "
                                              "other scenario, and each log, cut to its first SECONDS (default: all of it)."),
    penalties: int = typer.Option(0, "--penalties", min=0, help="spl-match-* scenarios: robots picked up so many "
                                  "times in all and put down again (as gtsjax simulate --penalties)."),
    without_outline: bool = typer.Option(False, "--without-outline",
                                         help="Score the model with its learnt outlines left out (no stage e′: "
                                              "headings as the GP reads them), to see what the refinement gains."),
    smooth: bool = typer.Option(False, "--smooth", help="Score the rows replay --smooth writes: each track "
                                                        "smoothed over its whole life."),
):
    """Score a model against labelled logs or held-out simulated scenarios."""
    from ..drivers.evaluation import evaluate_log, per_point
    from ..drivers.setup import attach_site, fit_to_model, load
    from ..io import load_log, load_site
    from ..io.site import one_sensor
    from ..sim import simulate
    from ..sim.match import is_match
    from ..viz import error_map_figure

    if not (scenario or logs):
        raise fail("evaluate", "give labelled logs with --site, or --scenario NAME[:SEED]")
    if seconds is not None:
        check_length("--seconds", seconds, 0.0, MAX_SCENARIO_S, "length of a simulated scenario", unit="s")
    if logs and site is None:
        raise fail("evaluate", "logs need --site SITE.json")
    bases = [load(p, confirm_scans=confirm_scans, max_tracks=max_tracks, without_outline=without_outline)
             for p in models]
    base = bases[0]
    jobs, matches = [], []
    for spec in scenario or []:
        name, seed = scenario_spec(spec)
        if is_match(name):
            matches.append((spec, name, seed))
            continue
        jobs.append((spec, lambda name=name, seed=seed: (*simulate(name, seed=seed, seconds=seconds), False)))
    if logs:
        site_obj = one_sensor(load_site(site), sensor, site)
        for p in logs:  # every log is read and checked before the first is evaluated: a bad one fails fast
            log = load_log(p)
            if not log.labelled:
                raise fail(p, "not a labelled log (no truth_poses)")
            log = fit_to_model(log, base, p)
            if seconds is not None:  # its first SECONDS, as a scenario's
                log = log.slice(0, int(np.sum(log.stamps - log.stamps[0] <= seconds + 1e-9)))
            jobs.append((str(p), lambda log=log: (log, site_obj, True)))
    if jobs and len(bases) > 1:
        raise fail("--model", f"given {len(bases)} times: several models are for match scenarios of lasers of "
                              "different scanners (spl-match-N-mixed), not for logs or one-laser scenarios")
    if matches and robots > base.max_tracks:
        Console(stderr=True).print(f"warning: {robots} robots on the field and {base.max_tracks} track slots in the model: "
                                   f"it cannot track them all (--max-tracks {robots + 4})", soft_wrap=True)
    check_out_dir(out_dir)  # after the inputs are checked (a bad one leaves nothing behind), before any replay
    results = {}
    for spec, name, seed in matches:
        results.update(_evaluate_match(bases, spec, name, seed, robots, 60.0 if seconds is None else seconds, smooth,
                                       penalties))
    for label, get in jobs:
        log, site_obj, fitted = get()
        if not log.labelled:
            raise fail(label, "not a labelled log (no truth_poses)")
        m = attach_site(base, site_obj)
        res = evaluate_log(m, log, where=label, fitted=fitted, smooth=smooth)
        pts, pos, th, cnt = per_point(log, res)
        errors = res.pop("_errors")
        static = len(pts) <= 64 and cnt.size and cnt.min() >= 3
        if static:
            res["points"] = [{"x": float(p[0]), "y": float(p[1]), "n": int(c), "position_mse_m2": float(a**2),
                              "position_rmse_m": float(a), "heading_mse_rad2": float(b**2),
                              "heading_rmse_deg": float(np.degrees(b))} for p, a, b, c in zip(pts, pos, th, cnt, strict=True)]
            fig = error_map_figure(site_obj, pts, pos, np.degrees(th), title=f"{label}: error by place on the field")
            png = out_dir / f"{label.replace('/', '_').replace(':', '_')}-errors.png"
            fig.savefig(png, dpi=100)
            res["figure"] = str(png)
        results[label] = res
        del errors
    console = Console(width=140)
    what = " and ".join(map(str, models)) + (" without its outlines" if without_outline else "")
    console.print(_table(f"ground truth (confirmed tracks) of {what}", COLUMNS, results))
    console.print(_table("per scan, before tracking (the paper's per-sample errors)", DET_COLUMNS, results))
    console.print(_table("error bars and bias of the confirmed tracks' rows", BAR_COLUMNS, results))
    from ..drivers.evaluation import heading_turns

    half = [c for c, n in zip(base.classes, heading_turns(base), strict=True) if n == 2]
    note = (f"headings of {', '.join(half)} judged modulo 180°: the outline looks the same turned half a turn"
            if half else None)
    if note:
        console.print(note, soft_wrap=True)
    (out_dir / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    md = (["Ground truth (confirmed tracks):", ""] + _markdown(COLUMNS, results)
          + ["", "Per scan, before tracking (the paper's per-sample errors):", ""] + _markdown(DET_COLUMNS, results)
          + ["", "Error bars and bias of the confirmed tracks' rows:", ""] + _markdown(BAR_COLUMNS, results)
          + (["", note[0].upper() + note[1:] + "."] if note else []))
    (out_dir / "results.md").write_text("\n".join(md) + "\n")
    Console(stderr=True).print(f"wrote {out_dir / 'results.md'} and {out_dir / 'results.json'}")
    from ._common import print_warnings

    for label, res in results.items():
        print_warnings(Console(stderr=True), res.get("diagnosis"), base, prefix=f"{label}: ")


def _evaluate_match(bases, spec: str, name: str, seed: int, robots: int, seconds: float, smooth: bool = False,
                    penalties: int = 0) -> dict:
    """A match of several lasers (``spl-match-N``), scored with each laser alone, with two opposite
    ones (of four) and with all: rows ``SPEC LASER[+LASER...]``. ``bases``: the models, one per
    scanner model of the match's lasers (:func:`~gtsjax.drivers.several.models_for_lasers`)."""
    from ..drivers.evaluation import evaluate_outputs
    from ..drivers.setup import attach_site, fit_to_model
    from ..drivers.several import merge_logs, models_for_lasers, process_several, site_poses, widened
    from ..io.site import one_sensor
    from ..sim.match import simulate_match

    logs, site = simulate_match(name, seed=seed, n_robots=robots, seconds=seconds, penalties=penalties)
    names = list(logs)
    models, kinds = models_for_lasers([attach_site(b, one_sensor(site, names[0])) for b in bases], site, names)
    model_of = {n: models[kinds[i]] for i, n in enumerate(names)}
    logs = {n: fit_to_model(log, model_of[n], f"{spec} {n}") for n, log in logs.items()}
    combos = [(n,) for n in names]
    if len(names) == 4:
        combos.append((names[0], names[3]))  # north-west and south-east: two lasers facing each other
    if len(names) > 1:
        combos.append(tuple(names))
    out = {}
    for combo in combos:
        used = sorted({kinds[names.index(n)] for n in combo})
        mixed = len(used) > 1
        merged = merge_logs({n: logs[n] for n in combo}, mixed=mixed)
        combo_models = tuple(models[i] for i in used)
        if len(models) == 1:  # every combination through one program: the state holds every laser
            merged = widened(merged, tuple(names))
        _, o = process_several(combo_models, merged, site_poses(site, merged.names),
                               kinds=tuple(used.index(kinds[names.index(n)]) for n in merged.names), filtered=smooth)
        if smooth:
            from ..drivers.smoothing import smooth_output

            o = smooth_output(o[0], o[1], merged.log.stamps, combo_models[0].tracker)
        res = evaluate_outputs(combo_models[0], merged.log, o)
        res.pop("_errors")
        res["lasers"] = len(combo)
        res["occluded_share"] = occluded_share(merged, site)
        out[f"{spec} {'+'.join(combo)}"] = res
    return out


def occluded_share(merged, site, radius: float = 0.15) -> float:
    """Of the robot views a laser's scan could have had (the robot inside the field, within the laser's
    reach: 5.6 m … its range and field of view by the site's pose guess), the share hidden behind
    another robot: the line of sight passes within ``radius`` of a robot nearer the laser. From the
    truth alone: what the scene hides, whatever the model does."""
    from ..sensors import get_model

    sensors = [get_model((merged.sources.get(n) or merged.log).sensor_model) for n in merged.names]
    truth = merged.log.truth_poses
    views = hidden = 0
    for t in range(truth.shape[0]):
        pose = np.asarray(site.sensor(merged.names[merged.laser[t]]).pose, float)
        xy = truth[t, :, :2]
        present = ~np.isnan(xy[:, 0])
        rel = xy - pose[:2]
        rng = np.hypot(rel[:, 0], rel[:, 1])
        reach = present & sensors[merged.laser[t]].beams.reach(pose, xy)
        for i in np.flatnonzero(reach):
            views += 1
            u = rel[i] / rng[i]
            along = rel[present] @ u
            across = np.abs(rel[present, 0] * u[1] - rel[present, 1] * u[0])
            others = (along > 0) & (along < rng[i] - radius) & (across < radius)
            hidden += int(others.any())
    return hidden / max(views, 1)
