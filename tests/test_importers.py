"""Importers of other programs' logs (gtsjax.io.importers), each checked against a second, obvious
reader written here: ROS 1 LaserScan messages decoded byte by byte with ``struct`` (only the bag
container is read with rosbags' low-level reader), CARMEN and BreezySLAM text split line by line in
plain Python. The real logs are those of ``shared/data/logs`` (SOURCES.md); ROS 2 bags, and the cases
no real file shows (zero header stamps, a geometry change, ROBOTLASER1 lines), are written here."""

import gzip
import math
import struct

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.cli import main
from gtsjax.errors import InputWarning
from gtsjax.io import load_log, save_log, to_scans
from gtsjax.io.importers import (
    FLASER_RANGE_MAX,
    MAX_STAMP_STEP_BACK,
    detect_format,
    import_log,
    read_breezyslam,
    read_carmen,
    read_rosbag,
)
from gtsjax.sensors import URG_04LX

LEG_BAG = "leg_tracker_positive_1.bag"
LEG_EXTRACTED = "leg_tracker_positive_1_extracted.bag"
CARMEN = "carmen_intel-corrected.log.gz"
BREEZY = "breezyslam_exp1.dat"


@pytest.fixture(scope="module")
def logs(shared_file):
    for name in (LEG_BAG, LEG_EXTRACTED, CARMEN, BREEZY):
        shared_file("data", "logs", name)
    return shared_file("data", "logs")


# ------------------------------------------------------------------------------------------ ROS 1, real


def decode_ros1_laserscans(path, topic):
    """The LaserScan messages of ``topic`` decoded by hand from their ROS 1 serialisation: header
    (seq, stamp sec/nsec, frame_id), seven float32 (angle_min … range_max), then ranges[] and
    intensities[] (uint32 length + float32 data)."""
    from rosbags.rosbag1 import Reader

    out = []
    with Reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for _, t_rec, raw in reader.messages(connections=conns):
            _seq, sec, nsec = struct.unpack_from("<III", raw, 0)
            (flen,) = struct.unpack_from("<I", raw, 12)
            off = 16 + flen
            amin, _amax, inc, _tinc, _stime, rmin, rmax = struct.unpack_from("<7f", raw, off)
            off += 28
            (n,) = struct.unpack_from("<I", raw, off)
            ranges = np.frombuffer(raw, "<f4", n, off + 4)
            off += 4 + 4 * n
            (m,) = struct.unpack_from("<I", raw, off)
            out.append(dict(stamp=sec + 1e-9 * nsec, rec=t_rec * 1e-9, amin=amin, inc=inc, rmin=rmin, rmax=rmax,
                            ranges=ranges, n_int=m))
    return out


@pytest.mark.parametrize("name,topic,count", [(LEG_BAG, "right_scan", 400), (LEG_EXTRACTED, "/training_scan", 197)])
def test_ros1_bag_matches_hand_decoded_messages(logs, name, topic, count):
    ref = decode_ros1_laserscans(logs / name, topic)
    log = import_log(logs / name)  # the only LaserScan topic is picked without --topic
    assert len(ref) == count and log.ranges.shape == (count, 768)
    np.testing.assert_array_equal(log.ranges, np.stack([m["ranges"] for m in ref]))
    np.testing.assert_array_equal(log.stamps, [m["stamp"] for m in ref])
    assert log.ranges.dtype == np.float32 and log.intensities is None  # the bags carry no intensities
    assert all(m["n_int"] == 0 for m in ref)
    assert log.angle_min == ref[0]["amin"] and log.angle_increment == ref[0]["inc"]
    assert (log.range_min, log.range_max) == (ref[0]["rmin"], ref[0]["rmax"])
    assert log.angle_min == pytest.approx(-2.356, abs=1e-3)  # SOURCES.md: −2.356 … 2.350 rad, 0.03–11 m
    assert log.angles()[-1] == pytest.approx(2.350, abs=1e-3)
    assert (log.range_min, log.range_max) == pytest.approx((0.03, 11.0))
    assert log.sensor_model is None
    assert "stamps: message header stamps" in str(log.extra["source"])


