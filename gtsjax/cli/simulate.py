"""``gtsjax simulate SCENARIO --out LOG.npz --site SITE.json``: labelled logs from simulated scenes."""

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from ..io import save_log, save_site
from ._app import app, fail
from ._common import check_out_dir, check_out_file, distinct_paths


@app.command("simulate")
def simulate_cmd(
    scenario: str | None = typer.Argument(None, help="Scenario name (see --list)."),
    out: Path | None = typer.Option(None, "--out", help="Scan log (.npz) to write."),
    site: Path | None = typer.Option(None, "--site", help="Site file (.json) to write."),
    seed: int = typer.Option(0, min=0, help="Seed (an integer from 0 up): noise, paths and the rough sensor-pose guess."),
    scans: int | None = typer.Option(None, "--scans", min=1, help="Number of scans (default: the scenario's)."),
    sensor: str | None = typer.Option(None, "--scanner", help="Scanner model: URG-04LX, UTM-30LX (default: the scenario's)."),
    robots: int = typer.Option(10, "--robots", min=1, max=14, help="spl-match-*: robots on the field."),
    seconds: float = typer.Option(60.0, "--seconds", min=0.1, help="spl-match-*: how long."),
    referee: bool = typer.Option(True, "--referee/--no-referee", help="spl-match-*: a referee walking about."),
    penalties: int = typer.Option(0, "--penalties", min=0, help="spl-match-*: robots picked up so many times in "
                                  "all, 3–8 s each, and put down where their paths have gone on to (identities "
                                  "after a put-down: gtsjax evaluate)."),
    tags: bool | None = typer.Option(None, "--tags/--no-tags", help="Robots wearing reflective tags, one code "
                                     "each, recorded in the site's 'tags' (default: where a scanner reports "
                                     "intensity, the UTM-30LX; --no-tags renders them bare, as before)."),
    beliefs: Path | None = typer.Option(None, "--out-beliefs", help="Also write each robot's simulated self-localisation "
                                        "to this folder (NAME.csv, and put-in.json: what was put in), for gtsjax grade."),
    list_: bool = typer.Option(False, "--list", help="List the scenarios and exit."),
):
    """Write a labelled scan log and its site file from a simulated scenario; a match scenario of
    several lasers writes one log per laser, OUT-NAME.npz, and a site listing them."""
    from ..sim import SCENARIOS, simulate
    from ..sim.match import is_match, simulate_match

    if list_:
        table = Table(title="scenarios")
        table.add_column("name")
        table.add_column("what it simulates")
        for name, desc in SCENARIOS.items():
            table.add_row(name, desc)
        table.add_row("spl-match-N[-utm|-mixed]", "full-size SPL field (9 × 6 m, its goals' posts), N = 1, 2 or 4 "
                      "lasers (URG-04LX, UTM-30LX with -utm, alternately one and the other with -mixed) 0.5 m "
                      "outside the side lines, --robots walking (10), a "
                      "referee; one log per laser (OUT-NAME.npz), the site with its sensors list")
        Console(width=120).print(table)
        return
    if scenario is None or out is None or site is None:
        raise fail("simulate", "needs SCENARIO, --out LOG.npz and --site SITE.json (or --list)")
    distinct_paths({}, {"--out": out, "--site": site, "--out-beliefs": beliefs})
    for path, option in ((out, "--out"), (site, "--site")):
        check_out_file(path, option)
    if beliefs is not None:
        check_out_dir(beliefs, "--out-beliefs")
    t0 = time.perf_counter()
    if is_match(scenario):
        logs, site_obj = simulate_match(scenario, seed=seed, n_robots=robots, seconds=seconds, referee=referee,
                                        tags=tags, penalties=penalties)
        paths = [out.with_name(f"{out.stem}-{name}{out.suffix or '.npz'}") for name in logs]
        distinct_paths({}, {**{f"--out (laser {name})": p for name, p in zip(logs, paths, strict=True)}, "--site": site})
        for path in paths:
            check_out_file(path, "--out")
        for path, log in zip(paths, logs.values(), strict=True):
            save_log(log, path)
        save_site(site_obj, site)
        _write_beliefs(beliefs, list(logs.values()), site_obj, seed)
        kinds = {}
        for log in logs.values():
            kinds.setdefault((log.n_scans, log.sensor_model), []).append(log)
        each = " and ".join(f"{len(v)} × {n} scans ({sm})" for (n, sm), v in kinds.items())
        Console(stderr=True).print(
            f"{scenario}: {len(logs)} lasers, {each}, {robots} robots{_tags_note(site_obj)}, "
            f"{seconds:g} s in {time.perf_counter() - t0:.1f} s -> {', '.join(map(str, paths))}, {site}")
        return
    log, site_obj = simulate(scenario, seed=seed, n_scans=scans, sensor=sensor, tags=tags)
    save_log(log, out)
    save_site(site_obj, site)
    _write_beliefs(beliefs, [log], site_obj, seed)
    Console(stderr=True).print(
        f"{scenario}: {log.n_scans} scans × {log.n_beams} beams ({log.sensor_model}, "
        f"{log.n_scans * (log.stamps[1] - log.stamps[0]) if log.n_scans > 1 else 0:.1f} s){_tags_note(site_obj)} "
        f"in {time.perf_counter() - t0:.1f} s -> {out}, {site}")


def _tags_note(site_obj) -> str:
    t = site_obj.tags
    return "" if t is None else f", tagged ({len(t.robots)} codes of {t.cells} cells)"


def _write_beliefs(folder: Path | None, logs: list, site_obj, seed: int) -> None:
    """Each labelled robot's simulated beliefs (:mod:`gtsjax.sim.beliefs`) from the truth of every
    laser's log, merged in stamp order."""
    if folder is None:
        return
    import numpy as np

    from ..sim.beliefs import simulate_beliefs, write_beliefs

    stamps = np.concatenate([log.stamps for log in logs])
    truth = np.concatenate([log.truth_poses for log in logs])
    order = np.argsort(stamps, kind="stable")
    robots = [m for m, c in enumerate(logs[0].truth_classes) if c == "robot"]
    if not robots:
        raise fail("--out-beliefs", "the scenario has no robot to simulate beliefs for")
    x0, y0, x1, y1 = site_obj.bounds if site_obj.bounds is not None else (0.0, 0.0, 0.0, 0.0)
    sims = simulate_beliefs(stamps[order], truth[order][:, robots], ((x0 + x1) / 2, (y0 + y1) / 2), seed=seed)
    write_beliefs(sims, folder)
    mirrored = [p.name for p, _, _ in sims if p.frame == "mirrored"]
    Console(stderr=True).print(
        f"beliefs of {len(sims)} robots -> {folder}/ (30 Hz, each its own clock offset"
        + (f"; {mirrored[0]} in the mirrored frame" if mirrored else "") + "; what was put in: put-in.json)",
        markup=False, highlight=False)
