"""An emulated Hokuyo scanner: SCIP 2.0 served over a real pseudo-terminal, with injectable faults.

Why a pty and not a mock: the serial link (:mod:`gtsjax.io.serial`) is tested through the same
pyserial calls, termios settings, blocking reads and hang-ups that a USB scanner gives it, and
``gtsjax emulate`` lets a person try the whole live pipeline without hardware. Clients open
:attr:`SensorEmulator.path` (a symlink to the current pty slave, so that it stays the same across an
emulated unplug and replug, as a udev name such as ``/dev/ttyACM0`` does).

What it answers, as a real sensor does (the replies are built by :mod:`gtsjax.io.scip`):

* ``SCIP2.0`` (status ``00``), ``VV``, ``PP`` (MODL, DMIN, DMAX, ARES, AMIN, AMAX, AFRT, SCAN), ``II``,
  ``BM`` (``02`` if the laser is already on), ``QT``, ``RS``, ``TM0``/``TM1``/``TM2``;
* ``GD``/``GS``/``GE`` one-shot (status ``10`` while the laser is off, as the URG does: send ``BM``),
  answered when the scan under way ends, with that scan and its timestamp, so that a client asking
  again at once gets the next scan one period later (the sensor's scans are tied to its motor);
  commands that arrive meanwhile wait their turn, as on the sensor;
* the multi-echo ``HD``/``HE`` (one-shot) and ``ND``/``NE`` (continuous) on a UTM-30LX
  (:data:`MULTIECHO_MODELS`): the same replies with each step's echoes, ``&`` before each after the
  first; a simulated scan has one echo per beam, so no ``&`` appears. Other models answer them
  ``0E``, as a URG-04LX does to a command it does not know;
* ``MD``/``MS``/``ME`` streaming: an ``00`` acknowledgement, then one ``99`` data block per scan at
  the model's rate (every ``skip + 1``-th scan), the echo carrying the remaining-scan count; a count
  of 0 streams until ``QT``/``RS``; after the last of a finite count the laser goes off;
* ``GE``/``ME`` only on models with intensity; an unknown or malformed command gets its echo and
  status ``0E``; a bad step range ``04`` (end beyond AMAX) or ``05`` (end before start);
* an empty line sent alone is answered with an empty line: Hokuyo's urg_library sends ``"\\n"``
  and then reads lines until its timeout, so any reply is consumed, and an empty one leaves
  nothing in the stream for a later command to trip over.

The 24-bit millisecond timestamp comes from the emulator's clock (``time.monotonic`` since
:meth:`start`, plus ``timestamp_offset_ms``, modulo 2**24) at the scheduled time of each scan.

Frames come from a *frame source*: a callable ``source(i) -> (ranges_mm int[n_beams], intensities
or None)`` called with the scan (rotation) index since start, or a :class:`~gtsjax.io.logs.ScanLog`
replayed in a loop (metres to millimetres, 0 where the log has no return). The emulator cuts the
requested steps ``start..end`` out of it (steps outside AMIN..AMAX report 0) and clusters them
(the smallest non-zero value of each group, as the sensor reports the nearest return).

Faults (:class:`Faults`, all drawn from one seeded generator, one draw per data block): a data
line's sum character corrupted (``checksum_p``; ``line_checksum_p`` draws per data line instead, so
that a frame may carry several bad lines, as on a noisy cable), a run of 1..8 bytes dropped (``drop_p``), a stall
(``stall_p``: nothing is read or sent for ``stall_s`` seconds; scans due meanwhile are lost, as a
blocked USB endpoint loses them), a disconnect (``disconnect_p``: the pty master is closed, so the
client's next read fails with an I/O error or EOF; after ``reopen_after_s`` a new pty appears under
the same :attr:`path`, the sensor powered up afresh with the laser off; ``None`` leaves it
unplugged). :meth:`inject_stall` and :meth:`inject_disconnect` trigger one on demand.
"""

