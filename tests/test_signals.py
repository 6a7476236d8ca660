"""SIGTERM and SIGHUP stop ``run``, ``replay``, ``train`` and ``emulate`` as Ctrl-C does (issue 17):
service managers and containers stop a program with SIGTERM, a closed terminal sends SIGHUP. Each
test starts the real command in a child process, sends the signal mid-work, and checks what Ctrl-C
would have left: the emulator's link gone, the live run's QT sent, CSV complete and recording
finalised, a replay's rows kept, no half-trained model written."""

import json
import os
import re
import select
import signal
import subprocess
import time

import numpy as np
import pytest

from gtsjax.cli.demo import demo_model_path
from gtsjax.io import load_log, save_log, save_site
from gtsjax.io.gtd import read_gtd
from gtsjax.io.record import journal_path
from gtsjax.sensors import URG_04LX
from gtsjax.sim import simulate
from gtsjax.sim.emulator import SensorEmulator
from tests._utils import popen_cli

PATIENCE_S = 300.0  # a child that compiles on a loaded 2-core machine; never a measurement


def _lines_until(stream, pattern: str, timeout: float = PATIENCE_S) -> list[str]:
    """Lines of a child's text ``stream`` up to the first that matches ``pattern`` (or the end)."""
    lines, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([stream], [], [], 0.5)
        if ready:
            line = stream.readline()
            if not line:
                break
            lines.append(line)
            if re.search(pattern, line):
                break
    return lines


def _stopped(proc, sig) -> tuple[str, str]:
    """Send ``sig``, wait for the child to end (killed if it does not), return its remaining output."""
    proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise
    return out or "", err or ""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_emulate_removes_its_link(tmp_path, sig):
    log, _ = simulate("spl-trajectory", seed=43, n_scans=20)
    save_log(log, tmp_path / "scene.npz")
    proc = popen_cli("emulate", tmp_path / "scene.npz")
    first = _lines_until(proc.stdout, r" on \S+ \(pty", timeout=60)
    assert first, proc.stderr.read() if proc.poll() is not None else "no path printed"
    path = re.search(r" on (\S+) \(pty", first[-1])[1]
    assert os.path.lexists(path)
    out, err = _stopped(proc, sig)
    # Its normal end, but stopped by a signal all the same: the status and line of a stopped command.
    assert proc.returncode == 128 + sig and err.strip().splitlines()[-1].startswith("gtsjax: stopped by"), (out, err)
    assert not os.path.lexists(path) and not os.path.exists(os.path.dirname(path))


def test_run_stops_cleanly_on_sigterm(tmp_path):
    """``run --record`` stopped by SIGTERM: QT reaches the sensor (its laser is off), the summary is
    printed, the CSV holds every row the JSON lines reported, the recording is finalised (no journal);
    it ends with the line and status of a stopped command (128 + 15), as it does while compiling."""
    log, site = simulate("spl-trajectory", seed=41, n_scans=150)
    save_site(site, tmp_path / "site.json")
    raw, out = tmp_path / "raw.npz", tmp_path / "gtd.csv"
    with SensorEmulator(URG_04LX, log) as emu:
        proc = popen_cli("run", "--port", emu.path, "--site", tmp_path / "site.json", "--model", demo_model_path(),
                         "--out", out, "--record", raw, "--json", "--quiet", "--seconds", "600")
        lines = []
        deadline = time.monotonic() + PATIENCE_S
        while len(lines) < 15 and time.monotonic() < deadline and proc.poll() is None:
            lines += _lines_until(proc.stdout, r".", timeout=5)
        assert len(lines) >= 15, proc.stderr.read() if proc.poll() is not None else "no JSON lines"
        rest, err = _stopped(proc, signal.SIGTERM)
        laser_on = emu._laser  # the emulator's own state: BM turns it on, QT off
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "gtsjax: stopped by SIGTERM", err
    assert not laser_on
    assert re.search(r"\d+ frames, \d+ rows -> ", err), err
    reported = [json.loads(ln) for ln in lines + rest.splitlines() if ln.strip()]
    from_json = [(r["stamp"], t["track_id"], t["class"]) for r in reported for t in r["tracks"]]
    csv_rows = [(r.stamp, r.track_id, r.cls) for r in read_gtd(out)]
    # the CSV is written before a frame's JSON line: it holds every reported row, and at most the rows
    # of one frame more (the signal between the two)
    assert from_json and csv_rows[: len(from_json)] == from_json
    assert len({r[0] for r in csv_rows[len(from_json):]}) <= 1
    assert raw.exists() and not journal_path(raw).exists()
    rec = load_log(raw)
    assert rec.n_scans >= len(reported) - 1 and rec.sensor_model == "URG-04LX"


