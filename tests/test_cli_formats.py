"""The commands for formats people already use: ``convert``, ``info`` and ``replay`` on ROS bags,
CARMEN and BreezySLAM logs; ``export-tum`` read back by an independent TUM parser and by evo;
``plot`` with and without ``--truth``. Every bad input is exit status 2 and exactly one line on
stderr naming the file, with nothing left half-written (the importers' own messages, one case each, are
tested in ``test_importers.py``)."""

import csv
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.core.geometry import wrap as wrap_angle
from gtsjax.io import ScanLog, load_log, save_log
from gtsjax.io.gtd import GTDWriter, TrackRow, read_gtd
from gtsjax.io.importers import import_log
from tests._utils import run_cli

LEG_BAG = "leg_tracker_positive_1.bag"
CARMEN = "carmen_intel-corrected.log.gz"
BREEZY = "breezyslam_exp1.dat"
DEMO_MODEL = Path(__file__).resolve().parents[1] / "gtsjax" / "data" / "demo-model.npz"
SPL_SITE = ('{"landmarks": [{"class": "post", "x": 0.0, "y": 1.3}, {"class": "post", "x": 0.0, "y": 2.7},'
            ' {"class": "post", "x": 6.0, "y": 1.3}, {"class": "post", "x": 6.0, "y": 2.7}],'
            ' "sensor_pose": [3.0, 4.0, -1.5708], "bounds": [0.0, 0.0, 6.0, 4.0]}')


@pytest.fixture(scope="module")
def logs(shared_file):
    for name in (LEG_BAG, CARMEN, BREEZY):
        shared_file("data", "logs", name)
    return shared_file("data", "logs")


def run(*args):
    return run_cli(*args, timeout=300)


def one_line_exit_2(res, path, *fragments):
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("gtsjax: ") and str(path) in lines[0] and "Traceback" not in res.stderr
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------------------------------ convert, info


