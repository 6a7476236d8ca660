"""An incremental SCIP 2.0 decoder for the live link: bytes in any chunking, complete replies out.

It never raises on bad input and never waits for more than it holds: each byte is looked at a
bounded number of times, a line longer than ``max_line`` or a reply longer than ``max_lines`` is
dropped (counted), so memory stays bounded whatever arrives.

How it stays in step: a reply starts at a line that *ends* in a command echo (anything glued in
front of it is garbage) and is confirmed by the next line being a status line with a valid sum;
it ends at an empty line. A reply that fails to parse is dropped whole and counted by reason, but
first the decoder looks inside it for a later echo-plus-status pair (the previous reply was cut short
and the next one ran into it), and parses from there, so one damaged reply costs only itself. A scan reply damaged only in its data
lines (a bad sum, bytes lost inside a line) is salvaged instead: delivered without those lines' beams.
"""

import dataclasses

from ._scip_codec import ScipError
from ._scip_commands import find_echo
from ._scip_reply import Reply, ScanFrame, is_status_line, parse_lines

#: Faults a scan reply is salvaged from when they lie in its data lines (see ``StreamDecoder._salvage``).
SALVAGEABLE = ("checksum", "truncated")

@dataclasses.dataclass
class StreamStats:
    """Counters of a :class:`StreamDecoder`. Every dropped reply is counted once, by its first fault."""

    frames_ok: int = 0
    salvaged: int = 0  # scan frames delivered without the beams of damaged data lines
    checksum_errors: int = 0
    truncated: int = 0
    malformed: int = 0
    oversize: int = 0
    garbage_bytes: int = 0

    @property
    def dropped(self) -> int:
        return self.checksum_errors + self.truncated + self.malformed + self.oversize


