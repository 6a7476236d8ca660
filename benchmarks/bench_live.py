"""Live frame-to-GTD latency: the emulated scanner on a real pseudo-terminal, the real serial link
(pyserial, reader thread, SCIP stream decoder) and the real live loop (``gtsjax.live.run_live``, as
``gtsjax run`` runs it), measured by the loop itself: from the moment a frame's last byte was
decoded to the moment its GTD rows were written and flushed.

Two cases: the SPL field with a URG-04LX at 10 Hz (``spl-trajectory``, the shipped demo model), and
the lab with a UTM-30LX at 40 Hz with intensities (``lab-trajectory``, the benchmark's UTM model).
The step is compiled before the sensor streams, as ``gtsjax run`` does.
"""

import tempfile
from pathlib import Path

import numpy as np

from gtsjax.io.serial import Link
from gtsjax.live import run_live, warm_up
from gtsjax.sensors import URG_04LX, UTM_30LX
from gtsjax.sim.emulator import SensorEmulator

from . import _data

SECTION = "live"


def live_case(ctx, key: str, sensor, log, model, duration: float) -> None:
    """Run the live loop on the emulated ``sensor`` replaying ``log`` for ``duration`` seconds."""
    intensity = sensor.has_intensity
    with tempfile.TemporaryDirectory(prefix="gtsjax-bench-") as tmp:
        compiled = warm_up(model, sensor)
        with SensorEmulator(sensor, log) as emu:
            link = Link(emu.path, intensity=intensity)
            link.start()
            try:
                stats = run_live(link, model, Path(tmp) / "gtd.csv", duration=duration, compiled=compiled,
                                 with_intensity=intensity)
            finally:
                link.stop()
            link_stats = link.stats
    lat = np.asarray(stats.latencies_ms) / 1e3
    if lat.size == 0:
        raise RuntimeError(f"live {sensor.name}: no frame reached the loop in {duration} s")
    ctx.results.add(f"live.{key}", "ms", lat, section=SECTION,
                    label=f"live, frame decoded → GTD row flushed, {sensor.name} at {sensor.rate_hz:g} Hz",
                    sensor=sensor.name, rate_hz=sensor.rate_hz, duration_s=duration, frames=stats.frames,
                    rows=stats.rows, late=stats.late, bad_frames=link_stats.bad_frames, dropped=link_stats.dropped)
    ctx.results.checks[f"live.{key}"] = {"frames": stats.frames, "gtd_rows": stats.rows, "late_frames": stats.late,
                                         "expected_frames": int(duration * sensor.rate_hz)}


def run(ctx) -> None:
    duration = 3.0 if ctx.quick else 15.0
    log, site = _data.scenario("spl-trajectory", 7, 300)
    live_case(ctx, "urg-04lx_10hz", URG_04LX, log, _data.demo_model(site), duration)
    ulog, usite = _data.scenario("lab-trajectory", 5, 200 if ctx.quick else 600)
    live_case(ctx, "utm-30lx_40hz", UTM_30LX, ulog, _data.utm_model(usite, ctx.log), duration)
