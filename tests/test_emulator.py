"""The pty sensor emulator, spoken to through a real pseudo-terminal with real pyserial, and checked
with the strict codec: each reply must parse exactly as a real scanner's would."""

import time

import numpy as np
import pytest
import serial

from gtsjax.io import scip
from gtsjax.io.logs import ScanLog
from gtsjax.sensors import URG_04LX, UTM_30LX
from gtsjax.sim.emulator import Faults, SensorEmulator, log_source
from tests._utils import frame_source


class Client:
    """A bare SCIP client: write a command, read until enough replies came (or a deadline)."""

    def __init__(self, path):
        self.ser = serial.serial_for_url(path, baudrate=115200, timeout=0.02)
        self.dec = scip.StreamDecoder()
        self.raw = bytearray()

    def read_replies(self, n, timeout=10.0):  # a bound against hanging: returns once n replies are in
        out = []
        deadline = time.monotonic() + timeout
        while len(out) < n and time.monotonic() < deadline:
            chunk = self.ser.read(self.ser.in_waiting or 1)
            if chunk:
                self.raw += chunk
                out += self.dec.feed(chunk)
        return out

    def ask(self, command: bytes, n=1, timeout=10.0):
        self.ser.write(command)
        return self.read_replies(n, timeout)

    def close(self):
        self.ser.close()


@pytest.fixture
def urg():
    with SensorEmulator(URG_04LX, frame_source(URG_04LX)) as emu:
        client = Client(emu.path)
        yield emu, client
        client.close()


def test_handshake_replies_parse_as_the_codec_expects(urg):
    emu, c = urg
    c.ser.write(b"\n")
    time.sleep(0.1)
    assert c.ser.read(c.ser.in_waiting or 1) == b"\n"  # an empty line is answered with an empty line
    (r,) = c.ask(scip.scip2_command())
    assert (r.command, r.status) == ("SCIP2.0", "00")
    (vv,) = c.ask(scip.vv_command())
    assert vv.ok and set(vv.fields) == {"VEND", "PROD", "FIRM", "PROT", "SERI"}
    assert vv.fields["PROT"] == "SCIP 2.0" and URG_04LX.name in vv.fields["PROD"]
    (pp,) = c.ask(scip.pp_command())
    assert scip.sensor_model_from_pp(pp) == URG_04LX
    assert set(pp.fields) == {"MODL", "DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN"}
    (ii,) = c.ask(scip.ii_command())
    assert ii.fields["LASR"] == "OFF" and ii.fields["MODL"] == URG_04LX.name
    for cmd in (scip.qt_command(), scip.rs_command()):
        (r,) = c.ask(cmd)
        assert r.status == "00" and r.ok
    (r,) = c.ask(scip.pp_command(string="tag"))
    assert r.command == "PP;tag" and r.ok  # the optional string is echoed back
    assert emu.commands[:2] == ["", "SCIP2.0"]


def test_one_shot_needs_the_laser_and_reports_errors_like_the_urg(urg):
    emu, c = urg
    (r,) = c.ask(scip.gd_command(44, 725))
    assert r.status == "10"  # laser off
    (r,) = c.ask(scip.bm_command())
    assert r.status == "00"
    (r,) = c.ask(scip.bm_command())
    assert r.status == "02"  # already on, as the real URG-04LX-UG01 capture shows
    (f,) = c.ask(scip.gd_command(44, 725))
    assert isinstance(f, scip.ScanFrame) and f.status == "00" and f.n_values == URG_04LX.n_beams
    (r,) = c.ask(scip.ge_command(44, 725))
    assert r.status == "0E"  # no intensity on a URG-04LX
    (r,) = c.ask(scip.md_command(44, 800))
    assert r.status == "04"
    assert c.dec.stats.dropped == 0 and c.dec.stats.garbage_bytes == 0
    c.raw.clear()
    assert c.ask(b"XY\n", timeout=0.3) == []  # not a command the codec knows, so garbage to it
    assert bytes(c.raw) == b"XY\n0Ee\n\n"  # echo and status 0E: undefined command


