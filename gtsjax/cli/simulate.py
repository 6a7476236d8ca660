"""``gtsjax simulate SCENARIO --out LOG.npz --site SITE.json``: labelled logs from simulated scenes."""

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from ..io import save_log, save_site
from ._app import app, fail


@app.command("simulate")
def simulate_cmd(
    scenario: str | None = typer.Argument(None, help="Scenario name (see --list)."),
    out: Path | None = typer.Option(None, "--out", help="Scan log (.npz) to write."),
    site: Path | None = typer.Option(None, "--site", help="Site file (.json) to write."),
    seed: int = typer.Option(0, help="Seed: noise, paths and the rough sensor-pose guess."),
    scans: int | None = typer.Option(None, "--scans", min=1, help="Number of scans (default: the scenario's)."),
    sensor: str | None = typer.Option(None, help="Sensor model (default: the scenario's)."),
    list_: bool = typer.Option(False, "--list", help="List the scenarios and exit."),
):
    """Write a labelled scan log and its site file from a simulated scenario."""
    from ..sim import SCENARIOS, simulate

    if list_:
        table = Table(title="scenarios")
        table.add_column("name")
        table.add_column("what it simulates")
        for name, desc in SCENARIOS.items():
            table.add_row(name, desc)
        Console(width=120).print(table)
        return
    if scenario is None or out is None or site is None:
        raise fail("simulate", "needs SCENARIO, --out LOG.npz and --site SITE.json (or --list)")
    t0 = time.perf_counter()
    log, site_obj = simulate(scenario, seed=seed, n_scans=scans, sensor=sensor)
    for p in (out, site):
        p.parent.mkdir(parents=True, exist_ok=True)
    save_log(log, out)
    save_site(site_obj, site)
    Console(stderr=True).print(
        f"{scenario}: {log.n_scans} scans × {log.n_beams} beams ({log.sensor_model}, "
        f"{log.n_scans * (log.stamps[1] - log.stamps[0]) if log.n_scans > 1 else 0:.1f} s) "
        f"in {time.perf_counter() - t0:.1f} s -> {out}, {site}")
