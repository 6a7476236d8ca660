"""Crash-safe recording: the clean-close round trip, a child killed with SIGKILL and recovered, torn
and damaged journals, and the one-line recovery command."""

import os
import select
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from gtsjax.errors import InputError
from gtsjax.io.logs import load_log
from gtsjax.io.record import Recorder, journal_path, main, read_journal, recover
from gtsjax.sensors import URG_04LX, UTM_30LX
from tests._utils import CHILD as CHILD_CLI
from tests._utils import cli_env, run_cli


def _scan(k, n):
    r = ((np.arange(n) * 7 + k * 13) % 3000 / 500.0 + 0.1).astype(np.float32)
    r[k % 50 :: 50] = 0.0
    return r


def test_clean_close_writes_a_log_that_round_trips_exactly(tmp_path):
    out = tmp_path / "raw.npz"
    rng = np.random.default_rng(0)
    n = UTM_30LX.n_beams
    ranges = rng.uniform(0.1, 30.0, (25, n)).astype(np.float32)
    ranges[rng.random((25, n)) < 0.1] = 0.0
    inten = rng.uniform(0, 5000, (25, n)).astype(np.float32)
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.02, 0.03, 25))
    with Recorder(out, UTM_30LX, intensities=True) as rec:
        assert rec.journal == journal_path(out) and rec.journal.exists()
        for k in range(25):
            rec.append(ranges[k], stamps[k], inten[k])
    assert out.exists() and not rec.journal.exists()
    log = load_log(out)
    np.testing.assert_array_equal(log.ranges, ranges)
    np.testing.assert_array_equal(log.intensities, inten)
    np.testing.assert_array_equal(log.stamps, stamps)
    assert log.ranges.dtype == np.float32 and log.stamps.dtype == np.float64
    assert log.angle_min == UTM_30LX.angle_min and log.angle_increment == UTM_30LX.angle_increment
    assert (log.range_min, log.range_max) == (UTM_30LX.range_min, UTM_30LX.range_max)
    assert log.sensor_model == "UTM-30LX"


def test_geometry_without_a_model_and_clamped_stamps(tmp_path):
    out = tmp_path / "raw.npz"
    rec = Recorder(out, n_beams=5, angle_min=-1.0, angle_increment=0.5, sensor_model="custom")
    rec.append(np.ones(5), 10.0)
    rec.append(np.ones(5), 9.5)  # a clock step back after a reconnect
    rec.append(np.ones(5), 11.0)
    assert rec.close() == 3
    assert rec.clamped == 1
    log = load_log(out)
    np.testing.assert_array_equal(log.stamps, [10.0, 10.0, 11.0])
    assert log.intensities is None and log.range_max == 30.0
    with pytest.raises(InputError):
        Recorder(tmp_path / "x.npz")  # no geometry


def test_empty_recording_writes_nothing_and_an_old_journal_is_never_clobbered(tmp_path):
    out = tmp_path / "raw.npz"
    assert Recorder(out, URG_04LX).close() is None
    assert not out.exists() and not journal_path(out).exists()
    rec = Recorder(out, URG_04LX)
    rec.append(np.ones(URG_04LX.n_beams), 1.0)
    with pytest.raises(InputError, match="recover it first"):
        Recorder(out, URG_04LX)
    rec.close()


CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from gtsjax.io.record import Recorder
    from gtsjax.sensors import UTM_30LX
    n = UTM_30LX.n_beams
    rec = Recorder(sys.argv[1], UTM_30LX, intensities=True)
    k = 0
    while True:
        r = ((np.arange(n) * 7 + k * 13) % 3000 / 500.0 + 0.1).astype(np.float32)
        r[k % 50 :: 50] = 0.0
        rec.append(r, 1000.0 + 0.025 * k, np.full(n, k, np.float32))
        print(k, flush=True)
        k += 1
        time.sleep(0.025)
    """
)


def record_then_sigkill(out, n_scans):
    """Run the recording child until it has appended ``n_scans`` scans, SIGKILL it; the last scan it
    reported appended."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(out)], stdout=subprocess.PIPE, text=True, bufsize=1,
                            env=cli_env())
    last = -1
    deadline = time.monotonic() + 60.0  # against a child that never starts, not a measurement
    try:
        while last < n_scans - 1 and time.monotonic() < deadline:
            ready, _, _ = select.select([proc.stdout], [], [], 0.5)
            if ready:
                line = proc.stdout.readline()
                if not line:
                    break
                last = int(line)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
        proc.stdout.close()
    assert last >= n_scans - 1, "the recording child did not get going"
    assert proc.returncode == -signal.SIGKILL and not out.exists()
    return last


def test_sigkill_loses_at_most_the_last_second(tmp_path):
    out = tmp_path / "raw.npz"
    last = record_then_sigkill(out, 41)  # about a second of scans at 40 Hz
    log = recover(journal_path(out))  # the one documented command, as a function
    assert log is not None and out.exists()
    n_scans = load_log(out).n_scans
    assert last + 1 - 40 <= n_scans <= last + 2  # at most 1 s (40 scans) lost; in fact none is
    for k in range(n_scans):
        np.testing.assert_array_equal(log.ranges[k], _scan(k, UTM_30LX.n_beams))
        assert log.intensities[k, 0] == k and log.stamps[k] == 1000.0 + 0.025 * k


