"""Hokuyo's own client library (urg_library, shared/clients/urg_library) against ``gtsjax emulate``.

The library is built in a copy (``make``: its C part only) and its C samples are run with ``-s PTY``
against the emulator of each scanner model, serving a scan log made here, so that every number a
sample prints is checked against the scan served and the model's geometry:

* front-beam ranges (and intensities, echoes) against the log's scan that the sensor timestamp
  names (scan ``k`` is served at ``k`` periods, the emulator's clock starting at 0);
* timestamps one scan period apart, for the streaming (``MD``/``ME``/``ND``/``NE``) samples and for
  ``get_distance_handshake`` (one ``GD`` per scan: the sensor answers each at its scan period);
* ``calculate_xy``: the points of a served scan, as the model's step angles place them;
* the multi-echo and intensity samples on the UTM-30LX only: a URG-04LX refuses them (``0E``), and
  the library says ``invalid response``, as against the real sensor.

Not run: ``find_port`` (it probes the host's serial devices, ``/dev/ttyACM*``, not a given path) and
``reboot_test`` (``RB``, a firmware reboot the emulator does not model).
"""

import math
import os
import re
import shutil
import subprocess

import numpy as np
import pytest

from gtsjax.io.logs import ScanLog, save_log
from gtsjax.sensors import URG_04LX, UTM_30LX
from gtsjax.sim.emulator import log_source
from tests._utils import popen_cli, read_lines, stop_with_ctrl_c
from tests.conftest import SHARED, need

SOURCE = SHARED / "clients" / "urg_library"
CC = shutil.which("cc") or shutil.which("gcc")


@pytest.fixture(scope="module", autouse=True)
def _tools():
    """A C compiler, make and Hokuyo's library: skipped without them here, failed without them in CI
    (``.ci/run`` installs build-essential where it is missing)."""
    need(CC is not None and shutil.which("make") is not None and os.path.isdir(SOURCE),
         "needs a C compiler, make and shared/clients/urg_library")


N_SCANS = 40


