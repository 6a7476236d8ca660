"""What ``run`` and ``demo`` share: open a sensor link, run the live driver on it, and the terminal view."""

import time
from pathlib import Path

import numpy as np
from rich.console import Console, Group
from rich.live import Live
from rich.markup import escape
from rich.table import Table

from ..core.geometry import wrap


def live_view(model, link, stats, output, stamp, laser: str | None = None, names: "dict | None" = None) -> Group:
    """The terminal view: confirmed tracks, latency, the sensor pose as the map transformation sees it,
    frame and fault counters. ``link``: the sensor's link, or with several lasers a dict of them by
    name (a counters line each), ``laser`` naming the one whose scan ``output`` is. ``names``: with
    ``--beliefs``, each track's robot by track id; a model that reads tags names them by their tags
    first (a ``robot`` column, empty where none yet)."""
    tagged = bool(getattr(model, "tag_names", ()))
    named = names is not None or tagged
    t = Table(title="tracks", expand=False)
    for col in ("id", "class", "x [m]", "y [m]", "θ [°]", "σx [cm]", "σθ [°]") + (("robot",) if named else ()):
        t.add_column(escape(col), justify="right")  # units in [] are not Rich markup
    if output is not None:
        m = np.asarray(output.track_mask)
        read = np.asarray(output.track_robot) if tagged and output.track_robot is not None else None
        for i in np.flatnonzero(m):
            p, v = np.asarray(output.track_pose[i]), np.asarray(output.track_var[i])
            tid = int(output.track_id[i])
            name = (model.tag_names[int(read[i])] if read is not None and read[i] >= 0
                    else (names or {}).get(tid, ""))
            t.add_row(str(tid), model.classes[int(output.track_class[i])], f"{p[0]:.3f}",
                      f"{p[1]:.3f}", f"{np.degrees(wrap(p[2])):.1f}",
                      f"{100 * np.sqrt(v[0]):.1f}", f"{np.degrees(np.sqrt(v[2])):.1f}",
                      *((escape(name),) if named else ()))
    med, p99 = stats.latency()
    lines = [f"frames {stats.frames}  rows {stats.rows}  latency median {med:.2f} ms  p99 {p99:.2f} ms  "
             f"late {stats.late}"]
    if output is not None and getattr(output, "track_hold", None) is not None:
        lines.append(tentative_line(model, output))
    if output is not None:
        tf, sp = output.transform, np.asarray(output.sensor_pose)
        lines.append(f"{laser or 'sensor'} in O: x={sp[0]:.3f} m  y={sp[1]:.3f} m  θ={np.degrees(sp[2]):.2f}°"
                     f"  landmarks {int(tf.n_landmarks)}  {'DEGRADED (kept last transform)' if bool(tf.degraded) else ''}")
    for name, one in (link.items() if isinstance(link, dict) else [("link", link)]):
        ls = one.stats
        lines.append(f"{name}: dropped {ls.dropped}  checksum {ls.checksum_errors}  salvaged {ls.salvaged}  "
                     f"truncated {ls.truncated}  malformed {ls.malformed}  garbage bytes {ls.garbage_bytes}  "
                     f"timeouts {ls.timeouts}  reconnects {ls.reconnects}")
    return Group(t, *lines)


def tentative_line(model, output) -> str:
    """The view's line of tracks not (yet) confirmed, per class and why (``g_track.HOLDS``)."""
    from ..core.g_track import HOLDS

    hold = np.asarray(output.track_hold)
    waiting = np.asarray(output.track_live) & (hold > 0)
    per = {}
    for i in np.flatnonzero(waiting):
        per.setdefault(model.classes[int(output.track_class[i])], []).append(HOLDS[int(hold[i])])
    if not per:
        return "tentative: none"
    return "tentative: " + "; ".join(
        f"{c} {len(h)} ({', '.join(f'{w} {h.count(w)}' for w in dict.fromkeys(h))})" for c, h in sorted(per.items()))


def check_ports(ports: list[str]) -> None:
    """A port that cannot be a scanner, one line before the model is loaded and the step compiled (seconds
    of waiting for nothing): a plain path with nothing there, or a URL of a scheme pyserial does not know.
    A port that exists but does not answer (busy, not yet up) is the reconnect logic's."""
    import os

    import serial

    from ..errors import InputError

    for p in ports:
        if "://" in p:  # socket://, rfc2217://, loop://: pyserial's URL handlers, checked without connecting
            try:
                serial.serial_for_url(p, do_not_open=True)
            except ValueError as err:
                raise InputError("--port", f"{p}: {err}") from None
        elif not os.path.exists(p):
            raise InputError(p, "no such serial port (nothing at this path): is the scanner plugged in? "
                                "(ls /dev/ttyACM* /dev/ttyUSB*)")


