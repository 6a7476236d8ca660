"""Live commands: ``gtsjax run`` (sensor → ground truth in real time), ``gtsjax emulate`` (a simulated
sensor on a pseudo-terminal, speaking SCIP 2.0) and ``gtsjax recover`` (a recording after a crash)."""

from pathlib import Path

import typer
from rich.console import Console

from ..drivers.setup import MAX_TRACKS_LIMIT
from ..errors import InputError
from ._app import CONFIRM_HELP, MAX_TRACKS_HELP, QUIET_HELP, app
from ._checks import MAX_SMOOTH_LAG_S
from ._common import (
    CSV_UNITS_HELP,
    OUT_BAG_HELP,
    VIEW_HELP,
    VIEW_SAVE_HELP,
    check_out_file,
    distinct_paths,
    one_model,
    print_warnings,
    track_summary,
)
from ._live import print_beliefs, smoothing_line, track_live


@app.command("run")
def run_cmd(
    port: list[str] = typer.Option(..., "--port", metavar="PORT", help="Serial port or pyserial URL (/dev/ttyACM0, a pty, "
                                                       "socket://host:port); with a site of several lasers, "
                                                       "NAME=PORT once per laser."),
    site: Path = typer.Option(..., "--site", help="Site file (.json)."),
    sensor: str | None = typer.Option(None, "--laser", help="With a site of several lasers: the one the scans are "
                                                          "from (its name in the site's sensors list)."),
    models: list[Path] = typer.Option(..., "--model", help="Model file from gtsjax train. With --port NAME=PORT, one "
                                                           "per scanner model of the site's lasers (each laser gets "
                                                           "the one trained for the scanner its sensors entry names)."),
    out: Path = typer.Option(..., "--out", help="Ground-truth CSV to write (flushed every scan)."),
    record: Path | None = typer.Option(None, "--record", help="Also record the raw scans (crash-safe) to this .npz."),
    json_lines: bool = typer.Option(False, "--json", help="Stream each scan's tracks as JSON lines on stdout."),
    udp: str | None = typer.Option(None, "--udp", help="Send each scan's tracks as JSON to HOST:PORT."),
    duration: float | None = typer.Option(None, "--seconds", min=0.0,
                                          help="Stop after this many seconds (default: until Ctrl-C)."),
    frames: int | None = typer.Option(None, "--frames", min=1, help="Stop after this many frames (default: until Ctrl-C)."),
    intensity: bool = typer.Option(True, "--intensity/--no-intensity",
                                   help="Stream intensities (ME) if the sensor has them (models trained with them need them)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
    confirm_scans: int | None = typer.Option(None, "--confirm-scans", min=1, help=CONFIRM_HELP),
    max_tracks: int | None = typer.Option(None, "--max-tracks", min=1, max=MAX_TRACKS_LIMIT, help=MAX_TRACKS_HELP),
    out_bag: Path | None = typer.Option(None, "--out-bag", help=OUT_BAG_HELP),
    view: str | None = typer.Option(None, "--view", metavar="[web]", help=VIEW_HELP),
    view_save: Path | None = typer.Option(None, "--view-save", help=VIEW_SAVE_HELP),
    csv_units: bool = typer.Option(False, "--csv-units", help=CSV_UNITS_HELP),
    summary: Path | None = typer.Option(None, "--summary", help="Write the run's counters (frames, rows, latency, "
                                        "link faults by cause, the diagnosis of what it reported) as JSON here when "
                                        "it stops."),
    reconnect_timeout: float = typer.Option(10.0, "--reconnect-timeout", min=0.5, metavar="SECONDS",
                                            help="A sensor gone this long (unplugged, its port vanished) ends the "
                                                 "run with one line; what was written is kept (default 10 s). With "
                                                 "several lasers, one gone is a warning and the others go on; all "
                                                 "gone ends the run."),
    beliefs: str | None = typer.Option(None, "--beliefs", metavar="udp:[HOST:]PORT",
                                       help="Listen here for the robots' own poses as JSON lines ({\"robot\", "
                                            "\"stamp\", \"x\", \"y\", \"theta\"}) and name each track with its "
                                            "robot: a robot column in the CSV, the table and the view "
                                            "(docs/live-beliefs.md)."),
    smooth_lag: str | None = typer.Option(None, "--smooth-lag", metavar="SECONDS",
                                          help="Also write a fixed-lag smoothed CSV beside --out, "
                                               "<stem>-smoothed.csv (gtd.csv: gtd-smoothed.csv): the same rows in "
                                               "the same format, each written SECONDS late (in scans, at least one) "
                                               "with its pose smoothed over the scans up to then; the rows still "
                                               "held are written when the run stops (docs/smoothing.md)."),
    keep_warm: bool = typer.Option(True, "--keep-warm/--no-keep-warm",
                                   help="Shortly before each frame is due, run the step once on the last frame and "
                                        "throw the result away, so the frame finds it in the caches (lower latency "
                                        "for one more step per frame)."),
):
    """Track robots live from a sensor: GTD CSV, optional JSON lines / UDP, optional raw recording."""
    if udp is not None:
        from ..drivers.live import udp_address

        udp_address(udp)
    lag = smoothed = None
    if smooth_lag is not None:
        from ..drivers.fixed_lag import smoothed_path

        lag, smoothed = _lag_seconds(smooth_lag), smoothed_path(out)
    distinct_paths({"--site": site, "--model": models},
                   {"--out": out, "--record": record, "--out-bag": out_bag, "--view-save": view_save,
                    "--summary": summary, "the --smooth-lag CSV": smoothed})
    for path, option in ((out, "--out"), (record, "--record"), (summary, "--summary"), (smoothed, "--smooth-lag")):
        if path is not None:
            check_out_file(path, option)
    if out_bag is not None:
        from ..io.bag_out import check_bag_dir

        check_bag_dir(out_bag)
    lasers = _laser_ports(port, site, sensor)
    listener = None
    if beliefs is not None:  # bound now: a port in use is one line before seconds of loading
        from ..io.beliefs_udp import BeliefListener

        listener = BeliefListener(beliefs)
    try:
        _run(port, lasers, models, site, out, record=record, json_lines=json_lines, udp=udp, duration=duration,
             frames=frames, intensity=intensity, quiet=quiet, confirm_scans=confirm_scans, max_tracks=max_tracks,
             out_bag=out_bag, view=view, view_save=view_save, csv_units=csv_units, summary=summary,
             reconnect_timeout=reconnect_timeout, keep_warm=keep_warm, sensor=sensor, beliefs=listener,
             smooth_lag=lag)
    finally:
        if listener is not None:
            listener.stop()


def _run(port, lasers, models, site, out, *, record, json_lines, udp, duration, frames, intensity, quiet,
         confirm_scans, max_tracks, out_bag, view, view_save, csv_units, summary, reconnect_timeout, keep_warm,
         sensor, beliefs, smooth_lag) -> None:
    """``run`` after its options are checked: one laser or several, then the summary."""
    if lasers is not None:
        from ._live import track_live_several

        track_live_several(lasers, models, site, out, record=record, json_lines=json_lines, udp=udp,
                           duration=duration, frames=frames, intensity=intensity, view=not quiet,
                           confirm_scans=confirm_scans, summary=summary, max_tracks=max_tracks, keep_warm=keep_warm,
                           csv_units=csv_units, reconnect_timeout=reconnect_timeout, out_bag=out_bag,
                           rerun_view=view, view_save=view_save, beliefs=beliefs, smooth_lag=smooth_lag)
        return
    port, model = port[0], one_model(models)
    stats, link_stats, loaded = track_live(port, model, site, out, record=record, json_lines=json_lines, udp=udp,
                                   duration=duration, frames=frames, intensity=intensity, view=not quiet,
                                   confirm_scans=confirm_scans, sensor=sensor, max_tracks=max_tracks,
                                   out_bag=out_bag, rerun_view=view, view_save=view_save, keep_warm=keep_warm,
                                   reconnect_timeout=reconnect_timeout, csv_units=csv_units, beliefs=beliefs,
                                   smooth_lag=smooth_lag)
    med, p99 = stats.latency()
    Console(stderr=True).print(
        f"{stats.frames} frames, {stats.rows} rows -> {out}; latency median {med:.2f} ms, p99 {p99:.2f} ms; "
        f"link: {link_stats.bad_frames} bad frames, {link_stats.salvaged} salvaged, {link_stats.dropped} dropped, "
        f"{link_stats.reconnects} reconnects"
        + (f"; raw scans -> {record}" if record else ""))
    if stats.smoothing is not None:
        Console(stderr=True).print(smoothing_line(stats.smoothing), soft_wrap=True)
    print_beliefs(Console(stderr=True), stats.beliefs)
    if summary is not None:
        from ..drivers.live import summary_json

        summary.write_text(summary_json(stats, link_stats) + "\n")
    Console(stderr=True).print(track_summary(loaded, stats.track_ids, stats.unlike, stats.off_envelope),
                               soft_wrap=True)
    print_warnings(Console(stderr=True), stats.tally.finish() if stats.tally is not None else None)


@app.command("emulate")
def emulate_cmd(
    scenario: str = typer.Argument(..., help="Scenario name (gtsjax simulate --list) or a scan log (.npz)."),
    sensor: str | None = typer.Option(None, "--scanner", help="Scanner model to emulate: URG-04LX, UTM-30LX "
                                                                "(default: the scenario's)."),
    seed: int = typer.Option(0, min=0, help="Scenario seed (an integer from 0 up)."),
    checksum_errors: float = typer.Option(0.0, min=0.0, max=1.0, help="Probability of a bad checksum per data block."),
    line_errors: float = typer.Option(0.0, min=0.0, max=1.0, help="Probability of a bad checksum per data line (several per block)."),
    drop_bytes: float = typer.Option(0.0, min=0.0, max=1.0, help="Probability of dropped bytes per data block."),
    stalls: float = typer.Option(0.0, min=0.0, max=1.0, help="Probability of a stall per data block."),
    stall_seconds: float = typer.Option(0.5, min=0.0, help="How long a stall lasts."),
    disconnects: float = typer.Option(0.0, min=0.0, max=1.0, help="Probability of an unplug (and re-plug) per data block."),
    robots: int = typer.Option(10, "--robots", min=1, max=14, help="spl-match-*: robots on the field."),
    seconds: float = typer.Option(60.0, "--seconds", min=0.1, help="spl-match-*: length of the looped scene."),
    referee: bool = typer.Option(True, "--referee/--no-referee", help="spl-match-*: a referee walking about."),
):
    """Serve a simulated sensor over a pseudo-terminal (SCIP 2.0), printing the path to open; a match
    scenario of several lasers (spl-match-N) serves each on its own pty."""
    from ..sim.emulator import Faults, serve, serve_match
    from ..sim.match import is_match

    faults = Faults(checksum_p=checksum_errors, line_checksum_p=line_errors, drop_p=drop_bytes, stall_p=stalls,
                    stall_s=stall_seconds, disconnect_p=disconnects, seed=seed)
    if is_match(scenario):
        if sensor is not None:
            raise InputError("--scanner", "a match scenario names its scanner (spl-match-N: URG-04LX, "
                                        "spl-match-N-utm: UTM-30LX, spl-match-N-mixed: both)")
        serve_match(scenario, faults, seed=seed, n_robots=robots, seconds=seconds, referee=referee,
                    print_fn=lambda s: print(s, flush=True))
        return
    serve(scenario, sensor, faults, seed=seed, print_fn=lambda s: print(s, flush=True))


@app.command("recover")
def recover_cmd(
    journal: Path = typer.Argument(..., help="The RAW.npz.journal left next to a recording that did not close."),
    out: Path | None = typer.Argument(None, help="Log to write (default: the journal's name without .journal)."),
):
    """Turn the journal of an interrupted --record into a scan log."""
    from ..io.record import main as record_main

    distinct_paths({"JOURNAL": journal}, {"OUT": out})

    code = record_main([str(journal)] + ([str(out)] if out else []))
    if code:
        raise typer.Exit(code)


def _laser_ports(ports: list[str], site: Path, sensor: str | None) -> "dict[str, str] | None":
    """``--port NAME=PORT`` per laser of a site with several (``None``: one port, one laser). A port
    is a laser's when the text before its first ``=`` names one of the site's sensors."""
    from ..io import load_site

    site_obj = load_site(site)
    names = {s.name for s in site_obj.sensors}
    pairs = [p.partition("=") for p in ports]
    named = [(n, path) for n, eq, path in pairs if eq and n in names]
    if len(ports) == 1 and not named:
        return None
    if len(named) != len(ports):
        bad = next(p for p, (n, eq, _) in zip(ports, pairs, strict=True) if not (eq and n in names))
        raise InputError("--port", f"{bad!r}: with several ports each is NAME=PORT, NAME one of the site's sensors "
                                   f"({', '.join(sorted(names)) or 'it has no sensors list'})")
    if sensor is not None:
        raise InputError("--laser", "picks one laser; with NAME=PORT per laser, leave it out")
    lasers = dict(named)
    if len(lasers) != len(named):
        raise InputError("--port", "a laser named twice")
    return lasers


def _lag_seconds(text: str) -> float:
    """``--smooth-lag``'s value: seconds, a finite number above 0 (one line, exit 2, otherwise)."""
    import math

    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not math.isfinite(seconds) or seconds <= 0:
        raise InputError("--smooth-lag", f"{text!r}: the lag is a number of seconds above 0 (0.5 for half a second)")
    if seconds > MAX_SMOOTH_LAG_S:
        raise InputError("--smooth-lag", f"{text!r}: at most {MAX_SMOOTH_LAG_S:g} s (the window holds that long of "
                                         "every track's states; "
                                         + (f"{seconds / 1000:g} s if that was milliseconds; " if seconds <= 1000 * MAX_SMOOTH_LAG_S else "")
                                         + "replay --smooth smooths a recording over each track's whole life)")
    return seconds