import collections
import dataclasses
import os
import select
import shutil
import tempfile
import termios
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import scip
from ..io.logs import ScanLog, load_log
from ..sensors import SensorModel, get_model

FrameSource = Callable[[int], "tuple[np.ndarray, np.ndarray | None]"]

#: Bytes the emulator holds for a client that does not read; beyond it whole blocks are discarded.
MAX_PENDING = 1 << 18

#: Models that answer the multi-echo commands ``HD``/``HE``/``ND``/``NE`` (the UTM-30LX's SCIP 2.0).
MULTIECHO_MODELS = frozenset({"UTM-30LX"})


@dataclasses.dataclass(frozen=True)
class Faults:
    """Probabilities (per data block) and sizes of the injected faults; ``seed`` fixes the draws."""

    checksum_p: float = 0.0
    line_checksum_p: float = 0.0  # per data line, not per block
    drop_p: float = 0.0
    stall_p: float = 0.0
    stall_s: float = 0.5
    disconnect_p: float = 0.0
    reopen_after_s: float | None = 0.3
    seed: int = 0


@dataclasses.dataclass
class FaultCounts:
    """How many of each fault the emulator injected."""

    checksum: int = 0
    lines: int = 0  # data lines corrupted by ``line_checksum_p``
    dropped: int = 0
    stalls: int = 0
    disconnects: int = 0

    @property
    def total(self) -> int:
        return self.checksum + self.lines + self.dropped + self.stalls + self.disconnects


def log_source(log: ScanLog) -> FrameSource:
    """A frame source replaying ``log`` in a loop: metres to millimetres, 0 where there is no return."""
    valid = log.valid()
    mm = np.where(valid, np.rint(np.where(valid, log.ranges, 0.0) * 1000.0), 0).astype(np.int64)
    inten = None
    if log.intensities is not None:
        inten = np.rint(np.clip(np.nan_to_num(log.intensities), 0, None)).astype(np.int64)

    def source(i: int):
        k = i % mm.shape[0]
        return mm[k], None if inten is None else inten[k]

    return source


