"""A robot's own poses read for grading (``gtsjax.io.beliefs``): TUM and CSV written here by hand, with
the values typed in, read back; and each way a team's file goes wrong refused in one line naming the
file, the line and what to do."""

import math

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.io.beliefs import read_beliefs, read_beliefs_source
from gtsjax.io.gtd import write_tum

HEADINGS = [0.0, 1.0, -2.5, math.pi - 1e-4, -math.pi + 1e-4]


def _tum_line(t, x, y, th):
    # The quaternion of a turn θ about z, written out: (0, 0, sin θ/2, cos θ/2).
    return f"{t:.6f} {x:.6f} {y:.6f} 0.0 0.0 0.0 {math.sin(th / 2):.9f} {math.cos(th / 2):.9f}"


def test_tum_and_csv_read_back_as_written(tmp_path):
    rows = [(100.0 + 0.1 * k, 0.5 * k, -0.25 * k, th) for k, th in enumerate(HEADINGS)]
    tum = tmp_path / "nao3.txt"
    tum.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(_tum_line(*r) for r in rows) + "\n")
    b = read_beliefs(tum)
    assert b.name == "nao3" and b.n == len(rows)
    np.testing.assert_allclose(b.stamps, [r[0] for r in rows], atol=1e-6)
    np.testing.assert_allclose(b.poses[:, :2], [r[1:3] for r in rows], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (b.poses[:, 2] - HEADINGS))), 0.0, atol=1e-6)
    # The heading of a yaw with a little roll and pitch: the quaternion q_z(ψ) q_y(0.02) q_x(0.01), by hand.
    psi, p, r = 0.7, 0.02, 0.01
    cz, sz, cy, sy, cx, sx = (math.cos(psi / 2), math.sin(psi / 2), math.cos(p / 2), math.sin(p / 2),
                              math.cos(r / 2), math.sin(r / 2))
    qw, qx = cz * cy * cx + sz * sy * sx, cz * cy * sx - sz * sy * cx
    qy, qz = cz * sy * cx + sz * cy * sx, sz * cy * cx - cz * sy * sx
    tilted = tmp_path / "tilted.tum"
    tilted.write_text(f"5.0 1.0 2.0 0.3 {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n")
    assert read_beliefs(tilted, "x").poses[0, 2] == pytest.approx(psi, abs=1e-6)
    # A CSV with its columns in another order and one more, read by name.
    csv = tmp_path / "beliefs.csv"
    csv.write_text("theta,stamp,confidence,x,y\n" + "\n".join(f"{th},{t},0.9,{x},{y}" for t, x, y, th in rows) + "\n")
    c = read_beliefs(csv, "nao3")
    np.testing.assert_allclose(c.stamps, b.stamps, atol=1e-6)
    np.testing.assert_allclose(c.poses, b.poses, atol=1e-6)
    # What gtsjax's own export-tum writes reads back (a track exported, then graded against).
    track = np.array([[1.0, 0.1, 0.2, 3.0], [1.1, 0.2, 0.2, -3.0]])
    write_tum(tmp_path / "track.tum", track)
    t = read_beliefs(tmp_path / "track.tum")
    np.testing.assert_allclose(np.c_[t.stamps, t.poses], track, atol=1e-6)


@pytest.mark.parametrize("name, text, words", [
    ("late.csv", "stamp,x,y,theta\n1.0,0,0,0\n1.2,0,0,0\n1.1,0,0,0\n", "pose 3 (stamp 1.1) is not after"),
    ("twice.txt", _tum_line(1.0, 0, 0, 0) + "\n" + _tum_line(1.0, 0, 0, 0) + "\n", "pose 2 (stamp 1.0) is not after"),
    ("nan.csv", "stamp,x,y,theta\n1.0,0,0,0\n1.1,nan,0,0\n1.2,0,inf,0\n", "line 3 has a value that is not a number"),
    ("mm.csv", "stamp,x,y,theta\n1.0,1500,2200,0\n", "in millimetres?"),
    ("deg.csv", "stamp,x,y,theta\n1.0,1.5,2.2,90\n", "in degrees?"),
    ("quat.txt", "1.0 0 0 0 0 0 0.5 0.5\n", "line 1: the quaternion"),
    ("short.txt", "1.0 0 0 0\n", "line 1 has 4 fields"),
    ("header.csv", "t,x,y,yaw\n1,0,0,0\n", "missing stamp, theta"),
    ("word.csv", "stamp,x,y,theta\n1.0,0,zero,0\n", "line 2 has a non-numeric"),
    ("empty.csv", "stamp,x,y,theta\n", "holds no poses"),
    ("comments.txt", "# nothing\n", "holds no poses"),
])
def test_a_bad_belief_file_is_one_line_naming_it(tmp_path, name, text, words):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_beliefs(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(path)) and words in msg, msg


