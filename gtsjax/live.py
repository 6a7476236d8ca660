"""The live loop: frames from the sensor link through the same jitted ``step`` as replay, into the
GTD CSV (flushed per scan), optionally JSON lines on stdout or UDP, a raw recording, and a live view.

The loop owns nothing numeric: it turns each :class:`~gtsjax.io.serial.LinkFrame` into a padded
:class:`~gtsjax.Scan`, calls ``step``, writes rows, and measures latency from the moment the frame's
last byte was decoded (``LinkFrame.recv_perf``) to the moment its rows are flushed.
"""

import dataclasses
import json
import socket
import sys
import threading
import time
from collections import deque
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ._pipeline import init_state, make_step
from ._scan import Scan
from .errors import InputError
from .io.gtd import GTDWriter, json_line, rows_from_output
from .model import Model
from .sensors import SensorModel


@dataclasses.dataclass
class LiveStats:
    frames: int = 0
    rows: int = 0
    degraded: int = 0
    late: int = 0  # frames whose processing took longer than one scan period
    latencies_ms: deque = dataclasses.field(default_factory=lambda: deque(maxlen=2000))

    def latency(self) -> tuple[float, float]:
        """Median and p99 of the recent frame-to-GTD latencies, ms."""
        if not self.latencies_ms:
            return float("nan"), float("nan")
        a = np.asarray(self.latencies_ms)
        return float(np.median(a)), float(np.percentile(a, 99))


def frame_to_scan(ranges_m: np.ndarray, intensities: np.ndarray | None, sensor: SensorModel, n_beams: int,
                  dt: float) -> Scan:
    """One frame as the padded scan the step takes (beams past the frame's are padding)."""
    n = ranges_m.shape[0]
    r = np.zeros(n_beams, np.float32)
    r[:n] = ranges_m
    valid = np.zeros(n_beams, bool)
    valid[:n] = (ranges_m >= sensor.range_min) & (ranges_m <= sensor.range_max) & np.isfinite(ranges_m)
    r = np.where(valid, r, 0.0).astype(np.float32)
    inten = np.zeros(n_beams, np.float32)
    if intensities is not None:
        inten[:n] = np.where(valid[:n], intensities, 0.0)
    return Scan(jnp.asarray(r), jnp.asarray(inten), jnp.asarray(valid), jnp.asarray(sensor.angle_min, jnp.float32),
                jnp.asarray(sensor.angle_increment, jnp.float32), jnp.asarray(dt, jnp.float32))


def check_sensor(model: Model, sensor: SensorModel, where: str) -> None:
    if model.sensor_model not in (sensor.name, "unknown") or sensor.n_beams > model.n_beams:
        raise InputError(where, f"the model was trained for {model.sensor_model} ({model.n_beams} beams) but the sensor "
                                f"is a {sensor.name} ({sensor.n_beams} beams)")


class Outputs:
    """Where each scan's rows go besides the CSV: JSON lines on stdout and/or a UDP address."""

    def __init__(self, json_stdout: bool = False, udp: str | None = None):
        self.json_stdout = json_stdout
        self.sock = None
        self.addr = None
        if udp:
            host, _, port = udp.rpartition(":")
            if not host or not port.isdigit():
                raise InputError(udp, "UDP address must be HOST:PORT")
            self.addr = (host, int(port))
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, rows, stamp, **extra) -> None:
        if not (self.json_stdout or self.sock):
            return
        line = json_line(rows, stamp, **extra)
        if self.json_stdout:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        if self.sock is not None:
            try:
                self.sock.sendto(line.encode(), self.addr)
            except OSError:
                pass  # a receiver that is not there must not stop the ground truth

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()


def warm_up(model: Model, sensor: SensorModel):
    """The step for ``model``, compiled before the first real frame so that the first latency is not a
    compile; and the initial state."""
    state = init_state(model)
    step = make_step(model)
    scan = frame_to_scan(np.zeros(sensor.n_beams, np.float32), None, sensor, model.n_beams, 0.0)
    jax.block_until_ready(step(state, scan))
    return step, state


def run_live(link, model: Model, out: Path, *, record: Path | None = None, outputs: Outputs | None = None,
             duration: float | None = None, stop: threading.Event | None = None, on_scan=None,
             with_intensity: bool = False, compiled=None) -> LiveStats:
    """Track from a started :class:`~gtsjax.io.serial.Link` until ``duration`` seconds, ``stop`` is set,
    or Ctrl-C. ``on_scan(stats, output, stamp)`` is called after each scan (the live view).
    ``compiled``: ``(step, state)`` from :func:`warm_up`, done before the link started streaming."""
    from .io.record import Recorder

    sensor = link.model
    check_sensor(model, sensor, str(getattr(link, "port", "sensor")))
    step, state = compiled if compiled is not None else warm_up(model, sensor)
    while link.get(timeout=0) is not None:  # frames that queued up while compiling are stale
        pass
    stats = LiveStats()
    outputs = outputs or Outputs()
    recorder = Recorder(record, model=sensor, intensities=with_intensity and sensor.has_intensity) if record else None
    t_end = None if duration is None else time.monotonic() + duration
    prev_stamp = None
    try:
        with GTDWriter(out) as writer:
            while not (stop is not None and stop.is_set()) and (t_end is None or time.monotonic() < t_end):
                lf = link.get(timeout=0.2)
                if lf is None:
                    continue
                if recorder is not None:
                    recorder.append_frame(lf)
                dt = 0.0 if prev_stamp is None else max(0.0, lf.stamp - prev_stamp)
                prev_stamp = lf.stamp
                scan = frame_to_scan(lf.ranges_m, lf.intensities, sensor, model.n_beams, dt)
                state, o = step(state, scan)
                o = jax.device_get(o)
                rows = rows_from_output(lf.stamp, o.track_id, o.track_class, o.track_pose, o.track_var, o.track_mask,
                                        model.classes)
                writer.write(rows)
                outputs.send(rows, lf.stamp, degraded=bool(o.degraded))
                lat = (time.perf_counter() - lf.recv_perf) * 1000.0
                stats.latencies_ms.append(lat)
                stats.frames += 1
                stats.rows += len(rows)
                stats.degraded += int(o.degraded)
                stats.late += int(lat > sensor.period * 1000.0)
                if on_scan is not None:
                    on_scan(stats, o, lf.stamp)
    except KeyboardInterrupt:
        pass
    finally:
        outputs.close()
        if recorder is not None:
            recorder.close()
    return stats


def summary_json(stats: LiveStats, link_stats) -> str:
    med, p99 = stats.latency()
    return json.dumps({"frames": stats.frames, "rows": stats.rows, "latency_ms_median": med, "latency_ms_p99": p99,
                       "late": stats.late, "degraded": stats.degraded, **dataclasses.asdict(link_stats)})
