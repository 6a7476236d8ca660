"""SCIP 2.0 replies: parse a complete reply into a typed result, and format replies as a sensor does.

A reply is the echoed command line, a status line (two characters and a sum), payload lines, and an
empty line. Scan replies (``GD``/``GS``/``GE`` with status ``00``, ``MD``/``MS``/``ME`` data blocks
with status ``99``) carry a timestamp line and then data lines; ``VV``/``PP``/``II`` carry
``KEY:value;sum`` field lines whose sum covers ``KEY:value`` (the value may itself hold ``;``, and the
sum character may be ``;``).

Range values below 20 are error codes, not distances: :class:`ScanFrame` reports them as 0 in
``ranges_mm`` (and ``False`` in ``valid``) and keeps the codes in ``raw_ranges``.
"""

import dataclasses
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from ..errors import InputError
from ..sensors import SensorModel
from ._scip_codec import (
    LINE_PAYLOAD,
    ScipError,
    checked_payload,
    data_lines,
    data_payload,
    decode_timestamp_line,
    decode_values,
    encode_values,
    format_line,
    format_timestamp_line,
    sum_byte,
    verify_line,
)
from ._scip_commands import (
    CONTINUOUS_CODES,
    SCAN_CODES,
    STATUS_DATA,
    STATUS_OK,
    Command,
    parse_command,
    status_message,
    status_ok,
)

#: Raw range values below this are error codes (no return), not distances.
MIN_VALID_RANGE = 20
FIELD_CODES = frozenset({"VV", "PP", "II"})


@dataclasses.dataclass(frozen=True)
class Reply:
    """A reply without scan data: the echoed ``command`` line, its ``status`` and the payload lines
    as received (sum characters included, LFs removed)."""

    command: str
    status: str
    lines: tuple[str, ...] = ()

    @property
    def params(self) -> Command:
        return parse_command(self.command)

    @property
    def code(self) -> str:
        return self.params.code

    @property
    def ok(self) -> bool:
        return status_ok(self.code, self.status)

    @property
    def message(self) -> str:
        return status_message(self.code, self.status)

    @property
    def fields(self) -> dict[str, str]:
        """``KEY -> value`` of a ``VV``/``PP``/``II`` reply (sums verified)."""
        return parse_fields(self.lines, where=f"{self.command} reply")


@dataclasses.dataclass(frozen=True, eq=False)
class ScanFrame:
    """One scan reply: a ``Gx`` reply or one ``Mx`` data block.

    ``timestamp_ms`` is the sensor's raw 24-bit counter (see :class:`TimestampUnwrapper`).
    ``ranges_mm`` (``int32[n]``) holds 0 where ``valid`` is false: error codes (raw < 20), or, when
    decoded with ``strict=False``, values touched by a data line that failed its sum (``bad_lines``
    counts those lines; it is 0 for strictly decoded frames). ``remaining_scans`` is the count the
    echo of an ``Mx`` block carries, ``None`` for ``Gx``.
    """

    command: str
    status: str
    timestamp_ms: int
    ranges_mm: np.ndarray
    intensities: np.ndarray | None
    remaining_scans: int | None
    bad_lines: int
    raw_ranges: np.ndarray
    valid: np.ndarray

    @property
    def params(self) -> Command:
        return parse_command(self.command)

    @property
    def code(self) -> str:
        return self.command[:2]

    @property
    def n_values(self) -> int:
        return int(self.raw_ranges.shape[0])


# --------------------------------------------------------------------------- parsing


def _parse_status(line: bytes, where: str) -> str:
    if len(line) == 3:
        if line[2] != sum_byte(line[:2]):
            raise ScipError(where, "status line fails its sum", "checksum")
        return line[:2].decode("latin-1")
    if len(line) == 1:  # a SCIP 1.1 sensor (or one in the wrong mode) answers with one bare character
        return line.decode("latin-1")
    raise ScipError(
        where, f"status line has {len(line)} characters, expected 3", "truncated" if len(line) < 3 else "malformed"
    )


def is_status_line(line: bytes) -> bool:
    """Whether ``line`` can be a status line: two printable characters and their sum."""
    return len(line) == 3 and line[2] == sum_byte(line[:2]) and 0x20 < line[0] < 0x7F and 0x20 < line[1] < 0x7F