class SensorEmulator:
    """A SCIP 2.0 scanner of ``model`` on a pty, run by a background thread.

    ``with SensorEmulator(URG_04LX, source) as emu: serial.serial_for_url(emu.path)``. Counters:
    :attr:`frames_sent` (data blocks written), :attr:`faults` (:class:`FaultCounts`),
    :attr:`commands` (every command line received, in order).
    """

    def __init__(
        self,
        model: SensorModel,
        source: "FrameSource | ScanLog | None" = None,
        *,
        faults: Faults | None = None,
        timestamp_offset_ms: int = 0,
        link_dir: "str | os.PathLike | None" = None,
    ):
        self.model = model
        if source is None:
            source = _flat_source(model)
        elif isinstance(source, ScanLog):
            if source.n_beams != model.n_beams:
                raise InputError("scan log", f"has {source.n_beams} beams, the {model.name} has {model.n_beams}")
            source = log_source(source)
        self._source = source
        self.fault_config = faults or Faults()
        self._rng = np.random.default_rng(self.fault_config.seed)
        self._ts_offset = int(timestamp_offset_ms)
        self._own_dir = link_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="gtsjax-emu-")) if link_dir is None else Path(link_dir)
        self.path = str(self._dir / "ttyEMU0")
        self.frames_sent = 0
        self.faults = FaultCounts()
        self.commands: list[str] = []
        #: (raw timestamp ms, ``time.monotonic()`` when handed to the pty) of recent data blocks.
        self.sent_log: collections.deque[tuple[int, float]] = collections.deque(maxlen=4096)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self.pty_name: str | None = None
        self._t0 = time.monotonic()
        self._pending_stall: float | None = None
        self._pending_disconnect: tuple[bool, float | None] | None = None
        self._reset_state()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> "SensorEmulator":
        if self._thread is not None:
            return self
        self._t0 = time.monotonic()
        self._open_pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="gtsjax-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close_pty()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        if self._own_dir:
            shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> "SensorEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def connected(self) -> bool:
        return self._master is not None

    def inject_stall(self, seconds: float) -> None:
        """Stop reading and sending for ``seconds`` (from the emulator thread's next turn)."""
        with self._lock:
            self._pending_stall = float(seconds)

    def inject_disconnect(self, reopen_after_s: float | None = 0.3) -> None:
        """Unplug: close the pty master; replug after ``reopen_after_s`` (``None``: never)."""
        with self._lock:
            self._pending_disconnect = (True, reopen_after_s)

    def timestamp_ms(self, t: float | None = None) -> int:
        """The sensor's 24-bit clock at monotonic time ``t`` (now by default)."""
        t = time.monotonic() if t is None else t
        # Rounded, not truncated: a scan due at t0 + k * 0.1 s must read k * 100 ms, not 99 ms.
        return (int(round((t - self._t0) * 1000.0)) + self._ts_offset) % scip.TIMESTAMP_MODULUS

    # ------------------------------------------------------------------ pty

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        # Raw on both ends: no echo of what the client sends and no LF -> CRLF on what we send.
        tty.setraw(slave, termios.TCSANOW)
        os.set_blocking(master, False)
        self.pty_name = os.ttyname(slave)
        tmp = self.path + ".new"
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        os.symlink(self.pty_name, tmp)
        os.replace(tmp, self.path)  # atomic: a client never sees the name missing while replugging
        self._inbuf = bytearray()
        self._outbuf = bytearray()
        self._master, self._slave = master, slave  # last: ``connected`` means the name is ready

    def _close_pty(self) -> None:
        # Closing the master hangs the line up: the client's reads fail (EIO) or return nothing.
        # Our own slave fd (held so that a client closing its end does not hang *us* up) goes too.
        fds = (self._master, self._slave)
        self._master = self._slave = None  # first: ``connected`` must not outlive the line
        for fd in fds:
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    # ------------------------------------------------------------------ state

    def _reset_state(self) -> None:
        """Power-up state: laser off, not streaming, not in time-adjust mode."""
        self._laser = False
        self._stream: scip.Command | None = None
        self._remaining = 0
        self._next_due = 0.0
        self._tm_mode = False
        self._oneshot: tuple[float, scip.Command] | None = None
        self._stall_until = 0.0
        self._realign = False
        self._reopen_at: float | None = None
        self._inbuf = bytearray()
        self._outbuf = bytearray()

    def _run(self) -> None:
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                stall, self._pending_stall = self._pending_stall, None
                disc, self._pending_disconnect = self._pending_disconnect, None
            if disc is not None and self._master is not None:
                self._disconnect(now, disc[1])
            if stall is not None:
                self._start_stall(now, stall)
            if self._master is None:
                if self._reopen_at is not None and now >= self._reopen_at:
                    self._reset_state()
                    self._open_pty()
                else:
                    self._stop.wait(0.02)
                continue
            if now < self._stall_until:
                self._stop.wait(min(self._stall_until - now, 0.05))
                continue
            timeout = 0.05
            if self._stream is not None:
                timeout = max(0.0, min(timeout, self._next_due - now))
            if self._oneshot is not None:
                timeout = max(0.0, min(timeout, self._oneshot[0] - now))
            master = self._master
            try:
                r, w, _ = select.select([master], [master] if self._outbuf else [], [], timeout)
            except (OSError, ValueError):
                continue
            if r:
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError:
                    data = b""
                if data:
                    self._inbuf += data
                    self._handle_input()
            if self._master is not None and self._stream is not None and time.monotonic() >= self._next_due:
                self._emit_scan()
            if self._master is not None and self._oneshot is not None and time.monotonic() >= self._oneshot[0]:
                self._emit_oneshot()
                self._handle_input()  # the commands that waited behind it
            if self._master is not None and self._outbuf:
                self._flush()

    def _flush(self) -> None:
        try:
            n = os.write(self._master, self._outbuf)
        except BlockingIOError:
            return
        except OSError:
            return
        del self._outbuf[:n]

    def _send(self, data: bytes) -> bool:
        if len(self._outbuf) + len(data) > MAX_PENDING:
            return False  # nobody is reading: the block is lost, as on a full USB endpoint
        self._outbuf += data
        self._flush()
        return True

    def _disconnect(self, now: float, reopen_after_s: float | None) -> None:
        self.faults.disconnects += 1
        self._close_pty()
        self._stream = None
        self._oneshot = None
        self._reopen_at = None if reopen_after_s is None else now + reopen_after_s

    def _start_stall(self, now: float, seconds: float) -> None:
        self.faults.stalls += 1
        self._stall_until = now + seconds
        self._realign = True

    # ------------------------------------------------------------------ commands

    def _handle_input(self) -> None:
        while self._oneshot is None:
            i = self._inbuf.find(b"\n")
            j = self._inbuf.find(b"\r")
            ends = [k for k in (i, j) if k >= 0]
            if not ends:
                if len(self._inbuf) > 256:  # no sensor buffers a line that long
                    self._inbuf.clear()
                return
            k = min(ends)
            line = bytes(self._inbuf[:k])
            skip = 2 if self._inbuf[k : k + 2] == b"\r\n" else 1
            del self._inbuf[: k + skip]
            self._command(line)
            if self._master is None:
                return

    def _command(self, line: bytes) -> None:
        text = line.decode("latin-1")
        self.commands.append(text)
        if not line:
            self._send(b"\n")
            return
        try:
            cmd = scip.parse_command(line)
        except scip.ScipError:
            self._send(scip.format_reply(line, "0E") if line.isascii() else b"\n")
            return
        code = cmd.code
        if code == "SCIP2.0":
            self._send(scip.format_reply(cmd, "00"))
        elif code == "VV":
            self._send(scip.format_field_reply(cmd, self._vv_fields()))
        elif code == "PP":
            self._send(scip.format_pp_reply(self.model, cmd))
        elif code == "II":
            self._send(scip.format_field_reply(cmd, self._ii_fields()))
        elif code == "BM":
            self._send(scip.format_reply(cmd, "02" if self._laser else "00"))
            self._laser = True
        elif code in ("QT", "RS", "RT"):
            self._stream = None
            self._laser = False
            if code != "QT":
                self._tm_mode = False
            self._send(scip.format_reply(cmd, "00"))
        elif code.startswith("TM"):
            self._time_adjust(cmd)
        elif cmd.is_scan:
            self._scan_command(cmd)
        else:
            self._send(scip.format_reply(cmd, "0E"))

    def _time_adjust(self, cmd: scip.Command) -> None:
        mode = cmd.code[2]
        if mode == "0":
            self._send(scip.format_reply(cmd, "02" if self._tm_mode else "00"))
            self._tm_mode = True
            self._stream = None
            self._laser = False
        elif mode == "1":
            if not self._tm_mode:
                self._send(scip.format_reply(cmd, "04"))
            else:
                self._send(scip.format_reply(cmd, "00", scip.format_timestamp_line(self.timestamp_ms())))
        else:
            self._send(scip.format_reply(cmd, "00" if self._tm_mode else "03"))
            self._tm_mode = False

    def _scan_command(self, cmd: scip.Command) -> None:
        m = self.model
        if (cmd.has_intensity and not m.has_intensity) or (cmd.is_multiecho and m.name not in MULTIECHO_MODELS):
            self._send(scip.format_reply(cmd, "0E"))
            return
        if cmd.end > m.amax:
            self._send(scip.format_reply(cmd, "04"))
            return
        if cmd.end < cmd.start:
            self._send(scip.format_reply(cmd, "05"))
            return
        if self._tm_mode:
            self._send(scip.format_reply(cmd, "0E"))
            return
        if not cmd.is_continuous:
            if not self._laser:
                self._send(scip.format_reply(cmd, "10"))
                return
            # The reply goes out when the scan under way ends (the next motor revolution's start).
            k = int((time.monotonic() - self._t0) / m.period) + 1
            self._oneshot = (self._t0 + k * m.period, cmd)
            return
        self._send(scip.format_reply(cmd, "00"))
        self._laser = True
        self._stream = cmd
        self._remaining = cmd.count or 0
        # The first block follows at the next rotation, as the sensor's scans are tied to its motor.
        now = time.monotonic()
        k = int((now - self._t0) / m.period) + 1
        self._next_due = self._t0 + k * m.period

    # ------------------------------------------------------------------ data

    def _values(self, cmd: scip.Command, i: int) -> "tuple[np.ndarray, np.ndarray | None]":
        m = self.model
        ranges, inten = self._source(i)
        ranges = np.asarray(ranges, dtype=np.int64)
        if ranges.shape != (m.n_beams,):
            raise InputError("frame source", f"gave {ranges.shape} ranges, the {m.name} has {m.n_beams} beams")
        steps = np.arange(cmd.start, cmd.end + 1)
        inside = (steps >= m.amin) & (steps <= m.amax)
        idx = np.clip(steps - m.amin, 0, m.n_beams - 1)
        r = np.where(inside, ranges[idx], 0)
        chars = cmd.chars or 3
        top = (1 << (6 * chars)) - 1
        r = np.clip(r, 0, top)
        it = None
        if cmd.has_intensity:
            src = np.zeros(m.n_beams, np.int64) if inten is None else np.asarray(inten, dtype=np.int64)
            it = np.clip(np.where(inside, src[idx], 0), 0, top)
        c = max(cmd.cluster or 1, 1)
        if c > 1:
            n = cmd.n_values
            pad = n * c - r.shape[0]
            groups = np.pad(r, (0, pad)).reshape(n, c)
            masked = np.where(groups > 0, groups, top + 1)
            pick = masked.argmin(axis=1)
            r = np.where(masked.min(axis=1) > top, 0, groups[np.arange(n), pick])
            if it is not None:
                it = np.pad(it, (0, pad)).reshape(n, c)[np.arange(n), pick]
        return r, it

    def _emit_scan(self) -> None:
        m = self.model
        cmd = self._stream
        assert cmd is not None
        due = self._next_due
        now = time.monotonic()
        step = m.period * ((cmd.interval or 0) + 1)
        self._next_due = due + step
        if self._next_due < now and (self._realign or now - due > 1.0):
            # After a stall the scans meanwhile are gone; a thread merely scheduled late (a busy
            # host) catches up instead, since a real sensor would not have lost them.
            self._next_due = due + step * (int((now - due) / step) + 1)
        self._realign = False
        f = self.fault_config
        # One set of draws per block, always, so that a seed gives the same faults whatever fires.
        u = self._rng.random(4)
        if u[2] < f.stall_p:
            self._start_stall(now, f.stall_s)
            return
        if u[3] < f.disconnect_p:
            self._disconnect(now, f.reopen_after_s)
            return
        if cmd.count:
            self._remaining -= 1
            echo = cmd.with_remaining(max(self._remaining, 0))
        else:
            echo = cmd.with_remaining(0)
        i = int(round((due - self._t0) / m.period))
        ranges, inten = self._values(cmd, i)
        stamp = self.timestamp_ms(due)
        block = scip.format_md_frame(echo, stamp, ranges, inten)
        if u[0] < f.checksum_p:
            block = self._corrupt_sum(block)
            self.faults.checksum += 1
        if f.line_checksum_p > 0:  # drawn only when asked for: other seeds' faults stay as they were
            block, n_bad = self._corrupt_lines(block, f.line_checksum_p)
            self.faults.lines += n_bad
        if u[1] < f.drop_p:
            n = int(self._rng.integers(1, 9))
            at = int(self._rng.integers(0, max(len(block) - n, 1)))
            block = block[:at] + block[at + n :]
            self.faults.dropped += 1
        if len(self._outbuf) + len(block) <= MAX_PENDING:
            # Counted before the write, so that a client never holds a block the counter misses.
            self.frames_sent += 1
            self.sent_log.append((stamp, time.monotonic()))
            self._send(block)
        if cmd.count and self._remaining <= 0:
            self._stream = None
            self._laser = False

    def _emit_oneshot(self) -> None:
        assert self._oneshot is not None
        due, cmd = self._oneshot
        self._oneshot = None
        i = int(round((due - self._t0) / self.model.period))
        ranges, inten = self._values(cmd, i)
        stamp = self.timestamp_ms(due)
        self.frames_sent += 1
        self.sent_log.append((stamp, time.monotonic()))
        self._send(scip.format_gd_frame(cmd, stamp, ranges, inten))

    def _bad_sum(self, line: bytes) -> bytes:
        """``line`` with its sum character changed to another valid one."""
        out = bytearray(line)
        old = out[-1] - 0x30
        out[-1] = 0x30 + (old + 1 + int(self._rng.integers(0, 63))) % 64
        return bytes(out)

    @staticmethod
    def _data_lines(lines: list[bytes]) -> list[int]:
        # lines: echo, status, timestamp, data..., "", ""
        return [k for k in range(3, len(lines)) if lines[k]]

    def _corrupt_sum(self, block: bytes) -> bytes:
        lines = block.split(b"\n")
        data_idx = self._data_lines(lines)
        k = data_idx[int(self._rng.integers(0, len(data_idx)))]
        lines[k] = self._bad_sum(lines[k])
        return b"\n".join(lines)

    def _corrupt_lines(self, block: bytes, p: float) -> tuple[bytes, int]:
        """Each data line's sum corrupted with probability ``p``; the block and how many were."""
        lines = block.split(b"\n")
        data_idx = self._data_lines(lines)
        bad = [k for k, u in zip(data_idx, self._rng.random(len(data_idx)), strict=True) if u < p]
        for k in bad:
            lines[k] = self._bad_sum(lines[k])
        return b"\n".join(lines), len(bad)

    def _vv_fields(self) -> dict[str, str]:
        return {
            "VEND": "Hokuyo Automatic Co.,Ltd.",
            "PROD": f"SOKUIKI Sensor {self.model.name} (gtsjax emulator)",
            "FIRM": "0.1.0(gtsjax)",
            "PROT": "SCIP 2.0",
            "SERI": "H0000000",
        }

    def _ii_fields(self) -> dict[str, str]:
        return {
            "MODL": self.model.name,
            "LASR": "ON" if self._laser else "OFF",
            "SCSP": f"Initial({self.model.scan_rpm}[rpm])",
            "MESM": "Measuring by Normal Mode" if self._stream is not None else "Idle",
            "SBPS": "USB only",
            "TIME": scip.encode_value(self.timestamp_ms(), 4).decode("ascii"),
            "STAT": "Sensor works well.",
        }