def test_md_streams_at_the_model_rate_with_remaining_counts(urg):
    emu, c = urg
    replies = c.ask(scip.md_command(44, 725, count=5), n=6, timeout=30.0)
    ack, *frames = replies
    assert (ack.command, ack.status) == ("MD0044072501005", "00")
    assert [f.remaining_scans for f in frames] == [4, 3, 2, 1, 0]
    assert all(f.status == "99" for f in frames)
    stamps = np.array([f.timestamp_ms for f in frames])
    assert np.all(np.abs(np.diff(stamps) - 100) <= 1)  # 10 Hz, from the sensor's clock (not the host's load)
    source = frame_source(URG_04LX)
    for f in frames:
        i = int(f.ranges_mm[0]) - 1000
        np.testing.assert_array_equal(f.ranges_mm, source(i)[0])
    assert c.read_replies(1, timeout=0.3) == []  # a finite count ends the stream
    assert emu.frames_sent == 5


def test_me_carries_intensities_and_clusters_steps():
    model = UTM_30LX
    src = frame_source(model)
    with SensorEmulator(model, src) as emu:
        c = Client(emu.path)
        ack, f1, f2 = c.ask(scip.me_command(0, 1080, count=2), n=3)
        assert ack.status == "00" and f1.remaining_scans == 1 and f2.remaining_scans == 0
        assert abs((f2.timestamp_ms - f1.timestamp_ms) - 25) <= 1  # 40 Hz
        r, inten = src(int(f1.ranges_mm[0]) - 1000)
        np.testing.assert_array_equal(f1.ranges_mm, r)
        np.testing.assert_array_equal(f1.intensities, inten)
        # A sub-range, clustered by 3: the nearest non-zero return of each group, as a loop computes it.
        ack, f = c.ask(scip.md_command(100, 210, cluster=3, count=1), n=2)
        r, _ = src(int(f.timestamp_ms / model.period / 1000 + 0.5))
        steps = list(range(100, 211))
        expected = []
        for k in range(0, len(steps), 3):
            group = [int(r[s - model.amin]) for s in steps[k : k + 3]]
            nonzero = [v for v in group if v > 0]
            expected.append(min(nonzero) if nonzero else 0)
        assert f.n_values == 37
        np.testing.assert_array_equal(f.raw_ranges, expected)
        c.close()


def test_scan_log_replays_in_a_loop_in_millimetres():
    n = URG_04LX.n_beams
    ranges = np.full((3, n), 1.5, np.float32)
    ranges[:, 10] = 0.0  # no return
    ranges[1] = 2.25
    ranges[2, 5] = np.nan
    log = ScanLog(
        ranges=ranges, stamps=np.arange(3.0), angle_min=URG_04LX.angle_min, angle_increment=URG_04LX.angle_increment
    )
    src = log_source(log)
    assert src(0)[0][0] == 1500 and src(0)[0][10] == 0 and src(4)[0][0] == 2250 and src(2)[0][5] == 0
    with SensorEmulator(URG_04LX, log) as emu:
        c = Client(emu.path)
        ack, *frames = c.ask(scip.md_command(44, 725, count=3), n=4)
        assert sorted(int(f.ranges_mm[0]) for f in frames) == [1500, 1500, 2250]
        c.close()


def test_line_checksum_faults_hit_several_lines_and_every_one_is_caught():
    """``line_checksum_p`` draws per data line (a noisy cable), so a frame may carry several bad lines:
    the decoder counts exactly the lines the emulator corrupted, each frame is delivered (salvaged)
    with only those lines' beams missing, and the same seed corrupts the same lines."""
    faults = Faults(line_checksum_p=0.05, seed=4)
    runs = []
    for _ in range(2):
        with SensorEmulator(UTM_30LX, frame_source(UTM_30LX), faults=faults) as emu:
            c = Client(emu.path)
            frames = [r for r in c.ask(scip.md_command(0, 1080, count=6)) if isinstance(r, scip.ScanFrame)]
            deadline = time.monotonic() + 30.0
            while len(frames) < 6 and time.monotonic() < deadline:
                frames += [r for r in c.read_replies(1, timeout=0.1) if isinstance(r, scip.ScanFrame)]
            assert len(frames) == 6 == emu.frames_sent and c.dec.stats.dropped == 0
            assert sum(f.bad_lines for f in frames) == emu.faults.lines
            assert max(f.bad_lines for f in frames) >= 2  # 51 lines a frame at 5 %: several per frame
            for f in frames:  # 1 081 values × 3 characters: each bad line costs at most 22 beams
                assert (~f.valid).sum() <= 22 * f.bad_lines + np.sum(f.raw_ranges < 20)
            runs.append([f.bad_lines for f in frames])
            c.close()
    assert runs[0] == runs[1]


