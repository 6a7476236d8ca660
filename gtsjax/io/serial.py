"""The live link to a Hokuyo scanner: pyserial, a reader thread, reconnection, and sensor-to-host time.

Why a thread and a bounded queue: the tracker must always work on the newest scan. The reader
thread does nothing but read bytes, decode them (:class:`~gtsjax.io.scip.StreamDecoder`) and put
each :class:`LinkFrame` into a ``queue.Queue`` of ``queue_size`` frames; when the consumer falls
behind the *oldest* frame is dropped and counted, so latency stays bounded by the queue length.

Handshake (:meth:`Link.start`, and again after every reconnect): ``QT`` (stop whatever a previous
session left streaming; a SCIP 1.1 sensor answers ``E`` and is then sent ``SCIP2.0``), ``SCIP2.0``
(any status), optionally ``RS``, ``VV`` (kept as :attr:`Link.version`), ``PP`` (its reply builds
:attr:`Link.model` via :func:`~gtsjax.io.scip.sensor_model_from_pp`), then ``MD`` over the model's
whole step range, or ``ME`` when ``intensity`` is asked for and the model reports it, with count 0
(stream until ``QT``). Replies are matched to requests by their echo, so stale data blocks from an
earlier session are skipped, never mistaken for an answer.

Faults are never fatal: a frame that fails its sums, is cut short or is malformed is dropped and
counted (the decoder's counters); the decoder resynchronises on the next echo. No frame for more than
``timeout_periods`` scan periods (a stall), or an I/O error or EOF (an unplugged cable; pyserial
raises ``SerialException``/``OSError``), closes the port and reconnects: open, handshake, resume,
with exponential back-off between failed attempts (``backoff_s`` doubling up to ``backoff_max_s``).

Time (:class:`ClockSync`): each frame carries the host's ``time.time()`` and ``time.perf_counter()``
at the moment its last byte was decoded, and ``stamp``, the sensor's timestamp mapped to host time.
"""

import collections
import dataclasses
import queue
import threading
import time
from collections.abc import Iterator

import numpy as np
import serial

from ..errors import InputError
from ..sensors import SensorModel
from . import scip


class LinkError(InputError):
    """The port cannot be opened, or what answers on it is not a SCIP 2.0 scanner."""


@dataclasses.dataclass
class LinkStats:
    """Counters of a :class:`Link`, cumulative over reconnects (a snapshot from :attr:`Link.stats`).

    ``dropped`` counts frames discarded because the queue was full (the consumer fell behind);
    ``checksum_errors``, ``truncated``, ``malformed`` count frames lost on the wire; ``salvaged``
    frames delivered without the beams of a data line that failed its sum (the frame's other lines
    intact: see :class:`~gtsjax.io.scip.StreamDecoder`); ``timeouts``
    the periods without frames that forced a reconnect; ``reconnects`` the successful re-handshakes;
    ``sensor_errors`` replies with an error status while streaming.
    """

    frames: int = 0
    dropped: int = 0
    salvaged: int = 0
    checksum_errors: int = 0
    truncated: int = 0
    malformed: int = 0
    garbage_bytes: int = 0
    reconnects: int = 0
    timeouts: int = 0
    io_errors: int = 0
    sensor_errors: int = 0
    last_error: str | None = None

    @property
    def bad_frames(self) -> int:
        return self.checksum_errors + self.truncated + self.malformed


