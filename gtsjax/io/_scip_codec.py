"""SCIP 2.0 character level: checksums, the 2/3/4-character value encodings, data lines, timestamps.

Every SCIP value is written in characters that each carry 6 bits, offset by ``0x30`` (so ``'0'`` is 0
and ``'o'`` is 63), most significant character first. A line ends with one sum character,
``(sum(bytes of the line before it) & 0x3F) + 0x30``, then LF. Scan payloads are cut into lines of
64 characters (the last one shorter); one value's characters may straddle two lines, so the payload
is the concatenation of the lines with their sum characters removed.

Decoding is vectorised: the payload becomes a ``uint8`` array, reshaped to ``[n, chars]``, and the
characters are combined with shifts; there is no Python loop over values.
"""

from collections.abc import Sequence

import numpy as np

from ..errors import InputError

#: Characters per data line before the sum character.
LINE_PAYLOAD = 64
#: The timestamp is 24 bits of milliseconds (four 6-bit characters); it wraps every 2**24 ms (~4.66 h).
TIMESTAMP_MODULUS = 1 << 24
_LF = 0x0A


class ScipError(InputError):
    """A SCIP reply (or command argument) that cannot be decoded, from the strict one-shot functions.

    ``reason`` names the failure for counters: ``"checksum"``, ``"truncated"`` or ``"malformed"``
    (and ``"status"`` where a reply reports an error status that a caller asked to be OK).
    """

    def __init__(self, where: object, problem: str, reason: str = "malformed"):
        super().__init__(where, problem)
        self.reason = reason


def _as_bytes(data: bytes | bytearray | memoryview | str) -> bytes:
    if isinstance(data, str):
        try:
            return data.encode("ascii")
        except UnicodeEncodeError:
            raise ScipError("SCIP text", f"non-ASCII text {data!r}") from None
    return bytes(data)


def sum_byte(data: bytes | bytearray | memoryview) -> int:
    """The sum character of ``data`` as a byte value: ``(sum(data) & 0x3F) + 0x30``."""
    return (sum(data) & 0x3F) + 0x30


def checksum(data: bytes | str) -> str:
    """The SCIP 2.0 sum character of a line's text (everything before the sum character)."""
    return chr(sum_byte(_as_bytes(data)))


def verify_line(line: bytes | str) -> bool:
    """Whether the last character of ``line`` (no LF) is the sum of the characters before it."""
    b = _as_bytes(line)
    return len(b) >= 2 and b[-1] == sum_byte(b[:-1])


# --------------------------------------------------------------------------- values


def _check_chars(chars: int) -> None:
    if chars not in (2, 3, 4):
        raise ScipError("SCIP encoding", f"chars must be 2, 3 or 4, got {chars!r}")


def decode_values(payload: bytes | bytearray | memoryview | str | np.ndarray, chars: int) -> np.ndarray:
    """Decode a payload of ``chars``-character values into ``int32[n]`` (vectorised).

    Raises :class:`ScipError` if the length is not a multiple of ``chars`` or a character lies
    outside ``0x30..0x6F``.
    """
    _check_chars(chars)
    if isinstance(payload, np.ndarray):
        arr = payload.astype(np.uint8, copy=False).ravel()
    else:
        arr = np.frombuffer(_as_bytes(payload), dtype=np.uint8)
    if arr.size % chars:
        raise ScipError(
            "SCIP payload", f"{arr.size} characters is not a whole number of {chars}-character values", "truncated"
        )
    shifted = arr - np.uint8(0x30)  # wraps below 0x30, so one max() checks both ends of the range
    if shifted.size and int(shifted.max()) > 63:
        raise ScipError("SCIP payload", "character outside the encoding range 0x30..0x6F")
    digits = shifted.reshape(-1, chars)
    out = digits[:, 0].astype(np.int32)
    for i in range(1, chars):  # 1 to 3 passes over the whole array, not a loop over values
        out <<= 6
        out |= digits[:, i]
    return out


def decode_value(text: bytes | str) -> int:
    """Decode one value written in 2, 3 or 4 characters (its length picks the encoding)."""
    b = _as_bytes(text)
    _check_chars(len(b))
    v = 0
    for c in b:  # at most 4 characters: plain Python beats a NumPy round trip here
        d = c - 0x30
        if not 0 <= d <= 63:
            raise ScipError("SCIP value", f"character {chr(c)!r} outside the encoding range 0x30..0x6F")
        v = (v << 6) | d
    return v


