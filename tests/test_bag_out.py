"""``--out-bag``: the ground truth as a ROS 2 bag (MCAP storage), written with rosbags and read back
here with rosbags' own reader (``AnyReader``), every message also decoded by a second library
(``mcap`` with its ROS 2 support, as Foxglove reads the file), against the GTD CSV and the sensor
CSV of the same run and the log's float64 stamps converted exactly (``decimal``); for one laser and
for two."""

import dataclasses
import decimal
import math
import time
from pathlib import Path

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.io import save_log, save_site
from gtsjax.io.bag_out import stamp_ns
from gtsjax.io.gtd import read_gtd
from gtsjax.sim import simulate

from ._utils import read_mcap

# The URG-04LX's data sheet: 100 ms per scan, 1024 steps per revolution (one revolution per scan).
URG_SCAN_TIME, URG_STEPS = 0.1, 1024
TRACK_TYPES = {"/tf": "tf2_msgs/msg/TFMessage", "/gtsjax/tracks": "geometry_msgs/msg/PoseArray",
               "/gtsjax/markers": "visualization_msgs/msg/MarkerArray", "/gtsjax/track_odom": "nav_msgs/msg/Odometry"}


def _exact_ns(stamp: float) -> int:
    """A float64's exact value in nanoseconds, rounded half to even: ``Decimal`` holds the float
    exactly, and with 100 digits the product is exact too."""
    with decimal.localcontext(prec=100):
        return int((decimal.Decimal(stamp) * 10**9).to_integral_value(rounding=decimal.ROUND_HALF_EVEN))


def _yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y**2 + q.z**2))