@dataclasses.dataclass(frozen=True, eq=False)
class LinkFrame:
    """One decoded scan with its times.

    ``stamp``: host time (epoch seconds) of the scan, from :class:`ClockSync`. ``recv_time`` /
    ``recv_perf``: ``time.time()`` / ``time.perf_counter()`` when its last byte was read (before decoding).
    ``sensor_ms``: the sensor's unwrapped millisecond count. ``seq``: order of arrival (0, 1, ...).
    """

    frame: scip.ScanFrame
    stamp: float
    recv_time: float
    recv_perf: float
    sensor_ms: int
    seq: int

    @property
    def ranges_m(self) -> np.ndarray:
        """Ranges in metres, float32, 0 where there is no return (the millimetres in float32 divided
        by 1000 in float32, in one NumPy call: the live loop's path)."""
        return np.divide(self.frame.ranges_mm, np.float32(1000.0), dtype=np.float32)

    @property
    def intensities(self) -> np.ndarray | None:
        i = self.frame.intensities
        return None if i is None else i.astype(np.float32)


class ClockSync:
    """Maps the sensor's wrapping 24-bit millisecond stamps to host time.

    The sensor time ``s`` (unwrapped by :class:`~gtsjax.io.scip.TimestampUnwrapper`) and the host
    receive time ``h`` of each frame differ by the clock offset plus the transport delay, and the
    delay is never negative. So the offset is estimated as ``min(h - s)`` over the last ``window``
    frames: one frame that got through quickly pins it, late frames (USB scheduling, a busy host)
    cannot pull it, and the sliding window follows the slow drift between the two crystals
    (~50 ppm, 0.25 ms over 5 s). The host stamp of a frame is ``s + offset``: the scan's time on the
    host clock, late by the minimum transport delay, which no one-way link can measure.
    """

    def __init__(self, window: int = 200):
        self.window = int(window)
        self._unwrap = scip.TimestampUnwrapper()
        self._diffs: collections.deque[float] = collections.deque(maxlen=self.window)
        self.offset: float | None = None
        self.last_sensor_ms: int | None = None

    def reset(self) -> None:
        """Forget everything (a reconnected sensor may have restarted its clock)."""
        self._unwrap.reset()
        self._diffs.clear()
        self.offset = None
        self.last_sensor_ms = None

    def update(self, stamp_ms: int, host_time: float) -> float:
        """Take one frame's raw 24-bit stamp and host receive time; return its host-time stamp."""
        ms = self._unwrap.update(stamp_ms)
        self.last_sensor_ms = ms
        s = ms / 1000.0
        self._diffs.append(host_time - s)
        self.offset = min(self._diffs)
        return s + self.offset