def encode_values(values: Sequence[int] | np.ndarray, chars: int) -> bytes:
    """Encode non-negative integers below ``64**chars`` in ``chars`` characters each (vectorised)."""
    _check_chars(chars)
    v = np.asarray(values)
    if v.size == 0:
        return b""
    if not np.issubdtype(v.dtype, np.integer):
        if not np.all(np.isfinite(v)) or not np.array_equal(v, np.round(v)):
            raise ScipError("SCIP encoding", "values must be integers")
    v = v.astype(np.int64).ravel()
    if int(v.min()) < 0 or int(v.max()) >= 1 << (6 * chars):
        raise ScipError("SCIP encoding", f"value out of range 0..{(1 << (6 * chars)) - 1} for {chars} characters")
    shifts = 6 * np.arange(chars - 1, -1, -1, dtype=np.int64)
    digits = ((v[:, None] >> shifts[None, :]) & 0x3F) + 0x30
    return digits.astype(np.uint8).tobytes()


def encode_value(value: int, chars: int) -> bytes:
    return encode_values(np.array([value]), chars)


# --------------------------------------------------------------------------- lines


def format_line(text: bytes | str) -> bytes:
    """``text`` + its sum character + LF."""
    b = _as_bytes(text)
    return b + bytes((sum_byte(b),)) + b"\n"


def data_lines(payload: bytes | str) -> bytes:
    """Cut a payload into lines of 64 characters (the last shorter), each with its sum and LF."""
    b = _as_bytes(payload)
    n = len(b)
    if n == 0:
        return b""
    n_full = n // LINE_PAYLOAD
    out = []
    if n_full:
        full = np.frombuffer(b, dtype=np.uint8, count=n_full * LINE_PAYLOAD).reshape(n_full, LINE_PAYLOAD)
        block = np.empty((n_full, LINE_PAYLOAD + 2), dtype=np.uint8)
        block[:, :LINE_PAYLOAD] = full
        block[:, LINE_PAYLOAD] = (full.sum(axis=1, dtype=np.int64) & 0x3F) + 0x30
        block[:, LINE_PAYLOAD + 1] = _LF
        out.append(block.tobytes())
    rest = b[n_full * LINE_PAYLOAD :]
    if rest:
        out.append(format_line(rest))
    return b"".join(out)


def join_data_lines(lines: Sequence[bytes], *, where: str = "SCIP data", strict: bool = True) -> tuple[bytes, int]:
    """The payload of data lines (sum characters removed) and the number of lines whose sum fails.

    Every line but the last must carry 64 characters before its sum, the last 1 to 64. With
    ``strict`` a failing sum raises :class:`ScipError` (reason ``"checksum"``); otherwise the count of
    failing lines is returned alongside the payload.
    """
    payload, bad = data_payload(lines, where=where, strict=strict)
    return payload.tobytes(), int(bad.sum())


