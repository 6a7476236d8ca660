"""The serial link end to end against the pty emulator (real pyserial, no mocks), and ClockSync
against a synthetic clock. Every wait is bounded by a deadline, and no assertion is on the wall clock:
what the link delivered is counted against what the emulator sent (a busy machine delivers later,
not differently)."""

import os
import time
import tty

import numpy as np
import pytest

from gtsjax.io import scip
from gtsjax.io.serial import ClockSync, Link, LinkError
from gtsjax.sensors import URG_04LX, UTM_30LX
from gtsjax.sim.emulator import Faults, SensorEmulator
from tests._utils import assert_allclose, frame_source

# Time allowed for a wanted number of frames to arrive: a bound against hanging, never a measurement.
PATIENCE_S = 30.0


def collect(link, n, timeout=PATIENCE_S):
    """The next ``n`` frames the link delivers (fewer only if ``timeout`` seconds pass first)."""
    out = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and len(out) < n:
        f = link.get(timeout=max(0.0, min(0.1, deadline - time.monotonic())))
        if f is not None:
            out.append(f)
    return out


def scan_index(f):
    """Which scan of ``frame_source`` a frame is: beam 0 holds 1000 + i; where a salvaged frame lost
    beam 0 (its first data line failed its sum), beam b >= 1 holds 500 + (7 b + 13 i) % 3000."""
    if f.frame.valid[0]:
        return int(f.frame.ranges_mm[0]) - 1000
    b = int(np.flatnonzero(f.frame.valid[1:])[0]) + 1
    return (int(f.frame.ranges_mm[b]) - 500 - 7 * b) * pow(13, -1, 3000) % 3000


def check_frames(frames, model):
    """Every delivered frame must be what the source gave for its scan: no damage slips through. A
    frame salvaged from data lines that failed their sum or lost bytes (issue 17) has those beams as no return and
    every other beam exact."""
    src = frame_source(model)
    for f in frames:
        r, inten = src(scan_index(f))
        ok = f.frame.valid if f.frame.bad_lines else np.ones(r.shape, bool)
        np.testing.assert_array_equal(f.frame.ranges_mm[ok], r[ok])
        assert np.all(f.frame.ranges_mm[~ok] == 0)
        if f.frame.intensities is not None:
            np.testing.assert_array_equal(f.frame.intensities[ok], inten[ok])
        assert_allclose(f.ranges_m[ok], r[ok] / 1000.0)


def lost_between(frames):
    """Scans the source produced between the first and the last delivered frame that were not delivered."""
    idx = np.array([scan_index(f) for f in frames])
    assert np.all(np.diff(idx) >= 1), idx  # in order, no frame twice
    return int(np.sum(np.diff(idx) - 1))


def assert_sensor_spacing(stamps, period):
    """Stamps follow the sensor clock (ms resolution), not arrival jitter. The offset estimate only
    moves down while it converges (a quicker frame came through), so a gap can only shrink, never grow."""
    d = np.diff(np.asarray(stamps))
    assert np.all(d <= period + 0.0011)
    assert np.median(np.abs(d - period)) <= 0.0011


def wait_until(cond, timeout):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)
    return cond()


def test_link_streams_urg04lx_at_10hz_with_correct_ranges_and_stamps():
    # A queue that holds every frame of the test: none is dropped however late the test thread runs.
    with SensorEmulator(URG_04LX, frame_source(URG_04LX)) as emu, Link(emu.path, queue_size=64) as link:
        assert link.model == URG_04LX
        assert link.version["PROT"] == "SCIP 2.0"
        assert link.command == scip.md_command(44, 725)
        frames = collect(link, 10)
        assert len(frames) == 10
        check_frames(frames, URG_04LX)
        assert lost_between(frames) == 0
        # What the link delivered is exactly what the emulator sent, block for block from the first.
        sent = list(emu.sent_log)
        assert [f.frame.timestamp_ms for f in frames] == [ms for ms, _ in sent[: len(frames)]]
        stamps = np.array([f.stamp for f in frames])
        assert_sensor_spacing(stamps, 0.1)
        recv = np.array([f.recv_time for f in frames])
        assert np.all(recv - stamps >= -1e-9)  # a stamp is never later than the frame's arrival
        # Each frame was in our hands after the emulator handed its block to the pty, not before.
        assert all(f.recv_perf >= t for f, (_, t) in zip(frames, sent, strict=False))
        s = link.stats
        assert s.frames >= len(frames) and s.dropped == s.bad_frames == s.reconnects == s.timeouts == 0
    assert emu.commands[:5] == ["QT", "SCIP2.0", "VV", "PP", "MD0044072501000"]


def test_stop_sends_qt_and_the_sensor_stops_streaming():
    with SensorEmulator(URG_04LX, frame_source(URG_04LX)) as emu:
        link = Link(emu.path).start()
        assert link.get(timeout=1.0) is not None
        link.stop()
        assert wait_until(lambda: emu.commands[-1] == "QT" and emu._stream is None, 1.0)
        assert link._thread is None and link._ser is None