class Link:
    """A streaming connection to a scanner on ``port`` (anything ``serial.serial_for_url`` opens).

    ``start()`` connects and handshakes in the caller's thread (raising :class:`LinkError` when that
    fails), then hands over to the reader thread. Read frames with :meth:`get` or iterate
    :meth:`frames`. ``stop()`` sends ``QT``, closes the port and joins the thread.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        intensity: bool = False,
        queue_size: int = 8,
        timeout_periods: float = 10.0,
        min_timeout_s: float = 0.5,
        reply_timeout_s: float = 1.0,
        backoff_s: float = 0.1,
        backoff_max_s: float = 2.0,
        reset: bool = False,
        clock_window: int = 200,
    ):
        self.port = str(port)
        self.baudrate = int(baudrate)
        self.intensity = bool(intensity)
        self.timeout_periods = float(timeout_periods)
        self.min_timeout_s = float(min_timeout_s)
        self.reply_timeout_s = float(reply_timeout_s)
        self.backoff_s = float(backoff_s)
        self.backoff_max_s = float(backoff_max_s)
        self.reset = bool(reset)
        self.queue: queue.Queue[LinkFrame] = queue.Queue(maxsize=max(1, int(queue_size)))
        self.clock = ClockSync(clock_window)
        self.model: SensorModel | None = None
        self.version: dict[str, str] = {}
        self.command: bytes | None = None
        self._ser: serial.SerialBase | None = None
        self._decoder = scip.StreamDecoder()
        self._lock = threading.Lock()
        self._stats = LinkStats()
        self._base = scip.StreamStats()  # counters of decoders of earlier connections
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._last_frame = 0.0
        self._lost_at: float | None = None  # monotonic time the connection was lost; None while connected

    # ------------------------------------------------------------------ public

    def start(self) -> "Link":
        """Connect and handshake (raises :class:`LinkError`), then start the reader thread."""
        if self._thread is not None:
            return self
        try:
            self._connect()
        except (serial.SerialException, OSError) as err:
            self._close()
            raise LinkError(self.port, f"cannot open the port ({err})") from None
        except LinkError:
            self._close()
            raise
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="gtsjax-serial", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop streaming (``QT``), close the port, join the reader thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)
            self._thread = None
        self._close(send_qt=True)

    def __enter__(self) -> "Link":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def get(self, timeout: float | None = None) -> LinkFrame | None:
        """The oldest queued frame, waiting up to ``timeout`` seconds; ``None`` if none came."""
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def frames(self, poll_s: float = 0.1) -> Iterator[LinkFrame]:
        """Frames as they come, until :meth:`stop`."""
        while not self._stop.is_set():
            f = self.get(timeout=poll_s)
            if f is not None:
                yield f

    @property
    def stats(self) -> LinkStats:
        """A snapshot of the counters."""
        with self._lock:
            d = self._decoder.stats
            b = self._base
            return dataclasses.replace(
                self._stats,
                checksum_errors=b.checksum_errors + d.checksum_errors,
                salvaged=b.salvaged + d.salvaged,
                truncated=b.truncated + d.truncated,
                malformed=b.malformed + d.malformed + b.oversize + d.oversize,
                garbage_bytes=b.garbage_bytes + d.garbage_bytes,
            )

    @property
    def frame_timeout_s(self) -> float:
        """No frame for this long means the link is stalled."""
        period = self.model.period if self.model is not None else 0.1
        return max(self.timeout_periods * period, self.min_timeout_s)

    # ------------------------------------------------------------------ connection

    def _new_decoder(self) -> None:
        with self._lock:
            self._decoder.reset()  # a frame cut off by the reconnect is counted (truncated), not lost silently
            d = self._decoder.stats
            for f in dataclasses.fields(scip.StreamStats):
                setattr(self._base, f.name, getattr(self._base, f.name) + getattr(d, f.name))
            self._decoder = scip.StreamDecoder()

    def _connect(self) -> None:
        self._close()
        self._new_decoder()
        ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.02, write_timeout=1.0)
        self._ser = ser
        try:
            ser.reset_input_buffer()
        except (serial.SerialException, OSError, AttributeError):
            pass
        # QT first stops a stream left running; a SCIP 1.1 sensor answers it with one character and
        # SCIP2.0 switches it over, while a SCIP 2.0 one acknowledges SCIP2.0 with any status.
        self._request(scip.qt_command())
        self._request(scip.scip2_command())
        if self.reset:
            self._request(scip.rs_command())
        vv = self._request(scip.vv_command())
        try:
            self.version = vv.fields
        except scip.ScipError:
            self.version = {}
        pp = self._request(scip.pp_command())
        try:
            model = scip.sensor_model_from_pp(pp)
        except InputError as err:
            raise LinkError(self.port, f"bad PP reply ({err.problem})") from None
        if self.model is not None and (model.amin, model.amax) != (self.model.amin, self.model.amax):
            # Another scanner was plugged in: frames of a different width would break the consumer.
            raise LinkError(self.port, f"the sensor changed from {self.model.name} to {model.name}")
        self.model = model
        build = scip.me_command if (self.intensity and model.has_intensity) else scip.md_command
        self.command = build(model.amin, model.amax, 1, 0, 0)
        ack = self._request(self.command)
        if ack.status != scip.STATUS_OK:
            raise LinkError(self.port, f"{ack.command}: status {ack.status} ({ack.message})")
        self.clock.reset()
        self._last_frame = time.monotonic()

    def _request(self, command: bytes) -> scip.Reply:
        """Send ``command``; return the reply whose echo is it (other replies are skipped)."""
        ser = self._ser
        assert ser is not None
        echo = command.rstrip(b"\n").decode("ascii")
        ser.write(command)
        ser.flush()
        deadline = time.monotonic() + self.reply_timeout_s
        while time.monotonic() < deadline:
            if self._stop.is_set() and self._thread is not None:
                raise LinkError(self.port, "stopped")
            chunk = ser.read(ser.in_waiting or 1)
            if not chunk:
                continue
            for r in self._decoder.feed(chunk):
                if isinstance(r, scip.Reply) and r.command == echo:
                    return r
        raise LinkError(self.port, f"no reply to {echo} within {self.reply_timeout_s:g} s (is it a SCIP 2.0 scanner?)")

    def _close(self, send_qt: bool = False) -> None:
        ser, self._ser = self._ser, None
        if ser is None:
            return
        if send_qt:
            try:
                ser.write(scip.qt_command())
                ser.flush()
            except (serial.SerialException, OSError):
                pass
        try:
            ser.close()
        except (serial.SerialException, OSError):
            pass

    # ------------------------------------------------------------------ reader thread

    def lost_for(self) -> float:
        """Seconds since the connection was lost and not yet re-established (0 while connected): how
        long the reader has been trying to reconnect, for a caller that gives up after a while."""
        lost = self._lost_at
        return 0.0 if lost is None else time.monotonic() - lost

    @property
    def last_error(self) -> str | None:
        with self._lock:
            return self._stats.last_error

    def _run(self) -> None:
        backoff = self.backoff_s
        while not self._stop.is_set():
            if self._ser is None:
                if self._lost_at is None:
                    self._lost_at = time.monotonic()
                try:
                    self._connect()
                except (serial.SerialException, OSError, LinkError) as err:
                    self._close()
                    with self._lock:
                        self._stats.last_error = str(err)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2.0, self.backoff_max_s)
                    continue
                backoff = self.backoff_s
                self._lost_at = None
                with self._lock:
                    self._stats.reconnects += 1
            try:
                self._read_once()
            except (serial.SerialException, OSError) as err:
                with self._lock:
                    self._stats.io_errors += 1
                    self._stats.last_error = str(err)
                self._close()
                continue
            if time.monotonic() - self._last_frame > self.frame_timeout_s:
                with self._lock:
                    self._stats.timeouts += 1
                    self._stats.last_error = f"no frame for {self.frame_timeout_s:g} s"
                self._close()
        # stop(): QT and close happen there, after the join, so that only one thread touches the port.

    def _read_once(self) -> None:
        ser = self._ser
        assert ser is not None
        chunk = ser.read(ser.in_waiting or 1)
        if not chunk:
            return
        # The moment the bytes (a frame's last among them) were in hand: the live latency runs from here.
        t_wall, t_perf = time.time(), time.perf_counter()
        replies = self._decoder.feed(chunk)
        if not replies:
            return
        for r in replies:
            if isinstance(r, scip.ScanFrame):
                self._deliver(r, t_wall, t_perf)
            elif not r.ok:
                with self._lock:
                    self._stats.sensor_errors += 1
                    self._stats.last_error = f"{r.command}: status {r.status} ({r.message})"

    def _deliver(self, frame: scip.ScanFrame, t_wall: float, t_perf: float) -> None:
        stamp = self.clock.update(frame.timestamp_ms, t_wall)
        lf = LinkFrame(frame, stamp, t_wall, t_perf, int(self.clock.last_sensor_ms or 0), self._seq)
        self._seq += 1
        self._last_frame = time.monotonic()
        while True:
            try:
                self.queue.put_nowait(lf)
                break
            except queue.Full:
                try:
                    self.queue.get_nowait()
                    with self._lock:
                        self._stats.dropped += 1
                except queue.Empty:
                    pass
        with self._lock:
            self._stats.frames += 1
