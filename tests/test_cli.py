"""The command line's promises: a user's mistake is one line on stderr and exit status 2."""

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
    np.savez(
        log,
        ranges=np.ones((3, 10), np.float32),
        stamps=np.arange(3.0),
        angle_min=np.float64(-1.0),
        angle_increment=np.float64(0.01),
    )
    site = tmp_path / "site.json"
    site.write_text(
        '{"landmarks": [{"class": "post", "x": 0, "y": 0}, {"class": "post", "x": 1, "y": 0},'
        ' {"class": "post", "x": 0, "y": 1}], "sensor_pose": [0.5, -1, 1.57]}'
    )
    assert main(["info", str(log), str(site)]) == 0
    out = capsys.readouterr().out
    assert "3 scans × 10 beams" in out and "3 landmarks" in out


def test_usage_error_exit_2():
    assert run("info", "--no-such-flag").returncode == 2


# The data sheets' figures, typed out here (not read from gtsjax.sensors): the SCIP 2.0 ``PP`` reply's steps
# (first–last measurable step / steps per turn, and the step along the forward axis), so the beams and the
# field of view follow; the range window [m]; scans per second; whether it reports intensity. URG-04LX:
# 360°/1024 steps, 240° scanned (steps 44–725, front 384: 682 beams, a captured GD reply of one
# holds 682 values; docs that say "683 steps" count the step interval's ends), 20 mm–5.6 m in SCIP 2.0
# (DMIN 20, DMAX 5600), 100 ms a scan. UTM-30LX and UST-10LX: 0.25° steps (1440 a turn), 270° scanned
# (steps 0–1080, front 540: 1081 beams), 0.1–30 m and 0.06–10 m, 25 ms a scan, intensities.
DATA_SHEETS = {
    "URG-04LX": ((44, 725, 1024), 384, 682, 240, (0.02, 5.6), 10, "no"),
    "URG-04LX-UG01": ((44, 725, 1024), 384, 682, 240, (0.02, 5.6), 10, "no"),
    "UTM-30LX": ((0, 1080, 1440), 540, 1081, 270, (0.1, 30), 40, "yes"),
    "UST-10LX": ((0, 1080, 1440), 540, 1081, 270, (0.06, 10), 40, "yes"),
}
# The range noise (σ, one scan to the next) as gtsjax.sensors' docstring sets it down: the URG-04LX's
# measured on a real unit and taken 1.5× (3 mm up to 1 m, 0.3 % of the range beyond), the UG01's three
# times that (its data sheet's accuracy is three times the URG-04LX's), the UTM-30LX's and UST-10LX's
# the data sheets' repeatability σ < 10 mm (the UTM-30LX's 15 mm beyond 10 m: its accuracy figure
# grows from ±30 to ±50 mm there). As text, as the table prints it, and as σ [m] at 0.5, 3 and 20 m.
NOISE = {
    "URG-04LX": ("3 mm ≤ 1 m, then 0.3 %", (0.003, 0.009, 0.060)),
    "URG-04LX-UG01": ("9 mm ≤ 1 m, then 0.9 %", (0.009, 0.027, 0.180)),
    "UTM-30LX": ("10 mm ≤ 10 m, then 15 mm", (0.010, 0.010, 0.015)),
    "UST-10LX": ("10 mm", (0.010, 0.010, 0.010)),
}


def test_sensors_lists_the_data_sheet_figures(capsys, monkeypatch):
    """``gtsjax sensors``: one row per known scanner with its data sheet's figures, and its noise as a
    reader would write it (3 mm up to 1 m, then 0.3 % of the range, for the URG-04LX), each against the
    figures typed out above."""
    monkeypatch.setenv("COLUMNS", "200")  # one line per row
    assert main(["sensors"]) == 0
    rows = {}
    for line in capsys.readouterr().out.splitlines():
        cells = [c.strip() for c in line.split("│")[1:-1]]
        if cells:
            rows[cells[0]] = cells
    assert sorted(rows) == sorted(DATA_SHEETS)
    for name, ((amin, amax, ares), front, beams, fov, (lo, hi), rate, inten) in DATA_SHEETS.items():
        _, n, steps, front_text, fov_text, window, rate_text, inten_text, noise = rows[name]
        assert steps == f"{amin}–{amax}/{ares}" and int(front_text) == front, rows[name]
        assert int(n) == beams and abs(float(fov_text) - fov) < 1.0, rows[name]
        assert tuple(float(v) for v in window.split("–")) == (lo, hi) and float(rate_text) == rate, rows[name]
        assert inten_text == inten
        assert noise == NOISE[name][0], rows[name]


def test_sensor_models_are_the_data_sheets():
    """The models themselves (what the emulator, the simulator and the step use), against the same
    figures: beam angles in steps of 360°/ARES about the forward axis, the range window, the period, the
    intensity and the noise's σ at three ranges."""
    from gtsjax.sensors import MODELS

    assert sorted(MODELS) == sorted(DATA_SHEETS)
    for name, ((amin, amax, ares), front, beams, fov, (lo, hi), rate, inten) in DATA_SHEETS.items():
        m = MODELS[name]
        step = 2 * np.pi / ares
        assert m.n_beams == beams == amax - amin + 1, name
        np.testing.assert_allclose(m.angles, (np.arange(amin, amax + 1) - front) * step, rtol=0, atol=1e-12)
        assert abs(np.degrees(m.angles[-1] - m.angles[0]) - fov) < 1.0, name
        assert np.degrees(m.angles[0]) == pytest.approx(-np.degrees(m.angles[-1]), abs=0.5), name  # about the front
        assert (m.range_min, m.range_max) == (lo, hi) and m.period == pytest.approx(1 / rate), name
        assert m.has_intensity == (inten == "yes"), name
        np.testing.assert_allclose(m.noise.std(np.array([0.5, 3.0, 20.0])), NOISE[name][1], rtol=1e-9, err_msg=name)


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