def test_replay_keeps_its_rows_on_sighup(tmp_path):
    """``replay`` stopped by SIGHUP mid-log: exit status 128 + 1 and one line saying so; the CSV written
    so far is whole (it reads back, every row complete) and holds the first scans' rows, not all.
    Replay writes a block of 16 chunks at a time: with 16-scan chunks the log is twelve blocks, so the
    signal, sent once the first block's rows are on disk, comes while later blocks are computed."""
    log, site = simulate("spl-trajectory", seed=44, n_scans=3000)
    save_log(log, tmp_path / "long.npz")
    save_site(site, tmp_path / "site.json")
    out = tmp_path / "gtd.csv"
    proc = popen_cli("replay", tmp_path / "long.npz", "--site", tmp_path / "site.json", "--model", demo_model_path(),
                     "--out", out, "--step-by-step", "--chunk", "16")
    deadline = time.monotonic() + PATIENCE_S
    while time.monotonic() < deadline and proc.poll() is None:
        if out.exists() and out.stat().st_size > 2000:
            break
        time.sleep(0.05)
    assert proc.poll() is None, proc.stderr.read()
    _, err = _stopped(proc, signal.SIGHUP)
    assert proc.returncode == 128 + signal.SIGHUP, err
    assert err.strip().splitlines()[-1] == "gtsjax: stopped by SIGHUP"
    stamps = np.unique([r.stamp for r in read_gtd(out)])  # every row parses: none was cut
    assert stamps.size > 0 and stamps[-1] < log.stamps[-1]  # rows were kept, and the log was not finished
    assert np.all(np.isin(np.round(stamps, 6), np.round(log.stamps, 6)))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "ctrl-c"])
def test_train_writes_nothing_on_sigterm(tmp_path, sig):
    """``train`` stopped by SIGTERM or Ctrl-C while fitting (the fit runs in a thread of its own, so
    the stop does not wait for it to end): exit status 128 + 15, or 130, one line saying so, no model
    and no report written, and no abort at exit (the thread is left with the process). The signal
    comes once labelling is done, as the first GP's fit compiles and runs (waiting for that fit's own
    line cost a fit's time for nothing)."""
    a, site = simulate("spl-train", seed=21, n_scans=250)
    save_log(a, tmp_path / "a.npz")
    save_site(site, tmp_path / "site.json")
    proc = popen_cli("train", tmp_path / "a.npz", "--site", tmp_path / "site.json", "--out", tmp_path / "m.npz",
                     "--report", tmp_path / "r.json", "--max-per-class", "200", "--max-pose", "300",
                     stderr=subprocess.STDOUT)
    seen = _lines_until(proc.stdout, r"labelling: done")
    assert any("labelling: done" in ln for ln in seen), "".join(seen)
    out, _ = _stopped(proc, sig)
    assert proc.returncode == (130 if sig == signal.SIGINT else 128 + signal.SIGTERM), out
    assert out.strip().splitlines()[-1] == ("gtsjax: interrupted" if sig == signal.SIGINT else
                                            "gtsjax: stopped by SIGTERM"), out
    assert "terminate called" not in out and "Fatal" not in out, out
    assert not (tmp_path / "m.npz").exists() and not (tmp_path / "r.json").exists()