def test_checksum_faults_are_seeded_and_caught_by_the_decoder():
    """A data line's sum corrupted (the emulator's checksum fault) is caught line by line: the frame is
    delivered without that line's beams (issue 17), every other beam as the source gave it."""
    faults = Faults(checksum_p=0.5, seed=3)
    counts = []
    src = frame_source(URG_04LX)
    for _ in range(2):
        with SensorEmulator(URG_04LX, src, faults=faults) as emu:
            c = Client(emu.path)
            frames = [r for r in c.ask(scip.md_command(44, 725, count=8)) if isinstance(r, scip.ScanFrame)]
            deadline = time.monotonic() + 30.0
            while len(frames) < 8 and time.monotonic() < deadline:
                frames += [r for r in c.read_replies(1, timeout=0.1) if isinstance(r, scip.ScanFrame)]
            assert len(frames) == 8 == emu.frames_sent
            assert c.dec.stats.checksum_errors == 0
            assert c.dec.stats.salvaged == emu.faults.checksum == sum(f.bad_lines > 0 for f in frames) > 0
            for f in frames:
                assert f.bad_lines in (0, 1)
                # which scan: beam b >= 1 holds 500 + (7 b + 13 i) % 3000 (frame_source), 13 is invertible mod 3000
                b = int(np.flatnonzero(f.valid[1:])[0]) + 1
                i = (int(f.ranges_mm[b]) - 500 - 7 * b) * pow(13, -1, 3000) % 3000
                sent = np.asarray(src(i)[0])
                np.testing.assert_array_equal(f.ranges_mm[f.valid], sent[f.valid])
                assert f.valid.sum() >= sent.size - (22 if f.bad_lines else 0) - np.sum(sent < 20)
            counts.append(emu.faults.checksum)
            c.close()
    assert counts[0] == counts[1]


def test_disconnect_hangs_up_the_client_and_replugs_under_the_same_path(urg):
    emu, c = urg
    old = emu.pty_name
    c.ask(scip.md_command(44, 725), n=2)
    emu.inject_disconnect(reopen_after_s=0.2)
    with pytest.raises((serial.SerialException, OSError)):  # in_waiting's ioctl raises a bare EIO
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            c.ser.read(c.ser.in_waiting or 1)
    c.close()
    assert emu.faults.disconnects == 1
    deadline = time.monotonic() + 2.0
    while not emu.connected and time.monotonic() < deadline:
        time.sleep(0.02)
    c2 = Client(emu.path)
    (pp,) = c2.ask(scip.pp_command())
    assert scip.sensor_model_from_pp(pp) == URG_04LX
    assert emu.pty_name != old or emu.connected
    (ii,) = c2.ask(scip.ii_command())
    assert ii.fields["LASR"] == "OFF"  # powered up afresh
    c2.close()


def test_stall_sends_nothing_for_its_duration(urg):
    emu, c = urg
    c.ask(scip.md_command(44, 725), n=2)
    emu.inject_stall(0.5)
    deadline = time.monotonic() + 30.0
    while emu.faults.stalls == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    before = emu.frames_sent
    assert len(c.read_replies(3, timeout=30.0)) == 3  # the stream resumes after the stall
    assert emu.faults.stalls == 1
    # By the emulator's own record, not this thread's timing: nothing handed to the pty for at least the
    # stall, from a block sent before it was seen; one jump of the sensor clock there (the first block
    # after a stall still carries the slot that fell due first, so the jump may follow it), the scans
    # that fell due in the stall lost; else a block every 100 ms.
    sent = list(emu.sent_log)
    stamps, times = np.array([ms for ms, _ in sent]), np.array([t for _, t in sent])
    gap = int(np.argmax(np.diff(times)))
    jumps = np.flatnonzero(np.diff(stamps) > 101)
    assert times[gap + 1] - times[gap] >= 0.45 and gap < before, (np.diff(times), before)
    assert len(jumps) == 1 and jumps[0] in (gap, gap + 1), (np.diff(stamps), gap)
    assert stamps[jumps[0] + 1] - stamps[jumps[0]] >= 500 - 100
    assert np.all(np.abs(np.delete(np.diff(stamps), jumps[0]) - 100) <= 1)