def track_live(port: str, model_path: Path, site: Path, out: Path, *, record: Path | None = None,
               json_lines: bool = False, udp: str | None = None, duration: float | None = None,
               frames: int | None = None, intensity: bool = True, view: bool = True, console: Console | None = None,
               confirm_scans: int | None = None, sensor: str | None = None, max_tracks: int | None = None,
               out_bag: Path | None = None, rerun_view: str | None = None, view_save: Path | None = None,
               keep_warm: bool = True, reconnect_timeout: float | None = None, csv_units: bool = False,
               beliefs=None, smooth_lag: float | None = None):
    """Open the sensor, run the live loop, show the view (the terminal's table; with ``rerun_view`` or
    ``view_save``, Rerun's: :mod:`gtsjax.viewer`); returns (live stats, link stats, the model run).
    ``beliefs``: a bound :class:`~gtsjax.io.beliefs_udp.BeliefListener` (``--beliefs``): each track
    named with its robot (:class:`~gtsjax.grade.online.OnlineIdentity`), the per-robot report in
    the stats' ``beliefs``; the caller stops it. ``smooth_lag``: also the fixed-lag smoothed CSV
    beside ``out`` (:mod:`gtsjax.drivers.fixed_lag`), each row this many seconds late."""
    from ..drivers.live import Outputs, run_live, warm_up
    from ..drivers.setup import check_sensor, load
    from ..io.serial import Link
    from ..io.site import load_site, one_sensor
    from ..sensors import MODELS

    console = console or Console(stderr=True)
    site_obj = one_sensor(load_site(site), sensor, site)
    check_ports([port])  # before seconds of loading and compiling
    model = load(model_path, site_obj, where=str(site), confirm_scans=confirm_scans, max_tracks=max_tracks)
    # Compile before the sensor streams, when the model names a known scanner (else after connecting).
    filtered = smooth_lag is not None
    compiled = warm_up(model, MODELS[model.sensor_model], filtered) if model.sensor_model in MODELS else None
    from ._common import open_view

    shown = open_view(model, rerun_view, view_save, console)
    identity = start_identity(beliefs)
    names = identity.names if identity is not None else None
    link = Link(port, intensity=intensity)
    link.start()
    last = {"t": 0.0}
    try:
        check_sensor(model, link.model, port, intensity=intensity)  # before anything is printed: a wrong scanner is one line
        console.print(f"connected to {link.model.name} on {port} ({link.model.n_beams} beams, "
                      f"{link.model.rate_hz:g} Hz)")
        if view:
            with Live(console=console, refresh_per_second=4, transient=False) as live:
                def on_scan(stats, o, stamp):
                    now = time.monotonic()
                    if now - last["t"] > 0.25:
                        last["t"] = now
                        live.update(live_view(model, link, stats, o, stamp, names=names))

                stats = run_live(link, model, out, record=record, outputs=Outputs(json_lines, udp, csv_units),
                                 duration=duration, on_scan=on_scan, with_intensity=intensity,
                                 compiled=compiled, max_frames=frames, out_bag=out_bag, view=shown,
                                 keep_warm=keep_warm, reconnect_timeout=reconnect_timeout, sensor_checked=True,
                                 identity=identity, smooth_lag=smooth_lag)
            if not console.is_terminal:  # rich ends the last view with a newline only on a terminal
                console.line()
        else:
            stats = run_live(link, model, out, record=record, outputs=Outputs(json_lines, udp, csv_units), duration=duration,
                             with_intensity=intensity, compiled=compiled, max_frames=frames, out_bag=out_bag,
                             view=shown, keep_warm=keep_warm, reconnect_timeout=reconnect_timeout,
                             sensor_checked=True, identity=identity, smooth_lag=smooth_lag)
    finally:
        link.stop()
    if identity is not None:
        stats.beliefs = beliefs_report(beliefs, identity)
    return stats, link.stats, model