def parse_fields(lines: Iterable[bytes | str], *, where: str = "SCIP reply") -> dict[str, str]:
    """``KEY -> value`` from ``KEY:value;S`` lines; each sum ``S`` must cover ``KEY:value``."""
    out: dict[str, str] = {}
    for i, raw in enumerate(lines):
        line = raw.encode("latin-1") if isinstance(raw, str) else bytes(raw)
        if len(line) < 4 or line[-2] != 0x3B:
            raise ScipError(where, f"field line {i + 1} is not KEY:value;sum: {line[:40]!r}", "malformed")
        body = line[:-2]
        if line[-1] != sum_byte(body):
            raise ScipError(where, f"field line {i + 1} ({body[:8]!r}) fails its sum", "checksum")
        key, sep, value = body.partition(b":")
        if not sep or not key:
            raise ScipError(where, f"field line {i + 1} has no KEY: {line[:40]!r}", "malformed")
        out[key.decode("latin-1")] = value.decode("latin-1")
    return out


def parse_lines(lines: Sequence[bytes], *, where: str = "SCIP reply", strict: bool = True) -> "Reply | ScanFrame":
    """Parse one reply given as its lines (LFs and the closing empty line removed).

    Raises :class:`ScipError` with ``reason`` ``"checksum"``, ``"truncated"`` or ``"malformed"``.
    ``strict=False`` accepts scan data lines that fail their sum (see :class:`ScanFrame`).
    """
    if not lines:
        raise ScipError(where, "empty reply", "truncated")
    cmd = parse_command(lines[0], where=where)
    if len(lines) < 2:
        raise ScipError(where, f"{cmd.text}: no status line", "truncated")
    status = _parse_status(lines[1], where)
    payload = lines[2:]
    if len(status) == 1 and cmd.code in SCAN_CODES and payload:
        # A SCIP 1.1 answer is one bare character and nothing after; a scan reply that lost its status
        # line (the timestamp's sum character left as the "status") must not pass as a reply.
        raise ScipError(where, f"{cmd.text}: one-character status followed by {len(payload)} line(s)", "malformed")
    data_status = STATUS_DATA if cmd.code in CONTINUOUS_CODES else STATUS_OK
    if cmd.code in SCAN_CODES and status == data_status:
        return _parse_scan(cmd, lines[0], status, payload, where, strict)
    if cmd.code in FIELD_CODES and status == STATUS_OK:
        parse_fields(payload, where=where)
    else:
        for i, line in enumerate(payload):
            if not verify_line(line):
                raise ScipError(where, f"payload line {i + 1} fails its sum", "checksum")
    return Reply(lines[0].decode("latin-1"), status, tuple(line.decode("latin-1") for line in payload))


def _parse_scan(
    cmd: Command, echo: bytes, status: str, payload: Sequence[bytes], where: str, strict: bool
) -> ScanFrame:
    if not payload:
        raise ScipError(where, f"{cmd.text}: no timestamp", "truncated")
    stamp = decode_timestamp_line(payload[0], where=where)
    lines = payload[1:]
    if not lines:
        raise ScipError(where, f"{cmd.text}: no data lines", "truncated")
    try:
        data, bad_lines = data_payload(lines, where=where, strict=strict)
    except ScipError as err:
        relaid = None if strict or err.reason != "truncated" else _relaid(cmd, lines)
        if relaid is None:
            raise
        lines = relaid
        data, bad_lines = data_payload(lines, where=where, strict=False)
    return _scan_frame(cmd, echo, status, stamp, data, bad_lines, lambda: [len(line) - 1 for line in lines], where)