def test_serve_prints_the_path_and_serves_a_saved_log_until_stopped(tmp_path):
    import threading

    from gtsjax.io.logs import save_log
    from gtsjax.sim.emulator import serve

    n = UTM_30LX.n_beams
    log = ScanLog(
        ranges=np.full((2, n), 3.0, np.float32),
        stamps=np.array([0.0, 0.025]),
        angle_min=UTM_30LX.angle_min,
        angle_increment=UTM_30LX.angle_increment,
        sensor_model="UTM-30LX",
    )
    save_log(log, tmp_path / "scene.npz")
    lines, stop = [], threading.Event()
    t = threading.Thread(
        target=serve,
        args=(str(tmp_path / "scene.npz"), None, Faults()),
        kwargs={"print_fn": lines.append, "stop": stop, "link_dir": tmp_path},
        daemon=True,
    )
    t.start()
    try:
        deadline = time.monotonic() + 3.0
        while not lines and time.monotonic() < deadline:
            time.sleep(0.02)
        path = str(tmp_path / "ttyEMU0")
        assert lines and path in lines[0]
        c = Client(path)
        (pp,) = c.ask(scip.pp_command())
        assert scip.sensor_model_from_pp(pp) == UTM_30LX
        ack, f = c.ask(scip.md_command(0, 1080, count=1), n=2)
        assert np.all(f.ranges_mm == 3000)
        c.close()
    finally:
        stop.set()
        t.join(timeout=3.0)
    assert not t.is_alive()


@pytest.mark.parametrize("model", [URG_04LX, UTM_30LX], ids=lambda m: m.name)
def test_urg_library_sample_sequence(model):
    """The order Hokuyo's own client library (urg_library's samples) speaks in, with no SCIP2.0 or VV
    first: an empty line (whose reply it reads and discards until a timeout), QT, PP (of which it
    needs all seven of DMIN, DMAX, ARES, AMIN, AMAX, AFRT, SCAN), then MD (or ME where the sensor has
    intensities) streaming, then QT."""
    with SensorEmulator(model, frame_source(model)) as emu:
        c = Client(emu.path)
        try:
            c.ser.write(b"\n")
            time.sleep(0.1)
            c.ser.read(c.ser.in_waiting or 1)
            (qt,) = c.ask(scip.qt_command())
            assert qt.ok and qt.status == "00"
            (pp,) = c.ask(scip.pp_command())
            assert {"DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN"} <= set(pp.fields)
            assert scip.sensor_model_from_pp(pp) == model
            cmd = (scip.me_command if model.has_intensity else scip.md_command)(model.amin, model.amax, count=0)
            frames = [f for f in c.ask(cmd, n=4, timeout=30.0) if isinstance(f, scip.ScanFrame) and f.status == "99"]
            assert len(frames) >= 2 and all(f.n_values == model.n_beams for f in frames)
            c.ser.write(scip.qt_command())
            replies = c.read_replies(20, timeout=3.0)  # frames already on their way, then QT's reply
            assert any(getattr(r, "command", "") == "QT" and r.ok for r in replies)
            assert c.dec.stats.dropped == 0
        finally:
            c.close()


def test_gd_is_answered_once_per_scan_with_that_scan(urg):
    """A real sensor answers each GD when the scan under way ends: asked back to back, the replies are
    one period apart (sensor clock), each a different scan, the one its timestamp names."""
    emu, c = urg
    (r,) = c.ask(scip.bm_command())
    assert r.status == "00"
    source = frame_source(URG_04LX)
    frames, t0 = [], time.monotonic()
    for _ in range(5):
        (f,) = c.ask(scip.gd_command(44, 725))
        frames.append(f)
    elapsed = time.monotonic() - t0
    stamps = np.array([f.timestamp_ms for f in frames])
    gaps = np.diff(stamps)  # 100 ms, not 0-1 ms (a whole number of periods, should the host be slow)
    assert np.all((gaps >= 100) & (gaps % round(URG_04LX.period * 1000) == 0)), stamps
    assert elapsed >= 4 * URG_04LX.period  # and in real time too
    for f in frames:
        i = round(f.timestamp_ms / (URG_04LX.period * 1000))  # scan i is served at i periods
        np.testing.assert_array_equal(f.ranges_mm, source(i)[0])
    assert len({int(f.ranges_mm[0]) for f in frames}) == 5
    (r,) = c.ask(scip.qt_command())  # a command after a GD is answered after it, in order
    assert r.command == "QT" and r.ok