def smoothing_line(lag) -> str:
    """The end-of-run line of ``--smooth-lag`` (:class:`~gtsjax.drivers.fixed_lag.LagStats`)."""
    med, p99 = lag.quantiles()
    return (f"smoothed, {lag.lag} scans late: {lag.rows} rows -> {lag.path}; added per scan median {med:.2f} ms, "
            f"p99 {p99:.2f} ms")


def start_identity(beliefs):
    """The live association over a bound listener, which starts listening now (``None``: no ``--beliefs``)."""
    if beliefs is None:
        return None
    from ..grade.online import OnlineIdentity

    beliefs.start()
    return OnlineIdentity(beliefs)


def beliefs_report(beliefs, identity) -> dict:
    """Per robot heard from: poses received, malformed lines that named it, the share of the time it
    sent beliefs that a track held its name (``None`` where it never sent for a whole window); and the
    malformed lines by reason, which name no robot as often as one."""
    counts = beliefs.counts_copy()
    share = identity.named_share()
    robots = sorted(set(counts.poses) | set(counts.malformed_by_robot))
    return {"listen": f"udp:{beliefs.host}:{beliefs.port}", "datagrams": counts.datagrams,
            "malformed": dict(sorted(counts.malformed.items())), "out_of_order": counts.out_of_order,
            "robots_refused": counts.robots_refused, "renames": identity.renames,
            "robots": {r: {"poses": counts.poses.get(r, 0), "malformed": counts.malformed_by_robot.get(r, 0),
                           "named_share": share.get(r)} for r in robots}}


def print_beliefs(console: Console, report: "dict | None") -> None:
    """The end-of-run lines of ``--beliefs``: one per robot, and what was malformed by reason."""
    if report is None:
        return
    bad = report["malformed"]
    console.print(f"beliefs on {report['listen']}: {report['datagrams']} datagrams, "
                  f"{sum(bad.values())} malformed lines"
                  + (f" ({', '.join(f'{k} {v}' for k, v in bad.items())})" if bad else "")
                  + (f", {report['out_of_order']} out of order" if report["out_of_order"] else ""), soft_wrap=True)
    if not report["robots"]:
        console.print("  no robot's beliefs received", soft_wrap=True)
    for r, d in report["robots"].items():
        named = ("sent no whole second of beliefs" if d["named_share"] is None
                 else f"named on a track {100 * d['named_share']:.0f} % of the time it sent beliefs")
        console.print(f"  {escape(r)}: {d['poses']} poses, {d['malformed']} malformed lines; {named}", soft_wrap=True)


