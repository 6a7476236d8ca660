"""The robots' beliefs, live: a UDP port on the laptop where each robot sends its own pose as JSON
lines (``run --beliefs udp:PORT``; the sender: ``docs/live-beliefs.md``).

One line is ``{"robot": "nao3", "stamp": 12.5, "x": 1.2, "y": -0.4, "theta": 0.3}`` (metres, radians,
the field's frame; ``stamp`` the robot's own clock, any origin); a datagram may hold several lines. A
listener thread keeps each robot's latest poses in a bounded buffer (:data:`KEEP`) with the laptop's
receive time: the robots' clocks are not the laptop's, so the live association
(:mod:`gtsjax.grade.online`) places each pose by when it arrived; the robot's own stamp is kept too,
and orders the lines one datagram carries (a robot that sends a batch gets the last line stamped on
arrival, each earlier one its stamp's difference before it). A line may also be cut across datagrams
(a sender that writes a stream in chunks): a datagram's last piece that is not a whole JSON line
waits, per sender, for the next datagram from that sender to complete it (:data:`PENDING_S`,
:data:`PENDING_BYTES`); a piece that no datagram completes is counted ``cut short``.

What arrives on a network is not ours to trust: a datagram that is not UTF-8, a line that is not a
JSON object, a field missing, a name that is not text, a number that is not finite, are each counted
by reason (and by robot where the robot is named) and skipped; nothing a sender does stops the run.
A port that cannot be bound (in use, no permission) is one line (:class:`InputError`) before the run
starts.
"""

import json
import math
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

#: Poses kept per robot: 60 s at 30 Hz, more than any association window looks back.
KEEP = 1800
#: Robots kept at most: a sender that makes up a new name per line does not fill the laptop's memory.
MAX_ROBOTS = 64
#: The longest name kept; longer ones are malformed (a name is a CSV field and a view label).
MAX_NAME = 64
#: Within one datagram a robot's earlier lines are placed at most this far before its last.
MAX_BATCH_S = 1.0
#: A piece of a line waits this long for the rest from its sender, and is at most this long.
PENDING_S = 1.0
PENDING_BYTES = 4096
_FIELDS = ("stamp", "x", "y", "theta")


def parse_beliefs_address(text: str, option: str = "--beliefs") -> tuple[str, int]:
    """``udp:PORT`` or ``udp:HOST:PORT`` (host default ``0.0.0.0``: every interface) as (host, port);
    anything else one line naming ``option``. Port 0 binds a free port (tests)."""
    scheme, _, rest = text.partition(":")
    if scheme != "udp" or not rest:
        raise InputError(option, f"{text!r}: expected udp:PORT or udp:HOST:PORT")
    host, _, port = rest.rpartition(":")
    host = host.strip("[]") or "0.0.0.0"
    try:
        number = int(port)
    except ValueError:
        raise InputError(option, f"{text!r}: the port {port!r} is not a number") from None
    if not 0 <= number <= 65535:
        raise InputError(option, f"{text!r}: the port must be 0–65535")
    return host, number


@dataclass
class BeliefCounts:
    """What the listener received: poses per robot, malformed lines by reason, and by robot where the
    line named one; datagrams; lines older than the robot's last (a network reorders datagrams)."""

    datagrams: int = 0
    poses: dict = field(default_factory=dict)  # robot -> poses kept
    malformed: dict = field(default_factory=dict)  # reason -> lines
    malformed_by_robot: dict = field(default_factory=dict)  # robot -> malformed lines that named it
    out_of_order: int = 0
    robots_refused: int = 0  # lines of robots past MAX_ROBOTS

    def bad(self, reason: str, robot: str | None = None) -> None:
        self.malformed[reason] = self.malformed.get(reason, 0) + 1
        if robot is not None:
            self.malformed_by_robot[robot] = self.malformed_by_robot.get(robot, 0) + 1

    @property
    def n_malformed(self) -> int:
        return sum(self.malformed.values())


def parse_line(line: str, counts: BeliefCounts) -> "tuple[str, float, float, float, float] | None":
    """One JSON line as (robot, stamp, x, y, theta), or ``None`` with its reason counted."""
    try:
        obj = json.loads(line)
    except ValueError:
        counts.bad("not JSON")
        return None
    if not isinstance(obj, dict):
        counts.bad("not a JSON object")
        return None
    robot = obj.get("robot")
    if not isinstance(robot, str) or not robot.strip() or len(robot) > MAX_NAME:
        counts.bad("no robot name (a non-empty string)")
        return None
    robot = robot.strip()
    vals = []
    for key in _FIELDS:
        v = obj.get(key)
        if v is None:
            counts.bad(f"no {key}", robot)
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            counts.bad(f"{key} not a number", robot)
            return None
        if not math.isfinite(v):
            counts.bad(f"{key} not finite", robot)
            return None
        vals.append(float(v))
    return (robot, *vals)