def _flat_source(model: SensorModel) -> FrameSource:
    """A default scene: a wall 2 m away, with the scan index written into beam 0 (handy in tests)."""
    base = np.full(model.n_beams, 2000, dtype=np.int64)

    def source(i: int):
        r = base.copy()
        r[0] = 1000 + i % 1000
        return r, np.full(model.n_beams, 500, dtype=np.int64) if model.has_intensity else None

    return source


def serve(
    scenario_log: "ScanLog | str | os.PathLike | FrameSource | None",
    model: "SensorModel | str | None" = None,
    faults: Faults | None = None,
    *,
    seed: int = 0,
    print_fn: Callable[[str], None] = print,
    stop: threading.Event | None = None,
    link_dir: "str | os.PathLike | None" = None,
) -> None:
    """Serve a scenario on a pty until Ctrl-C (or until ``stop`` is set); print the path to open.

    ``scenario_log`` is a :class:`ScanLog`, a path to an ``.npz`` scan log, a frame source, a
    simulator scenario name (run through ``gtsjax.sim.simulate``), or ``None`` for a flat wall.
    ``model`` defaults to the log's ``sensor_model``. ``link_dir`` is where the stable name
    ``ttyEMU0`` is made (a fresh temporary folder by default).
    """
    source = scenario_log
    if isinstance(source, str | os.PathLike) and not callable(source):
        p = Path(source)
        if p.suffix == ".npz" or p.exists():
            source = load_log(p)
        else:
            from . import simulate  # the simulator, only when a scenario is named

            # Rendered for the scanner asked for (``emulate spl-eval --scanner UTM-30LX``), else the scenario's.
            scanner = None if model is None else getattr(model, "name", model)
            source, _ = simulate(str(scenario_log), seed=seed, sensor=scanner)
    if model is None:
        name = source.sensor_model if isinstance(source, ScanLog) else None
        if name is None:
            raise InputError("emulator", "no sensor model given and the scenario names none")
        model = name
    if isinstance(model, str):
        model = get_model(model)
    with SensorEmulator(model, source, faults=faults, link_dir=link_dir) as emu:
        try:  # the stop may come as soon as the path is out
            print_fn(f"{model.name} emulator on {emu.path} (pty {emu.pty_name}); Ctrl-C to stop")
            while not (stop is not None and stop.wait(0.2)):
                if stop is None:
                    time.sleep(0.2)
        except KeyboardInterrupt:
            pass


