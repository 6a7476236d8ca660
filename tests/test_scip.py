"""SCIP 2.0 codec: known answers from the specification, real captures, round trips, and a stream
decoder that survives whatever the link delivers."""

import json
import math
import os
import random

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gtsjax.io import scip
from gtsjax.sensors import MODELS, URG_04LX, UTM_30LX

# GTSJAX_FUZZ_EXAMPLES=2000 for a longer search than the quick default.
FUZZ = settings(
    max_examples=int(os.environ.get("GTSJAX_FUZZ_EXAMPLES", "60")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)


@pytest.fixture(scope="module")
def scip_dir(shared_file):
    return shared_file("data", "scip")


@pytest.fixture(scope="module")
def vectors(scip_dir):
    return json.loads((scip_dir / "spec_vectors.json").read_text())


def _read(scip_dir, name):
    return (scip_dir / name).read_bytes()


# ----------------------------------------------------------------------------- reference (obvious) code


def ref_decode(text: bytes, chars: int) -> list[int]:
    out = []
    for i in range(0, len(text), chars):
        v = 0
        for c in text[i : i + chars]:
            v = (v << 6) | (c - 0x30)
        out.append(v)
    return out


def ref_sum(text: bytes) -> int:
    return (sum(text) & 0x3F) + 0x30


# ----------------------------------------------------------------------------- spec vectors


def test_checksum_vectors(vectors):
    for v in vectors["checksum"]:
        assert scip.checksum(v["text"]) == v["sum_char"], v
        assert scip.verify_line(v["text"] + v["sum_char"])


def test_decode_vectors(vectors):
    for v in vectors["decode"]:
        assert scip.decode_value(v["enc"]) == v["value"]
        assert scip.decode_values(v["enc"], v["chars"]).tolist() == [v["value"]]
        assert scip.encode_value(v["value"], v["chars"]) == v["enc"].encode()


def test_time_field_with_semicolon_in_value(vectors):
    (time_vec,) = [v for v in vectors["checksum"] if v["text"].startswith("TIME")]
    line = time_vec["text"] + ";" + time_vec["sum_char"]
    fields = scip.parse_fields([line])
    assert fields == {"TIME": "j;o["}
    reply = scip.parse_reply(b"II\n00P\n" + line.encode() + b"\n\n")
    assert reply.fields["TIME"] == "j;o["
    assert scip.decode_value(reply.fields["TIME"]) == ref_decode(b"j;o[", 4)[0]


def test_field_whose_sum_char_is_semicolon():
    body = next(f"SERI:H{i:07d}" for i in range(10000) if scip.checksum(f"SERI:H{i:07d}") == ";")
    assert scip.parse_fields([body + ";;"]) == {"SERI": body[5:]}
    assert scip.format_fields({"SERI": body[5:]}) == (body + ";;\n").encode()


def test_status_tables(vectors):
    md, gd = vectors["status_codes_MD_MS"], vectors["status_codes_GD_GS"]
    for code in ("01", "02", "03", "04", "05", "06", "07", "98"):
        assert scip.status_message("MD", code) == md[code]
    assert scip.status_message("GD", "10") == gd["10"]
    assert scip.status_message("MS", "30") == md["21-49"]
    assert scip.status_message("GS", "98") == gd["50-98"]
    assert scip.status_message("BM", "02") == "laser already on"
    assert scip.status_ok("MD", "99") and scip.status_ok("GD", "00") and not scip.status_ok("GD", "99")


# ----------------------------------------------------------------------------- characters and lines


@FUZZ
@given(chars=st.sampled_from([2, 3, 4]), data=st.data())
def test_encode_decode_round_trip(chars, data):
    values = data.draw(st.lists(st.integers(0, (1 << (6 * chars)) - 1), max_size=300))
    text = scip.encode_values(values, chars)
    assert len(text) == chars * len(values)
    assert all(0x30 <= c <= 0x6F for c in text)
    assert ref_decode(text, chars) == values
    decoded = scip.decode_values(text, chars)
    assert decoded.dtype == np.int32 and decoded.tolist() == values


def test_encode_rejects_out_of_range():
    for chars in (2, 3, 4):
        with pytest.raises(scip.ScipError):
            scip.encode_values([1 << (6 * chars)], chars)
        with pytest.raises(scip.ScipError):
            scip.encode_values([-1], chars)
    with pytest.raises(scip.ScipError):
        scip.encode_values([1], 5)
    with pytest.raises(scip.ScipError):
        scip.decode_values(b"0000", 3)  # not a whole number of values
    with pytest.raises(scip.ScipError):
        scip.decode_values(b"0p", 2)  # 'p' is above the 6-bit range


@FUZZ
@given(payload=st.binary(max_size=400).map(lambda b: bytes(0x30 + (c & 0x3F) for c in b)))
def test_data_lines_split_and_join(payload):
    block = scip.data_lines(payload)
    lines = block.split(b"\n")
    assert lines[-1] == b""
    lines = lines[:-1]
    assert len(lines) == math.ceil(len(payload) / 64)
    for i, line in enumerate(lines):
        assert len(line) == (65 if i < len(lines) - 1 else len(payload) - 64 * i + 1)
        assert line[-1] == ref_sum(line[:-1])
    joined, bad = scip.join_data_lines(lines)
    assert joined == payload and bad == 0


def test_value_split_across_lines():
    values = np.arange(100, 100 + 30)  # 90 characters: value 21 straddles the first line break
    block = scip.data_lines(scip.encode_values(values, 3))
    lines = block.split(b"\n")[:-1]
    assert len(lines[0]) == 65 and (64 % 3) != 0
    payload, _ = scip.join_data_lines(lines)
    assert scip.decode_values(payload, 3).tolist() == values.tolist()


def test_timestamp_line_wraps():
    line = scip.format_timestamp_line((1 << 24) + 5)
    assert scip.decode_timestamp_line(line[:-1]) == 5
    assert scip.decode_timestamp_line(b"m2@0" + scip.checksum("m2@0").encode()) == 16000000
    with pytest.raises(scip.ScipError) as err:
        scip.decode_timestamp_line(b"1l4l")
    assert err.value.reason == "truncated"


def test_timestamp_unwrapper():
    unwrap = scip.TimestampUnwrapper()
    stamps = np.arange(0, 3 * (1 << 24), 997_001, dtype=np.int64)
    out = [unwrap(int(s % (1 << 24))) for s in stamps]
    assert out == stamps.tolist()
    assert unwrap.wraps == 2
    last = out[-1]
    assert unwrap(int((stamps[-1] - 10) % (1 << 24))) == last  # a step back holds, never decreases
    assert unwrap.backsteps == 1
    assert unwrap(int((stamps[-1] + 25) % (1 << 24))) == last + 25
    unwrap.reset()
    assert unwrap.last_ms is None and unwrap(7) == 7


# ----------------------------------------------------------------------------- commands


def test_command_builders():
    assert scip.scip2_command() == b"SCIP2.0\n"
    assert scip.vv_command() == b"VV\n" and scip.pp_command() == b"PP\n" and scip.ii_command() == b"II\n"
    assert scip.bm_command() == b"BM\n" and scip.qt_command() == b"QT\n" and scip.rs_command() == b"RS\n"
    assert scip.tm_command(1) == b"TM1\n"
    assert scip.gd_command(44, 725) == b"GD0044072501\n"
    assert scip.gs_command(44, 725, 3) == b"GS0044072503\n"
    assert scip.ge_command(0, 1080, 0) == b"GE0000108000\n"
    assert scip.md_command(44, 725, cluster=1, skip=0, count=3) == b"MD0044072501003\n"
    assert scip.ms_command(384, 384, count=1) == b"MS0384038401001\n"
    assert scip.me_command(0, 1080, string="abc") == b"ME0000108001000;abc\n"
    assert scip.qt_command(string="x y") == b"QT;x y\n"
    for bad in (
        lambda: scip.md_command(10, 5),
        lambda: scip.md_command(0, 10000),
        lambda: scip.md_command(0, 10, cluster=100),
        lambda: scip.md_command(0, 10, skip=10),
        lambda: scip.md_command(0, 10, count=100),
        lambda: scip.md_command(0, 10, string="x" * 17),
        lambda: scip.gd_command(0, 10, string="a\nb"),
        lambda: scip.tm_command(3),
    ):
        with pytest.raises(scip.ScipError):
            bad()


def test_parse_command_round_trip():
    for raw in (b"MD0044072501003;hello", b"GE0000108000", b"VV", b"SCIP2.0", b"TM2", b"MS0384038400000"):
        cmd = scip.parse_command(raw)
        assert cmd.encode() == raw + b"\n"
    cmd = scip.parse_command(b"MD0044072503103")
    assert (cmd.code, cmd.start, cmd.end, cmd.cluster, cmd.interval, cmd.count) == ("MD", 44, 725, 3, 1, 3)
    assert cmd.n_values == math.ceil(682 / 3) and cmd.chars == 3 and not cmd.has_intensity
    assert cmd.with_remaining(2).text == "MD0044072503102"
    with pytest.raises(scip.ScipError):
        scip.parse_command(b"XX0044072501")


# ----------------------------------------------------------------------------- frame round trips


def _raw_ranges(rng, n, hi):
    raw = rng.integers(20, hi, size=n)
    errors = rng.random(n) < 0.1
    raw[errors] = rng.integers(0, 20, size=int(errors.sum()))
    raw[:5] = [0, 1, 7, 19, 20]
    return raw


@pytest.mark.parametrize(
    "code,model,string,cluster",
    [
        ("MD", URG_04LX, None, 1),
        ("MS", URG_04LX, None, 1),
        ("GD", URG_04LX, None, 1),
        ("GS", URG_04LX, "ab;c", 1),
        ("GD", URG_04LX, None, 3),
        ("ME", UTM_30LX, None, 1),
        ("GE", UTM_30LX, None, 1),
        ("ME", UTM_30LX, "x", 2),
    ],
)
def test_scan_frame_round_trip(code, model, string, cluster):
    rng = np.random.default_rng(0)
    builder = {
        "MD": scip.md_command,
        "MS": scip.ms_command,
        "ME": scip.me_command,
        "GD": scip.gd_command,
        "GS": scip.gs_command,
        "GE": scip.ge_command,
    }[code]
    cmd = scip.parse_command(builder(model.amin, model.amax, cluster, string=string)[:-1])
    n = cmd.n_values
    assert n == math.ceil(model.n_beams / cluster)
    chars = cmd.chars
    raw = _raw_ranges(rng, n, min(1 << (6 * chars), model.dmax_mm + 1))
    inten = rng.integers(0, 1 << 18, size=n) if cmd.has_intensity else None
    stamp = 16_777_000 + 500  # beyond 2**24: written wrapped
    if cmd.is_continuous:
        echo = cmd.with_remaining(7)
        data = scip.format_md_frame(echo, stamp, raw, inten)
    else:
        echo = cmd
        data = scip.format_gd_frame(echo, stamp, raw, inten)
    for line in data.split(b"\n")[1:-2]:
        assert scip.verify_line(line)
    frame = scip.parse_reply(data)
    assert isinstance(frame, scip.ScanFrame)
    assert frame.command == echo.text
    assert frame.status == ("99" if cmd.is_continuous else "00")
    assert frame.timestamp_ms == stamp % (1 << 24)
    assert frame.remaining_scans == (7 if cmd.is_continuous else None)
    assert frame.raw_ranges.tolist() == raw.tolist()
    np.testing.assert_array_equal(frame.valid, raw >= 20)
    np.testing.assert_array_equal(frame.ranges_mm, np.where(raw >= 20, raw, 0))
    assert frame.ranges_mm.dtype == np.int32
    if inten is None:
        assert frame.intensities is None
    else:
        assert frame.intensities.tolist() == inten.tolist()
    assert frame.bad_lines == 0
    # The stream decoder agrees, fed in one go.
    dec = scip.StreamDecoder()
    (again,) = dec.feed(data)
    assert again.raw_ranges.tolist() == raw.tolist()


def test_format_scan_frame_checks_its_arguments():
    cmd = scip.parse_command(b"MS0044072501000")
    with pytest.raises(scip.ScipError):
        scip.format_md_frame(cmd, 0, np.zeros(682, int), chars=3)  # MS is 2-character
    with pytest.raises(scip.ScipError):
        scip.format_md_frame(cmd, 0, np.zeros(681, int))
    with pytest.raises(scip.ScipError):
        scip.format_md_frame(cmd, 0, np.full(682, 4096))  # does not fit 2 characters
    with pytest.raises(scip.ScipError):
        scip.format_md_frame("ME0000108001000", 0, np.zeros(1081, int))  # ME needs intensities


def test_pp_round_trip_every_known_model():
    for model in MODELS.values():
        assert scip.sensor_model_from_pp(scip.format_pp_reply(model)) == model


def test_simple_replies_round_trip():
    data = scip.format_reply("QT", "00")
    assert data == b"QT\n00P\n\n"
    assert scip.parse_reply(data) == scip.Reply("QT", "00", ())
    data = scip.format_field_reply(b"VV", {"VEND": "Hokuyo", "PROT": "SCIP 2.0"})
    assert scip.parse_reply(data).fields == {"VEND": "Hokuyo", "PROT": "SCIP 2.0"}


# ----------------------------------------------------------------------------- real captures


def test_capture_gd(scip_dir):
    frame = scip.parse_reply(_read(scip_dir, "GD0044072501_urg04lx_capture.bin"))
    assert isinstance(frame, scip.ScanFrame)
    assert frame.command == "GD0044072501" and frame.status == "00"
    assert frame.timestamp_ms == 4106836 and frame.remaining_scans is None
    assert frame.n_values == 682 and frame.ranges_mm.min() == 90 and frame.ranges_mm.max() == 178
    assert frame.valid.all()
    text = _read(scip_dir, "GD0044072501_urg04lx_capture.bin").split(b"\n")
    assert frame.raw_ranges.tolist() == ref_decode(b"".join(line[:-1] for line in text[3:-2]), 3)


def test_capture_ms(scip_dir):
    frame = scip.parse_reply(_read(scip_dir, "MS0044072501003_urg04lx_capture.bin"))
    assert frame.code == "MS" and frame.status == "99" and frame.remaining_scans == 3
    assert frame.timestamp_ms == 508219
    assert frame.n_values == 682 and frame.raw_ranges.min() == 0 and frame.raw_ranges.max() == 4095
    errors = frame.raw_ranges < 20
    assert errors.any() and (frame.ranges_mm[errors] == 0).all() and not frame.valid[errors].any()


def test_capture_md_one_step(scip_dir):
    ack, frame = scip.parse_replies(_read(scip_dir, "omnimobot2_MD0384038400001_urg04lx.bin"))
    assert ack == scip.Reply("MD0384038400001", "00", ()) and ack.ok
    assert frame.command == "MD0384038400000" and frame.status == "99" and frame.remaining_scans == 0
    assert frame.ranges_mm.tolist() == [254]


def test_capture_vv_bm_pp(scip_dir):
    vv = scip.parse_reply(_read(scip_dir, "VV_urg04lx-ug01_FRM-G5.bin"))
    assert vv.fields == {
        "VEND": "Hokuyo Automatic Co.,Ltd.",
        "PROD": "SOKUIKI Sensor URG-04LX-UG01(Simple-URG)",
        "FIRM": "3.4.03(17/Dec./2012)",
        "PROT": "SCIP 2.0",
        "SERI": "H1510998",
    }
    bm = scip.parse_reply(_read(scip_dir, "BM_laser_already_on_urg04lx-ug01_FRM-G5.bin"))
    assert (bm.code, bm.status, bm.ok, bm.message) == ("BM", "02", False, "laser already on")
    pp = scip.parse_reply(_read(scip_dir, "PP_utm30lx-ew_from_comment.bin"))
    assert pp.fields["MODL"] == "UTM-30LX-EW" and pp.fields["DMAX"] == "60000"
    model = scip.sensor_model_from_pp(pp)
    assert (model.name, model.amin, model.amax, model.ares, model.afrt) == ("UTM-30LX", 0, 1080, 1440, 540)
    assert (model.dmin_mm, model.dmax_mm, model.scan_rpm, model.has_intensity) == (23, 60000, 2400, True)
    assert model.n_beams == 1081


def test_capture_ts_truncated_strict_and_stream(scip_dir):
    data = _read(scip_dir, "omnimobot2_MD0370045000001_urg04lx_ts_truncated.bin")
    with pytest.raises(scip.ScipError) as err:
        scip.parse_replies(data)
    assert err.value.reason == "truncated"
    good = _read(scip_dir, "omnimobot2_MD0384038400001_urg04lx.bin") + b"\n\n"
    for glue in (b"\n\n", b""):
        dec = scip.StreamDecoder()
        out = dec.decode(data + glue + good)
        assert [type(o).__name__ for o in out] == ["Reply", "Reply", "ScanFrame"]
        assert out[-1].ranges_mm.tolist() == [254]
        assert dec.stats.truncated == 1 and dec.stats.dropped == 1 and dec.stats.frames_ok == 3


def test_capture_bad_sums_strict_lenient_and_stream(scip_dir):
    data = _read(scip_dir, "omnimobot2_MD0046060000001_urg04lx_5badsum.bin")
    with pytest.raises(scip.ScipError) as err:
        scip.parse_replies(data)
    assert err.value.reason == "checksum"
    _, lenient = scip.parse_replies(data, strict=False)
    assert lenient.bad_lines == 5 and lenient.n_values == 555
    assert lenient.valid.sum() < (lenient.raw_ranges >= 20).sum()
    good = _read(scip_dir, "GD0044072501_urg04lx_capture.bin")
    for glue in (b"\n\n", b""):  # with the closing blank line restored, and with the next reply glued on
        dec = scip.StreamDecoder()
        out = dec.decode(data + glue + good)
        # the damaged block's lines are all of their length: its good lines are kept (issue 17)
        assert [o.command for o in out] == ["MD0046060000001", "MD0046060000000", "GD0044072501"]
        salvaged = out[1]
        assert salvaged.bad_lines == 5
        np.testing.assert_array_equal(salvaged.valid, lenient.valid)
        np.testing.assert_array_equal(salvaged.ranges_mm, lenient.ranges_mm)
        assert out[-1].timestamp_ms == 4106836 and out[-1].n_values == 682
        assert dec.stats.salvaged == 1 and dec.stats.checksum_errors == 0 and dec.stats.dropped == 0
        assert dec.stats.frames_ok == 2


# ----------------------------------------------------------------------------- stream decoder


def _stream(n_frames=4, seed=1):
    """A realistic exchange: PP, MD ack, MD data blocks (3-char), and a GS reply."""
    rng = np.random.default_rng(seed)
    parts = [scip.format_pp_reply(URG_04LX), scip.format_reply("MD0044072501003", "00")]
    cmd = scip.parse_command(b"MD0044072501003")
    for k in range(n_frames):
        parts.append(
            scip.format_md_frame(cmd.with_remaining(max(2 - k, 0)), 1000 + 100 * k, rng.integers(0, 5600, 682))
        )
    parts.append(scip.format_gd_frame("GS0100020002", 7, rng.integers(0, 4096, 51)))
    return parts


def _summary(out):
    return [(o.command, getattr(o, "timestamp_ms", None)) for o in out]


def test_stream_split_at_every_byte_boundary():
    parts = _stream(2)
    data = b"".join(parts)
    want = _summary(scip.parse_replies(data))
    assert len(want) == len(parts)
    for cut in range(len(data) + 1):
        dec = scip.StreamDecoder()
        out = dec.feed(data[:cut]) + dec.feed(data[cut:]) + dec.flush()
        assert _summary(out) == want, cut
        assert dec.stats.dropped == 0 and dec.stats.garbage_bytes == 0


def test_stream_byte_by_byte_and_random_chunks():
    data = b"".join(_stream(3))
    want = _summary(scip.parse_replies(data))
    dec = scip.StreamDecoder()
    out = [o for i in range(len(data)) for o in dec.feed(data[i : i + 1])]
    assert _summary(out) == want
    rng = random.Random(3)
    for _ in range(20):
        dec = scip.StreamDecoder()
        out, i = [], 0
        while i < len(data):
            j = i + rng.randint(0, 200)
            out += dec.feed(data[i:j])
            i = j
        assert _summary(out) == want


@FUZZ
@given(
    garbage=st.lists(st.binary(max_size=80).map(lambda b: b.replace(b";", b"")), min_size=7, max_size=7),
    ends=st.lists(st.booleans(), min_size=7, max_size=7),
)
def test_stream_garbage_between_frames(garbage, ends):
    parts = _stream(4)
    data = b"".join(g + (b"\n" if e else b"") + p for g, e, p in zip(garbage, ends, parts, strict=True))
    dec = scip.StreamDecoder()
    out = dec.decode(data)
    assert _summary(out) == _summary(scip.parse_replies(b"".join(parts)))
    assert dec.stats.garbage_bytes <= sum(len(g) + 1 for g in garbage)


def _damage(reply: bytes, line: int, at: int = 10) -> bytes:
    """``reply`` with one character of its ``line``-th line (0: the echo) changed, its length kept."""
    b = bytearray(reply)
    start = 0
    for _ in range(line):
        start = b.index(b"\n", start) + 1
    b[start + at] = 0x30 + ((b[start + at] - 0x30 + 1) & 0x3F)
    return bytes(b)


@pytest.mark.parametrize("line", [3, 5, 13])  # the 1st data line, one inside, the last (after the timestamp)
def test_stream_bad_data_line_keeps_the_frames_other_lines(line):
    """A data line failing its sum, every line of its length: the frame is delivered with the beams that
    line touches as no return and every other beam as sent (issue 17); nothing is dropped. The beams of
    a line: its 64 characters' run of the 3-character values, counted here by hand."""
    parts = _stream(4)
    clean = scip.parse_replies(parts[3])[0]
    n_lines = parts[3].count(b"\n") - 4  # echo, status, timestamp, data lines, the closing empty line
    line = min(line, 2 + n_lines)
    parts[3] = _damage(parts[3], line)
    dec = scip.StreamDecoder()
    out = dec.decode(b"".join(parts))
    assert len(out) == len(parts)
    assert dec.stats.salvaged == 1 and dec.stats.checksum_errors == 0 and dec.stats.frames_ok == len(parts) - 1
    frame = out[3]
    assert frame.bad_lines == 1 and frame.timestamp_ms == clean.timestamp_ms
    hit = _beams_of_lines({line - 3}, 682, 3)  # line - 3: the data line's index
    np.testing.assert_array_equal(frame.valid, clean.valid & ~hit)
    np.testing.assert_array_equal(frame.ranges_mm[~hit], clean.ranges_mm[~hit])
    assert np.all(frame.ranges_mm[hit] == 0)


def test_a_character_moved_by_64_fails_its_line_though_its_sum_holds():
    """A character moved by 64 (``0``–``?`` to ``p``–DEL) leaves the 6-bit sum as it was: the strict
    decoder refuses the frame, the lenient ones (``parse_reply(strict=False)``, the stream decoder)
    drop that line's beams and keep every other beam as sent."""
    parts = _stream(4)
    clean = scip.parse_replies(parts[3])[0]
    b = bytearray(parts[3])
    start = 0
    for _ in range(5):  # the third data line
        start = b.index(b"\n", start) + 1
    at = next(k for k in range(64) if 0x30 <= b[start + k] <= 0x3F)
    b[start + at] += 64
    assert scip.checksum(bytes(b[start:start + 64])) == chr(b[start + 64])  # the sum cannot see it
    with pytest.raises(scip.ScipError) as err:
        scip.parse_reply(bytes(b))
    assert err.value.reason == "checksum"
    hit = _beams_of_lines({2}, 682, 3)
    dec = scip.StreamDecoder()
    for frame in (scip.parse_reply(bytes(b), strict=False), dec.decode(b"".join(parts[:3]) + bytes(b))[3]):
        assert frame.bad_lines == 1
        np.testing.assert_array_equal(frame.valid, clean.valid & ~hit)
        np.testing.assert_array_equal(frame.ranges_mm[~hit], clean.ranges_mm[~hit])


@pytest.mark.parametrize("what", ["timestamp", "every data line", "a byte lost from the timestamp"])
def test_stream_frame_beyond_salvage_is_dropped(what):
    """A bad timestamp, every data line bad, or a byte lost from the timestamp: that frame is dropped
    and counted, the others delivered."""
    parts = _stream(4)
    reply = parts[3]
    n_lines = reply.count(b"\n") - 4
    if what == "timestamp":
        reply = _damage(reply, 2, at=1)
    elif what == "every data line":
        for line in range(3, 3 + n_lines):
            reply = _damage(reply, line)
    else:
        cut = reply.index(b"\n", reply.index(b"\n") + 1) + 2
        reply = reply[:cut] + reply[cut + 1:]
    parts[3] = reply
    dec = scip.StreamDecoder()
    out = dec.decode(b"".join(parts))
    assert len(out) == len(parts) - 1 and dec.stats.dropped == 1 and dec.stats.salvaged == 0
    assert [o.timestamp_ms for o in out if isinstance(o, scip.ScanFrame) and o.code == "MD"] == [1000, 1200, 1300]


def _beams_of_lines(lines, n_values, chars):
    """Which values the data lines ``lines`` (0: the first) touch: value v occupies characters
    ``chars * v .. chars * v + chars - 1`` of the joined payload, line k characters 64 k .. 64 k + 63."""
    hit = np.zeros(n_values, bool)
    for v in range(n_values):
        if any(k * 64 <= c < (k + 1) * 64 for k in lines for c in range(chars * v, chars * (v + 1))):
            hit[v] = True
    return hit


@pytest.mark.parametrize(("line", "at", "n"), [(0, 10, 1), (4, 0, 8), (5, 63, 2), (4, 64, 1), (4, 60, 8),
                                             (10, 5, 3), (10, 25, 1)])
def test_stream_bytes_lost_in_a_data_line_keep_the_other_lines(line, at, n):
    """Bytes lost inside a data line (``at`` 64: its sum character and line feed, so two lines run
    together; ``(10, 25)``: the last line, 682 × 3 characters = 10 full lines + 42): the frame is
    delivered with the beams of the lines the loss touched as no return, every other beam as sent."""
    parts = _stream(4)
    clean = scip.parse_replies(parts[3])[0]
    reply = parts[3]
    start = 0
    for _ in range(3 + line):  # echo, status, timestamp, then the data lines
        start = reply.index(b"\n", start) + 1
    cut = start + at
    parts[3] = reply[:cut] + reply[cut + n:]
    touched = {line} | ({line + 1} if at + n > 65 else set())
    dec = scip.StreamDecoder()
    out = dec.decode(b"".join(parts))
    assert len(out) == len(parts) and dec.stats.salvaged == 1 and dec.stats.dropped == 0
    frame = out[3]
    assert frame.bad_lines == len(touched) and frame.timestamp_ms == clean.timestamp_ms
    hit = _beams_of_lines(touched, 682, 3)
    np.testing.assert_array_equal(frame.valid, clean.valid & ~hit)
    np.testing.assert_array_equal(frame.ranges_mm[~hit], clean.ranges_mm[~hit])


@FUZZ
@given(at=st.integers(0, 10_000), n=st.integers(1, 8), seed=st.integers(0, 2**16))
def test_stream_a_lost_run_of_bytes_costs_at_most_its_frame(at, n, seed):
    """A run of 1–8 bytes lost anywhere in one MD frame of a stream: every frame delivered is one that
    was sent, with its beams as sent wherever it says they are valid; the frames around are delivered
    whole; the damaged one is delivered (salvaged) or counted dropped, never both, never silently."""
    parts = _stream(4, seed=seed)
    sent = [scip.parse_replies(p)[0] for p in parts]
    at %= len(parts[3]) - n
    parts[3] = parts[3][:at] + parts[3][at + n:]
    dec = scip.StreamDecoder()
    out = dec.decode(b"".join(parts))
    assert dec.stats.salvaged + dec.stats.dropped == 1
    assert len(out) == len(parts) - dec.stats.dropped
    by_stamp = {getattr(f, "timestamp_ms", None): f for f in sent if isinstance(f, scip.ScanFrame)}
    for o in out:
        if isinstance(o, scip.ScanFrame):
            want = by_stamp[o.timestamp_ms]
            np.testing.assert_array_equal(o.ranges_mm[o.valid], want.ranges_mm[o.valid])
            assert o.bad_lines > 0 or np.array_equal(o.valid, want.valid)


def test_stream_truncated_frames_resynchronise():
    parts = _stream(3)
    victim = 3
    rng = random.Random(0)
    for cut in sorted(rng.sample(range(1, len(parts[victim])), 60)):
        damaged = parts[:victim] + [parts[victim][:cut]] + parts[victim + 1 :]
        dec = scip.StreamDecoder()
        out = dec.decode(b"".join(damaged))
        others = _summary(scip.parse_replies(b"".join(parts[:victim] + parts[victim + 1 :])))
        got = _summary(out)
        assert [g for g in got if g[1] != 1100] == others, cut
        assert dec.stats.dropped + dec.stats.garbage_bytes > 0 or len(got) == len(parts)


def test_stream_memory_is_bounded():
    dec = scip.StreamDecoder(max_line=256, max_lines=64)
    for _ in range(100):
        assert dec.feed(b"x" * 1000) == []
    assert len(dec._partial) <= 256
    dec.feed(b"\nGD0000001001\n00P\n" + b"0000\n" * 500)
    assert len(dec._lines) <= 64 and dec.stats.oversize == 1
    (frame,) = dec.feed(scip.format_gd_frame("GD0000001001", 5, np.arange(20, 31)))
    assert frame.ranges_mm.tolist() == list(range(20, 31))


# ----------------------------------------------------------------------------- fuzzing


def _only_scip_errors(fn, *args, **kw):
    try:
        return fn(*args, **kw)
    except scip.ScipError:
        return None


@FUZZ
@given(data=st.binary(max_size=2000))
def test_fuzz_random_bytes(data):
    _only_scip_errors(scip.parse_reply, data)
    _only_scip_errors(scip.parse_replies, data)
    _only_scip_errors(scip.parse_replies, data, strict=False)
    _only_scip_errors(scip.decode_values, data, 3)
    _only_scip_errors(scip.parse_fields, data.split(b"\n"))
    _only_scip_errors(scip.sensor_model_from_pp, data)
    dec = scip.StreamDecoder()
    out = dec.decode(data)
    assert dec.stats.frames_ok == len(out)


_VALID = [
    scip.format_md_frame("MD0044072501002", 123456, np.arange(682) % 5000),
    scip.format_md_frame("ME0000108001000", 654321, np.arange(1081) % 30000, np.arange(1081)),
    scip.format_gd_frame("GS0044072501", 99, np.arange(682) % 4096),
    scip.format_pp_reply(UTM_30LX),
    scip.format_reply("BM", "02"),
]


@FUZZ
@given(
    which=st.integers(0, len(_VALID) - 1),
    edits=st.lists(
        st.tuples(st.sampled_from(["flip", "ins", "del"]), st.integers(0, 10**6), st.integers(0, 255)),
        min_size=1,
        max_size=4,
    ),
)
def test_fuzz_mutated_frames(which, edits):
    data = bytearray(_VALID[which])
    for op, pos, byte in edits:
        pos %= len(data) + 1
        if op == "ins":
            data[pos:pos] = bytes([byte])
        elif data and pos < len(data):
            if op == "flip":
                data[pos] = byte
            else:
                del data[pos]
    data = bytes(data)
    for strict in (True, False):
        _only_scip_errors(scip.parse_replies, data, strict=strict)
    good = _VALID[2]
    dec = scip.StreamDecoder()
    out = dec.decode(data + b"\n\n" + good)
    assert out and out[-1].command == "GS0044072501" and out[-1].timestamp_ms == 99


@FUZZ
@given(
    edits=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
    cuts=st.lists(st.integers(0, 10**6), max_size=12),
)
def test_fuzz_stream_is_independent_of_chunking(edits, cuts):
    data = bytearray(b"".join(_VALID) + b"".join(_stream(2)))
    for pos, byte in edits:
        data[pos % len(data)] = byte
    data = bytes(data)
    whole = scip.StreamDecoder(max_line=200)
    want = _summary(whole.decode(data))
    bounds = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    chunked = scip.StreamDecoder(max_line=200)
    got = [o for a, b in zip(bounds[:-1], bounds[1:], strict=True) for o in chunked.feed(data[a:b])]
    got += chunked.flush()
    assert _summary(got) == want
    assert chunked.stats == whole.stats


def test_stream_counts_missing_data_line_as_truncated():
    frame = scip.format_gd_frame("GD0044072501", 42, np.full(682, 1000))
    lines = frame.split(b"\n")
    damaged = b"\n".join(lines[:5] + lines[6:])  # one whole 64-character line lost
    with pytest.raises(scip.ScipError) as err:
        scip.parse_reply(damaged)
    assert err.value.reason == "truncated"
    dec = scip.StreamDecoder()
    (out,) = dec.decode(damaged + frame)
    assert out.timestamp_ms == 42 and dec.stats.truncated == 1 and dec.stats.frames_ok == 1


def test_scip11_and_tm_replies():
    assert scip.parse_reply(b"QT\nE\n\n") == scip.Reply("QT", "E", ())
    assert scip.status_message("QT", "0E") == "sensor in time-adjust (TM) mode"
    tm = scip.format_reply("TM1", "00", scip.format_timestamp_line(123456))
    reply = scip.parse_reply(tm)
    assert reply.code == "TM1"[:3] and scip.decode_timestamp_line(reply.lines[0]) == 123456
    dec = scip.StreamDecoder()
    assert [r.command for r in dec.decode(b"QT\nE\n\n" + tm)] == ["QT", "TM1"]
    with pytest.raises(scip.ScipError) as err:
        scip.parse_reply(tm.replace(b"00P", b"00Q"))
    assert err.value.reason == "checksum"


def test_multiecho_frames_put_an_ampersand_before_each_further_echo():
    """HD/HE/ND/NE: each step's first echo, then '&' and each further echo's value(s) (urg_library's
    format); the decoder keeps each step's first echo."""
    ranges = np.array([[1000, 1500, 0], [2000, 0, 0], [3000, 3100, 3200]])
    inten = np.array([[10, 20, 0], [30, 0, 0], [40, 50, 60]])
    block = scip.format_gd_frame("HE0000000201", 7, ranges, inten)
    enc = lambda v: scip.encode_value(v, 3)  # noqa: E731
    payload = (enc(1000) + enc(10) + b"&" + enc(1500) + enc(20) + enc(2000) + enc(30)
               + enc(3000) + enc(40) + b"&" + enc(3100) + enc(50) + b"&" + enc(3200) + enc(60))
    assert block.split(b"\n")[3] == scip.format_line(payload).rstrip(b"\n")
    frame = scip.parse_reply(block)
    assert frame.ranges_mm.tolist() == [1000, 2000, 3000] and frame.intensities.tolist() == [10, 30, 40]
    single = scip.parse_reply(scip.format_md_frame("ND0000000201000", 7, ranges[:, 0]))
    assert single.ranges_mm.tolist() == [1000, 2000, 3000] and single.status == "99"


@pytest.mark.parametrize("cut", [0, 7, 40, 300])
def test_a_reply_cut_by_a_reset_is_counted_truncated(cut):
    """The link resets its decoder when it reconnects: a reply it held part of (``cut`` bytes of an MD
    frame) is counted truncated, as a frame lost, not only as garbage bytes; nothing held, nothing counted."""
    frame = _stream(1)[2]
    dec = scip.StreamDecoder()
    assert dec.feed(frame[:cut]) == []
    dec.reset()
    assert dec.stats.truncated == (1 if cut else 0) and dec.stats.garbage_bytes >= cut
    assert [o.timestamp_ms for o in dec.decode(frame)] == [1000]  # and it decodes the next whole frame
