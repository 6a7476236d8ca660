"""The live loop, a driver: frames from the sensor link through the pipeline's ``step``, into the
GTD CSV (flushed per scan), optionally JSON lines on stdout or UDP, a raw recording, and a live view.

The loop owns nothing numeric: it hands each :class:`~gtsjax.io.serial.LinkFrame`'s ranges to the
step, writes rows, and measures latency from the moment the frame's last byte was read
(``LinkFrame.recv_perf``) to the moment its rows are flushed. Its skeleton is shared with the
several-laser loop's (:mod:`gtsjax.drivers.live_loop`); what is one laser's here is how its frames
are waited for (:class:`OneLink`).

What crosses between host and device per scan is kept small, since at 40 Hz the host's share of the
latency matters as much as the step's (:class:`LiveStep`): the frame goes in as one buffer, copied
as it came (the valid beams, the padding and the :class:`Scan` are worked out inside the compiled
function), and what comes back is one array with the GTD rows' fields (:func:`pack_tracks`); the
state and the full :class:`~gtsjax.Output` cross as one buffer per dtype, the output left on the
device until a view or a bag unpacks it.
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

from ..core.model import Model
from ..core.pipeline import Output, PipelineState, init_state, step
from ..core.scan import Scan, valid_beams
from ..errors import InputError
from ..io import scip
from ..io.gtd import PACKED, STATUS, format_rows, json_line, rows_from_table
from ..io.logs import frame_dt
from ..sensors import SensorModel
from .packing import Packing
from .setup import check_sensor as check_sensor

#: Bin edges (ms) of the whole-run latency histogram: 40 bins a decade from 10 µs to 100 s.
LATENCY_EDGES_MS = np.geomspace(1e-2, 1e5, 281)


@dataclasses.dataclass
class LiveStats:
    frames: int = 0
    rows: int = 0
    degraded: int = 0
    late: int = 0  # frames whose processing took longer than one scan period
    stale: int = 0  # frames that queued up before the loop began (compiling), let go unprocessed
    unlike: int = 0  # candidates dropped as unlike every training example of their class
    off_envelope: int = 0  # candidates outside their best class's shape envelope
    warm_ups: int = 0  # throwaway steps run just before a frame was due (``run_live``'s ``keep_warm``)
    track_ids: dict = dataclasses.field(default_factory=dict)  # class name -> ids of reported tracks (the sink's)
    latencies_ms: deque = dataclasses.field(default_factory=lambda: deque(maxlen=2000))
    # Every frame's latency since the start, binned (LATENCY_EDGES_MS; first and last bins open-ended).
    latency_counts: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(LATENCY_EDGES_MS.size + 1, np.int64))
    latency_max_ms: float = 0.0
    # Why the run reports what it does (:class:`~gtsjax.drivers.diagnose.Tally`, fed each frame's packed
    # table after its latency is taken); None outside the live loops.
    tally: object = None
    # ``run --beliefs``: per robot, what its beliefs came to (:func:`gtsjax.cli._live.beliefs_report`).
    beliefs: dict | None = None
    # ``run --smooth-lag``: the smoothed CSV's counters and the time it added per scan
    # (:class:`~gtsjax.drivers.fixed_lag.LagStats`); None without it.
    smoothing: object = None

    def add_latency(self, ms: float) -> None:
        self.latencies_ms.append(ms)
        self.latency_counts[int(np.searchsorted(LATENCY_EDGES_MS, ms))] += 1
        self.latency_max_ms = max(self.latency_max_ms, ms)

    def count(self, rows, lat_ms: float, degraded: bool, period_ms: float) -> None:
        """One processed frame: its rows, latency, whether its transform was degraded, late or not."""
        self.add_latency(lat_ms)
        self.frames += 1
        self.rows += len(rows)
        self.degraded += int(degraded)
        self.late += int(lat_ms > period_ms)

    def latency_quantile(self, q: float) -> float:
        """The ``q`` quantile of every latency since the start, to the histogram's resolution (the
        upper edge of its bin, at most 6 % above the value)."""
        n = int(self.latency_counts.sum())
        if n == 0:
            return float("nan")
        k = int(np.searchsorted(np.cumsum(self.latency_counts), q * n))
        return float(min(LATENCY_EDGES_MS[min(k, LATENCY_EDGES_MS.size - 1)], self.latency_max_ms))

    def latency(self) -> tuple[float, float]:
        """Median and p99 of the recent frame-to-GTD latencies, ms."""
        if not self.latencies_ms:
            return float("nan"), float("nan")
        a = np.asarray(self.latencies_ms)
        return float(np.median(a)), float(np.percentile(a, 99))


def frame_arrays(ranges_m: np.ndarray, intensities: np.ndarray | None, sensor: SensorModel, n_beams: int):
    """One frame's ranges, intensities and validity, padded to ``n_beams`` (beams past the frame's
    are padding), as the float32/bool NumPy arrays of a :class:`Scan`: on the host, what
    :class:`LiveStep` works out inside its compiled step from the frame as it came."""
    n = ranges_m.shape[0]
    valid = np.zeros(n_beams, bool)
    valid[:n] = valid_beams(ranges_m, sensor.range_min, sensor.range_max)
    r = np.zeros(n_beams, np.float32)
    r[:n] = np.where(valid[:n], ranges_m, 0.0)
    inten = np.zeros(n_beams, np.float32)
    if intensities is not None:
        inten[:n] = np.where(valid[:n], intensities, 0.0)
    return r, inten, valid


# Classes a status row's bit field of detected classes can hold (exact in float32 below 2^24).
_CLASS_BITS = 24


def pack_tracks(o: Output):
    """The GTD rows' fields of one output as a single ``[M + 1, 15]`` float32 array (the layout
    :data:`~gtsjax.io.gtd.PACKED`, defined beside its reader; track ids and classes are exact in
    float32 below 2^24), so that one transfer brings a scan's rows to the host, with what the run's
    diagnosis counts (each slot's live flag, hold and estimated motion:
    :mod:`gtsjax.drivers.diagnose`) and the identity each track reports from its tag (-1 for none, and
    for a model that reads no tags). The last row holds the scan's status
    (:data:`~gtsjax.io.gtd.STATUS`): degraded, objects, candidates unlike their class's examples,
    candidates outside their best class's envelope, and the classes detected in the scan as a bit
    field (bit ``c``: class ``c``, for the first 24 classes)."""
    f32 = jnp.float32
    pose, var = o.track_pose.astype(f32), o.track_var.astype(f32)
    columns = {"track_id": o.track_id, "class": o.track_class, "x": pose[:, 0], "y": pose[:, 1], "theta": pose[:, 2],
               "var_x": var[:, 0], "var_y": var[:, 1], "var_theta": var[:, 2], "cov_xy": o.track_cov_xy,
               "reported": o.track_mask, "live": o.track_live, "hold": o.track_hold, "speed": o.track_speed,
               "turn_rate": o.track_turn_rate,
               "robot": robot if (robot := getattr(o, "track_robot", None)) is not None else jnp.full_like(o.track_id, -1)}
    tracks = jnp.stack([columns[c].astype(f32) for c in PACKED], axis=1)
    bit = jnp.arange(_CLASS_BITS, dtype=jnp.int32)
    seen = jnp.any(o.det_mask[:, None] & (o.det_class[:, None] == bit[None, :]), axis=0)
    detected = jnp.sum(jnp.where(seen, jnp.left_shift(1, bit), 0), dtype=jnp.int32)
    fields = {"degraded": o.degraded, "n_objects": o.n_objects, "unlike": o.unlike, "off_envelope": o.off_envelope,
              "detected": detected}
    status = jnp.zeros((1, len(PACKED)), f32).at[0, :len(STATUS)].set(jnp.stack([fields[f].astype(f32) for f in STATUS]))
    return jnp.concatenate([tracks, status], axis=0)


class LiveStep:
    """The live step for one model and scanner, jitted once with the model closed over (a constant of
    the compiled program: a call does not flatten the model's hundred-odd arrays on the host, a third
    of a step's time on a 2-core laptop): the pipeline's ``step`` on one frame.

    ``step(state, ranges_m, intensities, dt) -> (state, output, packed)``, with the frame as the link
    delivers it (:class:`~gtsjax.io.serial.LinkFrame`: its ranges in metres, its intensities or
    ``None``, at most the model's ``n_beams``). What crosses the call is kept to a few buffers, each
    costing the call some microseconds on the host whatever its size: the frame goes in as one
    float32 buffer, copied as it came (which beams hold a return, :func:`~gtsjax.core.scan.valid_beams`,
    and the padding are worked out inside the compiled step); the state and the output cross as one
    buffer per dtype (:class:`~gtsjax.drivers.packing.Packing`: 3 each way instead of 21 and 28
    arrays). The state is opaque between calls (start from :meth:`initial_state`, read it with
    :meth:`pipeline_state`); the output stays on the device until :meth:`output` unpacks it;
    ``packed`` is :func:`pack_tracks`'s array, what the GTD rows need."""

    def __init__(self, model: Model, sensor: SensorModel, *, state0=None, core=None, extras: int = 0,
                 filtered: bool = False):
        """``core(state, scan, extra) -> (state, output)``: the pipeline's step (by default ``step``
        from :func:`~gtsjax.core.pipeline.init_state`'s state, or ``state0``), ``extra`` the
        ``extras`` float32 values a call passes after ``dt`` (the several-laser step's laser index and
        time span, :mod:`gtsjax.drivers.live_several`). ``filtered``: ``packed`` also carries the
        track table's filtered state after the scan, columns after :func:`pack_tracks`'s
        (:func:`~gtsjax.drivers.fixed_lag.pack_filtered`; zeros in the status row), for the
        fixed-lag smoother (``run --smooth-lag``): in the same transfer as the rows."""
        from .fixed_lag import pack_filtered

        self.model, self.sensor, self.extras, self.filtered = model, sensor, extras, filtered
        angle_min = jnp.asarray(sensor.angle_min, jnp.float32)
        angle_increment = jnp.asarray(sensor.angle_increment, jnp.float32)
        state0 = init_state(model) if state0 is None else state0
        core = core or (lambda state, scan, extra: step(model, state, scan))
        self.state_layout = Packing.of(state0)
        n = model.n_beams

        # Jitted so that ``live_step`` finds the trace ``eval_shape`` made of it (JAX caches a jitted
        # function's trace by its arguments' shapes): the step is traced once at start-up, not twice.
        @jax.jit
        def run(state, frame):
            raw, dt = frame[:2 * n].reshape(2, n), frame[2 * n]
            valid = valid_beams(raw[0], sensor.range_min, sensor.range_max)
            ranges, intensities = jnp.where(valid[None], raw, 0.0)
            scan = Scan(ranges, intensities, valid, angle_min, angle_increment, dt)
            return core(state, scan, frame[2 * n + 1:])

        frame = jax.ShapeDtypeStruct((2 * n + 1 + extras,), jnp.float32)
        self.output_layout = Packing.of(jax.eval_shape(run, state0, frame)[1])

        @jax.jit
        def live_step(state, frame):
            new, o = run(self.state_layout.unpack(state), frame)
            packed = pack_tracks(o)
            if filtered:
                block = pack_filtered(new.tracker)
                packed = jnp.concatenate([packed, jnp.pad(block, ((0, 1), (0, 0)))], axis=1)
            return self.state_layout.pack(new), self.output_layout.pack(o), packed

        self.jitted = live_step
        self._state0 = self.state_layout.pack(state0)
        self._last = None

    def initial_state(self):
        """The state before the first frame (:func:`~gtsjax.core.pipeline.init_state`), packed."""
        return self._state0

    def frame(self, ranges_m: np.ndarray, intensities: np.ndarray | None, dt: float, *extra: float) -> np.ndarray:
        """The step's frame buffer: ranges (m) then intensities, each padded with zeros to the model's
        ``n_beams``, then ``dt`` and the ``extra`` values. A new array each call: on a CPU the
        device may read it in place while the call is in flight."""
        n = self.model.n_beams
        k = ranges_m.shape[0]
        if k > n:
            raise ValueError(f"a frame of {k} beams, more than the model's {n}")
        if len(extra) != self.extras:
            raise ValueError(f"{len(extra)} extra values after dt, the step takes {self.extras}")
        buf = np.zeros(2 * n + 1 + self.extras, np.float32)
        buf[:k] = ranges_m
        if intensities is not None:
            buf[n:n + k] = intensities
        buf[2 * n:] = (dt, *extra)
        return buf

    def __call__(self, state, ranges_m, intensities, dt, *extra):
        self._last = self.frame(ranges_m, intensities, dt, *extra)
        return self.jitted(state, self._last)

    def warm(self, state) -> None:
        """Run the step once more on the last frame from ``state``, throwing the result away, and wait
        for it: the step's code and constants back in the caches, and the core awake, for the next
        frame (see :func:`run_live`'s ``keep_warm``). Nothing changes: the step is a pure function."""
        if self._last is not None:
            jax.block_until_ready(self.jitted(state, self._last)[2])

    def pipeline_state(self, state) -> PipelineState:
        """A packed state as the pipeline's :class:`~gtsjax.core.pipeline.PipelineState` (NumPy arrays)."""
        return self.state_layout.unpack_host(state)

    def output(self, packed_output) -> Output:
        """A step's packed output as the pipeline's :class:`~gtsjax.Output` (NumPy arrays)."""
        return self.output_layout.unpack_host(packed_output)


def warm_up_lead(step_s, period: float) -> float:
    """How long before a frame is due its warm-up runs (``keep_warm``): twice a recent step's time
    (``step_s``, seconds) plus 2 ms, so that it ends well before the frame; at most half the period."""
    return min(0.002 + 2.0 * float(np.median(step_s)), 0.5 * period)


def decoder_sample(link) -> bytes | None:
    """A data block of the kind ``link`` streams (its ``command``: ``MD`` or ``ME``, its sensor's
    beams), for :func:`warm_host` to decode; ``None`` for a link that says neither."""
    command, sensor = getattr(link, "command", None), getattr(link, "model", None)
    if not isinstance(command, bytes) or sensor is None:
        return None
    try:
        echo = scip.parse_command(command.rstrip(b"\n")).with_remaining(0)
        n = echo.n_values or sensor.n_beams
        return scip.format_md_frame(echo, 0, np.full(n, 1500), np.full(n, 800) if echo.code == "ME" else None)
    except scip.ScipError:
        return None


def warm_host(live_step: "LiveStep", last, class_names, sample: bytes | None = None,
              robot_names: "tuple[str, ...]" = ()) -> None:
    """The host's part of a frame's path, run on the last frame and thrown away (``last``: its
    :class:`~gtsjax.io.serial.LinkFrame` and its packed rows as a list; nothing before the first):
    the decoding of a data block like the link's (``sample``, :func:`decoder_sample`, by a decoder of
    its own), the frame's ranges in metres, the step's frame buffer, its rows and their CSV text. The
    live loop runs it after :meth:`LiveStep.warm`: with the core idle between frames, the host's
    code (NumPy's above all) leaves the caches as the step's does, and the next frame's few NumPy
    calls before the step, and the reader thread's decoding, would each pay for bringing it back
    (measured in ``docs/speed.md``)."""
    if sample is not None:
        scip.StreamDecoder().feed(sample)
    if last is None:
        return
    lf, table = last
    live_step.frame(lf.ranges_m, lf.intensities, 0.0, *(0.0,) * live_step.extras)
    format_rows(rows_from_packed(lf.stamp, table, class_names, robot_names), robot=bool(robot_names))


def rows_from_packed(stamp: float, packed: "np.ndarray | list", class_names, robot_names: "tuple[str, ...]" = ()) -> list:
    """GTD rows from :func:`pack_tracks`'s array, or its ``tolist()`` (reported tracks, in id order,
    named with ``robot_names``, a model's ``tag_names``, where their tracks report one):
    :func:`~gtsjax.io.gtd.rows_from_table` of its track rows.

    The live loop passes the ``tolist()``, made once: on its path right after the step, when the
    interpreter's code has left the caches, each NumPy call costs about ten times what it does in a
    tight loop, so the conversion is plain Python on one list."""
    table = packed.tolist() if isinstance(packed, np.ndarray) else packed
    return rows_from_table(stamp, table[:-1], class_names, robot_names)


def udp_address(udp: str) -> tuple[str, int]:
    """``HOST:PORT`` of ``--udp`` as a socket address, checked: a port in 1–65535 and a host that
    resolves (a mistake is one line, before the sensor is opened)."""
    host, _, port = udp.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise InputError(udp, "UDP address must be HOST:PORT, PORT in 1–65535")
    try:
        socket.getaddrinfo(host, int(port), socket.AF_INET, socket.SOCK_DGRAM)
    except OSError as err:
        raise InputError(udp, f"cannot resolve the host {host!r} ({err.strerror or err})") from None
    return host, int(port)


class Outputs:
    """Where each scan's rows go besides the CSV: JSON lines on stdout and/or a UDP address; and the
    CSV's form (``csv_units``: the optional header with units and ``cov_xy``, :mod:`gtsjax.io.gtd`)."""

    def __init__(self, json_stdout: bool = False, udp: str | None = None, csv_units: bool = False):
        self.json_stdout, self.csv_units = json_stdout, csv_units
        self.sock = None
        self.addr = None
        if udp:
            self.addr = udp_address(udp)
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


def warm_up(model: Model, sensor: SensorModel, filtered: bool = False):
    """The live step for ``model`` on ``sensor``'s frames, compiled before the first real frame so
    that the first latency is not a compile; and the initial state. ``filtered``: see :class:`LiveStep`."""
    live_step = LiveStep(model, sensor, filtered=filtered)
    state = live_step.initial_state()
    jax.block_until_ready(live_step(state, np.zeros(sensor.n_beams, np.float32), None, 0.0))
    return live_step, state


class OneLink:
    """One laser's frames for the live loop (:func:`~gtsjax.drivers.live_loop.run_loop`), read as its
    link delivers them: with ``keep_warm`` (``warm``, a :class:`~gtsjax.drivers.live_loop.KeepWarm`)
    the frame is waited for until shortly before it is due, a warm-up run if it has not come, then
    waited for again; a link that has been reconnecting over ``reconnect_timeout`` seconds ends the
    run (``gone``)."""

    needs_output = False

    def __init__(self, link, live_step: LiveStep, stats: LiveStats, warm, reconnect_timeout: float | None):
        self.link, self.step, self.stats, self.warm = link, live_step, stats, warm
        self.reconnect_timeout = reconnect_timeout
        self.prev_stamp = None
        self.gone = None

    def next(self, state):
        link, warm, lf = self.link, self.warm, None
        if warm is not None and warm.due[0] is not None:  # the next frame is due then: wait until shortly before
            ahead = warm.due[0] - warm.lead - time.perf_counter()
            warm.due[0] = None  # one warm-up per frame: a sensor that stalls is waited for idle
            if ahead > 0:
                lf = link.get(timeout=ahead)
                if lf is None:
                    warm.warm(0, self.step, state)
        if lf is None:
            lf = link.get(timeout=0.2)
        if lf is None:
            lost = link.lost_for() if hasattr(link, "lost_for") else 0.0
            if self.reconnect_timeout is not None and lost > self.reconnect_timeout:
                self.gone = InputError(str(getattr(link, "port", "sensor")),
                                       f"the sensor has been gone for {lost:.0f} s and did not come back "
                                       f"({getattr(link, 'last_error', None) or 'no frames'}; "
                                       "--reconnect-timeout waits longer)")
            return None
        dt = frame_dt(lf.stamp, self.prev_stamp)
        self.prev_stamp = lf.stamp
        return lf, 0, self.step, (dt,)

    def count(self, k, lf, o, table, lat: float, degraded: bool) -> None:
        """Nothing of one link's own: the run's counts (``run_loop``) are all there is."""


def run_live(link, model: Model, out: Path, *, record: Path | None = None, outputs: Outputs | None = None,
             duration: float | None = None, stop: threading.Event | None = None, on_scan=None,
             with_intensity: bool = False, compiled=None, max_frames: int | None = None,
             out_bag: Path | None = None, view=None, keep_warm: bool = True,
             reconnect_timeout: float | None = None, sensor_checked: bool = False, identity=None,
             smooth_lag: float | None = None, smoothed_out: Path | None = None) -> LiveStats:
    """Track from a started :class:`~gtsjax.io.serial.Link` until ``duration`` seconds, ``max_frames``
    frames processed, ``stop`` set, or Ctrl-C; then stop the link (QT) and finalise the recording.
    ``on_scan(stats, output, stamp)`` is called after each scan (the live view; ``output`` is the
    step's full output, unpacked on the host only when a consumer asks for it).
    ``compiled``: ``(step, state)`` from :func:`warm_up`, done before the link started streaming.
    ``out_bag``: also a ROS 2 bag of the frames, laser poses and tracks (:mod:`gtsjax.io.bag_out`),
    written after each frame's latency is taken; ``view``: a :class:`~gtsjax.viewer.View` shown each
    frame (after the latency is taken; closed at the end). ``reconnect_timeout``: a link that has been
    reconnecting this many seconds (the sensor unplugged, its pty gone) ends the run with one line
    (:class:`InputError`) after what was written is closed, instead of retrying for ever.
    ``sensor_checked``: the caller has checked the link's sensor against the model
    (:func:`~gtsjax.drivers.setup.check_sensor`), which is otherwise done here first.
    ``identity``: the robots' names from their beliefs (``run --beliefs``,
    :class:`~gtsjax.grade.online.OnlineIdentity`): the CSV's ``robot`` column.
    ``smooth_lag``: also the fixed-lag smoothed CSV (:mod:`gtsjax.drivers.fixed_lag`), each row this
    many seconds late (in scans of the sensor's rate, at least one), at ``smoothed_out`` (by default
    :func:`~gtsjax.drivers.fixed_lag.smoothed_path` of ``out``); ``compiled`` must then be
    :func:`warm_up`'s with ``filtered``.

    ``keep_warm``: a few milliseconds before each frame is due (the last one's arrival plus the
    sensor's period), if it has not come, the step runs once on the last frame and its result is
    thrown away (:meth:`LiveStep.warm`), and so does the host's part of a frame's path
    (:func:`warm_host`: a data block decoded, the frame buffer, the rows and their CSV text), so that
    the frame finds the step's code and constants, and NumPy's, in the caches and the core awake:
    it leaves the median latency as it is and lowers the p99 (``scripts/ab_keep_warm.py``, figures
    in ``docs/speed.md``). The cost is one more step per frame, a few per cent of a core.

    The loop is :func:`~gtsjax.drivers.live_loop.run_loop`'s, with this link's frames (:class:`OneLink`)."""
    from ..io.bag_out import LASER
    from .live_loop import LiveSession, run_loop

    sensor = link.model
    if not sensor_checked:
        check_sensor(model, sensor, str(getattr(link, "port", "sensor")), intensity=with_intensity)
    live_step, state = compiled if compiled is not None else warm_up(model, sensor, filtered=smooth_lag is not None)
    smooth = None
    if smooth_lag is not None:
        from .fixed_lag import lag_scans, smoothed_path

        if not live_step.filtered:
            raise ValueError("run_live with smooth_lag needs warm_up(..., filtered=True)'s step")
        smooth = (lag_scans(smooth_lag, sensor.rate_hz), smoothed_out or smoothed_path(out))
    session = LiveSession({LASER: link}, model, out, named=False, record={LASER: record} if record else None,
                          outputs=outputs, with_intensity=with_intensity, out_bag=out_bag, view=view, on_scan=on_scan,
                          keep_warm=keep_warm, duration=duration, stop=stop, max_frames=max_frames,
                          identity=identity, smooth=smooth)
    stats, recorder = session.stats, session.recorders[0]
    frames = OneLink(link, live_step, stats, session.warm, reconnect_timeout)
    failed = run_loop(session, frames, state)
    if failed is not None:
        kept = (f"; the raw scans are in {recorder.journal} (gtsjax recover it when there is room)"
                if recorder is not None and failed.where != str(recorder.journal) else "")
        raise InputError(failed.where, f"{failed.problem}; stopped after {stats.frames} frames{kept}")
    if frames.gone is not None:
        kept = f" and the raw scans in {record}" if recorder is not None else ""
        raise InputError(frames.gone.where, f"{frames.gone.problem}; stopped after {stats.frames} frames, their rows "
                                            f"kept in {out}{kept}")
    return stats


def summary_json(stats: LiveStats, link_stats) -> str:
    """The counters of a live run as one JSON object (``gtsjax run --summary``): frames, rows, the
    recent latency (``latency_ms_*``, last 2 000 frames) and the whole run's (``latency_ms_run_*``,
    binned), late and degraded scans, tracks per class, the link's counters by cause (its
    ``frames``, the frames it delivered, as ``received``: ``frames`` is those processed), and the
    run's ``diagnosis`` (:mod:`gtsjax.drivers.diagnose`); with ``--beliefs``, ``beliefs``: per robot,
    poses received, malformed lines, the share of its time named on a track; with ``--smooth-lag``,
    ``smoothing``: the lag in scans, the smoothed CSV, its rows and the time the smoothing added per
    scan (median, p99, ms)."""
    med, p99 = stats.latency()
    link = dataclasses.asdict(link_stats)
    link["received"] = link.pop("frames")
    return json.dumps({"frames": stats.frames, "rows": stats.rows, "latency_ms_median": med, "latency_ms_p99": p99,
                       "latency_ms_run_median": stats.latency_quantile(0.5),
                       "latency_ms_run_p99": stats.latency_quantile(0.99),
                       "latency_ms_run_p999": stats.latency_quantile(0.999), "latency_ms_max": stats.latency_max_ms,
                       "late": stats.late, "stale": stats.stale, "degraded": stats.degraded, "unlike": stats.unlike,
                       "off_envelope": stats.off_envelope, "warm_ups": stats.warm_ups,
                       "tracks": {c: len(ids) for c, ids in sorted(stats.track_ids.items())},
                       **link, "diagnosis": stats.tally.finish() if stats.tally is not None else None,
                       **({"beliefs": stats.beliefs} if stats.beliefs is not None else {}),
                       **({"smoothing": stats.smoothing.as_dict()} if stats.smoothing is not None else {})})
