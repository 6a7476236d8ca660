"""``--out-bag``: the ground truth as a ROS 2 bag (MCAP storage), written with rosbags and read back
here with a second library (``mcap`` with its ROS 2 support), against the GTD CSV of the same run."""

import math

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.io import save_log, save_site
from gtsjax.io.gtd import read_gtd
from gtsjax.sim import simulate

from ._utils import read_mcap as _read_mcap


def _yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y**2 + q.z**2))


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    d = tmp_path_factory.mktemp("bag")
    log, site = simulate("spl-trajectory", seed=3, n_scans=120)
    save_log(log, d / "t.npz")
    save_site(site, d / "site.json")
    code = main(["replay", str(d / "t.npz"), "--site", str(d / "site.json"), "--model", str(demo_model_path()),
                 "--out", str(d / "gtd.csv"), "--out-bag", str(d / "gt"), "--sensor-out", str(d / "laser.csv")])
    assert code == 0
    return d, log


def test_bag_holds_the_csvs_tracks_scans_and_laser_poses(replayed):
    """Every GTD row is a PoseWithCovarianceStamped on its track's topic (same stamp, pose, yaw and
    variances) and a pose in that scan's PoseArray; every scan a LaserScan with its ranges; every
    scan's laser pose a field → laser transform, as the sensor CSV has it."""
    d, log = replayed
    rows = read_gtd(d / "gtd.csv")
    assert rows
    msgs = _read_mcap(next((d / "gt").glob("*.mcap")))
    by_topic: dict[str, list] = {}
    for m in msgs:
        by_topic.setdefault(m.channel.topic, []).append(m)
    assert {m.schema.name for m in msgs} == {"sensor_msgs/msg/LaserScan", "tf2_msgs/msg/TFMessage",
                                              "geometry_msgs/msg/PoseArray", "geometry_msgs/msg/PoseWithCovarianceStamped"}
    scans = by_topic["/scan"]
    assert len(scans) == log.n_scans
    for i in (0, 57, log.n_scans - 1):
        s = scans[i].ros_msg
        assert scans[i].log_time_ns == round(log.stamps[i] * 1e9)
        assert s.header.frame_id == "laser"
        valid = log.valid()[i]
        np.testing.assert_allclose(np.asarray(s.ranges)[valid], log.ranges[i][valid], rtol=1e-6)
        assert np.all(np.isinf(np.asarray(s.ranges)[~valid]))
        assert s.angle_min == pytest.approx(log.angle_min) and s.angle_increment == pytest.approx(log.angle_increment)
    track_msgs = [m for t, ms in by_topic.items() if t.startswith("/gtsjax/") and t != "/gtsjax/tracks" for m in ms]
    assert len(track_msgs) == len(rows)
    got = {(m.channel.topic, m.log_time_ns): m.ros_msg for m in track_msgs}
    for r in rows:
        p = got[(f"/gtsjax/{r.cls}_{r.track_id}", round(r.stamp * 1e9))]
        assert p.header.frame_id == "field"
        assert p.header.stamp.sec + p.header.stamp.nanosec * 1e-9 == pytest.approx(r.stamp, abs=1e-6)
        assert (p.pose.pose.position.x, p.pose.pose.position.y) == pytest.approx((r.x, r.y), abs=1e-6)
        assert _yaw(p.pose.pose.orientation) == pytest.approx(r.theta, abs=1e-6)
        cov = np.asarray(p.pose.covariance).reshape(6, 6)
        np.testing.assert_allclose(np.diag(cov)[[0, 1, 5]], [r.var_x, r.var_y, r.var_theta], rtol=1e-6)
    per_scan = {}
    for r in rows:
        per_scan.setdefault(round(r.stamp * 1e9), []).append(r)
    arrays = by_topic["/gtsjax/tracks"]
    assert len(arrays) == log.n_scans
    for m in arrays:
        mine = per_scan.get(m.log_time_ns, [])
        got_xy = np.asarray([(p.position.x, p.position.y) for p in m.ros_msg.poses]).reshape(-1, 2)
        np.testing.assert_allclose(got_xy, np.asarray([(r.x, r.y) for r in mine]).reshape(-1, 2), atol=1e-6)
    lasers = np.genfromtxt(d / "laser.csv", delimiter=",", names=True)
    tfs = by_topic["/tf"]
    assert len(tfs) == log.n_scans
    for m, row in zip(tfs, lasers, strict=True):
        t = m.ros_msg.transforms[0]
        assert (t.header.frame_id, t.child_frame_id) == ("field", "laser")
        assert (t.transform.translation.x, t.transform.translation.y) == pytest.approx((row["x"], row["y"]), abs=1e-5)
        assert _yaw(t.transform.rotation) == pytest.approx(row["theta"], abs=1e-5)


def test_out_bag_refuses_a_folder_that_exists(replayed, capsys):
    """A bag is a new folder: one that exists is one line, exit 2, before anything is replayed."""
    d, _ = replayed
    (d / "again.csv").unlink(missing_ok=True)
    code = main(["replay", str(d / "t.npz"), "--site", str(d / "site.json"), "--model", str(demo_model_path()),
                 "--out", str(d / "again.csv"), "--out-bag", str(d / "gt")])
    assert code == 2
    err = capsys.readouterr().err
    assert "already exists" in err and len(err.strip().splitlines()) == 1
    assert not (d / "again.csv").exists()
