"""SCIP 2.0 commands: builders for each command string, the parsed echo, and the status-code tables.

A command is a line the host sends; the sensor echoes it back as the first line of its reply. The
scan commands carry numeric fields (``GD`` + start(4) + end(4) + cluster(2); ``MD`` adds the scan
interval (1) and the number of scans (2)); any command may end in an optional ``;string`` of up to 16
characters, echoed back unchanged. In continuous mode (``MD``/``MS``/``ME``) each data block's echo
carries the *remaining* number of scans in place of the requested count.
"""

import dataclasses
import math
import re

from ._scip_codec import ScipError

#: Scan commands: code -> (characters per value, values per step: 1 range, or 2 range + intensity).
SCAN_CODES: dict[str, tuple[int, int]] = {
    "GD": (3, 1),
    "GS": (2, 1),
    "GE": (3, 2),
    "MD": (3, 1),
    "MS": (2, 1),
    "ME": (3, 2),
    # Multi-echo (UTM-30LX): HD/HE one scan, ND/NE continuous; each step is its first echo's value(s),
    # then ``&`` and the value(s) of each further echo (see :func:`format_scan_frame`).
    "HD": (3, 1),
    "HE": (3, 2),
    "ND": (3, 1),
    "NE": (3, 2),
}
CONTINUOUS_CODES = frozenset({"MD", "MS", "ME", "ND", "NE"})
MULTIECHO_CODES = frozenset({"HD", "HE", "ND", "NE"})
SIMPLE_CODES = frozenset({"VV", "PP", "II", "BM", "QT", "RS", "RT", "SCIP2.0"})
MAX_STRING = 16

STATUS_OK = "00"
STATUS_DATA = "99"

_STRING = rb"(?:;[\x20-\x7e]{0,16})?"
# One pattern per family, anchored at the end so that garbage glued in front of an echo is skipped.
ECHO_RE = re.compile(
    rb"(?:(?P<g>G[DSE]|H[DE])(?P<gs>\d{4})(?P<ge>\d{4})(?P<gc>\d{2})"
    rb"|(?P<m>M[DSE]|N[DE])(?P<ms>\d{4})(?P<me>\d{4})(?P<mc>\d{2})(?P<mi>\d)(?P<mn>\d{2})"
    rb"|(?P<t>TM[012])"
    rb"|(?P<s>VV|PP|II|BM|QT|RS|RT|SCIP2\.0))"
    rb"(?P<str>" + _STRING + rb")\Z"
)


@dataclasses.dataclass(frozen=True)
class Command:
    """A parsed SCIP command (or its echo).

    ``count`` is the requested number of scans in a command, the remaining number in an ``Mx`` data
    block's echo. Fields that a command does not carry are ``None``.
    """

    code: str
    start: int | None = None
    end: int | None = None
    cluster: int | None = None
    interval: int | None = None
    count: int | None = None
    string: str | None = None

    @property
    def is_scan(self) -> bool:
        return self.code in SCAN_CODES

    @property
    def is_continuous(self) -> bool:
        return self.code in CONTINUOUS_CODES

    @property
    def chars(self) -> int | None:
        """Characters per value of a scan command, else ``None``."""
        spec = SCAN_CODES.get(self.code)
        return None if spec is None else spec[0]

    @property
    def is_multiecho(self) -> bool:
        """``HD``/``HE``/``ND``/``NE``: every echo of each step, ``&`` before each after the first."""
        return self.code in MULTIECHO_CODES

    @property
    def has_intensity(self) -> bool:
        return SCAN_CODES.get(self.code, (0, 1))[1] == 2

    @property
    def n_values(self) -> int | None:
        """Values (steps after clustering) a scan reply carries: ``ceil((end - start + 1) / cluster)``."""
        if not self.is_scan:
            return None
        assert self.start is not None and self.end is not None and self.cluster is not None
        return math.ceil((self.end - self.start + 1) / max(self.cluster, 1))

    @property
    def text(self) -> str:
        if self.code in SCAN_CODES:
            s = f"{self.code}{self.start:04d}{self.end:04d}{self.cluster:02d}"
            if self.is_continuous:
                s += f"{self.interval:01d}{self.count:02d}"
        else:
            s = self.code
        if self.string is not None:
            s += ";" + self.string
        return s

    def encode(self) -> bytes:
        """The command line as sent, with its LF."""
        return self.text.encode("ascii") + b"\n"

    def with_remaining(self, remaining: int) -> "Command":
        """This ``Mx`` command as echoed in a data block with ``remaining`` scans still to come."""
        if not self.is_continuous:
            raise ScipError(self.text, "only MD/MS/ME/ND/NE echoes carry a remaining-scan count")
        _check_range("remaining scans", remaining, 0, 99)
        return dataclasses.replace(self, count=remaining)


