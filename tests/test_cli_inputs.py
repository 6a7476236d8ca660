"""A user's inputs are never destroyed, and a damaged file is one line (issue 39).

Every command that writes refuses, before any work, an output that is one of its inputs (by any
spelling: ``./x/../LOG``, a link) or two outputs that are one file: exit 2, one line naming both
options, every input byte for byte as it was, nothing written. Files that lie about themselves are
refused before they are used: an ``.npz`` whose array header claims more than the archive holds (a
10⁶ × 10⁶ array would ask for 4 TB), float32 stamps that rounding has collapsed, a model with NaN in
its numbers or a shape-fixing setting outside what a step can run with."""

import hashlib
import io
import json
import zipfile

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.io import save_log, save_site
from gtsjax.sim import simulate

DEMO_MODEL = demo_model_path()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    log, site = simulate("spl-eval", seed=1, n_scans=5)
    save_log(log, d / "log.npz")
    save_site(site, d / "site.json")
    (d / "model.npz").write_bytes(DEMO_MODEL.read_bytes())
    (d / "gtd.csv").write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n"
                               "1.0,1,robot,1.0,1.0,0.5,0.01,0.01,0.01\n")
    (d / "rec.npz.journal").write_bytes(b"\x00" * 64)
    (d / "link.npz").symlink_to(d / "log.npz")
    return d


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
            for p in sorted(folder.iterdir())}


R = ["--site", "{d}/site.json", "--model", "{d}/model.npz"]
CLASHES = {
    "convert onto its input": (["convert", "{d}/log.npz", "--out", "{d}/log.npz"], "destroy the input"),
    "convert onto its input, spelt another way": (["convert", "{d}/log.npz", "--out", "{d}/x/../log.npz"],
                                                  "destroy the input"),
    "convert a link onto what it points to": (["convert", "{d}/link.npz", "--out", "{d}/log.npz"], "destroy the input"),
    "simulate, the log and the site one file": (["simulate", "spl-eval", "--out", "{o}/x.npz", "--site", "{o}/x.npz"],
                                                "overwrite"),
    "replay onto its log": (["replay", "{d}/log.npz", *R, "--out", "{d}/log.npz"], "destroy the input"),
    "replay onto its site": (["replay", "{d}/log.npz", *R, "--out", "{d}/site.json"], "destroy the input"),
    "replay onto its model": (["replay", "{d}/log.npz", *R, "--out", "{d}/model.npz"], "destroy the input"),
    "replay, the sensor CSV onto the CSV": (["replay", "{d}/log.npz", *R, "--out", "{o}/o.csv", "--sensor-out",
                                             "{o}/o.csv"], "overwrite"),
    "replay, the summary onto the log": (["replay", "{d}/log.npz", *R, "--out", "{o}/o.csv", "--summary",
                                          "{d}/log.npz"], "destroy the input"),
    "train onto its site": (["train", "{d}/log.npz", "--site", "{d}/site.json", "--out", "{d}/site.json"],
                            "destroy the input"),
    "train, the report onto its log": (["train", "{d}/log.npz", "--site", "{d}/site.json", "--out", "{o}/m.npz",
                                        "--report", "{d}/log.npz"], "destroy the input"),
    "train, the report onto the model": (["train", "{d}/log.npz", "--site", "{d}/site.json", "--out", "{o}/m.npz",
                                          "--report", "{o}/m.npz"], "overwrite"),
    "plot onto its CSV": (["plot", "{d}/gtd.csv", "--site", "{d}/site.json", "--out", "{d}/gtd.csv"],
                          "destroy the input"),
    "run onto its model": (["run", "--port", "/dev/null", *R, "--out", "{d}/model.npz"], "destroy the input"),
    "run, the recording onto its site": (["run", "--port", "/dev/null", *R, "--out", "{o}/o.csv", "--record",
                                          "{d}/site.json"], "destroy the input"),
    "recover onto its journal": (["recover", "{d}/rec.npz.journal", "{d}/rec.npz.journal"], "destroy the input"),
}