def _relaid(cmd: Command, lines: Sequence[bytes]) -> "list[bytes] | None":
    """The data lines of a scan reply that lost bytes inside its data (one line short of its length,
    or two or more run together where line feeds were lost), laid out again as the command implies:
    every line of the right length kept, the damaged one replaced by as many placeholder lines as it
    spans, with a sum that fails, so that its beams count as no return. Each line of a reply holds a
    fixed run of the payload's characters, so the lines around the damage keep their beams. ``None``
    where the damage cannot be placed for sure: more than one damaged line (a line feed inserted, say,
    which shifts every line after it), more lines than the command implies, a damaged line whose
    length is far from the lines it would span, multi-echo replies (whose length varies)."""
    chars, per_step = SCAN_CODES[cmd.code]
    if cmd.is_multiecho or cmd.n_values is None:
        return None
    total = cmd.n_values * chars * per_step
    n_chunks = -(-total // LINE_PAYLOAD)
    last_len = total - (n_chunks - 1) * LINE_PAYLOAD + 1
    full_len = LINE_PAYLOAD + 1
    if not 0 < len(lines) <= n_chunks:
        return None
    ok = [len(line) == full_len for line in lines[:-1]] + [len(lines[-1]) == last_len]
    damaged = [i for i, good in enumerate(ok) if not good]
    if len(damaged) != 1:
        return None
    (d,) = damaged
    span = 1 + n_chunks - len(lines)  # the line feeds lost run that many lines into this one
    widths = [LINE_PAYLOAD if k < n_chunks - 1 else last_len - 1 for k in range(d, d + span)]
    spanned = sum(w + 1 for w in widths) + span - 1  # their characters, sums and inner line feeds
    if abs(len(lines[d]) - spanned) > MAX_LOST_BYTES:
        return None
    placeholders = [b"0" * w + (b"1" if sum_byte(b"0" * w) != 0x31 else b"2") for w in widths]
    return [bytes(line) for line in lines[:d]] + placeholders + [bytes(line) for line in lines[d + 1:]]


#: How far (bytes) a damaged data line's length may be from the lines it spans for
#: :func:`_relaid` to place it: a few bytes lost or garbled, not a line's worth.
MAX_LOST_BYTES = 16


def _scan_frame(cmd: Command, echo: bytes, status: str, stamp: int, data: np.ndarray, bad_lines: np.ndarray,
                line_chars, where: str) -> ScanFrame:
    """A scan reply's frame from its payload (``uint8``) and which of its data lines failed their sum
    (``line_chars()``: the payload characters of each line, asked for only when one failed)."""
    chars, per_step = SCAN_CODES[cmd.code]
    n = cmd.n_values
    assert n is not None
    keep = None
    if cmd.is_multiecho and np.any(data == 0x26):
        data, keep = _first_echoes(data, chars * per_step)
    expected = n * chars * per_step
    if len(data) != expected:
        reason = "truncated" if len(data) < expected else "malformed"
        raise ScipError(where, f"{cmd.text}: {len(data)} data characters, expected {expected}", reason)
    if bad_lines.any():  # a failing line may hold characters outside the encoding: its values are dropped below
        data = np.where((data >= 0x30) & (data <= 0x6F), data, np.uint8(0x30))
    values = decode_values(data, chars)
    if per_step == 2:
        pairs = values.reshape(n, 2)
        raw, intensities = pairs[:, 0].copy(), pairs[:, 1].copy()
    else:
        raw, intensities = values, None
    valid = raw >= MIN_VALID_RANGE
    bad = int(bad_lines.sum())
    if bad:
        per_char = np.repeat(bad_lines, line_chars())
        if keep is not None:
            per_char = per_char[keep]
        valid &= ~per_char.reshape(n, chars * per_step).any(axis=1)
    ranges = np.where(valid, raw, np.int32(0))
    remaining = cmd.count if cmd.is_continuous else None
    return ScanFrame(echo.decode("latin-1"), status, stamp, ranges, intensities, remaining, bad, raw, valid)


def _first_echoes(data: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A multi-echo payload cut to each step's first echo: every ``&`` and the ``size`` characters
    after it are dropped. Returns the kept characters and the mask of them."""
    keep = np.ones(len(data), bool)
    for i in np.flatnonzero(data == 0x26):
        keep[i : i + 1 + size] = False
    return data[keep], keep


_FULL_LINE = LINE_PAYLOAD + 2  # a full data line: 64 characters, its sum, LF


def _scan_reply_whole(b: bytes, strict: bool) -> "ScanFrame | None":
    """One scan reply decoded as one block, without cutting its data lines apart: the lines a command
    implies are checked and joined as one ``[lines, 66]`` array. ``None`` where ``b`` is anything else
    (another reply, several, a data block of another shape, a CR): :func:`parse_lines` then parses it
    line by line and says what is wrong."""
    if not b.endswith(b"\n\n") or b"\r" in b:
        return None
    i0 = b.find(b"\n")
    i1 = b.find(b"\n", i0 + 1)
    i2 = b.find(b"\n", i1 + 1)
    if i2 < 0:
        return None
    try:
        cmd = parse_command(b[:i0])
    except ScipError:
        return None
    if cmd.code not in SCAN_CODES or cmd.n_values is None:
        return None
    status = _parse_status(b[i0 + 1:i1], "SCIP reply")
    if status != (STATUS_DATA if cmd.code in CONTINUOUS_CODES else STATUS_OK):
        return None
    chars, per_step = SCAN_CODES[cmd.code]
    total = cmd.n_values * chars * per_step
    n_full, last = divmod(total - 1, LINE_PAYLOAD)
    last += 1
    block = np.frombuffer(b, np.uint8, offset=i2 + 1, count=len(b) - i2 - 2)  # the data lines, each with its LF
    if total < 1 or block.size != n_full * _FULL_LINE + last + 2 or np.count_nonzero(block == 0x0A) != n_full + 1:
        return None
    full = block[: n_full * _FULL_LINE].reshape(n_full, _FULL_LINE)
    tail = block[n_full * _FULL_LINE:]
    if (n_full and not np.all(full[:, -1] == 0x0A)) or tail[-1] != 0x0A:
        return None
    stamp = decode_timestamp_line(b[i1 + 1:i2], where="SCIP reply")
    data, bad = checked_payload(full, tail[:-1], where="SCIP reply", strict=strict)
    return _scan_frame(cmd, b[:i0], status, stamp, data, bad, lambda: [LINE_PAYLOAD] * n_full + [last], "SCIP reply")


def split_replies(data: bytes) -> list[list[bytes]]:
    """The replies in ``data`` as lists of lines. A last reply that lacks its closing empty line
    (or its final LF) at the end of ``data`` is kept: published captures often drop it."""
    b = bytes(data)
    if b"\r" in b:
        b = b.replace(b"\r\n", b"\n")
    if b.endswith(b"\n\n") and b.find(b"\n\n") == len(b) - 2 and not b.startswith(b"\n"):
        return [b[:-2].split(b"\n")]  # the common case, one whole reply: no per-line loop
    lines = b.split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    blocks: list[list[bytes]] = []
    cur: list[bytes] = []
    for line in lines:
        if line:
            cur.append(line)
        elif cur:
            blocks.append(cur)
            cur = []
        else:
            raise ScipError("SCIP data", "empty line outside a reply", "malformed")
    if cur:
        blocks.append(cur)
    return blocks


def parse_replies(data: bytes, *, strict: bool = True) -> "list[Reply | ScanFrame]":
    """Parse every reply in ``data`` (strict: the first bad one raises :class:`ScipError`)."""
    blocks = split_replies(data)
    return [parse_lines(block, where=f"SCIP reply {i + 1}", strict=strict) for i, block in enumerate(blocks)]


def parse_reply(data: bytes, *, strict: bool = True) -> "Reply | ScanFrame":
    """Parse exactly one complete reply; :class:`ScipError` if ``data`` is not one. A scan reply is
    decoded as one block (:func:`_scan_reply_whole`), anything else line by line."""
    frame = _scan_reply_whole(bytes(data), strict)
    if frame is not None:
        return frame
    blocks = split_replies(data)
    if len(blocks) != 1:
        raise ScipError(
            "SCIP data", f"expected one reply, found {len(blocks)}", "truncated" if not blocks else "malformed"
        )
    return parse_lines(blocks[0], strict=strict)


def decode_scan(data: bytes, *, strict: bool = True) -> ScanFrame:
    """Parse one scan reply (``Gx``, or an ``Mx`` data block); :class:`ScipError` for anything else."""
    out = parse_reply(data, strict=strict)
    if not isinstance(out, ScanFrame):
        raise ScipError(out.command, f"not a scan reply (status {out.status!r}: {out.message})", "status")
    return out


def sensor_model_from_pp(reply: "Reply | bytes") -> SensorModel:
    """The :class:`SensorModel` a ``PP`` reply describes (via :meth:`SensorModel.from_pp`)."""
    if not isinstance(reply, Reply):
        parsed = parse_reply(reply)
        if not isinstance(parsed, Reply):
            raise ScipError("PP reply", "not a PP reply")
        reply = parsed
    if reply.code != "PP":
        raise ScipError(reply.command, "not a PP reply")
    if reply.status != STATUS_OK:
        raise ScipError("PP reply", f"status {reply.status!r}", "status")
    try:
        return SensorModel.from_pp(reply.fields, where="PP reply")
    except ScipError:
        raise
    except InputError as err:
        raise ScipError(err.where, err.problem) from None


# --------------------------------------------------------------------------- formatting


def _text(x: "bytes | str | Command") -> bytes:
    if isinstance(x, Command):
        return x.text.encode("ascii")
    return x.encode("ascii") if isinstance(x, str) else bytes(x)


def format_reply(
    echo: "bytes | str | Command", status: str = STATUS_OK, payload_lines: "bytes | Sequence[bytes | str]" = ()
) -> bytes:
    """A complete reply: echo, status and its sum, the payload, and the closing empty line.

    ``payload_lines`` is either already formatted bytes (lines with sums and LFs, as from
    :func:`data_lines` or :func:`format_fields`), or a sequence of lines that already end in their sum.
    """
    if isinstance(payload_lines, bytes | bytearray):
        payload = bytes(payload_lines)
    else:
        payload = b"".join(_text(line) + b"\n" for line in payload_lines)
    return _text(echo) + b"\n" + format_line(status) + payload + b"\n"


def format_fields(fields: Mapping[str, str]) -> bytes:
    """``KEY:value;S`` lines (each with LF) for a ``VV``/``PP``/``II`` reply."""
    out = []
    for key, value in fields.items():
        body = f"{key}:{value}".encode("ascii")
        out.append(body + b";" + bytes((sum_byte(body),)) + b"\n")
    return b"".join(out)


def format_field_reply(echo: "bytes | str | Command", fields: Mapping[str, str], status: str = STATUS_OK) -> bytes:
    return format_reply(echo, status, format_fields(fields))


def format_pp_reply(model: SensorModel, echo: "bytes | str | Command" = "PP") -> bytes:
    """The ``PP`` reply a sensor of ``model`` sends."""
    return format_field_reply(echo, model.pp_fields())


def format_scan_frame(
    echo: "bytes | str | Command",
    status: str,
    timestamp_ms: int,
    ranges_mm: "np.ndarray | Sequence[int]",
    intensities: "np.ndarray | Sequence[int] | None" = None,
    chars: int | None = None,
) -> bytes:
    """A scan reply. ``ranges_mm`` are raw values (error codes below 20 included); ``chars`` defaults
    to the command's encoding and must agree with it; ``intensities`` are required exactly for
    ``GE``/``ME``/``HE``/``NE``; the timestamp is written modulo 2**24. A multi-echo command
    (``HD``/``HE``/``ND``/``NE``) also takes ``[n_values, echoes]`` arrays: column 0 the first echo,
    a later column's 0 range no further echo."""
    cmd = echo if isinstance(echo, Command) else parse_command(_text(echo), where="echo")
    if not cmd.is_scan:
        raise ScipError(cmd.text, "not a scan command")
    assert cmd.chars is not None
    if chars is not None and chars != cmd.chars:
        raise ScipError(cmd.text, f"{cmd.code} uses {cmd.chars}-character values, not {chars}")
    r = np.asarray(ranges_mm)
    echoes = cmd.is_multiecho and r.ndim == 2
    if (r.ndim != 1 and not echoes) or r.shape[0] != cmd.n_values:
        raise ScipError(cmd.text, f"{r.shape} ranges given, the command asks for {cmd.n_values}")
    if cmd.has_intensity:
        if intensities is None:
            raise ScipError(cmd.text, f"{cmd.code} needs intensities")
        inten = np.asarray(intensities)
        if inten.shape != r.shape:
            raise ScipError(cmd.text, f"intensities shape {inten.shape} differs from ranges {r.shape}")
        values = np.stack([r, inten], axis=-1)
    else:
        if intensities is not None:
            raise ScipError(cmd.text, f"{cmd.code} carries no intensities (use GE/ME)")
        values = r
    if echoes:
        # Multi-echo: each step's first echo, then "&" and the value(s) of each further echo that
        # returned (a range of 0 in a later column is no echo), as urg_library's parser reads them.
        per = values.reshape(r.shape[0], r.shape[1], -1)
        parts = []
        for k in range(r.shape[0]):
            parts.append(encode_values(per[k, 0], cmd.chars))
            for j in range(1, r.shape[1]):
                if r[k, j] > 0:
                    parts.append(b"&" + encode_values(per[k, j], cmd.chars))
        payload = b"".join(parts)
    else:
        payload = encode_values(values, cmd.chars)
    return format_reply(cmd, status, format_timestamp_line(timestamp_ms) + data_lines(payload))


def format_md_frame(
    echo_with_remaining: "bytes | str | Command",
    timestamp_ms: int,
    ranges_mm: "np.ndarray | Sequence[int]",
    intensities: "np.ndarray | Sequence[int] | None" = None,
    chars: int | None = None,
) -> bytes:
    """One ``MD``/``MS``/``ME``/``ND``/``NE`` data block (status ``99``); the echo carries the remaining-scan count."""
    return format_scan_frame(echo_with_remaining, STATUS_DATA, timestamp_ms, ranges_mm, intensities, chars)


def format_gd_frame(
    echo: "bytes | str | Command",
    timestamp_ms: int,
    ranges_mm: "np.ndarray | Sequence[int]",
    intensities: "np.ndarray | Sequence[int] | None" = None,
    chars: int | None = None,
) -> bytes:
    """A ``GD``/``GS``/``GE``/``HD``/``HE`` reply (status ``00``)."""
    return format_scan_frame(echo, STATUS_OK, timestamp_ms, ranges_mm, intensities, chars)
