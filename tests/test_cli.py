"""The command line's promises: a user's mistake is one line on stderr and exit status 2."""

import re

import numpy as np
import pytest

from gtsjax.cli import main
from tests._utils import run_cli


def run(*args):
    return run_cli(*args, timeout=120)


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


# The data sheets' figures: beams, field of view [°], range window [m], scans per second, intensity.
DATA_SHEETS = {
    "URG-04LX": (682, 240, (0.02, 5.6), 10, "no"),
    "URG-04LX-UG01": (682, 240, (0.02, 5.6), 10, "no"),
    "UTM-30LX": (1081, 270, (0.1, 30), 40, "yes"),
    "UST-10LX": (1081, 270, (0.06, 10), 40, "yes"),
}


def test_sensors_lists_the_data_sheet_figures(capsys, monkeypatch):
    """``gtsjax sensors``: one row per known scanner with its data sheet's figures, and its noise as a
    reader would write it (3 mm up to 1 m, then 0.3 % of the range, for the URG-04LX)."""
    from gtsjax.sensors import MODELS

    monkeypatch.setenv("COLUMNS", "200")  # one line per row
    assert main(["sensors"]) == 0
    rows = {}
    for line in capsys.readouterr().out.splitlines():
        cells = [c.strip() for c in line.split("│")[1:-1]]
        if cells and cells[0] in DATA_SHEETS:
            rows[cells[0]] = cells
    assert sorted(rows) == sorted(DATA_SHEETS) == sorted(MODELS)
    for name, (beams, fov, (lo, hi), rate, inten) in DATA_SHEETS.items():
        _, n, _, _, fov_text, window, rate_text, inten_text, noise = rows[name]
        assert int(n) == beams and abs(float(fov_text) - fov) < 1.0, rows[name]
        assert tuple(float(v) for v in window.split("–")) == (lo, hi) and float(rate_text) == rate, rows[name]
        assert inten_text == inten
        m = MODELS[name].noise
        far = m.frac_far * 100 if m.frac_far else m.sigma_far * 1000
        numbers = [float(v) for v in re.findall(r"\d+(?:\.\d+)?", noise)]
        assert numbers[0] == pytest.approx(m.sigma * 1000), noise
        if m.knee != float("inf"):
            assert numbers[1:] == pytest.approx([m.knee, far]), noise


def test_sensors_at_80_columns_names_every_model_in_full(capsys, monkeypatch):
    """At a terminal's usual 80 columns the other columns wrap, but each model's name, what a user
    types after --scanner, is printed whole."""
    from gtsjax.sensors import MODELS

    monkeypatch.setenv("COLUMNS", "80")
    assert main(["sensors"]) == 0
    out = capsys.readouterr().out
    assert max(len(line) for line in out.splitlines()) <= 80
    names = {line.split("│")[1].strip() for line in out.splitlines() if line.count("│") > 2}
    assert set(MODELS) <= names, names


def test_every_command_has_quiet_and_an_example_that_parses(capsys, monkeypatch):
    """Every command takes ``--quiet`` and ends its help with an example, and each example is a
    command line the command accepts (parsed by the command itself, after the vocabulary's aliases),
    so the help cannot show an option that has gone."""
    from gtsjax.cli import _spread, _vocabulary
    from gtsjax.cli._app import EXAMPLES, command

    monkeypatch.setenv("COLUMNS", "200")
    cmd = command()
    assert set(EXAMPLES) == set(cmd.commands)
    for name, sub in cmd.commands.items():
        assert any("--quiet" in p.opts for p in sub.params), name
        assert main([name, "--help"]) == 0
        help_text = capsys.readouterr().out
        for example in EXAMPLES[name]:
            assert example in " ".join(help_text.split()), (name, example)
            args = _spread(_vocabulary(example.split()[1:]))
            assert args[0] == name
            sub.make_context(name, args[1:])  # a usage error (an option that is not there) raises