def test_ros1_topic_given_with_or_without_slash(logs):
    a = import_log(logs / LEG_BAG, topic="/right_scan")
    b = import_log(logs / LEG_BAG, topic="right_scan")
    np.testing.assert_array_equal(a.ranges, b.ranges)


def test_ros1_non_laserscan_topic_is_refused(logs):
    with pytest.raises(InputError) as exc:
        import_log(logs / LEG_EXTRACTED, topic="/leg_cluster_positions")
    msg = str(exc.value)
    assert LEG_EXTRACTED in msg and "geometry_msgs/msg/PoseArray" in msg and "/training_scan" in msg


def test_ros1_missing_topic_lists_laserscan_topics(logs):
    with pytest.raises(InputError) as exc:
        import_log(logs / LEG_BAG, topic="/scan")
    msg = str(exc.value)
    assert "\n" not in msg and LEG_BAG in msg and "no topic /scan" in msg and "right_scan" in msg


def test_ros1_log_round_trips_and_feeds_the_pipeline(logs, tmp_path):
    log = import_log(logs / LEG_EXTRACTED)
    out = tmp_path / "legs.npz"
    save_log(log, out)
    back = load_log(out)
    np.testing.assert_array_equal(back.ranges, log.ranges)
    np.testing.assert_array_equal(back.stamps, log.stamps)
    assert (back.angle_min, back.angle_increment, back.range_min, back.range_max) == (
        log.angle_min, log.angle_increment, log.range_min, log.range_max)
    assert str(back.extra["source"]) == str(log.extra["source"])
    scans = to_scans(back, 1024)
    assert scans.ranges.shape == (197, 1024)
    valid = np.asarray(scans.valid)
    assert valid[:, 768:].sum() == 0
    # 0.0 = no return in these bags; to_scans marks exactly the beams inside [0.03, 11] m.
    r = log.ranges
    np.testing.assert_array_equal(valid[:, :768], (r >= np.float32(0.03)) & (r <= 11.0))


# ------------------------------------------------------------------------------------------ ROS 2, written here