def test_me_with_intensity_on_utm30lx_at_40hz():
    with SensorEmulator(UTM_30LX, frame_source(UTM_30LX)) as emu, Link(emu.path, intensity=True, queue_size=64) as link:
        assert link.command == scip.me_command(0, 1080)
        frames = collect(link, 20)
        assert len(frames) == 20 and lost_between(frames) == 0
        assert [f.frame.timestamp_ms for f in frames] == [ms for ms, _ in list(emu.sent_log)[:20]]
        check_frames(frames, UTM_30LX)
        assert frames[0].intensities is not None and frames[0].intensities.dtype == np.float32
        assert_sensor_spacing([f.stamp for f in frames], 0.025)


def test_bad_sums_keep_their_frames_good_lines():
    """A data line whose sum fails (the emulator corrupts one line's sum character) costs that line's
    beams, not the frame (issue 17): every frame arrives, its other beams and intensities exactly as
    the source gave them, the salvaged ones counted, none counted lost."""
    faults = Faults(checksum_p=0.3, seed=1)
    with SensorEmulator(UTM_30LX, frame_source(UTM_30LX), faults=faults) as emu, Link(emu.path) as link:
        frames = collect(link, 20)
        link_stats = link.stats
        injected = emu.faults.checksum  # read after the link's: the emulator is ahead
    assert len(frames) == 20
    check_frames(frames, UTM_30LX)
    idx = [scan_index(f) for f in frames]
    assert np.all(np.diff(idx) >= 1)
    salvaged = sum(f.frame.bad_lines > 0 for f in frames)
    assert 0 < salvaged <= link_stats.salvaged <= injected
    assert link_stats.checksum_errors == 0 and link_stats.reconnects == 0
    assert int(np.sum(np.diff(idx) - 1)) <= link_stats.dropped  # a scan missing was one the queue let go


def test_dropped_bytes_resynchronise_and_frames_keep_flowing():
    faults = Faults(drop_p=0.3, seed=2)
    with SensorEmulator(UTM_30LX, frame_source(UTM_30LX), faults=faults) as emu, Link(emu.path) as link:
        frames = collect(link, 20)
        s = link.stats
        damaged = emu.faults.dropped
        check_frames(frames, UTM_30LX)  # a damaged block is never handed on with a damaged beam
        assert len(frames) == 20 and damaged > 0
        # Bytes lost inside data lines cost those lines' beams (salvaged); elsewhere the block is counted.
        assert s.bad_frames + s.salvaged > 0
        # A scan goes missing only where bytes were dropped (a cut may spoil the next block's start too).
        assert lost_between(frames) <= 2 * damaged
        assert s.reconnects == 0


def test_stall_longer_than_the_timeout_reconnects_and_frames_resume():
    with (
        SensorEmulator(URG_04LX, frame_source(URG_04LX)) as emu,
        Link(emu.path, timeout_periods=3, reply_timeout_s=0.3, backoff_s=0.05) as link,
    ):
        assert len(collect(link, 2)) == 2
        emu.inject_stall(0.8)
        assert wait_until(lambda: link.stats.timeouts >= 1, PATIENCE_S)
        assert wait_until(lambda: link.stats.reconnects >= 1, PATIENCE_S)
        after = collect(link, 3)
        assert len(after) == 3
        check_frames(after, URG_04LX)
        assert emu.faults.stalls == 1


def test_short_stall_is_ridden_out_without_reconnecting():
    with SensorEmulator(URG_04LX, frame_source(URG_04LX)) as emu, Link(emu.path, timeout_periods=10) as link:
        assert link.get(timeout=PATIENCE_S) is not None
        emu.inject_stall(0.3)  # against a timeout of 10 periods, 1 s
        assert wait_until(lambda: emu.faults.stalls == 1, PATIENCE_S)
        assert len(collect(link, 2)) == 2
        assert link.stats.timeouts == link.stats.reconnects == 0


def test_disconnect_reconnects_with_backoff_and_frames_resume():
    with (
        SensorEmulator(UTM_30LX, frame_source(UTM_30LX)) as emu,
        Link(emu.path, reply_timeout_s=0.3, backoff_s=0.05, backoff_max_s=0.2) as link,
    ):
        assert len(collect(link, 3)) == 3
        emu.inject_disconnect(reopen_after_s=0.4)
        assert wait_until(lambda: link.stats.io_errors >= 1, PATIENCE_S)
        assert wait_until(lambda: link.stats.reconnects >= 1, PATIENCE_S)
        after = collect(link, 5)
        assert len(after) == 5
        check_frames(after, UTM_30LX)
        assert emu.faults.disconnects == 1 and link.model == UTM_30LX