def _read(bag: Path) -> dict[str, list]:
    """Every message of the bag by topic, in bag-time order, as ``(log time ns, message)``, read
    with rosbags' AnyReader; and the same count decoded by the mcap library (schemas a reader
    other than rosbags understands)."""
    from rosbags.highlevel import AnyReader

    by_topic: dict[str, list] = {}
    with AnyReader([bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            by_topic.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    other = read_mcap(next(bag.glob("*.mcap")))
    assert len(other) == sum(len(v) for v in by_topic.values())
    assert {m.channel.topic: m.schema.name for m in other} == types
    by_topic["types"] = types
    return by_topic


def _check_header(header, stamp: float, frame: str) -> None:
    assert header.frame_id == frame
    assert (header.stamp.sec, header.stamp.nanosec) == divmod(_exact_ns(stamp), 10**9)


def _check_tracks(got: dict[str, list], rows, scan_stamps: list[float], laser_frames: set[str]) -> None:
    """The tracks' topics against the GTD rows: per scan a PoseArray (rows in CSV order) and a
    MarkerArray (DELETEALL, then an arrow and a label per row, ns = class, id = track id); per row
    an Odometry (child frame CLASS_ID, the covariance laid out as x y z roll pitch yaw) and a
    field → CLASS_ID transform."""
    per_scan: dict[int, list] = {}
    for r in rows:
        per_scan.setdefault(_exact_ns(r.stamp), []).append(r)
    want_ns = [_exact_ns(s) for s in scan_stamps]
    for topic in ("/gtsjax/tracks", "/gtsjax/markers"):
        assert [t for t, _ in got[topic]] == want_ns, topic
    for (t, arr), (_, markers), stamp in zip(got["/gtsjax/tracks"], got["/gtsjax/markers"], scan_stamps, strict=True):
        mine = per_scan.get(t, [])
        _check_header(arr.header, stamp, "field")
        assert len(arr.poses) == len(mine)
        for p, r in zip(arr.poses, mine, strict=True):
            assert (p.position.x, p.position.y, _yaw(p.orientation)) == pytest.approx((r.x, r.y, r.theta), abs=1e-6)
        ms = markers.markers
        assert ms[0].action == 3  # DELETEALL: the scan before's tracks go
        arrows = [m for m in ms[1:] if m.type == 0]
        labels = [m for m in ms[1:] if m.type == 9]
        assert len(ms) == 1 + 2 * len(mine) and len(arrows) == len(labels) == len(mine)
        for a, lab, r in zip(arrows, labels, mine, strict=True):
            _check_header(a.header, stamp, "field")
            assert (a.ns, a.id, a.action) == (r.cls, r.track_id, 0)
            assert (a.pose.position.x, a.pose.position.y, _yaw(a.pose.orientation)) == pytest.approx(
                (r.x, r.y, r.theta), abs=1e-6)
            assert (lab.ns, lab.id, lab.text) == (f"{r.cls}/label", r.track_id, f"{r.cls} {r.track_id}")
    odom = {(t, m.child_frame_id): m for t, m in got.get("/gtsjax/track_odom", [])}
    assert len(odom) == len(got.get("/gtsjax/track_odom", [])) == len(rows) > 0
    tf_tracks = {(t, tf.child_frame_id): tf for t, m in got["/tf"] for tf in m.transforms
                 if tf.child_frame_id not in laser_frames}
    assert len(tf_tracks) == len(rows)
    for r in rows:
        key = (_exact_ns(r.stamp), f"{r.cls}_{r.track_id}")
        o = odom[key]
        _check_header(o.header, r.stamp, "field")
        p = o.pose.pose
        assert (p.position.x, p.position.y, p.position.z, _yaw(p.orientation)) == pytest.approx(
            (r.x, r.y, 0.0, r.theta), abs=1e-6)
        want = np.zeros((6, 6))
        want[0, 0], want[1, 1], want[5, 5], want[0, 1], want[1, 0] = r.var_x, r.var_y, r.var_theta, r.cov_xy, r.cov_xy
        want[2, 2] = want[3, 3] = want[4, 4] = 1e6  # z, roll, pitch: not observed
        np.testing.assert_allclose(np.asarray(o.pose.covariance).reshape(6, 6), want, rtol=1e-5, atol=1e-12)
        assert np.all(np.diag(np.asarray(o.twist.covariance).reshape(6, 6)) == 1e6)
        tf = tf_tracks[key]
        _check_header(tf.header, r.stamp, "field")
        tr = tf.transform
        assert (tr.translation.x, tr.translation.y, _yaw(tr.rotation)) == pytest.approx((r.x, r.y, r.theta), abs=1e-6)
    assert any(r.cov_xy != 0 for r in rows)  # the layout was checked with an x–y covariance


def _check_scans(scans: list, log, frame: str) -> None:
    """A laser's LaserScans against its log: one per scan, at its exact stamp, its returns."""
    assert [t for t, _ in scans] == [_exact_ns(s) for s in log.stamps]
    valid = log.valid()
    for i in (0, len(scans) // 2, len(scans) - 1):
        s = scans[i][1]
        _check_header(s.header, float(log.stamps[i]), frame)
        np.testing.assert_allclose(np.asarray(s.ranges)[valid[i]], log.ranges[i][valid[i]], rtol=1e-6)
        assert np.all(np.isinf(np.asarray(s.ranges)[~valid[i]]))
        assert s.angle_min == pytest.approx(log.angle_min) and s.angle_increment == pytest.approx(log.angle_increment)
        assert s.scan_time == pytest.approx(URG_SCAN_TIME)
        assert s.time_increment == pytest.approx(URG_SCAN_TIME / URG_STEPS)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    """One laser's replay with its stamps moved to awkward float64 values (1700000000.123456789 +
    k × 0.1 s, none a whole number of nanoseconds), the CSV with its x–y covariance column."""
    d = tmp_path_factory.mktemp("bag")
    log, site = simulate("spl-trajectory", seed=3, n_scans=120)
    log = dataclasses.replace(log, stamps=1700000000.123456789 + (log.stamps - log.stamps[0]))
    save_log(log, d / "t.npz")
    save_site(site, d / "site.json")
    code = main(["replay", str(d / "t.npz"), "--site", str(d / "site.json"), "--model", str(demo_model_path()),
                 "--out", str(d / "gtd.csv"), "--out-bag", str(d / "gt"), "--sensor-out", str(d / "laser.csv"),
                 "--csv-units"])
    assert code == 0
    return d, log


def test_bag_holds_the_csvs_tracks_scans_and_laser_poses(replayed):
    """Every scan a LaserScan on ``/scan`` (frame ``laser``, the scanner's timing) at the log's stamp
    to the nanosecond; every scan's laser pose a field → laser transform, as the sensor CSV has it;
    the tracks' topics as :func:`_check_tracks` says, against the GTD CSV."""
    d, log = replayed
    rows = read_gtd(d / "gtd.csv")
    assert rows
    got = _read(d / "gt")
    assert got["types"] == {"/scan": "sensor_msgs/msg/LaserScan", **TRACK_TYPES}
    _check_scans(got["/scan"], log, "laser")
    _check_tracks(got, rows, [float(s) for s in log.stamps], {"laser"})
    lasers = np.genfromtxt(d / "laser.csv", delimiter=",", names=True)
    assert len(got["/tf"]) == log.n_scans
    for (t, m), row in zip(got["/tf"], lasers, strict=True):
        tf = m.transforms[0]
        assert t == _exact_ns(row["stamp"])
        assert (tf.header.frame_id, tf.child_frame_id) == ("field", "laser")
        assert (tf.transform.translation.x, tf.transform.translation.y) == pytest.approx((row["x"], row["y"]), abs=1e-5)
        assert _yaw(tf.transform.rotation) == pytest.approx(row["theta"], abs=1e-5)


def test_stamps_convert_exactly_to_nanoseconds():
    """:func:`stamp_ns` against ``decimal``'s exact arithmetic, on stamps of today's epoch (where a
    float64 product ``stamp * 1e9`` is 256 ns coarse), their neighbours, and ties (k / 1024 s is a
    half nanosecond for odd k: rounded to even)."""
    rng = np.random.default_rng(0)
    base = 1700000000.123456789
    stamps = [base, float(np.nextafter(base, 0)), float(np.nextafter(base, 2e9)), 0.0, 1e-9, 123.456]
    stamps += rng.uniform(1.6e9, 1.8e9, 500).tolist() + [1700000000 + k / 1024 for k in (1, 3, 5, 1023)]
    assert [stamp_ns(s) for s in stamps] == [_exact_ns(s) for s in stamps]
    assert any(stamp_ns(s) != round(s * 1e9) for s in stamps)  # the float product would be off


def test_a_scanner_gtsjax_does_not_know_gets_its_timing_from_the_stamps():
    """A log naming no known scanner: ``scan_time`` the median interval of its stamps (a plain sort
    here; jittered stamps and a lost frame), ``time_increment`` that period's share per beam of a
    revolution (``scan_time`` = ``time_increment`` × beams per revolution)."""
    from gtsjax.io.bag_out import LaserGeometry

    log, _ = simulate("spl-trajectory", seed=3, n_scans=41)
    rng = np.random.default_rng(1)
    stamps = 1700000000.0 + 0.025 * np.arange(41) + rng.uniform(-0.002, 0.002, 41)
    stamps = np.delete(stamps, 17)  # a frame lost: one interval twice as long
    log = dataclasses.replace(log.slice(0, 40), stamps=stamps, sensor_model=None)
    g = LaserGeometry.of_log(log)
    steps = sorted(b - a for a, b in zip(stamps[:-1], stamps[1:], strict=True))
    assert len(steps) == 39 and g.scan_time == pytest.approx(steps[19], rel=1e-12)  # the middle one
    assert g.time_increment * (2 * math.pi / log.angle_increment) == pytest.approx(g.scan_time, rel=1e-12)


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


# ------------------------------------------------------------------------------------- two lasers


def _rerun_installed() -> bool:
    try:
        import rerun  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def two_lasers(tmp_path_factory):
    """``replay --log north=... --log south=...`` of a simulated two-laser match (test_several's,
    3 s), with ``--out-bag`` and, where the viewer extra is installed, ``--view-save``."""
    from gtsjax.sim.match import simulate_match

    d = tmp_path_factory.mktemp("bag2")
    logs, site = simulate_match("spl-match-2", seed=11, n_robots=2, seconds=3.0, referee=False)
    truth = {n: tuple(map(float, log.extra["truth_sensor_pose"][0])) for n, log in logs.items()}
    site = dataclasses.replace(site, sensors=tuple(dataclasses.replace(s, pose=truth[s.name]) for s in site.sensors))
    save_site(site, d / "site.json")
    for name, log in logs.items():
        save_log(log, d / f"{name}.npz")
    rrd = d / "view.rrd" if _rerun_installed() else None
    code = main(["replay", "--log", f"north={d / 'north.npz'}", "--log", f"south={d / 'south.npz'}", "--site",
                 str(d / "site.json"), "--model", str(demo_model_path()), "--out", str(d / "gtd.csv"), "--chunk", "32",
                 "--sensor-out", str(d / "lasers.csv"), "--out-bag", str(d / "gt"), "--csv-units"]
                + (["--view-save", str(rrd)] if rrd is not None else []))
    assert code == 0
    lasers = np.genfromtxt(d / "lasers.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    return d, logs, lasers, rrd


def test_two_lasers_bag_has_a_scan_topic_and_frame_per_laser_and_one_set_of_tracks(two_lasers):
    """Two lasers: each laser's scans on ``/NAME/scan``, frame NAME, at its log's stamps to the
    nanosecond; a field → NAME transform with each scan, at the pose the sensor CSV gives that laser
    then; the tracks' topics once, for the merged scans, as the one-laser bag has them."""
    d, logs, lasers, _ = two_lasers
    rows = read_gtd(d / "gtd.csv")
    assert rows
    got = _read(d / "gt")
    assert got["types"] == {"/north/scan": "sensor_msgs/msg/LaserScan", "/south/scan": "sensor_msgs/msg/LaserScan",
                            **TRACK_TYPES}
    for name, log in logs.items():
        _check_scans(got[f"/{name}/scan"], log, name)
    stamps = [float(s) for s in lasers["stamp"]]
    assert len({_exact_ns(s) for s in stamps}) == len(stamps)  # no two scans at one stamp: keys below are unique
    _check_tracks(got, rows, stamps, set(logs))
    assert [t for t, _ in got["/tf"]] == [_exact_ns(s) for s in stamps]
    for (_, m), row in zip(got["/tf"], lasers, strict=True):
        tf = m.transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ("field", row["laser"])
        assert (tf.transform.translation.x, tf.transform.translation.y) == pytest.approx((row["x"], row["y"]), abs=1e-5)
        assert _yaw(tf.transform.rotation) == pytest.approx(row["theta"], abs=1e-5)


def test_two_lasers_view_draws_each_lasers_scan_and_pose_under_its_name(two_lasers):
    """The two-laser replay's ``.rrd``, reopened with Rerun's reader: each laser's pose
    (``field/lasers/NAME/laser``) and returns (``field/lasers/NAME/scan``) once per scan of that
    laser, the pose where the sensor CSV puts it and the returns where that pose maps the log's
    ranges (a NumPy computation here), in a colour per laser; nothing under the one-laser entities;
    the field still mirrored to y up (``/field``'s transform); one track entity per track id."""
    d, logs, lasers, rrd = two_lasers
    if rrd is None:
        pytest.skip('the viewer extra is not installed (pip install "gtsjax[viewer]")')
    from rerun.chunk import RrdReader

    batches: dict[str, list] = {}
    for chunk in RrdReader(rrd).stream():
        batches.setdefault(str(chunk.entity_path), []).append(chunk.to_record_batch().to_pydict())

    def column(entity, name):
        return [v for b in batches.get(entity, []) for v in b[name]]

    assert column("/field", "Transform3D:mat3x3") == [[[1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0]]]
    assert "/field/scan" not in batches and "/field/laser" not in batches
    colours = {}
    for name, log in logs.items():
        mine = lasers[lasers["laser"] == name]
        origins = np.asarray([o[0] for o in column(f"/field/lasers/{name}/laser", "Arrows2D:origins")])
        assert len(origins) == log.n_scans
        np.testing.assert_allclose(origins, np.stack([mine["x"], mine["y"]], axis=1), atol=1e-5)
        points = column(f"/field/lasers/{name}/scan", "Points2D:positions")
        assert len(points) == log.n_scans
        i = log.n_scans // 2
        ok = log.valid()[i]
        a = log.angle_min + log.angle_increment * np.arange(log.n_beams)[ok] + mine["theta"][i]
        want = np.stack([mine["x"][i] + log.ranges[i][ok] * np.cos(a), mine["y"][i] + log.ranges[i][ok] * np.sin(a)], 1)
        np.testing.assert_allclose(np.asarray(points[i]), want, atol=1e-4)
        colours[name] = column(f"/field/lasers/{name}/scan", "Points2D:colors")[0][0]
    assert colours["north"] != colours["south"]
    rows = read_gtd(d / "gtd.csv")
    tracks = {e.split("/")[3] for e in batches if e.startswith("/field/tracks/")}
    assert tracks == {f"{r.cls}_{r.track_id}" for r in rows}


class _Frame:
    """What the live loop reads of a :class:`~gtsjax.io.serial.LinkFrame`."""

    def __init__(self, ranges_m, stamp):
        self.ranges_m, self.intensities, self.stamp, self.recv_perf = ranges_m, None, stamp, 0.0


class _Link:
    """A laser's link handing over its frames in turn, after one "nothing yet" (the loop drains what
    queued while it compiled until a link has nothing)."""

    def __init__(self, model, frames):
        self.model, self.port, self._frames, self._asked = model, "fake", list(frames), False

    def get(self, timeout=None):
        if not self._asked or not self._frames:
            self._asked = True
            return None
        f = self._frames.pop(0)
        f.recv_perf = time.perf_counter()
        return f


def test_live_two_lasers_write_the_bag_and_the_view_per_laser(two_lasers, tmp_path):
    """``run_live_several`` with ``out_bag`` and a view saved: each laser's frames on its own scan
    topic at their stamps to the nanosecond, the tracks' topics as the CSV has the rows, and each
    laser's pose and returns under its own entity of the ``.rrd``."""
    from gtsjax.drivers.live_several import run_live_several, warm_up_several
    from gtsjax.drivers.several import site_poses
    from gtsjax.io import load_site
    from gtsjax.io.modelfile import load_model
    from gtsjax.io.site import one_sensor
    from gtsjax.sensors import URG_04LX

    d, logs, _, _ = two_lasers
    site = load_site(d / "site.json")
    model = load_model(demo_model_path()).with_site(one_sensor(site, "north"))
    poses = site_poses(site, ["north", "south"])
    n = 12
    links, frames = {}, {}
    for name, log in logs.items():
        frames[name] = [_Frame(np.where(log.valid()[i], log.ranges[i], 0.0).astype(np.float32),
                               1700000000.123456789 + float(log.stamps[i] - logs["north"].stamps[0])) for i in range(n)]
        links[name] = _Link(URG_04LX, frames[name])
    stamps = {name: [f.stamp for f in fs] for name, fs in frames.items()}
    view = None
    if _rerun_installed():
        from gtsjax.viewer import View

        view = View(model, save=tmp_path / "live.rrd")
    stats, per, out_of_order = run_live_several(links, model, poses, tmp_path / "gtd.csv",
                                                compiled=warm_up_several(model, URG_04LX, poses), max_frames=2 * n,
                                                duration=60.0, hold_s=0.0, keep_warm=False, out_bag=tmp_path / "gt",
                                                view=view)
    assert stats.frames == 2 * n
    got = _read(tmp_path / "gt")
    for name in logs:
        assert [t for t, _ in got[f"/{name}/scan"]] == [_exact_ns(s) for s in stamps[name]]
        assert got[f"/{name}/scan"][0][1].header.frame_id == name
    rows = read_gtd(tmp_path / "gtd.csv")
    assert rows
    odom = sorted((t, m.child_frame_id, m.pose.pose.position.x) for t, m in got.get("/gtsjax/track_odom", []))
    want = sorted((_exact_ns(r.stamp), f"{r.cls}_{r.track_id}", r.x) for r in rows)
    assert [o[:2] for o in odom] == [w[:2] for w in want]
    np.testing.assert_allclose([o[2] for o in odom], [w[2] for w in want], atol=1e-6)
    assert len(got["/gtsjax/markers"]) == len(got["/gtsjax/tracks"]) == 2 * n
    if view is not None:
        from rerun.chunk import RrdReader

        counts: dict[str, int] = {}
        for chunk in RrdReader(tmp_path / "live.rrd").stream():
            counts[str(chunk.entity_path)] = counts.get(str(chunk.entity_path), 0) + chunk.num_rows
        for name in logs:
            assert counts[f"/field/lasers/{name}/laser"] == counts[f"/field/lasers/{name}/scan"] == n