def _journal_with(tmp_path, n_scans):
    out = tmp_path / "raw.npz"
    rec = Recorder(out, URG_04LX)
    for k in range(n_scans):
        rec.append(_scan(k, URG_04LX.n_beams), float(k))
    rec.sync()
    return out, rec


def test_recover_cuts_a_torn_record_and_skips_a_damaged_one(tmp_path):
    out, rec = _journal_with(tmp_path, 6)
    j = rec.journal
    size = j.stat().st_size
    rec_size = 8 + 4 * URG_04LX.n_beams + 4
    with open(j, "ab") as f:
        f.write(b"\x01" * (rec_size // 2))  # the process died inside a write
    log, report = read_journal(j)
    assert log.n_scans == 6 and report["torn_bytes"] == rec_size // 2 and report["bad_crc"] == 0
    with open(j, "r+b") as f:  # flip a byte inside record 2
        f.seek(size - 4 * rec_size + 100)
        b = f.read(1)
        f.seek(-1, os.SEEK_CUR)
        f.write(bytes([b[0] ^ 0xFF]))
    log, report = read_journal(j)
    assert report["bad_crc"] == 1 and log.n_scans == 5
    np.testing.assert_array_equal(log.stamps, [0, 1, 3, 4, 5])
    rec.close()


def test_recovery_command_line(tmp_path, capsys):
    """A recording killed with SIGKILL, recovered by ``gtsjax recover`` and by ``python -m
    gtsjax.io.record``: every scan the child had reported appended is there, as it was recorded."""
    out = tmp_path / "raw.npz"
    last = record_then_sigkill(out, 10)
    journal = journal_path(out)
    target = tmp_path / "recovered.npz"
    done = run_cli("recover", journal, target, timeout=120)
    assert done.returncode == 0, done.stderr
    n = load_log(target).n_scans
    assert f"recovered {n} scans" in done.stdout and last + 1 <= n <= last + 2  # none of those reported is lost
    log = load_log(target)
    for k in range(n):
        np.testing.assert_array_equal(log.ranges[k], _scan(k, UTM_30LX.n_beams))
        assert log.intensities[k, 0] == k and log.stamps[k] == 1000.0 + 0.025 * k
    cmd = [*CHILD_CLI, "--module", "gtsjax.io.record", str(journal), str(tmp_path / "again.npz")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=cli_env())
    assert done.returncode == 0, done.stderr
    assert load_log(tmp_path / "again.npz").n_scans == n
    # The same entry point in-process: default output is the journal's name without .journal.
    assert main([str(journal)]) == 0 and load_log(out).n_scans == n
    bad = tmp_path / "bad.journal"
    bad.write_bytes(b"not a journal")
    capsys.readouterr()
    assert main([str(bad)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "bad.journal" in err and "Traceback" not in err
    assert main([]) == 2


def test_records_a_live_link(tmp_path):
    from gtsjax.io.serial import Link
    from gtsjax.sim.emulator import SensorEmulator

    out = tmp_path / "live.npz"
    with SensorEmulator(UTM_30LX) as emu, Link(emu.path, intensity=True) as link:
        rec = Recorder(out, link.model, intensities=True)
        frames = []
        deadline = time.monotonic() + 30.0  # against a link that never delivers, not a measurement
        while len(frames) < 10 and time.monotonic() < deadline:
            f = link.get(timeout=0.1)
            if f is not None:
                rec.append_frame(f)
                frames.append(f)
        rec.close()
    log = load_log(out)
    assert log.n_scans == len(frames) == 10
    np.testing.assert_array_equal(log.ranges[-1], frames[-1].ranges_m)
    np.testing.assert_array_equal(log.stamps, [f.stamp for f in frames])


def test_a_long_recording_is_converted_a_block_at_a_time(tmp_path, monkeypatch):
    """The journal becomes the log a block of records at a time (here blocks of 7 of 45 scans, with a
    record damaged and a torn tail): the same log as reading the whole journal at once."""
    import gtsjax.io.record as R

    monkeypatch.setattr(R, "BLOCK_RECORDS", 7)
    out = tmp_path / "raw.npz"
    rng = np.random.default_rng(3)
    rec = Recorder(out, UTM_30LX, intensities=True)
    for i in range(45):
        rec.append(rng.uniform(0.1, 20, UTM_30LX.n_beams).astype(np.float32), 100.0 + 0.025 * i,
                   rng.uniform(0, 3000, UTM_30LX.n_beams).astype(np.float32))
    rec.close(keep_journal=True, write_log=False)
    j = journal_path(out)
    size = R._record_dtype(UTM_30LX.n_beams, True).itemsize
    data = bytearray(j.read_bytes())
    data[-3 * size + 100] ^= 0xFF  # the third record from the end fails its CRC
    j.write_bytes(bytes(data) + b"torn")
    whole, report = R.read_journal(j)
    got = R.journal_to_log(j, out)
    assert (got["records"], got["bad_crc"], got["torn_bytes"]) == (44, 1, 4) == (
        report["records"], report["bad_crc"], report["torn_bytes"])
    log = load_log(out)
    np.testing.assert_array_equal(log.ranges, whole.ranges)
    np.testing.assert_array_equal(log.intensities, whole.intensities)
    np.testing.assert_array_equal(log.stamps, whole.stamps)
    assert log.sensor_model == "UTM-30LX" and log.angle_increment == UTM_30LX.angle_increment