@pytest.mark.parametrize("name,shape", [(LEG_BAG, (400, 768)), (CARMEN, (910, 180)), (BREEZY, (756, 682))])
def test_convert_real_logs_round_trip(logs, tmp_path, capsys, name, shape):
    out = tmp_path / "sub" / "log.npz"
    assert main(["convert", str(logs / name), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"wrote {out}" in err and f"{shape[0]} scans × {shape[1]} beams" in err and "source:" in err
    back, direct = load_log(out), import_log(logs / name)
    assert back.ranges.shape == shape
    np.testing.assert_array_equal(back.ranges, direct.ranges)
    np.testing.assert_array_equal(back.stamps, direct.stamps)
    assert (back.angle_min, back.angle_increment, back.range_min, back.range_max, back.sensor_model) == (
        direct.angle_min, direct.angle_increment, direct.range_min, direct.range_max, direct.sensor_model)
    assert not list(out.parent.glob("*.part"))


def test_info_takes_imported_logs(logs, capsys):
    assert main(["info", str(logs / LEG_BAG), str(logs / CARMEN), str(logs / BREEZY), "--topic", "/right_scan"]) == 0
    out = capsys.readouterr().out
    assert f"{logs / LEG_BAG} (a ROS 1 bag): 400 scans × 768 beams" in out
    assert f"{logs / CARMEN} (a CARMEN log): 910 scans × 180 beams" in out
    assert f"{logs / BREEZY} (a BreezySLAM text log): 756 scans × 682 beams" in out
    assert "sensor URG-04LX" in out and "fov 179.0°" in out


def test_truncated_bag_exit_2(logs, tmp_path):
    bag = tmp_path / "cut.bag"
    bag.write_bytes((logs / LEG_BAG).read_bytes()[:300_000])
    out = tmp_path / "o.npz"
    one_line_exit_2(run("convert", bag, "--out", out), bag, "cannot be read as a ROS bag")
    assert not out.exists()


# ------------------------------------------------------------------------------------------ replay


def test_replay_breezyslam_log_with_demo_model(logs, tmp_path):
    """A real office seen by a URG-04LX, replayed with the shipped model: every scan goes through (one
    sensor row per scan, at the log's own stamps, read here by hand), and no robot is reported (there is
    none; docs/accuracy.md, *Real scenes with no robot*: these scans were in its background training)."""
    lines = (logs / BREEZY).read_text().splitlines()[:40]
    dat = tmp_path / "first40.dat"
    dat.write_text("\n".join(lines) + "\n")
    site = tmp_path / "site.json"
    site.write_text(SPL_SITE)
    out, sensor_out = tmp_path / "gtd.csv", tmp_path / "sensor.csv"
    res = run("replay", dat, "--site", site, "--model", DEMO_MODEL, "--out", out, "--sensor-out", sensor_out)
    assert res.returncode == 0, res.stderr
    assert "(a BreezySLAM text log): 40 scans × 682 beams" in res.stderr
    assert out.read_text().splitlines()[0] == "stamp,track_id,class,x,y,theta,var_x,var_y,var_theta"
    assert read_gtd(out) == []
    sensor = np.loadtxt(sensor_out, delimiter=",", skiprows=1, ndmin=2)
    stamps_us = [int(line.split()[0]) for line in lines]  # BreezySLAM's field 0: microseconds
    assert sensor.shape == (40, 6)
    np.testing.assert_allclose(sensor[:, 0], np.array(stamps_us) / 1e6, rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------------ export-tum


def parse_tum(path):
    """The TUM trajectory format by hand: 8 numbers a line (t tx ty tz qx qy qz qw), '#' comments."""
    rows = []
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            vals = [float(v) for v in line.split()]
            assert len(vals) == 8, line
            rows.append(vals)
    return np.array(rows)


def write_gtd(path, tracks):
    """A GTD CSV with ``tracks``: id -> (class, [(stamp, x, y, θ), ...]), rows interleaved per stamp."""
    by_stamp = {}
    for tid, (cls, poses) in tracks.items():
        for t, x, y, th in poses:
            row = TrackRow(float(t), int(tid), cls, float(x), float(y), float(wrap_angle(th)), 1e-4, 1e-4, 1e-2)
            by_stamp.setdefault(float(t), []).append(row)
    with GTDWriter(path) as w:
        for t in sorted(by_stamp):
            w.write(sorted(by_stamp[t], key=lambda r: r.track_id))


@pytest.fixture
def gtd_two_tracks(tmp_path):
    t = 1.7e9 + 0.1 * np.arange(30)
    th = np.linspace(-3.1, 3.1, 30)  # headings across ±π, where a quaternion sign error would show
    a = [(ti, 1.0 + 0.01 * k, 2.0 - 0.02 * k, h) for k, (ti, h) in enumerate(zip(t, th, strict=True))]
    b = [(ti, 4.0, 1.0, math.pi) for ti in t[10:20]]
    path = tmp_path / "run.csv"
    write_gtd(path, {3: ("robot", a), 7: ("ball", b)})
    return path, {3: ("robot", np.array(a)), 7: ("ball", np.array(b))}


def test_export_tum_files_per_track(gtd_two_tracks, capsys):
    path, tracks = gtd_two_tracks
    assert main(["export-tum", str(path)]) == 0
    out_dir = path.with_name("run-tum")
    assert sorted(p.name for p in out_dir.iterdir()) == ["ball_7.tum", "robot_3.tum"]
    err = capsys.readouterr().err
    assert "2 TUM trajectories" in err and "robot_3.tum" in err
    for tid, (cls, ref) in tracks.items():
        tum = parse_tum(out_dir / f"{cls}_{tid}.tum")
        assert tum.shape == (len(ref), 8)
        np.testing.assert_allclose(tum[:, 0], ref[:, 0], atol=1e-6)
        np.testing.assert_allclose(tum[:, 1:3], ref[:, 1:3], atol=1e-6)
        np.testing.assert_array_equal(tum[:, 3:6], 0.0)
        np.testing.assert_allclose(np.linalg.norm(tum[:, 6:8], axis=1), 1.0, atol=1e-8)
        yaw = 2 * np.arctan2(tum[:, 6], tum[:, 7])
        np.testing.assert_allclose(wrap_angle(yaw - ref[:, 3]), 0.0, atol=2e-6)


def test_export_tum_read_by_evo(gtd_two_tracks, tmp_path):
    from evo.tools import file_interface  # evo is a test dependency: the check runs, never skipped
    path, tracks = gtd_two_tracks
    out_dir = tmp_path / "tum"
    assert main(["export-tum", str(path), "--out-dir", str(out_dir)]) == 0
    for tid, (cls, ref) in tracks.items():
        traj = file_interface.read_tum_trajectory_file(str(out_dir / f"{cls}_{tid}.tum"))
        np.testing.assert_allclose(traj.timestamps, ref[:, 0], atol=1e-6)
        np.testing.assert_allclose(traj.positions_xyz[:, :2], ref[:, 1:3], atol=1e-6)
        w, x, y, z = traj.orientations_quat_wxyz.T
        np.testing.assert_allclose(wrap_angle(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)) - ref[:, 3]),
                                   0.0, atol=2e-6)
    evo_traj = Path(sys.executable).with_name("evo_traj")  # evo's own command line, installed with it
    assert evo_traj.exists(), f"{evo_traj} not found: the test extra installs evo and its evo_traj"
    res = subprocess.run([str(evo_traj), "tum", *sorted(map(str, out_dir.glob("*.tum")))], capture_output=True,
                         text=True, timeout=120, env={**os.environ, "HOME": str(tmp_path)})  # settings out of the home
    assert res.returncode == 0, res.stderr
    assert "30 poses" in res.stdout and "10 poses" in res.stdout


def test_export_tum_bad_csv_exit_2(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("not,a,gtd\n1,2,3\n")
    one_line_exit_2(run("export-tum", p), p, "header must be")
    assert not (tmp_path / "bad-tum").exists()


# ------------------------------------------------------------------------------------------ plot


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    from gtsjax.io import save_site
    from gtsjax.sim import simulate

    d = tmp_path_factory.mktemp("plot")
    log, site = simulate("spl-trajectory", seed=3, n_scans=40)
    save_log(log, d / "truth.npz")
    save_site(site, d / "site.json")
    return d, log


def test_truth_errors_nearest_track_of_the_class(labelled, tmp_path):
    from gtsjax.cli.plot import truth_errors

    _, log = labelled
    truth = log.truth_poses[:, 0]
    off = np.array([0.03, 0.04])  # 5 cm off, 0.1 rad
    rows = []
    for t in range(log.n_scans):
        if t in (5, 6):  # the robot is lost for two scans
            continue
        rows.append(TrackRow(float(log.stamps[t]), 1, "robot", *(truth[t, :2] + off), truth[t, 2] + 0.1, 0, 0, 0))
        # a ball track closer to the robot than the robot track: not a robot, so not its match
        rows.append(TrackRow(float(log.stamps[t]), 2, "ball", *(truth[t, :2] + 0.01), truth[t, 2], 0, 0, 0))
    [(cls, e_pos, e_th)] = truth_errors(rows, log, 0.5, "truth.npz")
    assert cls == "robot"
    assert np.isnan(e_pos[[5, 6]]).all()
    keep = np.setdiff1d(np.arange(log.n_scans), [5, 6])
    np.testing.assert_allclose(e_pos[keep], 0.05, atol=1e-9)
    np.testing.assert_allclose(e_th[keep], 0.1, atol=1e-9)


def test_plot_with_truth_writes_png(labelled, tmp_path):
    import matplotlib.image

    d, log = labelled
    truth = log.truth_poses[:, 0]
    write_gtd(tmp_path / "gtd.csv", {4: ("robot", [(s, x + 0.02, y, th) for s, (x, y, th) in
                                                   zip(log.stamps, truth, strict=True)])})
    res = run("plot", tmp_path / "gtd.csv", "--site", d / "site.json", "--truth", d / "truth.npz")
    assert res.returncode == 0, res.stderr
    png = tmp_path / "gtd.png"
    assert f"wrote {png}" in res.stderr
    assert "truth 0 (robot): tracked in 100% of its scans, RMSE 2.0 cm, 0.0°" in res.stderr
    img = matplotlib.image.imread(png)
    assert img.shape[0] > 500 and img.shape[1] > 500
    assert img[..., :3].std() > 0.05  # a picture, not a blank canvas


def test_plot_without_truth_and_many_tracks(labelled, tmp_path):
    import matplotlib.image

    d, _ = labelled
    t = np.arange(20) * 0.1
    write_gtd(tmp_path / "g.csv", {k: ("robot", [(ti, 1 + 0.2 * k, 0.5 + ti, 0.3) for ti in t]) for k in range(20)})
    out = tmp_path / "pics" / "g.png"
    res = run("plot", tmp_path / "g.csv", "--site", d / "site.json", "--out", out)
    assert res.returncode == 0, res.stderr
    assert f"wrote {out} (20 tracks)" in res.stderr
    assert matplotlib.image.imread(out).shape[2] in (3, 4)


def test_plot_bad_truth_exit_2(labelled, tmp_path):
    d, log = labelled
    gtd = tmp_path / "gtd.csv"
    write_gtd(gtd, {1: ("robot", [(1.0, 1.0, 1.0, 0.0)])})  # a stamp the truth log does not have
    one_line_exit_2(run("plot", gtd, "--site", d / "site.json", "--truth", d / "truth.npz"), d / "truth.npz",
                    "is it the log the CSV was made from?")
    plain = tmp_path / "plain.npz"
    save_log(ScanLog(ranges=log.ranges, stamps=log.stamps, angle_min=log.angle_min,
                     angle_increment=log.angle_increment), plain)
    one_line_exit_2(run("plot", gtd, "--site", d / "site.json", "--truth", plain), plain, "has no truth_poses")
    assert not (tmp_path / "gtd.png").exists()


def test_replay_csv_units_is_the_same_rows_with_units_and_cov_xy(labelled, tmp_path):
    """``replay --csv-units``: the spec's rows, column for column, under the header with units, and a
    ``cov_xy_m2`` column that makes each 2×2 position covariance positive semi-definite (|cov_xy| at
    most σx σy, the Cauchy–Schwarz bound), not all zero (the tracker's covariance is coupled)."""
    from gtsjax.io.gtd import UNITS_HEADER

    d, _ = labelled
    common = ["replay", str(d / "truth.npz"), "--site", str(d / "site.json"), "--model", str(DEMO_MODEL)]
    assert main([*common, "--out", str(tmp_path / "spec.csv")]) == 0
    assert main([*common, "--out", str(tmp_path / "units.csv"), "--csv-units"]) == 0
    with open(tmp_path / "spec.csv", newline="") as f:
        spec = list(csv.reader(f))
    with open(tmp_path / "units.csv", newline="") as f:
        units = list(csv.reader(f))
    assert tuple(units[0]) == UNITS_HEADER and len(units) == len(spec) > 20
    assert [r[:9] for r in units[1:]] == spec[1:]
    var_x, var_y, cov = (np.array([float(r[i]) for r in units[1:]]) for i in (6, 7, 9))
    assert np.all(np.abs(cov) <= np.sqrt(var_x * var_y) * (1 + 1e-5))
    assert np.any(cov != 0.0)