def write_ros2(path, topics, *, version=9):
    """A ROS 2 bag at ``path`` (a directory) with LaserScan messages: ``topics`` maps a topic to a list
    of dicts (stamp, rec [s], amin, inc, rmin, rmax, ranges, intensities)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    scan_t = ts.types["sensor_msgs/msg/LaserScan"]
    header_t, time_t = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    with Writer(path, version=version) as w:
        for topic, msgs in topics.items():
            conn = w.add_connection(topic, scan_t.__msgtype__, typestore=ts)
            for m in msgs:
                sec = int(m["stamp"])
                msg = scan_t(
                    header=header_t(stamp=time_t(sec=sec, nanosec=round((m["stamp"] - sec) * 1e9)), frame_id="laser"),
                    angle_min=m["amin"], angle_max=m["amin"] + m["inc"] * (len(m["ranges"]) - 1),
                    angle_increment=m["inc"], time_increment=0.0, scan_time=0.1, range_min=m["rmin"],
                    range_max=m["rmax"], ranges=np.asarray(m["ranges"], np.float32),
                    intensities=np.asarray(m.get("intensities", []), np.float32))
                w.write(conn, round(m["rec"] * 1e9), ts.serialize_cdr(msg, scan_t.__msgtype__))
    return path


def scan_msgs(k=5, n=6, *, stamp0=100.0, rec0=500.0, inc=0.01, intensities=True, seed=0):
    rng = np.random.default_rng(seed)
    return [dict(stamp=stamp0 + 0.1 * i if stamp0 else 0.0, rec=rec0 + 0.1 * i, amin=-0.5, inc=inc, rmin=0.05,
                 rmax=10.0, ranges=rng.uniform(0.1, 5, n).astype(np.float32),
                 intensities=rng.uniform(0, 100, n).astype(np.float32) if intensities else [])
            for i in range(k)]


def test_ros2_bag_read_from_directory_or_metadata(tmp_path):
    msgs = scan_msgs()
    bag = write_ros2(tmp_path / "bag2", {"/scan": msgs})
    assert detect_format(bag) == "ros2" and detect_format(bag / "metadata.yaml") == "ros2"
    for p in (bag, bag / "metadata.yaml"):
        log = import_log(p)
        np.testing.assert_array_equal(log.ranges, np.stack([m["ranges"] for m in msgs]))
        np.testing.assert_array_equal(log.intensities, np.stack([m["intensities"] for m in msgs]))
        np.testing.assert_allclose(log.stamps, [m["stamp"] for m in msgs], rtol=0, atol=1e-9)
        assert log.angle_min == float(np.float32(-0.5)) and log.angle_increment == float(np.float32(0.01))
        assert (log.range_min, log.range_max) == (float(np.float32(0.05)), 10.0)
        assert str(log.extra["source"]).startswith("ROS 2 bag bag2, topic /scan")


def test_zero_header_stamps_fall_back_to_record_time(tmp_path):
    msgs = scan_msgs(stamp0=0.0, intensities=False)
    log = import_log(write_ros2(tmp_path / "zero", {"/scan": msgs}))
    np.testing.assert_allclose(log.stamps, [m["rec"] for m in msgs], rtol=0, atol=1e-9)
    assert log.intensities is None
    assert "record times (header stamps are 0)" in str(log.extra["source"])


def test_geometry_change_mid_log_names_the_message(tmp_path):
    msgs = scan_msgs()
    msgs[3]["inc"] = 0.02
    bag = write_ros2(tmp_path / "geo", {"/scan": msgs})
    with pytest.raises(InputError) as exc:
        import_log(bag)
    msg = str(exc.value)
    assert "\n" not in msg and str(bag) in msg and "message 3 on /scan changes the scan geometry" in msg


def test_beam_count_change_mid_log_names_the_message(tmp_path):
    msgs = scan_msgs()
    msgs[2]["ranges"] = msgs[2]["ranges"][:-1]
    msgs[2]["intensities"] = msgs[2]["intensities"][:-1]
    with pytest.raises(InputError, match="message 2 on /scan changes the scan geometry"):
        import_log(write_ros2(tmp_path / "geo", {"/scan": msgs}))


def test_two_laserscan_topics_need_a_choice(tmp_path):
    bag = write_ros2(tmp_path / "two", {"/front": scan_msgs(seed=1), "/rear": scan_msgs(seed=2)})
    with pytest.raises(InputError) as exc:
        import_log(bag)
    assert "2 sensor_msgs/LaserScan topics" in str(exc.value) and "/front, /rear" in str(exc.value)
    rear = import_log(bag, topic="/rear")
    np.testing.assert_array_equal(rear.ranges[0], scan_msgs(seed=2)[0]["ranges"])


def test_clockwise_scanner_is_reversed_to_the_same_beam_directions(tmp_path):
    msgs = scan_msgs(inc=-0.01)
    log = import_log(write_ros2(tmp_path / "cw", {"/scan": msgs}))
    n = len(msgs[0]["ranges"])
    amin, inc = float(np.float32(-0.5)), float(np.float32(-0.01))
    assert log.angle_increment == -inc
    np.testing.assert_allclose(log.angles(), (amin + inc * np.arange(n))[::-1], atol=1e-12)
    np.testing.assert_array_equal(log.ranges[0], msgs[0]["ranges"][::-1])


def test_stamp_jitter_is_repaired_but_a_clock_jump_is_not(tmp_path):
    msgs = scan_msgs(k=6)
    msgs[3]["stamp"] = msgs[2]["stamp"] - 0.05
    log = import_log(write_ros2(tmp_path / "jit", {"/scan": msgs}))
    assert np.all(np.diff(log.stamps) >= 0) and log.stamps[3] == log.stamps[2]
    assert "1 stamp(s) that stepped back" in str(log.extra["source"])
    msgs[3]["stamp"] = msgs[2]["stamp"] - MAX_STAMP_STEP_BACK - 1
    with pytest.raises(InputError, match="message 3 on /scan: stamp"):
        import_log(write_ros2(tmp_path / "jump", {"/scan": msgs}))


# ------------------------------------------------------------------------------------------ CARMEN


def plain_carmen_flaser(path):
    """FLASER lines split by hand: ``FLASER n r1..rn x y th odom_x odom_y odom_th ipc_ts host logger_ts``."""
    ranges, stamps = [], []
    with gzip.open(path, "rt") as f:
        for line in f:
            tok = line.split()
            if tok and tok[0] == "FLASER":
                n = int(tok[1])
                ranges.append([float(v) for v in tok[2:2 + n]])
                stamps.append(float(tok[n + 8]))
    return np.array(ranges, dtype=np.float32), np.array(stamps)


def test_carmen_intel_log_matches_plain_parse(logs):
    ranges, stamps = plain_carmen_flaser(logs / CARMEN)
    log = import_log(logs / CARMEN)
    assert ranges.shape == (910, 180) and log.ranges.shape == (910, 180)
    np.testing.assert_array_equal(log.ranges, ranges)
    # 4 scans of this log step back in time (by up to 0.86 s); they keep their place and the stamp before them.
    assert int(np.sum(np.diff(stamps) < 0)) == 4
    np.testing.assert_array_equal(log.stamps, np.maximum.accumulate(stamps))
    assert "4 stamp(s) that stepped back" in str(log.extra["source"])
    # CARMEN's convention for 180-beam FLASER: -90° … +89° in 1° steps, 80 m window (81.83 m = no return).
    assert log.angle_min == -math.pi / 2 and log.angle_increment == pytest.approx(math.pi / 180)
    assert np.degrees(log.angles()[-1]) == pytest.approx(89.0)
    assert log.range_max == FLASER_RANGE_MAX
    assert not log.valid()[log.ranges > 81.0].any()


def test_carmen_round_trip_through_npz(logs, tmp_path):
    log = import_log(logs / CARMEN)
    save_log(log, tmp_path / "intel.npz")
    back = load_log(tmp_path / "intel.npz")
    np.testing.assert_array_equal(back.ranges, log.ranges)
    np.testing.assert_array_equal(back.stamps, log.stamps)
    scans = to_scans(back, 682)
    assert scans.ranges.shape == (910, 682) and int(np.asarray(scans.valid)[:, 180:].sum()) == 0


def robotlaser(n, ranges, stamp, *, start=-2.0, fov=4.0, res=0.02, rmax=20.0, remissions=None):
    rem = [] if remissions is None else list(remissions)
    fields = ["ROBOTLASER1", 2, start, fov, res, rmax, 0.01, 1 if rem else 0, n, *ranges, len(rem), *rem,
              0, 0, 0, 1, 2, 0.5, 0.1, 0.0, 0.5, 0.3, 0.2, stamp, "host", stamp + 0.01]
    return " ".join(str(v) for v in fields)


def test_carmen_robotlaser1_carries_its_geometry_and_remissions(tmp_path):
    p = tmp_path / "new.log"
    lines = ["# CARMEN Logfile", "PARAM robot_frontlaser_offset 0.0 nohost 0",
             "FLASER 3 1 1 1 0 0 0 0 0 0 0.5 host 0.5",  # the same scans in the old format: skipped
             robotlaser(3, [1.0, 2.5, 0.0], 1.0, remissions=[10, 20, 30]),
             "ODOM 0 0 0 0 0 0 1.05 host 1.05",
             robotlaser(3, [1.5, 2.0, 3.0], 1.1, remissions=[11, 21, 31])]
    p.write_text("\n".join(lines) + "\n")
    log = read_carmen(p)
    np.testing.assert_array_equal(log.ranges, np.float32([[1.0, 2.5, 0.0], [1.5, 2.0, 3.0]]))
    np.testing.assert_array_equal(log.intensities, np.float32([[10, 20, 30], [11, 21, 31]]))
    np.testing.assert_array_equal(log.stamps, [1.0, 1.1])
    assert (log.angle_min, log.angle_increment, log.range_max) == (-2.0, 0.02, 20.0)
    assert "2 ROBOTLASER1 lines" in str(log.extra["source"])


def test_carmen_plain_and_gzip_read_alike(tmp_path):
    text = "FLASER 3 1 2 3 0 0 0 0 0 0 5.0 h 5.0\nFLASER 3 4 5 6 0 0 0 0 0 0 5.2 h 5.2\n"
    (tmp_path / "a.log").write_text(text)
    with gzip.open(tmp_path / "b.log.gz", "wt") as f:
        f.write(text)
    a, b = import_log(tmp_path / "a.log"), import_log(tmp_path / "b.log.gz")
    np.testing.assert_array_equal(a.ranges, b.ranges)
    np.testing.assert_array_equal(a.stamps, [5.0, 5.2])
    assert a.angle_increment == pytest.approx(math.pi / 2)  # 3 beams: CARMEN spreads them over 180°


@pytest.mark.parametrize("line,match", [
    ("FLASER 180 1.0 1.0 1.0", "line 2: FLASER with 180 readings needs 189 to 191 fields"),
    ("FLASER x 1.0", "line 2: FLASER number of readings must be an integer"),
    ("FLASER 3 1 2 oops 0 0 0 0 0 0 5.0 h 5.0", "line 2: FLASER range 'oops' is not a number"),
    ("FLASER 3 1 2 3 0 0 0 0 0 0 nan h 5.0", "line 2: FLASER timestamp 'nan' is not finite"),
    ("FLASER 4 1 2 3 4 0 0 0 0 0 0 5.0 h 5.0", "line 2: FLASER geometry (4 beams"),
    ("ROBOTLASER1 0 -1.5", "line 2: ROBOTLASER1 has 3 fields"),
])
def test_carmen_bad_lines_are_named(tmp_path, line, match):
    p = tmp_path / "bad.log"
    p.write_text("FLASER 3 1 2 3 0 0 0 0 0 0 4.0 h 4.0\n" + line + "\n")
    with pytest.raises(InputError) as exc:
        read_carmen(p)
    msg = str(exc.value)
    assert "\n" not in msg and str(p) in msg and match in msg, msg


def test_carmen_without_laser_lines_and_binary_files(tmp_path):
    p = tmp_path / "odom.log"
    p.write_text("ODOM 0 0 0 0 0 0 1.0 h 1.0\n")
    with pytest.raises(InputError, match="no FLASER or ROBOTLASER1 lines"):
        import_log(p)
    q = tmp_path / "binary.log"
    q.write_bytes(b"FLASER 1 \xff\xfe\x00\x01")
    with pytest.raises(InputError, match="not text"):
        import_log(q)
    r = tmp_path / "cut.log.gz"
    r.write_bytes(gzip.compress(b"FLASER 3 1 2 3 0 0 0 0 0 0 4.0 h 4.0\n" * 200)[:60])
    with pytest.raises(InputError, match="damaged or truncated gzip"):
        import_log(r)


def _flaser(i: int) -> str:
    return f"FLASER 3 {i + 1} {i + 2} {i + 3} 0 0 0 0 0 0 {5 + 0.1 * i:.1f} h {5 + 0.1 * i:.1f}"


@pytest.mark.parametrize("gz", [False, True])
def test_carmen_cut_last_line_is_skipped_with_a_warning(tmp_path, gz):
    """A log that ends mid-line, as after a crash, reads as the same log without that line, with a
    warning naming it; the same line ended by a newline is still refused, and a whole last line
    without a newline is kept."""
    def write(name, text):
        p = tmp_path / (name + (".log.gz" if gz else ".log"))
        if gz:
            with gzip.open(p, "wt") as f:
                f.write(text)
        else:
            p.write_text(text)
        return p

    head = "".join(_flaser(i) + "\n" for i in range(3))
    whole, cut = write("whole", head), write("cut", head + _flaser(3)[:14])  # "FLASER 3 4 5 6" and nothing more
    with pytest.warns(InputWarning, match=r"line 4 is cut short") as rec:
        log = read_carmen(cut)
    msg = str(rec[0].message)
    assert msg.startswith(f"{cut}: ") and "\n" not in msg, msg
    ref = read_carmen(whole)
    assert log.n_scans == 3
    np.testing.assert_array_equal(log.ranges, ref.ranges)
    np.testing.assert_array_equal(log.stamps, ref.stamps)
    assert "cut short, skipped" in str(log.extra["source"])
    with pytest.raises(InputError, match="line 4: FLASER with 3 readings needs 12"):
        read_carmen(write("bad", head + _flaser(3)[:14] + "\n"))  # ended by a newline: not a cut line
    bad_middle = write("middle", _flaser(0) + "\n" + _flaser(1)[:14] + "\n" + _flaser(2))
    with pytest.raises(InputError, match="line 2: FLASER"):
        read_carmen(bad_middle)
    no_newline = read_carmen(write("nonl", head + _flaser(3)))
    np.testing.assert_array_equal(no_newline.ranges[:, 0], [1, 2, 3, 4])


def test_info_on_a_cut_carmen_log_warns_in_one_line(tmp_path, capsys):
    p = tmp_path / "crash.log"
    p.write_text("".join(_flaser(i) + "\n" for i in range(3)) + "FLASER 3 4")
    assert main(["info", str(p)]) == 0
    out, err = capsys.readouterr()
    assert "3 scans × 3 beams" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gtsjax: warning: {p}: line 4 is cut short"), lines


# ------------------------------------------------------------------------------------------ BreezySLAM


def test_breezyslam_log_matches_plain_parse(logs):
    stamps, ranges = [], []
    for line in (logs / BREEZY).read_text().splitlines():
        toks = line.split()[:-1]  # BreezySLAM's own reader drops the trailing field
        stamps.append(int(toks[0]))
        ranges.append([int(t) for t in toks[24:]])
    ranges = np.array(ranges)
    log = import_log(logs / BREEZY)
    assert ranges.shape == (756, 682) and log.ranges.shape == (756, 682)
    np.testing.assert_array_equal(log.ranges, (ranges / 1000.0).astype(np.float32))
    np.testing.assert_array_equal(log.stamps, np.array(stamps) / 1e6)
    np.testing.assert_allclose(log.angles(), URG_04LX.angles, atol=1e-12)
    assert log.sensor_model == "URG-04LX" and (log.range_min, log.range_max) == (0.02, 5.6)
    assert 0.4 < float(np.mean(ranges == 0)) < 0.6  # SOURCES.md: about half the values are 0
    assert not log.valid()[ranges == 0].any()


def test_breezyslam_bad_lines_are_named(tmp_path, logs):
    good = (logs / BREEZY).read_text().splitlines()[:3]
    p = tmp_path / "short.dat"
    p.write_text("\n".join(good + [" ".join(good[0].split()[:100])]) + "\n")
    with pytest.raises(InputError, match=r"line 4 has 100 fields; a BreezySLAM URG-04LX line has 707"):
        read_breezyslam(p)
    cut = tmp_path / "cut.dat"
    cut.write_text("\n".join(good) + "\n" + good[0][: len(good[0]) // 2])  # the last line cut mid-way, no newline
    with pytest.warns(InputWarning, match="line 4 is cut short"):
        log = read_breezyslam(cut)
    whole = tmp_path / "whole.dat"
    whole.write_text("\n".join(good) + "\n")
    np.testing.assert_array_equal(log.ranges, read_breezyslam(whole).ranges)
    assert log.n_scans == 3
    q = tmp_path / "garbage.dat"
    q.write_text("hello world\n")
    with pytest.raises(InputError, match="line 1 has 2 fields"):
        import_log(q)


# ------------------------------------------------------------------------------------------ detection


def test_detect_format_by_extension_and_content(tmp_path, logs):
    assert detect_format(logs / LEG_BAG) == "ros1"
    assert detect_format(logs / CARMEN) == "carmen"
    assert detect_format(logs / BREEZY) == "breezyslam"
    assert detect_format(tmp_path / "x.npz") == "npz"
    renamed = tmp_path / "bag_without_suffix"
    renamed.write_bytes((logs / LEG_EXTRACTED).read_bytes())
    assert detect_format(renamed) == "ros1"
    assert import_log(renamed).n_scans == 197
    gz = tmp_path / "intel_copy"
    gz.write_bytes((logs / CARMEN).read_bytes())
    assert detect_format(gz) == "carmen"
    other = tmp_path / "mystery.bin"
    other.write_bytes(b"\x00" * 32)
    assert detect_format(other) == "npz"
    with pytest.raises(InputError, match="not a NumPy .npz archive"):
        import_log(other)


def test_topic_for_a_non_bag_is_an_error(logs):
    with pytest.raises(InputError, match=r"a topic \(/scan\) applies to ROS bags only; this is a CARMEN log"):
        import_log(logs / CARMEN, topic="/scan")


def test_read_rosbag_missing_path(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_rosbag(tmp_path / "nope.bag")


def test_directory_that_is_not_a_ros2_bag(tmp_path):
    with pytest.raises(InputError, match="is a directory without a metadata.yaml: neither a ROS 2 bag nor a scan log"):
        import_log(tmp_path)