def track_live_several(lasers: "dict[str, str]", model_paths: "list[Path]", site: Path, out: Path, *, record: Path | None,
                       json_lines: bool, udp: str | None, duration: float | None, frames: int | None,
                       intensity: bool, view: bool, confirm_scans: int | None, summary: Path | None,
                       console: Console | None = None, max_tracks: int | None = None, keep_warm: bool = True,
                       csv_units: bool = False, reconnect_timeout: float | None = None, out_bag: Path | None = None,
                       rerun_view: str | None = None, view_save: Path | None = None, beliefs=None,
                       smooth_lag: float | None = None):
    """``run --port NAME=PORT ...``: every laser's link, one track table (see
    :mod:`gtsjax.drivers.live_several`); per-laser status when it stops, and in ``summary``. One
    model for every laser, or one per scanner model (each laser gets the one for the scanner the
    site names for it). ``out_bag``, ``rerun_view``, ``view_save``: the bag and Rerun's view, each
    laser's scans under its name. ``beliefs``, ``smooth_lag``: as :func:`track_live`'s."""
    import dataclasses
    import json

    from ..drivers.live import Outputs
    from ..drivers.live_several import run_live_several, warm_up_several
    from ..drivers.setup import load_for_lasers
    from ..drivers.several import models_for_lasers, site_poses
    from ..io.serial import Link
    from ..io.site import load_site
    from ..sensors import MODELS
    from ._common import open_view

    console = console or Console(stderr=True)
    site_obj = load_site(site)
    names = list(lasers)
    check_ports(list(lasers.values()))  # before seconds of loading and compiling
    models, kinds = models_for_lasers(load_for_lasers(model_paths, site_obj, str(site), confirm_scans=confirm_scans,
                                                      max_tracks=max_tracks), site_obj, names)
    poses = site_poses(site_obj, names)
    compiled = (warm_up_several(models, tuple(MODELS[m.sensor_model] for m in models), poses, kinds,
                                filtered=smooth_lag is not None)
                if all(m.sensor_model in MODELS for m in models) else None)
    shown = open_view(models[0], rerun_view, view_save, console)
    identity = start_identity(beliefs)
    names_of = identity.names if identity is not None else None
    links = {}
    record_paths = ({n: record.with_name(f"{record.stem}-{n}{record.suffix or '.npz'}") for n in names}
                    if record is not None else None)
    try:
        for n in names:
            links[n] = Link(lasers[n], intensity=intensity)
            links[n].start()
            console.print(f"{n}: connected to {links[n].model.name} on {lasers[n]}")
        last = {"t": 0.0}
        live = Live(console=console, refresh_per_second=4, transient=False) if view else None

        def on_scan(stats, o, stamp, laser):  # the one-laser view, a counters line per laser
            now = time.monotonic()
            if live is not None and now - last["t"] > 0.25:
                last["t"] = now
                live.update(live_view(models[0], links, stats, o, stamp, laser, names=names_of))

        def warn(msg: str) -> None:
            (live.console if live is not None else console).print(f"warning: {msg}", soft_wrap=True)

        if live is not None:
            live.start()
        try:
            stats, per, out_of_order = run_live_several(
                links, models, poses, out, record=record_paths, kinds=kinds, outputs=Outputs(json_lines, udp, csv_units),
                duration=duration, on_scan=on_scan, with_intensity=intensity, compiled=compiled, max_frames=frames,
                warn=warn, keep_warm=keep_warm, reconnect_timeout=reconnect_timeout, out_bag=out_bag, view=shown,
                identity=identity, smooth_lag=smooth_lag)
        finally:
            if live is not None:
                live.stop()
                if not console.is_terminal:  # rich ends the last view with a newline only on a terminal
                    console.line()
    finally:
        for link in links.values():
            link.stop()
    med, p99 = stats.latency()
    console.print(f"{stats.frames} frames, {stats.rows} rows -> {out}; latency median {med:.2f} ms, p99 {p99:.2f} ms; "
                  f"{out_of_order} frames out of stamp order")
    if stats.smoothing is not None:
        console.print(smoothing_line(stats.smoothing), soft_wrap=True)
    doc = {"frames": stats.frames, "rows": stats.rows, "latency_ms_median": med, "latency_ms_p99": p99,
           "late": stats.late, "stale": stats.stale, "out_of_order": out_of_order,
           "tracks": {c: len(ids) for c, ids in sorted(stats.track_ids.items())}, "lasers": {},
           **({"smoothing": stats.smoothing.as_dict()} if stats.smoothing is not None else {})}
    for n in names:
        ls, p = links[n].stats, per[n]
        lat = np.asarray(p.latencies_ms) if p.latencies_ms else np.asarray([np.nan])
        link = dataclasses.asdict(ls)
        link["received"] = link.pop("frames")  # frames the link delivered, processed or not
        dis = np.asarray(p.disagreement_m) if p.disagreement_m else np.asarray([np.nan])
        doc["lasers"][n] = {**link, "frames": p.frames, "degraded": p.degraded, "late": p.late,
                            "latency_ms_median": float(np.median(lat)), "latency_ms_p99": float(np.percentile(lat, 99)),
                            "disagreement_m_median": _finite(np.median(dis)), "disagreement_m_max": _finite(np.max(dis)),
                            "moved_warnings": p.moved_warnings, "gone_warnings": p.gone_warnings}
        console.print(f"  {n}: {p.frames} frames ({p.degraded} without a new map transformation), link: "
                      f"{ls.bad_frames} bad, {ls.salvaged} salvaged, {ls.dropped} dropped, {ls.reconnects} reconnects"
                      + (f"; calibration check: landmarks shared with another laser at most {p.disagreement_max_m * 100:.1f} cm "
                         "apart" if p.disagreement_m else "; no landmark shared with another laser")
                      + (f"; raw scans -> {record_paths[n]}" if record_paths else ""))
    if identity is not None:
        stats.beliefs = doc["beliefs"] = beliefs_report(beliefs, identity)
        print_beliefs(console, stats.beliefs)
    doc["diagnosis"] = stats.tally.finish() if stats.tally is not None else None
    if summary is not None:
        summary.write_text(json.dumps(doc) + "\n")
    from ._common import print_warnings

    print_warnings(console, doc["diagnosis"])
    return stats


def _finite(x: float) -> float | None:
    """``x`` for JSON, ``None`` where it is NaN (no sample)."""
    return None if np.isnan(x) else float(x)