def test_multiecho_on_the_utm_30lx_only():
    """ND/NE stream and HD/HE answer one scan on a UTM-30LX, one echo per simulated beam (so no '&');
    a URG-04LX answers them 0E, as to any command it does not know."""
    src = frame_source(UTM_30LX)
    with SensorEmulator(UTM_30LX, src) as emu:
        c = Client(emu.path)
        ack, f1, f2 = c.ask(b"NE0000108001002\n", n=3)
        assert (ack.command, ack.status) == ("NE0000108001002", "00")
        assert [f.remaining_scans for f in (f1, f2)] == [1, 0] and f1.status == "99"
        r, inten = src(int(f1.ranges_mm[0]) - 1000)
        np.testing.assert_array_equal(f1.ranges_mm, r)
        np.testing.assert_array_equal(f1.intensities, inten)
        assert b"&" not in c.raw
        (r,) = c.ask(scip.bm_command())
        (f,) = c.ask(b"HD0000108001\n")
        assert f.command == "HD0000108001" and f.status == "00"
        np.testing.assert_array_equal(f.ranges_mm, src(int(f.ranges_mm[0]) - 1000)[0])
        c.close()
    with SensorEmulator(URG_04LX, frame_source(URG_04LX)) as emu:
        c = Client(emu.path)
        for cmd in (b"ND0044072501000\n", b"NE0044072501000\n", b"HD0044072501\n", b"HE0044072501\n"):
            (r,) = c.ask(cmd)
            assert r.status == "0E" and r.command == cmd[:-1].decode()
        c.close()


def test_emulate_a_match_serves_every_laser_on_its_own_pty_at_its_phase(tmp_path):
    """``serve_match`` (``gtsjax emulate spl-match-2``): a pty per laser, each streaming its own
    laser's scans (as rendered in its log, to the millimetre), the south laser's frames half a period
    after the north's on the host clock."""
    import threading

    from gtsjax.io.serial import Link
    from gtsjax.sim.emulator import serve_match
    from gtsjax.sim.match import simulate_match

    logs, _ = simulate_match("spl-match-2", seed=5, n_robots=4, seconds=4.0)
    lines, stop = [], threading.Event()
    th = threading.Thread(target=serve_match, args=("spl-match-2",),
                          kwargs=dict(seed=5, n_robots=4, seconds=4.0, print_fn=lines.append, stop=stop,
                                      link_dir=tmp_path), daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 60
        while len(lines) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        paths = {ln.split(":")[0]: ln.split(" on ")[1].split(" ")[0] for ln in lines[:2]}
        assert set(paths) == {"north", "south"} and all(str(tmp_path) in p for p in paths.values()), lines
        stamps = {}
        for name, path in paths.items():
            served = {np.asarray(log_source(logs[name])(i)[0], np.int64).tobytes() for i in range(logs[name].n_scans)}
            with Link(path) as link:
                got = []
                while len(got) < 8 and time.monotonic() < deadline:
                    f = link.get(timeout=0.2)
                    if f is not None:
                        got.append(f)
            assert len(got) == 8
            assert all(f.frame.ranges_mm.astype(np.int64).tobytes() in served for f in got)
            stamps[name] = np.array([f.stamp for f in got])  # host time of each scan
        phase = np.mod(np.median(stamps["south"]) - np.median(stamps["north"]), URG_04LX.period)
        assert abs(phase - URG_04LX.period / 2) < 0.01, phase
    finally:
        stop.set()
        th.join(timeout=10)
    assert not th.is_alive() and not any(tmp_path.glob("*/ttyEMU0"))