def test_a_folder_or_binary_file_is_refused_in_one_line(tmp_path):
    (tmp_path / "poses.bin").write_bytes(b"\xff\xfe\x00\x81binary")
    for path, words in ((tmp_path, "is a folder"), (tmp_path / "poses.bin", "not a text file"),
                        (tmp_path / "gone.csv", "no such file")):
        with pytest.raises(InputError, match=words):
            read_beliefs(path)


# ------------------------------------------------------------------------------------------ ROS bags

POSE_T, COV_T, ODOM_T, TF_T = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
                               "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage")


def write_pose_bag(path, kind, topics):
    """A bag written with rosbags' writers: ``kind`` ``ros1`` (a ``.bag`` file), ``sqlite3`` or ``mcap`` (a ROS 2
    bag's folder). ``topics`` maps a topic to (message type, rows): rows of (stamp, x, y, θ), for TFMessage
    (stamp, child frame, x, y, θ), one transform a message (θ None: a zero quaternion); any other type gets ``std_msgs/String`` messages."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    if ros1:  # ROS 1's own Header (with seq); its store lacks tf2_msgs, whose one message is this
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_T))
    T = ts.types
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr

    def header(stamp, frame="map"):
        sec = int(stamp)
        t = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((stamp - sec) * 1e9))
        hdr = T["std_msgs/msg/Header"]
        return hdr(seq=0, stamp=t, frame_id=frame) if ros1 else hdr(stamp=t, frame_id=frame)

    def quat(th):  # a turn θ about z, by hand; None: an orientation never set, all zeros
        if th is None:
            return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0)
        return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))

    def pose(x, y, th):
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0), orientation=quat(th))

    def with_cov(x, y, th):
        return T["geometry_msgs/msg/PoseWithCovariance"](pose=pose(x, y, th), covariance=np.zeros(36))

    def message(msgtype, row):
        if msgtype == POSE_T:
            return T[msgtype](header=header(row[0]), pose=pose(*row[1:]))
        if msgtype == COV_T:
            return T[msgtype](header=header(row[0]), pose=with_cov(*row[1:]))
        if msgtype == ODOM_T:
            twist = T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36))
            return T[msgtype](header=header(row[0], "odom"), child_frame_id="base_link", pose=with_cov(*row[1:]),
                              twist=twist)
        stamp, child, x, y, th = row
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0), rotation=quat(th)))
        return T[msgtype](transforms=[tf])

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    with writer as w:
        for topic, (msgtype, rows) in topics.items():
            if msgtype not in (POSE_T, COV_T, ODOM_T, TF_T):
                msgtype, rows = "std_msgs/msg/String", [T["std_msgs/msg/String"](data=str(r)) for r in rows]
            else:
                rows = [message(msgtype, r) for r in rows]
            conn = w.add_connection(topic, msgtype, typestore=ts)
            for i, msg in enumerate(rows):
                w.write(conn, (600 + i) * 10**9, ser(msg, msgtype))
    return path


ROWS = [(1700000000.0 + 0.1 * k, 0.5 * k - 1.0, 0.25 * k, th) for k, th in enumerate(HEADINGS)]


def assert_rows(b, rows):
    np.testing.assert_allclose(b.stamps, [r[0] for r in rows], rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.poses[:, :2], [r[1:3] for r in rows], atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (b.poses[:, 2] - [r[3] for r in rows]))), 0.0, atol=1e-9)
    assert np.all(np.diff(b.stamps) > 0) and np.all(np.abs(b.poses[:, 2]) <= math.pi)


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_bag_topics_of_each_pose_type_read_back_as_written(tmp_path, kind):
    bag = write_pose_bag(tmp_path / ("run.bag" if kind == "ros1" else "run"), kind, {
        "/amcl_pose": (COV_T, ROWS), "/robot/pose": (POSE_T, ROWS[:3]), "/odom": (ODOM_T, ROWS[1:]),
        "/chatter": ("std_msgs/msg/String", range(3))})
    for topic, rows in (("/amcl_pose", ROWS), ("/robot/pose", ROWS[:3]), ("/odom", ROWS[1:])):
        source = f"{bag}:{topic}"
        b = read_beliefs_source(source, "nao3")
        assert (b.name, b.source, b.n) == ("nao3", source, len(rows))
        assert_rows(b, rows)
    if kind != "ros1":  # a ROS 2 bag named by the storage file or metadata.yaml in its folder
        store = next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
        for inner in (store, bag / "metadata.yaml"):
            assert_rows(read_beliefs_source(f"{inner}:/amcl_pose", "nao3"), ROWS)
    # A file that is no bag is read as TUM/CSV, as read_beliefs reads it.
    csv = tmp_path / "beliefs.csv"
    csv.write_text("stamp,x,y,theta\n" + "\n".join(",".join(map(str, r)) for r in ROWS) + "\n")
    assert_rows(read_beliefs_source(str(csv), "nao3"), ROWS)


def test_ros1_topic_stored_without_its_slash(tmp_path):
    bag = write_pose_bag(tmp_path / "old.bag", "ros1", {"odom": (ODOM_T, ROWS)})
    assert_rows(read_beliefs_source(f"{bag}:/odom", "r"), ROWS)


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_tf_reads_only_the_named_child_frame(tmp_path, kind):
    mine = [(s, "base_link", x, y, th) for s, x, y, th in ROWS]
    other = [(s + 0.05, "/ball", 9.0, -9.0, 0.3) for s, *_ in ROWS]
    rows = [r for pair in zip(mine, other, strict=True) for r in pair]  # interleaved, one transform a message
    bag = write_pose_bag(tmp_path / ("tf.bag" if kind == "ros1" else "tf"), kind, {"/tf": (TF_T, rows)})
    for child in ("base_link", "/base_link"):
        b = read_beliefs_source(f"{bag}:/tf:{child}", "nao3")
        assert b.source == f"{bag}:/tf:{child}"
        assert_rows(b, ROWS)
    assert_rows(read_beliefs_source(f"{bag}:/tf:ball", "nao3"), [(s + 0.05, 9.0, -9.0, 0.3) for s, *_ in ROWS])
    for source, words in ((f"{bag}:/tf:odom", "no transforms to child frame odom; its child frames: ball, base_link"),
                          (f"{bag}:/tf", "needs a child frame, as BAG:/tf:CHILD; its child frames: ball, base_link")):
        with pytest.raises(InputError) as err:
            read_beliefs_source(source, "nao3")
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(str(bag)) and words in msg, msg


@pytest.mark.parametrize("kind", ["ros1", "sqlite3"])
def test_a_bad_bag_topic_is_one_line_naming_the_bag(tmp_path, kind):
    late = ROWS[:2] + [(ROWS[0][0] + 0.05, 0.0, 0.0, 0.0)]
    mm = [(s, 1000 * x, 1000 * y, th) for s, x, y, th in ROWS]
    nan = ROWS[:2] + [(ROWS[2][0], math.nan, 0.0, 0.0)]
    bag = write_pose_bag(tmp_path / ("bad.bag" if kind == "ros1" else "bad"), kind, {
        "/late": (POSE_T, late), "/mm": (ODOM_T, mm), "/unset": (ODOM_T, ROWS[:1] + [(ROWS[1][0], 0.0, 0.0, None)]), "/nan": (COV_T, nan), "/empty": (POSE_T, []),
        "/chatter": ("std_msgs/msg/String", range(2)), "/tf": (TF_T, [(ROWS[0][0], "base_link", 0.0, 0.0, 0.0)])})
    cases = [
        ("/late", "message 2 (stamp 1700000000.05) is not after the one before (1700000000.1)"),
        ("/mm", "in millimetres?"),
        ("/nan", "message 2 has a value that is not a number"),
        ("/empty", "topic /empty has no messages"),
        ("/unset", "message 1: the quaternion (x y z w) has length 0, not 1"),
        ("/chatter", "topic /chatter carries std_msgs/msg/String, not a pose: the poses are read from "
                     "geometry_msgs/msg/PoseWithCovarianceStamped, geometry_msgs/msg/PoseStamped, nav_msgs/msg/Odometry"),
        ("/gone", "no topic /gone in the bag; its pose topics: /empty (geometry_msgs/msg/PoseStamped), /late "
                  "(geometry_msgs/msg/PoseStamped), /mm (nav_msgs/msg/Odometry), /nan "
                  "(geometry_msgs/msg/PoseWithCovarianceStamped), /tf (tf2_msgs/msg/TFMessage: name the child frame "
                  "as /tf:CHILD), /unset (nav_msgs/msg/Odometry)"),
        ("/mm:base_link", "topic /mm carries nav_msgs/msg/Odometry, not transforms"),
    ]
    for topic, words in cases:
        with pytest.raises(InputError) as err:
            read_beliefs_source(f"{bag}:{topic}", "nao3")
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(str(bag)) and words in msg, (topic, msg)
    # A bag without a topic, a topic of a missing bag, a file that is no bag.
    (tmp_path / "poses.csv").write_text("stamp,x,y,theta\n1,0,0,0\n")
    for source, where, words in ((str(bag), bag, "is a ROS bag: name the topic of the poses as"),
                                 (f"{tmp_path / 'gone.bag'}:/odom", tmp_path / "gone.bag", "no such file"),
                                 (f"{bag}:late", bag, f"a bag's topic starts with /: name it as {bag}:/late"),
                                 (f"{tmp_path / 'poses.csv'}:/odom", tmp_path / "poses.csv", "is not a ROS bag")):
        with pytest.raises(InputError) as err:
            read_beliefs_source(source, "nao3")
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(f"{where}: ") and words in msg, msg