def _whole(piece: str) -> bool:
    """Whether ``piece`` is one whole JSON value (a line's end may still be on its way if not)."""
    try:
        json.loads(piece)
    except ValueError:
        return False
    return True


class BeliefListener:
    """Binds ``udp:[HOST:]PORT`` at construction (so a port in use is one line before the run) and,
    once :meth:`start` ed, keeps what arrives (see the module). :meth:`snapshot` hands the live loop a
    copy, taken under a lock held only for the copy. ``clock``: the laptop's time, as the scans'
    stamps are (epoch seconds)."""

    def __init__(self, spec: str, *, keep: int = KEEP, clock=time.time, option: str = "--beliefs"):
        self.spec = spec
        host, port = parse_beliefs_address(spec, option)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind((host, port))
        except OSError as err:
            sock.close()
            raise InputError(option, f"cannot listen on UDP {host}:{port} ({err.strerror or err})") from None
        sock.settimeout(0.2)  # how soon stop() is noticed
        self.sock, self.host, self.port = sock, host, sock.getsockname()[1]
        self.keep, self.clock = keep, clock
        self.counts = BeliefCounts()
        self._poses: dict[str, deque] = {}
        self._pending: dict[object, tuple[float, str]] = {}  # sender -> (receive time, a line's first piece)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --------------------------------------------------------------------------------- receiving
    def start(self) -> "BeliefListener":
        self._thread = threading.Thread(target=self._run, name="beliefs-udp", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, sender = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:  # closed under us, or an ICMP error on some systems: keep listening
                if self._stop.is_set():
                    break
                time.sleep(0.01)
                continue
            self.feed(data, self.clock(), sender)

    def _lines(self, text: str, t_recv: float, sender) -> list[str]:
        """The whole lines of a datagram from ``sender``: a piece left by its last datagram joined to
        the first line where the two make one JSON line (else the piece counted ``cut short``), and
        its own last piece kept back where it is not a whole line by itself."""
        lines = text.split("\n")
        held = self._pending.pop(sender, None)
        if held is not None:
            if t_recv - held[0] <= PENDING_S and _whole(held[1] + lines[0]):
                lines[0] = held[1] + lines[0]
            else:
                self.counts.bad("cut short")
        tail = lines[-1]
        if tail.strip() and not _whole(tail) and len(tail) <= PENDING_BYTES:
            self._pending[sender] = (t_recv, tail)
            lines.pop()
        return lines

    def feed(self, data: bytes, t_recv: float, sender=None) -> None:
        """One datagram from ``sender`` received at ``t_recv`` (laptop time): its lines parsed, the
        good ones kept."""
        with self._lock:
            self.counts.datagrams += 1
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            with self._lock:
                self.counts.bad("not UTF-8")
            return
        parsed = []
        with self._lock:
            for line in self._lines(text, t_recv, sender):
                if line.strip():
                    p = parse_line(line, self.counts)
                    if p is not None:
                        parsed.append(p)
            last_stamp: dict[str, float] = {}
            for robot, stamp, *_ in parsed:
                last_stamp[robot] = max(stamp, last_stamp.get(robot, -math.inf))
            for robot, stamp, x, y, theta in parsed:
                buf = self._poses.get(robot)
                if buf is None:
                    if len(self._poses) >= MAX_ROBOTS:
                        self.counts.robots_refused += 1
                        continue
                    buf = self._poses[robot] = deque(maxlen=self.keep)
                if buf and stamp <= buf[-1][1]:
                    self.counts.out_of_order += 1
                    continue
                t = t_recv - min(last_stamp[robot] - stamp, MAX_BATCH_S)
                if buf and t <= buf[-1][0]:  # receive times strictly increasing, for interpolation
                    t = buf[-1][0] + 1e-6
                buf.append((t, stamp, x, y, theta))
                self.counts.poses[robot] = self.counts.poses.get(robot, 0) + 1

    # ----------------------------------------------------------------------------------- reading
    def snapshot(self, since: float = -math.inf) -> "dict[str, np.ndarray]":
        """Each robot's poses received after ``since`` (laptop time), as an array ``[n, 5]`` of
        (receive time, the robot's stamp, x, y, theta) in receive order; robots with none left out."""
        with self._lock:
            rows = {r: [p for p in buf if p[0] > since] if since > -math.inf else list(buf)
                    for r, buf in self._poses.items()}
        return {r: np.asarray(p, np.float64) for r, p in rows.items() if p}

    def counts_copy(self) -> BeliefCounts:
        """The counters as they stand (for the summary, after :meth:`stop`)."""
        with self._lock:
            c = self.counts
            return BeliefCounts(c.datagrams, dict(c.poses), dict(c.malformed), dict(c.malformed_by_robot),
                                c.out_of_order, c.robots_refused)

    def stop(self) -> None:
        """Stops the thread and closes the socket; a piece of a line still waiting is counted ``cut
        short``. Safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self.sock.close()
        with self._lock:
            for _ in self._pending:
                self.counts.bad("cut short")
            self._pending.clear()

    def __enter__(self) -> "BeliefListener":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