class StreamDecoder:
    """Feed it byte chunks; it returns the replies (:class:`Reply` / :class:`ScanFrame`) completed.

    ``feed(chunk)`` returns the replies whose closing empty line arrived in ``chunk``; ``flush()``
    ends the stream, returning a last reply that lacks only its closing empty line if it is otherwise
    complete (scan replies carry their own length, so a cut one is still caught as truncated).
    """

    def __init__(self, *, max_line: int = 1024, max_lines: int = 512):
        self.max_line = int(max_line)
        self.max_lines = int(max_lines)
        self.stats = StreamStats()
        self._partial = bytearray()
        self._skipping = False  # inside an over-long line: drop bytes until its LF
        self._lines: list[bytes] = []
        self._out: list[Reply | ScanFrame] = []
        self._orphan = 0  # lines in a row that were neither an echo nor part of a reply
        self._held = 0  # the run of such lines before the echo now waiting for its status line
        self._after_drop = False  # a reply was just dropped: lines without an echo may be its rest

    def reset(self) -> None:
        """Forget any partial reply (after reopening the port, say); counters are kept, a reply cut
        off so counted ``truncated``."""
        if self._lines or self._partial:
            self._count("truncated")
        self.stats.garbage_bytes += len(self._partial) + sum(len(line) + 1 for line in self._lines)
        self._partial.clear()
        self._lines = []
        self._skipping = False
        self._orphan = self._held = 0
        self._after_drop = False

    def feed(self, data: bytes | bytearray | memoryview) -> "list[Reply | ScanFrame]":
        data = bytes(data)
        parts = data.split(b"\n")
        tail = parts.pop()  # the bytes after the last LF: the start of a line still to come
        stats = self.stats
        plain = b"\r" not in data  # no line to strip of a CR (checked once for the chunk)
        i, n = 0, len(parts)
        while i < n:
            lines = self._lines
            if len(lines) >= 2 and plain and not self._partial and not self._skipping:
                # Inside a confirmed reply (echo and status seen) each non-empty line is appended as
                # it is: its data lines up to the closing empty line go in at once, which is what the
                # line-by-line path below does with them when none is over-long and they do not make
                # the reply over-long (else they take that path). A frame's hundred-odd lines cost
                # the link's reader thread microseconds each one by one.
                try:
                    j = parts.index(b"", i)
                except ValueError:
                    j = n
                run = parts[i:j]
                if run and len(lines) + len(run) <= self.max_lines and max(map(len, run)) <= self.max_line:
                    lines.extend(run)
                    i = j
                    if i == n:
                        break
            part = parts[i]
            i += 1
            if self._skipping:  # the rest of an over-long line
                stats.garbage_bytes += len(part) + 1
                self._skipping = False
                continue
            if self._partial:
                line = bytes(self._partial) + part
                self._partial.clear()
            else:
                line = part
            if len(line) > self.max_line:
                stats.garbage_bytes += len(line) + 1
                self._drop_reply("oversize")
                continue
            if line.endswith(b"\r"):
                line = line[:-1]
            self._on_line(line)
        if self._skipping:
            stats.garbage_bytes += len(tail)
        else:
            self._partial += tail
            if len(self._partial) > self.max_line:
                stats.garbage_bytes += len(self._partial)
                self._partial.clear()
                self._skipping = True
                self._drop_reply("oversize")
        out, self._out = self._out, []
        return out

    def flush(self) -> "list[Reply | ScanFrame]":
        """End of stream: treat what is held as ending here."""
        if self._partial and not self._skipping:
            line = bytes(self._partial)
            self._partial.clear()
            self._on_line(line)
        self._partial.clear()
        self._skipping = False
        if self._lines:
            lines, self._lines = self._lines, []
            if len(lines) == 1:
                self.stats.truncated += 1
            else:
                self._finish(lines)
        out, self._out = self._out, []
        return out

    def decode(self, data: bytes) -> "list[Reply | ScanFrame]":
        """``feed(data) + flush()``: decode a whole recording."""
        return self.feed(data) + self.flush()

    # ------------------------------------------------------------------ internals

    def _drop_reply(self, reason: str) -> None:
        if self._lines:
            self._count(reason)
            self._lines = []

    def _count(self, reason: str) -> None:
        self._after_drop = True
        s = self.stats
        if reason == "checksum":
            s.checksum_errors += 1
        elif reason == "truncated":
            s.truncated += 1
        elif reason == "oversize":
            s.oversize += 1
        else:
            s.malformed += 1

    def _start(self, line: bytes) -> None:
        at = find_echo(line) if line else -1
        if at < 0:
            self.stats.garbage_bytes += len(line) + 1
            self._orphan = self._orphan + 1 if line else self._end_orphans()
            return
        self._held, self._orphan = self._orphan, 0
        self.stats.garbage_bytes += at
        self._lines = [line[at:]]

    def _end_orphans(self, run: int | None = None) -> int:
        """A run of two or more lines with no echo, ended by an empty line or a confirmed echo, was a
        reply whose echo was damaged (a status, a timestamp, data lines): counted ``malformed``, so
        that a frame lost so is counted as a frame, besides its garbage bytes; not when a reply was
        dropped just before (the run is the rest of it, cut at a lost line feed: counted already)."""
        if (self._orphan if run is None else run) >= 2 and not self._after_drop:
            self.stats.malformed += 1
        self._orphan = 0
        self._after_drop = False
        return 0

    def _on_line(self, line: bytes) -> None:
        lines = self._lines
        if not lines:
            self._start(line)
        elif len(lines) == 1:
            if is_status_line(line) or len(line) == 1:
                lines.append(line)
                self._held = self._end_orphans(self._held)
            else:  # the "echo" was not followed by a status: it was garbage; look again at this line
                self.stats.garbage_bytes += len(lines[0]) + 1
                self._lines = []
                self._orphan, self._held = self._held + 1, 0
                self._start(line)
        elif not line:
            self._lines = []
            self._finish(lines)
        else:
            lines.append(line)
            if len(lines) > self.max_lines:
                self._drop_reply("oversize")

    def _finish(self, lines: list[bytes]) -> None:
        # Iterative, not recursive: each pass starts strictly later in ``lines``.
        while lines:
            try:
                self._out.append(parse_lines(lines, where="SCIP stream"))
                self.stats.frames_ok += 1
                return
            except ScipError as err:
                first_err = err
            if first_err.reason in SALVAGEABLE and self._salvage(lines):
                return
            k, at = self._embedded_start(lines)
            if k < 0:
                self._count(first_err.reason)
                return
            head = lines[:k]
            if at > 0:
                head = head + [lines[k][:at]]
            try:  # the head may be a whole reply that lost only its closing empty line
                self._out.append(parse_lines(head, where="SCIP stream"))
                self.stats.frames_ok += 1
            except ScipError as err:
                if not (err.reason in SALVAGEABLE and self._salvage(head)):
                    self._count(err.reason)
            lines = [lines[k][at:]] + lines[k + 1 :]

    def _salvage(self, lines: list[bytes]) -> bool:
        """A scan reply whose only faults are in its data lines: lines failing their sum, or bytes lost
        inside them (a line short of its length, two lines run together): delivered with the good
        lines' beams, the damaged lines' counted as no return (``ScanFrame.valid``). Each data line
        holds a known run of the payload, so the lines around the damage keep their beams (see
        ``parse_lines(strict=False)``). Not when its echo, status or timestamp is damaged, or every
        data line."""
        try:
            frame = parse_lines(lines, where="SCIP stream", strict=False)
        except ScipError:
            return False
        if not isinstance(frame, ScanFrame) or not 0 < frame.bad_lines < len(lines) - 3:
            return False
        self._out.append(frame)
        self.stats.salvaged += 1
        return True

    @staticmethod
    def _embedded_start(lines: list[bytes]) -> tuple[int, int]:
        for k in range(1, len(lines) - 1):
            if is_status_line(lines[k + 1]):
                at = find_echo(lines[k])
                if at >= 0:
                    return k, at
        return -1, -1
