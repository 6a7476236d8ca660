"""Live commands: ``gtsjax run`` (sensor → ground truth in real time), ``gtsjax emulate`` (a simulated
sensor on a pseudo-terminal, speaking SCIP 2.0) and ``gtsjax recover`` (a recording after a crash)."""

import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from ._app import CONFIRM_HELP, app


def live_view(model, link, stats, output, stamp) -> Group:
    """The terminal view: confirmed tracks, latency, the sensor pose as the map transformation sees it,
    frame and fault counters."""
    t = Table(title="tracks", expand=False)
    for col in ("id", "class", "x [m]", "y [m]", "θ [°]", "σx [cm]", "σθ [°]"):
        t.add_column(col, justify="right")
    if output is not None:
        m = np.asarray(output.track_mask)
        for i in np.flatnonzero(m):
            p, v = np.asarray(output.track_pose[i]), np.asarray(output.track_var[i])
            t.add_row(str(int(output.track_id[i])), model.classes[int(output.track_class[i])], f"{p[0]:.3f}",
                      f"{p[1]:.3f}", f"{np.degrees(np.angle(np.exp(1j * p[2]))):.1f}",
                      f"{100 * np.sqrt(v[0]):.1f}", f"{np.degrees(np.sqrt(v[2])):.1f}")
    med, p99 = stats.latency()
    ls = link.stats
    lines = [f"frames {stats.frames}  rows {stats.rows}  latency median {med:.2f} ms  p99 {p99:.2f} ms  "
             f"late {stats.late}"]
    if output is not None:
        tf = output.transform
        A, mu_s, mu_o = (np.asarray(a) for a in (tf.A, tf.mu_s, tf.mu_o))
        org = mu_o - A @ mu_s
        lines.append(f"sensor in O: x={org[0]:.3f} m  y={org[1]:.3f} m  θ={np.degrees(np.arctan2(A[1, 0], A[0, 0])):.2f}°"
                     f"  landmarks {int(tf.n_landmarks)}  {'DEGRADED (kept last transform)' if bool(tf.degraded) else ''}")
    lines.append(f"link: dropped {ls.dropped}  checksum {ls.checksum_errors}  truncated {ls.truncated}  "
                 f"malformed {ls.malformed}  garbage bytes {ls.garbage_bytes}  timeouts {ls.timeouts}  "
                 f"reconnects {ls.reconnects}")
    return Group(t, *lines)


def track_live(port: str, model_path: Path, site: Path, out: Path, *, record: Path | None = None,
               json_lines: bool = False, udp: str | None = None, duration: float | None = None,
               frames: int | None = None, intensity: bool = True, view: bool = True, console: Console | None = None,
               confirm_scans: int | None = None):
    """Open the sensor, run the live loop, show the view; returns (live stats, link stats)."""
    from ..io.modelfile import load_model
    from ..io.serial import Link
    from ..io.site import load_site
    from ..live import Outputs, check_sensor, run_live, warm_up
    from ..sensors import MODELS

    console = console or Console(stderr=True)
    site_obj = load_site(site)
    model = load_model(model_path).with_site(site_obj, where=str(site)).with_confirmation(confirm_scans)
    # Compile before the sensor streams, when the model names a known scanner (else after connecting).
    compiled = warm_up(model, MODELS[model.sensor_model]) if model.sensor_model in MODELS else None
    link = Link(port, intensity=intensity)
    link.start()
    last = {"t": 0.0}
    try:
        check_sensor(model, link.model, port)  # before anything is printed: a wrong scanner is one line
        console.print(f"connected to {link.model.name} on {port} ({link.model.n_beams} beams, "
                      f"{link.model.rate_hz:g} Hz)")
        if view:
            with Live(console=console, refresh_per_second=4, transient=False) as live:
                def on_scan(stats, o, stamp):
                    now = time.monotonic()
                    if now - last["t"] > 0.25:
                        last["t"] = now
                        live.update(live_view(model, link, stats, o, stamp))

                stats = run_live(link, model, out, record=record, outputs=Outputs(json_lines, udp),
                                 duration=duration, on_scan=on_scan, with_intensity=intensity,
                                 compiled=compiled, max_frames=frames)
            if not console.is_terminal:  # rich ends the last view with a newline only on a terminal
                console.line()
        else:
            stats = run_live(link, model, out, record=record, outputs=Outputs(json_lines, udp), duration=duration,
                             with_intensity=intensity, compiled=compiled, max_frames=frames)
    finally:
        link.stop()
    return stats, link.stats