@pytest.mark.parametrize("case", sorted(CLASHES))
def test_no_command_writes_over_its_input(inputs, tmp_path, capsys, case):
    args, fragment = CLASHES[case]
    before = _digest(inputs)
    capsys.readouterr()
    code = main([a.format(d=inputs, o=tmp_path) for a in args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("gtsjax: ") and fragment in err[0], err
    assert _digest(inputs) == before  # every input as it was
    assert list(tmp_path.iterdir()) == []  # and nothing written


def _lying_npz(path, key="ranges", shape=(1_000_000, 1_000_000)):
    """An .npz whose ``key`` holds 6 float32 but whose header claims ``shape``."""
    h = np.lib.format.header_data_from_array_1_0(np.zeros((2, 3), np.float32))
    h["shape"] = shape
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, h)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{key}.npy", buf.getvalue() + np.zeros(6, np.float32).tobytes())
        arr = io.BytesIO()
        np.lib.format.write_array(arr, np.arange(2.0))
        z.writestr("stamps.npy", arr.getvalue())


def _model_with(path, edit):
    z = dict(np.load(DEMO_MODEL))
    edit(z)
    np.savez(path, **z)


def _set_field(*where, value):
    def edit(z):
        header = json.loads(str(z["gtsjax_model"]))
        node = header["schema"]
        for name in where:
            node = node["fields"][name]
        node["value"] = value
        z["gtsjax_model"] = np.array(json.dumps(header))
    return edit


def _nan_leaf(z):
    key = next(k for k in sorted(z) if z[k].dtype.kind == "f" and z[k].size > 3)
    z[key] = z[key].copy()
    z[key].flat[0] = np.nan


def _f32_stamps(offset):
    def write(path):
        log, _ = simulate("spl-eval", seed=1, n_scans=30)
        d = log.to_dict()
        d["stamps"] = (d["stamps"] - d["stamps"][0] + offset).astype(np.float32)
        np.savez(path, **d)
    return write


BAD_FILES = {
    "a log whose header claims 10^6 x 10^6": (lambda p: _lying_npz(p), ["info", "{f}"], "claims shape"),
    "a model whose header claims 10^6 x 10^6": (lambda p: _lying_npz(p, "gtsjax_model"),
                                                ["replay", "{d}/log.npz", "--site", "{d}/site.json", "--model", "{f}",
                                                 "--out", "{o}/o.csv"], "claims shape"),
    "float32 seconds since 1970": (_f32_stamps(1.7e9), ["info", "{f}"], "the rounding lost the time"),
    "a model with NaN": (lambda p: _model_with(p, _nan_leaf), ["info", "{f}"], "holds NaN"),
    "a model with max_tracks -1": (lambda p: _model_with(p, _set_field("max_tracks", value=-1)), ["info", "{f}"],
                                   "max_tracks is -1, outside"),
    "a model with window 0": (lambda p: _model_with(p, _set_field("frontend", "window", value=0)), ["info", "{f}"],
                              "window is 0, outside"),
    "a model with max_candidates 0": (lambda p: _model_with(p, _set_field("frontend", "max_candidates", value=0)),
                                      ["replay", "{d}/log.npz", "--site", "{d}/site.json", "--model", "{f}",
                                       "--out", "{o}/o.csv"], "max_candidates is 0, outside"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_a_file_that_lies_about_itself_is_one_line(inputs, tmp_path_factory, tmp_path, capsys, case):
    make, args, fragment = BAD_FILES[case]
    f = tmp_path_factory.mktemp("bad") / "bad.npz"
    make(f)
    capsys.readouterr()
    code = main([a.format(d=inputs, f=f, o=tmp_path) for a in args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith(f"gtsjax: {f}") and fragment in err[0], err
    assert list(tmp_path.iterdir()) == []  # no header-only CSV left behind


def test_float32_stamps_that_still_increase_are_read_with_a_warning(tmp_path, capsys):
    f = tmp_path / "f32.npz"
    _f32_stamps(0.0)(f)
    capsys.readouterr()
    assert main(["info", str(f)]) == 0
    err = capsys.readouterr().err
    assert "'stamps' are float32, not float64" in err, err


def test_one_vocabulary_with_the_old_spellings_kept_for_a_release(tmp_path, capsys):
    """``--scanner`` is a scanner type on ``simulate`` (and ``emulate``); the old ``--sensor`` still
    works there, with a one-line warning naming the new one, and writes the same log."""
    new, old = tmp_path / "new.npz", tmp_path / "old.npz"
    common = ["simulate", "spl-eval", "--scans", "5", "--site", str(tmp_path / "s.json")]
    assert main([*common, "--out", str(new), "--scanner", "UTM-30LX"]) == 0
    capsys.readouterr()
    assert main([*common, "--out", str(old), "--sensor", "UTM-30LX"]) == 0
    err = capsys.readouterr().err
    assert "gtsjax: warning: --sensor: is now --scanner" in err, err
    a, b = np.load(new), np.load(old)
    assert str(a["sensor_model"]) == str(b["sensor_model"]) == "UTM-30LX"
    np.testing.assert_array_equal(a["ranges"], b["ranges"])
    # How long is --seconds on every command (demo, enrol, run); run's --duration still works, said once.
    capsys.readouterr()
    run = ["run", "--port", "/dev/null", "--site", str(tmp_path / "s.json"), "--model", "demo", "--out",
           str(tmp_path / "o.csv")]
    assert main([*run, "--duration", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == "gtsjax: warning: --duration: is now --seconds (the old name goes in a later release)", err
    assert len(err) == 2 and "'--seconds'" in err[1], err
    # A folder simulate writes is --out-beliefs (--beliefs is run's UDP listener); the old name still
    # writes the beliefs, said once.
    capsys.readouterr()
    sim = ["simulate", "spl-trajectory", "--scans", "20", "--site", str(tmp_path / "t.json"), "--out",
           str(tmp_path / "t.npz")]
    assert main([*sim, "--out-beliefs", str(tmp_path / "b-new")]) == 0
    capsys.readouterr()
    assert main([*sim, "--beliefs", str(tmp_path / "b-old")]) == 0
    assert "gtsjax: warning: --beliefs: is now --out-beliefs" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "b-new").iterdir()) == sorted(p.name for p in (tmp_path / "b-old").iterdir())
    assert (tmp_path / "b-new" / "put-in.json").is_file()


def test_the_shipped_model_by_name_and_the_version(capsys):
    capsys.readouterr()
    assert main(["info", "demo"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(str(DEMO_MODEL)) and "gtsjax model" in out, out
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("gtsjax ")


def _site_text(inputs):
    return (inputs / "site.json").read_text()


MORE_BAD = {
    "a site coordinate of 400 digits": (
        lambda d, f: f.write_text(_site_text(d).replace('"sensor_pose": [', '"sensor_pose": [' + "1" * 400 + ", ", 1)),
        ["info", "{f}"], "three finite numbers"),
    "a site of 5000 digits": (
        lambda d, f: f.write_text(_site_text(d).replace('"sensor_pose": [', '"sensor_pose": [' + "9" * 5000 + ", ", 1)),
        ["info", "{f}"], "a number too long to read"),
    "a site nested 200 000 deep": (lambda d, f: f.write_text("[" * 200_000 + "]" * 200_000), ["info", "{f}"],
                                   "nested deeper"),
    "run --udp to port 99999": (None, ["run", "--port", "/dev/null", "--site", "{d}/site.json", "--model", "demo",
                                       "--out", "{o}/o.csv", "--udp", "127.0.0.1:99999"], "PORT in 1–65535"),
    "plot --out a text file": (None, ["plot", "{d}/gtd.csv", "--site", "{d}/site.json", "--out", "{o}/p.txt"],
                               "must name a figure file"),
    # Scenario seeds (issue 54: three tracebacks, and a colon with no seed run as seed 1000 in silence).
    "evaluate a scenario of seed abc": (None, ["evaluate", "--model", "demo", "--scenario", "spl-eval:abc", "--out-dir",
                                               "{o}/ev"], "the seed 'abc' is not an integer"),
    "evaluate a scenario of seed -1": (None, ["evaluate", "--model", "demo", "--scenario", "spl-eval:-1", "--out-dir",
                                              "{o}/ev"], "the seed -1 is out of range"),
    "evaluate a scenario with no seed after its colon": (None, ["evaluate", "--model", "demo", "--scenario", "spl-eval:",
                                                                "--out-dir", "{o}/ev"], "no seed after the colon"),
    "simulate with seed -1": (None, ["simulate", "spl-eval", "--seed", "-1", "--out", "{o}/x.npz", "--site",
                                     "{o}/x.json"], "'--seed'"),
    # The beliefs' folder given as the log to write: it was made a folder, then writing the log failed.
    "simulate --out-beliefs the log it writes": (None, ["simulate", "spl-eval", "--scans", "5", "--out", "{o}/x.npz",
                                                         "--site", "{o}/x.json", "--out-beliefs", "{o}/x.npz"],
                                                "both --out and --out-beliefs"),
    # A class the labels do not have (once ignored in silence), before any fitting.
    "train --max-speed for a class the labels lack": (None, ["train", "{d}/log.npz", "--site", "{d}/site.json", "--out",
                                                             "{o}/m.npz", "--max-speed", "tractor=1"],
                                                      "no class 'tractor' in the labels"),
    # A lag of 10^6 s grew to 16.5 GB in 15 s.
    "run --smooth-lag of a million seconds": (None, ["run", "--port", "/dev/null", "--site", "{d}/site.json", "--model",
                                                     "demo", "--out", "{o}/o.csv", "--smooth-lag", "1e6"], "at most 60 s"),
    # A usage error (an unknown option) is one line too, not Click's box of six.
    "an option no command has": (None, ["replay", "{d}/log.npz", "--site", "{d}/site.json", "--model", "demo", "--out",
                                        "{o}/o.csv", "--smooth-lag", "1"], "No such option: --smooth-lag"),
}


@pytest.mark.parametrize("case", sorted(MORE_BAD))
def test_more_bad_inputs_are_one_line(inputs, tmp_path_factory, tmp_path, capsys, case):
    make, args, fragment = MORE_BAD[case]
    f = tmp_path_factory.mktemp("bad") / "bad.json"
    if make is not None:
        make(inputs, f)
    capsys.readouterr()
    code = main([a.format(d=inputs, f=f, o=tmp_path) for a in args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("gtsjax: ") and fragment in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_a_journal_header_without_its_angles_is_one_line(tmp_path, capsys):
    import struct

    from gtsjax.io.record import MAGIC

    head = json.dumps({"n_beams": 10, "angle_increment": 0.01, "intensities": False}).encode()
    j = tmp_path / "raw.npz.journal"
    j.write_bytes(MAGIC + struct.pack("<I", len(head)) + head + b"\0" * 100)
    capsys.readouterr()
    assert main(["recover", str(j)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing 'angle_min'" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw.npz.journal"]


def test_an_empty_journal_does_not_block_the_next_recording(tmp_path):
    """A recording killed before its first scan reached the disk leaves a 0-byte journal: the next
    recording to that file removes it (nothing to recover) with a warning, and records."""
    from gtsjax.errors import InputWarning
    from gtsjax.io.record import Recorder, journal_path
    from gtsjax.sensors import URG_04LX

    raw = tmp_path / "raw.npz"
    journal_path(raw).write_bytes(b"")
    with pytest.warns(InputWarning, match="held no scan"):
        rec = Recorder(raw, URG_04LX)
    rec.append(np.full(URG_04LX.n_beams, 1.5, np.float32), 10.0)
    rec.close()
    assert np.load(raw)["ranges"].shape == (1, URG_04LX.n_beams)


@pytest.mark.parametrize("args", [["emulate", "spl-eval", "--checksum-errors", "2.5"],
                                  ["emulate", "spl-eval", "--stalls", "-1"],
                                  ["emulate", "spl-eval", "--disconnects", "nan"],
                                  ["train", "{d}/log.npz", "--site", "{d}/site.json", "--out", "{o}/m.npz",
                                   "--max-pose", "-5"],
                                  # 1–64 track slots on every command (train's range; replay took 1000 and
                                  # failed at run time)
                                  ["replay", "{d}/log.npz", "--site", "{d}/site.json", "--model", "demo", "--out",
                                   "{o}/o.csv", "--max-tracks", "1000"]])
def test_settings_out_of_range_are_refused_before_any_work(inputs, tmp_path, capsys, args):
    """Click's usage error, in one line (exit 2, the option named) before a scene is served or a log read."""
    capsys.readouterr()
    assert main([a.format(d=inputs, o=tmp_path) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gtsjax: ") and args[-2] in err[0], err
    assert list(tmp_path.iterdir()) == []