@pytest.fixture(scope="module")
def samples(tmp_path_factory):
    root = tmp_path_factory.mktemp("urg") / "urg_library"
    shutil.copytree(SOURCE, root)
    for sub in ("src", "samples/c"):  # the C library and its C samples (the C++ ones are not used)
        done = subprocess.run(["make", "-j1", "-C", str(root / sub)], capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return root / "samples" / "c"


def _log(model) -> ScanLog:
    """Scans whose every beam differs from scan to scan: the front beam 1000 + 7 k mm in scan k, the
    others random in the model's window, and a few without a return (0 on the wire)."""
    rng = np.random.default_rng(17)
    mm = rng.integers(model.dmin_mm + 50, min(model.dmax_mm, 8000), size=(N_SCANS, model.n_beams))
    front = model.afrt - model.amin
    mm[:, front] = 1000 + 7 * np.arange(N_SCANS)
    ranges = (mm / 1000.0).astype(np.float32)
    ranges[:, 3::50] = np.nan  # no return
    inten = rng.integers(100, 5000, size=mm.shape).astype(np.float32) if model.has_intensity else None
    return ScanLog(
        ranges=ranges, stamps=np.arange(N_SCANS) * model.period, angle_min=model.angle_min,
        angle_increment=model.angle_increment, intensities=inten, range_min=model.dmin_mm / 1000.0,
        range_max=model.dmax_mm / 1000.0, sensor_model=model.name,
    )


def _run(samples, name, path, timeout=30):
    done = subprocess.run([str(samples / name), "-s", path], capture_output=True, text=True, timeout=timeout)
    return done.returncode, done.stdout + done.stderr


def _scan_at(model, stamp_ms):
    """The index of the log's scan the sensor served at ``stamp_ms`` (scan k at k periods)."""
    k = stamp_ms / (model.period * 1000.0)
    assert abs(k - round(k)) < 0.05, f"timestamp {stamp_ms} ms is not on a scan period"
    return round(k) % N_SCANS


def _check_stream(model, lines, served, inten=None, period_gap=True):
    """``value [mm], (stamp [msec])`` style lines: each front value is the served scan's at that
    stamp, and the stamps advance by one period each."""
    front = model.afrt - model.amin
    stamps = []
    for values, stamp in lines:
        k = _scan_at(model, stamp)
        assert values[0] == served[k][front], (values, stamp)
        if inten is not None:
            assert values[1] == inten[k][front], (values, stamp)
        stamps.append(stamp)
    assert len(stamps) == 10
    gaps = np.diff(stamps)
    if period_gap:
        assert np.all(np.abs(gaps - model.period * 1000) <= 1), stamps
    else:
        assert np.all(gaps >= model.period * 1000 - 1), stamps


@pytest.mark.parametrize("model", [UTM_30LX, URG_04LX], ids=lambda m: m.name)
def test_urg_library_samples_against_the_emulator(samples, tmp_path, model):
    log = _log(model)
    save_log(log, tmp_path / "scans.npz")
    src = log_source(log)
    served = [np.asarray(src(k)[0]) for k in range(N_SCANS)]
    inten = [np.asarray(src(k)[1]) for k in range(N_SCANS)] if model.has_intensity else None
    proc = popen_cli("emulate", tmp_path / "scans.npz")
    try:
        first = read_lines(proc, 1, timeout=60)
        assert first, proc.stderr.read() if proc.poll() is not None else "no path printed"
        path = re.search(r" on (\S+) \(pty", first[0])[1]
        out = {}
        for name in ("sensor_parameter", "get_distance", "get_distance_intensity", "get_multiecho",
                     "get_multiecho_intensity", "get_distance_handshake", "sync_time_stamp", "calculate_xy",
                     "timeout_test", "angle_convert_test"):
            out[name] = _run(samples, name, path)

        rc, text = out["sensor_parameter"]
        assert rc == 0, text
        assert f"step: [{model.amin - model.afrt}, {model.amax - model.afrt}]" in text
        assert f"distance: [{model.dmin_mm}, {model.dmax_mm})" in text
        assert f"scan interval: {round(model.period * 1e6)} [usec]" in text
        assert f"sensor data size: {model.amax + 1}" in text  # steps 0..AMAX, as the library counts them
        assert model.name in text

        mm_line = re.compile(r"^(\d+) \[mm\], \((\d+) \[msec\]\)$", re.M)
        for name, gap in (("get_distance", True), ("get_distance_handshake", False)):
            rc, text = out[name]
            assert rc == 0, (name, text)
            lines = [((int(d),), int(t)) for d, t in mm_line.findall(text)]
            _check_stream(model, lines, served, period_gap=gap)
            if name == "get_distance_handshake":  # one GD per scan: fresh scans, not one scan repeated
                assert len({v for v, _ in lines}) == 10, text

        refused = ("get_distance_intensity", "get_multiecho", "get_multiecho_intensity")
        if model.has_intensity:
            rc, text = out["get_distance_intensity"]
            assert rc == 0, text
            lines = [((int(d), int(i)), int(t))
                     for d, i, t in re.findall(r"^(\d+) \[mm\], (\d+) \[1\], \((\d+) \[msec\]\)$", text, re.M)]
            _check_stream(model, lines, served, inten)
            rc, text = out["get_multiecho"]  # URG_MAX_ECHO = 3 echoes per step: the one echo, then none
            assert rc == 0, text
            lines = [((int(a), int(b), int(c)), int(t))
                     for a, b, c, t in re.findall(r"^(\d+), (\d+), (\d+), (\d+)$", text, re.M)]
            assert all(v[1:] == (0, 0) for v, _ in lines), text
            _check_stream(model, [((v[0],), t) for v, t in lines], served)
            rc, text = out["get_multiecho_intensity"]
            assert rc == 0, text
            lines = [(tuple(map(int, g[:6])), int(g[6]))
                     for g in re.findall(r"^(\d+), (\d+), (\d+), (\d+), (\d+), (\d+), (\d+)$", text, re.M)]
            assert all(v[1:3] == (0, 0) and v[4:6] == (0, 0) for v, _ in lines), text
            _check_stream(model, [((v[0], v[3]), t) for v, t in lines], served, inten)
        else:  # no intensity, no multi-echo on a URG-04LX: refused, as the real one refuses them
            for name in refused:
                rc, text = out[name]
                assert rc == 1 and "invalid response" in text, (name, text)

        rc, text = out["sync_time_stamp"]
        assert rc == 0, text
        pairs = [(int(a), int(b)) for a, b in re.findall(r"^(-?\d+),\s+(-?\d+)$", text, re.M)]
        assert len(pairs) >= 2
        sensor = [b for _, b in pairs[1:]]  # after the first (raw) line: sensor time since sync, ms
        assert sensor == sorted(sensor) and all(abs(b - a) <= 5 for a, b in pairs[1:]), text

        rc, text = out["calculate_xy"]
        assert rc == 0, text
        got = np.array([tuple(map(int, p)) for p in re.findall(r"^(-?\d+), (-?\d+)$", text, re.M)])
        steps = np.arange(model.n_beams) + model.amin - model.afrt
        rad = steps * 2 * math.pi / model.ares
        matches = []
        for r in served:
            keep = (r >= model.dmin_mm) & (r <= model.dmax_mm)
            if keep.sum() != len(got):
                continue
            want = np.stack([np.trunc(r[keep] * np.cos(rad[keep])), np.trunc(r[keep] * np.sin(rad[keep]))], 1)
            matches.append(np.abs(want - got).max() <= 1)
        assert any(matches), f"{len(got)} points, matching no served scan"
        assert len(got) == model.n_beams - len(range(3, model.n_beams, 50))  # every beam with a return

        rc, text = out["timeout_test"]  # nothing unsolicited in 3 s: the read times out with 0 bytes
        assert rc == 0 and "n = 0" in text, text

        rc, text = out["angle_convert_test"]
        assert rc == 0, text
        lo, hi = model.amin - model.afrt, model.amax - model.afrt
        assert f"urg_step2deg({lo}): {lo * 360 / model.ares:.6f}" in text
        assert f"urg_step2deg({hi}): {hi * 360 / model.ares:.6f}" in text
    finally:
        stop_with_ctrl_c(proc)
    assert proc.returncode == 0