def data_payload(lines: Sequence[bytes], *, where: str = "SCIP data", strict: bool = True
                 ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`join_data_lines` as arrays, for the decoder: the payload (``uint8[chars]``) and, per
    line, whether it fails its sum (``bool[lines]``). One pass over the frame: the lines are joined
    once, the full ones checked as one ``[lines, 65]`` block."""
    n = len(lines)
    if n == 0:
        return np.zeros(0, np.uint8), np.zeros(0, bool)
    full_len = LINE_PAYLOAD + 1
    if n > 1 and set(map(len, lines[:-1])) != {full_len}:
        i = next(i for i in range(n - 1) if len(lines[i]) != full_len)
        raise ScipError(where, f"data line {i + 1} has {len(lines[i])} characters, expected {full_len}", "truncated")
    last = lines[-1]
    if not 2 <= len(last) <= full_len:
        raise ScipError(where, f"last data line has {len(last)} characters", "truncated")
    arr = np.frombuffer(b"".join(lines), dtype=np.uint8)
    n_full = n - 1
    return checked_payload(arr[: n_full * full_len].reshape(n_full, full_len), arr[n_full * full_len:],
                           where=where, strict=strict)


def checked_payload(full: np.ndarray, last: np.ndarray, *, where: str, strict: bool) -> tuple[np.ndarray, np.ndarray]:
    """The payload and per-line sum failures of data lines already cut into ``full`` (``[lines, ≥65]``:
    64 characters and the sum, anything after it ignored, e.g. the LF) and the ``last`` line
    (characters and sum): every sum checked at once, the payload joined in one copy. A line also fails
    where a character lies outside the encoding's ``0``–``o`` (``&`` allowed: multi-echo): the 6-bit
    sum cannot see a character moved by 64, which lands there from ``0``–``?``."""
    body = full[:, :LINE_PAYLOAD]
    tail = last[:-1].tobytes()
    payload = np.concatenate([body.reshape(-1), last[:-1]])
    bad = np.empty(full.shape[0] + 1, bool)
    bad[:-1] = ((body.sum(axis=1, dtype=np.int32) & 0x3F) + 0x30) != full[:, LINE_PAYLOAD]
    bad[-1] = int(last[-1]) != (sum(tail) & 0x3F) + 0x30
    if payload.tobytes().translate(None, _ENCODING_CHARS):  # some character outside them: find its lines
        bad[:-1] |= ((body > 0x6F) | ((body < 0x30) & (body != 0x26))).any(axis=1)
        bad[-1] |= bool(tail.translate(None, _ENCODING_CHARS))
    if strict and bad.any():
        raise ScipError(where, f"{int(bad.sum())} of {bad.size} data line(s) fail their sum", "checksum")
    return payload, bad


#: The characters a data line may carry: the encoding's ``0``–``o`` and multi-echo's ``&``.
_ENCODING_CHARS = bytes(range(0x30, 0x70)) + b"&"


# --------------------------------------------------------------------------- timestamps


def decode_timestamp_line(line: bytes | str, *, where: str = "SCIP timestamp") -> int:
    """The 24-bit millisecond timestamp from its line: four characters and a sum."""
    b = _as_bytes(line)
    if len(b) != 5:
        raise ScipError(where, f"timestamp line has {len(b)} characters, expected 5", "truncated")
    if b[4] != sum_byte(b[:4]):
        raise ScipError(where, "timestamp line fails its sum", "checksum")
    return decode_value(b[:4])


def format_timestamp_line(timestamp_ms: int) -> bytes:
    """The timestamp line for ``timestamp_ms``, wrapped modulo 2**24 as the sensor's counter is."""
    return format_line(encode_value(int(timestamp_ms) % TIMESTAMP_MODULUS, 4))


class TimestampUnwrapper:
    """Turns the sensor's wrapping 24-bit millisecond counter into a monotonic millisecond count.

    Each new stamp advances the count by the forward difference modulo 2**24. A stamp that lies
    less than half the range (2**23 ms, ~2.3 h) *behind* the previous one is taken as a reordering
    or jitter, not as a wrap: the count holds (it never decreases) and ``backsteps`` is counted.
    Gaps longer than 2**23 ms between consecutive stamps cannot be told from a step back.
    """

    def __init__(self, offset_ms: int = 0):
        self._offset = int(offset_ms)
        self._last: int | None = None
        self._count = int(offset_ms)
        self.wraps = 0
        self.backsteps = 0

    def reset(self) -> None:
        self._last = None
        self._count = self._offset
        self.wraps = 0
        self.backsteps = 0

    @property
    def last_ms(self) -> int | None:
        """The last unwrapped count, ``None`` before the first stamp."""
        return None if self._last is None else self._count

    def __call__(self, stamp_ms: int) -> int:
        return self.update(stamp_ms)

    def update(self, stamp_ms: int) -> int:
        stamp = int(stamp_ms)
        if not 0 <= stamp < TIMESTAMP_MODULUS:
            raise ScipError("SCIP timestamp", f"{stamp} is not a 24-bit millisecond stamp")
        if self._last is None:
            self._count = self._offset + stamp
            self._last = stamp
            return self._count
        delta = (stamp - self._last) % TIMESTAMP_MODULUS
        if delta >= TIMESTAMP_MODULUS // 2:
            self.backsteps += 1
            return self._count
        if stamp < self._last:
            self.wraps += 1
        self._count += delta
        self._last = stamp
        return self._count
