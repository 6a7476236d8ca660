"""Live frame-to-GTD latency: the emulated scanner on a real pseudo-terminal, the real serial link
(pyserial, reader thread, SCIP stream decoder) and the real live loop (``gtsjax.drivers.live.run_live``, as
``gtsjax run`` runs it), measured by the loop itself: from the moment a frame's last byte was read
(before decoding) to the moment its GTD rows were written and flushed.

Beside each case, the live step alone on the same frames, no sensor, no threads: called back to back,
and called once per sensor period with the thread asleep in between, as the live loop calls it. The
difference is what an idle period costs the next step, not the host loop; three more ways of spending
the period tell where it comes from (:data:`PAUSES`: busy-waiting, the caches emptied on purpose, the
caches kept warm by a throwaway step).

Two cases: the SPL field with a URG-04LX at 10 Hz (``spl-trajectory``, the shipped demo model), and
the lab with a UTM-30LX at 40 Hz with intensities (``lab-trajectory``, the benchmark's UTM model).
The step is compiled before the sensor streams, as ``gtsjax run`` does.
"""

import tempfile
import time
from pathlib import Path

import numpy as np

from gtsjax.drivers.live import run_live, warm_up
from gtsjax.io.serial import Link
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
                    label=f"live, frame read → GTD row flushed, {sensor.name} at {sensor.rate_hz:g} Hz",
                    sensor=sensor.name, rate_hz=sensor.rate_hz, duration_s=duration, frames=stats.frames,
                    rows=stats.rows, late=stats.late, bad_frames=link_stats.bad_frames, dropped=link_stats.dropped)
    ctx.results.checks[f"live.{key}"] = {"frames": stats.frames, "gtd_rows": stats.rows, "late_frames": stats.late,
                                         "expected_frames": int(duration * sensor.rate_hz)}


# How the step waits between calls in ``step_alone``: what an idle period costs, and why (issue 16,
# item 5). "sleep" is the live loop's way; "spin" busy-waits instead (the thread and the core never
# idle: a wake-up cost would vanish); "evict" sleeps after touching 64 MB (the caches emptied on
# purpose); "rewarm" spends the period stepping a throwaway copy of the state on the last frame (the
# step's code and constants kept in the caches).
PAUSES = ("sleep", "spin", "evict", "rewarm")


def step_alone(ctx, key: str, sensor, log, model, n: int) -> None:
    """The live step on ``n`` frames of ``log``: back to back, and once per ``sensor.period`` with
    the period spent each way of :data:`PAUSES`."""
    step, state0 = warm_up(model, sensor)
    frames = [(log.ranges[i % log.n_scans].astype(np.float64),
               None if log.intensities is None or not sensor.has_intensity else log.intensities[i % log.n_scans])
              for i in range(n)]
    dt = np.float32(sensor.period)
    big = np.zeros(64 * 2**20 // 8)
    cases = [("back_to_back", None, "back to back")] + [
        ("every_period" if p == "sleep" else f"every_period_{p}", p, f"once per period, the period spent: {p}")
        for p in PAUSES]
    for tag, pause, what in cases:
        state = state0
        out = np.empty(n)
        for i, (r, inten) in enumerate(frames):
            t0 = time.perf_counter()
            state, _, packed = step(state, r, inten, dt)
            np.asarray(packed)
            out[i] = time.perf_counter() - t0
            t = time.perf_counter()
            if pause == "sleep":
                time.sleep(sensor.period)
            elif pause == "evict":
                big += 1.0
                time.sleep(max(0.0, sensor.period - (time.perf_counter() - t)))
            elif pause in ("spin", "rewarm"):
                while time.perf_counter() - t < sensor.period:
                    if pause == "rewarm":
                        np.asarray(step(state, r, inten, dt)[2])
        ctx.results.add(f"live.{key}.step_{tag}", "ms", out[10:], section=SECTION,
                        label=f"live step alone, {sensor.name}, called {what}", sensor=sensor.name)


def run(ctx) -> None:
    duration = 3.0 if ctx.quick else 15.0
    log, site = _data.scenario("spl-trajectory", 7, 300)
    model = _data.demo_model(site)
    live_case(ctx, "urg-04lx_10hz", URG_04LX, log, model, duration)
    ulog, usite = _data.scenario("lab-trajectory", 5, 200 if ctx.quick else 600)
    umodel = _data.utm_model(usite, ctx.log, ctx.quick)
    live_case(ctx, "utm-30lx_40hz", UTM_30LX, ulog, umodel, duration)
    n = 20 if ctx.quick else 300  # the first 10 of each case are dropped (warm-up)
    step_alone(ctx, "urg-04lx_10hz", URG_04LX, log, model, n)
    step_alone(ctx, "utm-30lx_40hz", UTM_30LX, ulog, umodel, n)