@app.command("run")
def run_cmd(
    port: str = typer.Option(..., "--port", help="Serial port or pyserial URL (/dev/ttyACM0, a pty, socket://host:port)."),
    site: Path = typer.Option(..., "--site", help="Site file (.json)."),
    model: Path = typer.Option(..., "--model", help="Model file from gtsjax train."),
    out: Path = typer.Option(..., "--out", help="Ground-truth CSV to write (flushed every scan)."),
    record: Path | None = typer.Option(None, "--record", help="Also record the raw scans (crash-safe) to this .npz."),
    json_lines: bool = typer.Option(False, "--json", help="Stream each scan's tracks as JSON lines on stdout."),
    udp: str | None = typer.Option(None, "--udp", help="Send each scan's tracks as JSON to HOST:PORT."),
    duration: float | None = typer.Option(None, help="Stop after this many seconds (default: until Ctrl-C)."),
    frames: int | None = typer.Option(None, "--frames", min=1, help="Stop after this many frames (default: until Ctrl-C)."),
    intensity: bool = typer.Option(True, "--intensity/--no-intensity",
                                   help="Stream intensities (ME) if the sensor has them (models trained with them need them)."),
    quiet: bool = typer.Option(False, help="No live view."),
    confirm_scans: int | None = typer.Option(None, "--confirm-scans", min=1, help=CONFIRM_HELP),
):
    """Track robots live from a sensor: GTD CSV, optional JSON lines / UDP, optional raw recording."""
    stats, link_stats = track_live(port, model, site, out, record=record, json_lines=json_lines, udp=udp,
                                   duration=duration, frames=frames, intensity=intensity, view=not quiet,
                                   confirm_scans=confirm_scans)
    med, p99 = stats.latency()
    Console(stderr=True).print(
        f"{stats.frames} frames, {stats.rows} rows -> {out}; latency median {med:.2f} ms, p99 {p99:.2f} ms; "
        f"link: {link_stats.bad_frames} bad frames, {link_stats.dropped} dropped, {link_stats.reconnects} reconnects"
        + (f"; raw scans -> {record}" if record else ""))
    from ..io.modelfile import load_model
    from .replay import track_summary

    Console(stderr=True).print(track_summary(load_model(model), stats.track_ids, stats.unlike, stats.off_envelope),
                               soft_wrap=True)


@app.command("emulate")
def emulate_cmd(
    scenario: str = typer.Argument(..., help="Scenario name (gtsjax simulate --list) or a scan log (.npz)."),
    sensor: str | None = typer.Option(None, "--model", help="Sensor model to emulate (default: the scenario's)."),
    seed: int = typer.Option(0, help="Scenario seed."),
    checksum_errors: float = typer.Option(0.0, help="Probability of a bad checksum per data block."),
    drop_bytes: float = typer.Option(0.0, help="Probability of dropped bytes per data block."),
    stalls: float = typer.Option(0.0, help="Probability of a 0.5 s stall per data block."),
    disconnects: float = typer.Option(0.0, help="Probability of an unplug (and re-plug) per data block."),
):
    """Serve a simulated sensor over a pseudo-terminal (SCIP 2.0), printing the path to open."""
    from ..sim.emulator import Faults, serve

    faults = Faults(checksum_p=checksum_errors, drop_p=drop_bytes, stall_p=stalls, disconnect_p=disconnects, seed=seed)
    serve(scenario, sensor, faults, seed=seed, print_fn=lambda s: print(s, flush=True))


@app.command("recover")
def recover_cmd(
    journal: Path = typer.Argument(..., help="The RAW.npz.journal left next to a recording that did not close."),
    out: Path | None = typer.Argument(None, help="Log to write (default: the journal's name without .journal)."),
):
    """Turn the journal of an interrupted --record into a scan log."""
    from ..io.record import main as record_main

    code = record_main([str(journal)] + ([str(out)] if out else []))
    if code:
        raise typer.Exit(code)