def parse_command(text: bytes | str, *, where: str = "SCIP echo") -> Command:
    """Parse a command line or its echo (no LF). Raises :class:`ScipError` if it is not one."""
    b = text.encode("latin-1") if isinstance(text, str) else bytes(text)
    cmd = _ECHOES.get(b)
    if cmd is not None:
        return cmd
    m = ECHO_RE.match(b)
    if m is None:
        raise ScipError(where, f"not a SCIP 2.0 command: {b[:40]!r}")
    cmd = _command_from_match(m, where)
    if len(_ECHOES) < 256:  # a stream repeats a few echoes (the remaining count cycles through 100 values)
        _ECHOES[b] = cmd
    return cmd


# Parsed echoes by their bytes: a frame's echo is parsed once, not once per frame (a regular
# expression and a dataclass were a sixth of a UTM-30LX frame's decoding time). Commands are frozen.
_ECHOES: dict[bytes, Command] = {}


def find_echo(line: bytes) -> int:
    """Where a command echo starts such that it runs to the end of ``line``; -1 if none does."""
    m = ECHO_RE.search(line)
    return -1 if m is None else m.start()


def _command_from_match(m: re.Match, where: str) -> Command:
    raw = m.group("str")
    string = raw[1:].decode("ascii") if raw else None
    if m.group("g"):
        start, end = int(m.group("gs")), int(m.group("ge"))
        cmd = Command(m.group("g").decode(), start, end, int(m.group("gc")), string=string)
    elif m.group("m"):
        start, end = int(m.group("ms")), int(m.group("me"))
        cmd = Command(
            m.group("m").decode(), start, end, int(m.group("mc")), int(m.group("mi")), int(m.group("mn")), string
        )
    elif m.group("t"):
        cmd = Command(m.group("t").decode(), string=string)
    else:
        cmd = Command(m.group("s").decode(), string=string)
    if cmd.is_scan and cmd.end < cmd.start:  # type: ignore[operator]
        raise ScipError(where, f"end step {cmd.end} before start step {cmd.start}")
    return cmd


# --------------------------------------------------------------------------- builders