def test_random_faults_all_at_once_are_survived():
    faults = Faults(
        checksum_p=0.1, drop_p=0.1, stall_p=0.02, stall_s=0.4, disconnect_p=0.02, reopen_after_s=0.2, seed=7
    )
    with (
        SensorEmulator(UTM_30LX, frame_source(UTM_30LX), faults=faults) as emu,
        Link(emu.path, timeout_periods=8, reply_timeout_s=0.3, backoff_s=0.05, backoff_max_s=0.2) as link,
    ):
        frames = collect(link, 40)
        check_frames(frames, UTM_30LX)
        assert emu.faults.total > 0 and len(frames) == 40
        s = link.stats
        assert s.frames == len(frames) + link.queue.qsize()
        assert s.reconnects >= emu.faults.disconnects - 1


def test_full_queue_drops_the_oldest_frames():
    with SensorEmulator(UTM_30LX, frame_source(UTM_30LX)) as emu, Link(emu.path, queue_size=4) as link:
        # The consumer is busy: 20 frames arrive, only the newest 4 are kept.
        assert wait_until(lambda: link.stats.frames >= 20, PATIENCE_S)
        s = link.stats
        kept = [link.get(timeout=0.01) for _ in range(4)]
        assert all(f is not None for f in kept)
        seqs = [f.seq for f in kept]
        assert seqs == list(range(seqs[0], seqs[0] + 4))
        assert s.dropped >= s.frames - link.queue.maxsize >= 16
        assert emu.frames_sent >= s.frames
        fresh = link.get(timeout=PATIENCE_S)
        assert fresh is not None and fresh.seq > seqs[-1]


def test_timestamps_wrapping_past_24_bits_stay_monotonic():
    offset = scip.TIMESTAMP_MODULUS - 2000  # the sensor clock wraps 2 s after power-up
    with (
        SensorEmulator(URG_04LX, frame_source(URG_04LX), timestamp_offset_ms=offset) as emu,
        Link(emu.path) as link,
    ):
        frames = collect(link, 1)
        while frames and frames[-1].frame.timestamp_ms > offset and len(frames) < 100:  # on to past the wrap
            frames += collect(link, 1)
        frames += collect(link, 3)
        raw = [f.frame.timestamp_ms for f in frames]
        assert any(r < 1000 for r in raw) and any(r > offset for r in raw)  # it did wrap
        assert np.allclose(np.diff([f.sensor_ms for f in frames]), 100, atol=1)
        assert_sensor_spacing([f.stamp for f in frames], 0.1)


def test_start_fails_cleanly_on_a_missing_port_or_a_silent_one(tmp_path):
    with pytest.raises(LinkError, match="cannot open"):
        Link(str(tmp_path / "ttyNOPE")).start()
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with pytest.raises(LinkError, match="no reply to QT"):
            Link(os.ttyname(slave), reply_timeout_s=0.2).start()  # gives up, rather than waiting for ever
    finally:
        os.close(master)
        os.close(slave)


# ---------------------------------------------------------------------------- ClockSync


def _synthetic(n, *, rate=40.0, start_ms, offset, seed):
    """A sensor at ``rate`` Hz whose ms counter starts at ``start_ms`` (wrapping at 2**24), seen by a
    host ``offset`` seconds ahead, through a delay of 2 ms plus exponential jitter (mean 4 ms)."""
    rng = np.random.default_rng(seed)
    true_ms = start_ms + np.round(np.arange(n) * 1000.0 / rate).astype(np.int64)
    delay = 0.002 + rng.exponential(0.004, n)
    host = 1.7e9 + offset + true_ms / 1000.0 + delay
    raw = true_ms % scip.TIMESTAMP_MODULUS
    return raw, host, true_ms


def test_clock_sync_unwraps_and_removes_jitter():
    start = scip.TIMESTAMP_MODULUS - 3000  # wraps 3 s in
    raw, host, true_ms = _synthetic(800, start_ms=start, offset=12.5, seed=0)
    sync = ClockSync(window=100)
    stamps = np.array([sync.update(int(r), float(h)) for r, h in zip(raw, host, strict=True)])
    truth = 1.7e9 + 12.5 + true_ms / 1000.0
    err = stamps - truth
    assert np.all(np.diff(stamps) > 0)  # monotonic across the wrap
    assert raw[200] < raw[100]  # the wrap is in the data
    # After the window fills the error is the minimum delay (2 ms) plus the window's smallest jitter.
    assert np.all(err[100:] >= 0.002 - 1e-9) and np.all(err[100:] < 0.0025)
    # Host arrival times scatter by ~4 ms; the mapped stamps keep the sensor's 25 ms spacing.
    assert np.std(np.diff(host)) > 0.003 and np.std(np.diff(stamps[100:])) < 0.0005
    assert sync._unwrap.wraps == 1


def test_clock_sync_matches_a_sliding_minimum_loop():
    raw, host, _ = _synthetic(300, start_ms=5000, offset=-3.0, seed=1)
    sync = ClockSync(window=20)
    got = [sync.update(int(r), float(h)) for r, h in zip(raw, host, strict=True)]
    s = raw / 1000.0
    d = host - s
    for k in (0, 5, 19, 20, 150, 299):
        assert got[k] == pytest.approx(s[k] + min(d[max(0, k - 19) : k + 1]), abs=1e-9)
    sync.reset()
    assert sync.offset is None
