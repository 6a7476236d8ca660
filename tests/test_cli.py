"""The command line's promises: a user's mistake is one line on stderr and exit status 2."""

import subprocess
import sys

import numpy as np

from gtsjax.cli import main


def run(*args):
    return subprocess.run([sys.executable, "-m", "gtsjax", *args], capture_output=True, text=True, timeout=120)


def test_info_bad_file_one_line_exit_2(tmp_path):
    p = tmp_path / "garbage.npz"
    p.write_bytes(b"\x00\x01 not a zip")
    res = run("info", str(p))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and str(p) in lines[0] and "Traceback" not in res.stderr


def test_info_good_files(tmp_path, capsys):
    log = tmp_path / "log.npz"
    np.savez(log, ranges=np.ones((3, 10), np.float32), stamps=np.arange(3.0), angle_min=np.float64(-1.0),
             angle_increment=np.float64(0.01))
    site = tmp_path / "site.json"
    site.write_text('{"landmarks": [{"class": "post", "x": 0, "y": 0}, {"class": "post", "x": 1, "y": 0},'
                    ' {"class": "post", "x": 0, "y": 1}], "sensor_pose": [0.5, -1, 1.57]}')
    assert main(["info", str(log), str(site)]) == 0
    out = capsys.readouterr().out
    assert "3 scans × 10 beams" in out and "3 landmarks" in out


def test_usage_error_exit_2():
    assert run("info", "--no-such-flag").returncode == 2
    assert run("sensors").returncode == 0