def serve_match(
    scenario: str,
    faults: Faults | None = None,
    *,
    seed: int = 0,
    n_robots: int = 10,
    seconds: float = 60.0,
    referee: bool = True,
    print_fn: Callable[[str], None] = print,
    stop: threading.Event | None = None,
    link_dir: "str | os.PathLike | None" = None,
) -> None:
    """Serve every laser of a match scenario (``spl-match-N[-utm|-mixed]``, :mod:`gtsjax.sim.match`), each on
    its own pty, until Ctrl-C (or ``stop``): one line per laser, ``NAME: … emulator on PATH``. The
    lasers keep their phases: laser ``k`` of ``K`` starts ``k / K`` of a period after the first, so its
    scans come at the times its log was rendered for. ``link_dir``: a folder that gets one sub-folder
    per laser holding its ``ttyEMU0`` (fresh temporary folders by default). Each laser draws its own
    faults (the seed plus its index)."""
    import contextlib

    from .match import simulate_match

    logs, _ = simulate_match(scenario, seed=seed, n_robots=n_robots, seconds=seconds, referee=referee)
    first = next(iter(logs.values()))
    faults = faults or Faults()
    with contextlib.ExitStack() as stack:
        emus = []
        t_start = time.monotonic()
        for k, (name, log) in enumerate(logs.items()):
            model = get_model(log.sensor_model)  # each laser's own scanner (a mixed match has two)
            delay = t_start + float(log.stamps[0] - first.stamps[0]) - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            where = None
            if link_dir is not None:
                where = Path(link_dir) / name
                where.mkdir(parents=True, exist_ok=True)
            f = dataclasses.replace(faults, seed=faults.seed + k)
            emus.append((name, stack.enter_context(SensorEmulator(model, log, faults=f, link_dir=where))))
        try:
            for name, emu in emus:
                print_fn(f"{name}: {emu.model.name} emulator on {emu.path} (pty {emu.pty_name})")
            print_fn("Ctrl-C to stop")
            while not (stop is not None and stop.wait(0.2)):
                if stop is None:
                    time.sleep(0.2)
        except KeyboardInterrupt:
            pass