def _check_range(name: str, value: int, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ScipError("SCIP command", f"{name} must be an integer in {lo}..{hi}, got {value!r}")
    return value


def _check_string(string: str | None) -> str | None:
    if string is None:
        return None
    if len(string) > MAX_STRING or not all(0x20 <= ord(c) <= 0x7E for c in string):
        raise ScipError("SCIP command", f"string must be at most {MAX_STRING} printable ASCII characters: {string!r}")
    return string


def _simple(code: str, string: str | None) -> bytes:
    return Command(code, string=_check_string(string)).encode()


def scip2_command() -> bytes:
    """``SCIP2.0``: switch a SCIP 1.1 sensor to SCIP 2.0."""
    return b"SCIP2.0\n"


def vv_command(string: str | None = None) -> bytes:
    """``VV``: version information."""
    return _simple("VV", string)


def pp_command(string: str | None = None) -> bytes:
    """``PP``: sensor parameters (AMIN, AMAX, ARES, AFRT, DMIN, DMAX, SCAN)."""
    return _simple("PP", string)


def ii_command(string: str | None = None) -> bytes:
    """``II``: status information."""
    return _simple("II", string)


def bm_command(string: str | None = None) -> bytes:
    """``BM``: laser on."""
    return _simple("BM", string)


def qt_command(string: str | None = None) -> bytes:
    """``QT``: laser off (stops continuous scanning)."""
    return _simple("QT", string)


def rs_command(string: str | None = None) -> bytes:
    """``RS``: reset the sensor's settings."""
    return _simple("RS", string)


def tm_command(mode: int, string: str | None = None) -> bytes:
    """``TM0`` enter time-adjust mode, ``TM1`` read the sensor clock, ``TM2`` leave the mode."""
    _check_range("TM mode", mode, 0, 2)
    return Command(f"TM{mode}", string=_check_string(string)).encode()


def _single(code: str, start: int, end: int, cluster: int, string: str | None) -> bytes:
    _check_range("start step", start, 0, 9999)
    _check_range("end step", end, 0, 9999)
    _check_range("cluster count", cluster, 0, 99)
    if end < start:
        raise ScipError("SCIP command", f"end step {end} before start step {start}")
    return Command(code, start, end, cluster, string=_check_string(string)).encode()


def _multi(code: str, start: int, end: int, cluster: int, skip: int, count: int, string: str | None) -> bytes:
    _check_range("start step", start, 0, 9999)
    _check_range("end step", end, 0, 9999)
    _check_range("cluster count", cluster, 0, 99)
    _check_range("scan interval", skip, 0, 9)
    _check_range("number of scans", count, 0, 99)
    if end < start:
        raise ScipError("SCIP command", f"end step {end} before start step {start}")
    return Command(code, start, end, cluster, skip, count, _check_string(string)).encode()


def gd_command(start: int, end: int, cluster: int = 1, string: str | None = None) -> bytes:
    """``GD``: one scan, ranges in 3 characters."""
    return _single("GD", start, end, cluster, string)


def gs_command(start: int, end: int, cluster: int = 1, string: str | None = None) -> bytes:
    """``GS``: one scan, ranges in 2 characters (0..4095 mm)."""
    return _single("GS", start, end, cluster, string)


def ge_command(start: int, end: int, cluster: int = 1, string: str | None = None) -> bytes:
    """``GE``: one scan, range and intensity per step, 3 characters each."""
    return _single("GE", start, end, cluster, string)


def md_command(
    start: int, end: int, cluster: int = 1, skip: int = 0, count: int = 0, string: str | None = None
) -> bytes:
    """``MD``: continuous scans (``count`` scans, 0 = until ``QT``), ranges in 3 characters;
    ``skip`` scans are skipped between transmitted ones."""
    return _multi("MD", start, end, cluster, skip, count, string)


def ms_command(
    start: int, end: int, cluster: int = 1, skip: int = 0, count: int = 0, string: str | None = None
) -> bytes:
    """``MS``: as ``MD`` with ranges in 2 characters."""
    return _multi("MS", start, end, cluster, skip, count, string)


def me_command(
    start: int, end: int, cluster: int = 1, skip: int = 0, count: int = 0, string: str | None = None
) -> bytes:
    """``ME``: as ``MD`` with range and intensity per step."""
    return _multi("ME", start, end, cluster, skip, count, string)


# --------------------------------------------------------------------------- status codes

# From Hokuyo's SCIP 2.0 specification (C-42-03320B), as tabulated in shared/data/scip/spec_vectors.json.
_SCAN_ERRORS = {
    "01": "start step non-numeric",
    "02": "end step non-numeric",
    "03": "cluster count non-numeric",
    "04": "end step out of range",
    "05": "end step < start step",
}
_STATUS_TABLES: dict[str, dict[str, str]] = {
    "M": {
        "00": "command received OK",
        "99": "data follows",
        **_SCAN_ERRORS,
        "06": "scan interval non-numeric",
        "07": "number of scans non-numeric",
        "98": "resumed after confirming normal laser operation",
    },
    "G": {"00": "OK", **_SCAN_ERRORS, "10": "laser is off"},
    "TM": {
        "00": "OK",
        "01": "invalid control code",
        "02": "adjust mode already on",
        "03": "adjust mode already off",
        "04": "adjust mode off when time requested",
    },
    "BM": {"00": "OK", "01": "unable to control the laser (malfunction)", "02": "laser already on"},
}


def status_message(code: str, status: str) -> str:
    """A short description of ``status`` in reply to command ``code`` (e.g. ``"MD"``, ``"GD"``)."""
    family = {"N": "M", "H": "G"}.get(code[:1], code[:1]) if code in SCAN_CODES else code[:2]
    table = _STATUS_TABLES.get(family, {})
    if status in table:
        return table[status]
    if status == STATUS_OK:
        return "OK"
    if status.isdigit():
        n = int(status)
        if family == "M" and 21 <= n <= 49:
            return "processing stopped to verify error"
        if family == "M" and 50 <= n <= 97:
            return "hardware trouble"
        if family == "G" and 50 <= n <= 98:
            return "hardware trouble"
    if status == "0E" and code == "QT":
        return "sensor in time-adjust (TM) mode"
    if len(status) == 1:
        return "SCIP 1.1 reply"
    return f"status {status!r}"


def status_ok(code: str, status: str) -> bool:
    """Whether ``status`` means success for command ``code`` (``99`` counts for ``Mx`` data blocks)."""
    return status == STATUS_OK or (code in CONTINUOUS_CODES and status == STATUS_DATA)
