"""``gtsjax info`` on a ROS bag of several topics and on a ground-truth CSV (issue 39).

A bag's topics are listed (name, type, messages, a LaserScan topic's geometry) instead of the bag being
refused, each checked against what the bag was written with here (rosbags' own writers: ROS 1, ROS 2
in SQLite and in MCAP); a CSV is summarised, its figures checked against the file read with the
``csv`` module."""

import csv
import math

import numpy as np
import pytest

from gtsjax.cli import main
from tests._badfiles import scans, write_bag

TOPICS = {"/front": scans(4, 8, amin=-1.0, inc=0.25), "/rear": scans(3, 6, intensities=True, amin=-0.5, inc=0.1,
                                                                       rmin=0.1, rmax=4.0, seed=1),
          "/chatter": 2}


def _geometry(msgs) -> str:
    """A LaserScan topic's line as it must read, from the messages written (float32 in the bag)."""
    m = msgs[0]
    f32 = lambda v: float(np.float32(v))  # noqa: E731
    n, amin, inc = len(m["ranges"]), f32(m["amin"]), f32(m["inc"])
    return (f"{n} beams from {math.degrees(amin):.1f}° to {math.degrees(amin + (n - 1) * inc):.1f}° by "
            f"{math.degrees(inc):.3f}°, returns in [{f32(m['rmin']):g}, {f32(m['rmax']):g}] m, "
            f"intensities {'yes' if len(m['intensities']) else 'no'}")


@pytest.mark.parametrize("kind,name", [("ros1", "several.bag"), ("sqlite3", "several"), ("mcap", "several"),
                                       ("mcap", "several/several.mcap")])
def test_info_lists_the_topics_of_a_bag_and_says_how_to_pick_one(tmp_path, capsys, kind, name):
    write_bag(tmp_path / name.split("/")[0], kind, TOPICS)
    path = tmp_path / name
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    listed = [line for line in out if line.startswith("  topic ")]
    assert listed == [f"  topic /chatter: std_msgs/msg/String, {TOPICS['/chatter']} messages",
                      f"  topic /front: sensor_msgs/msg/LaserScan, 4 messages, {_geometry(TOPICS['/front'])}",
                      f"  topic /rear: sensor_msgs/msg/LaserScan, 3 messages, {_geometry(TOPICS['/rear'])}"], out
    assert out[0].startswith(f"{path} (a {'ROS 1' if kind == 'ros1' else 'ROS 2'} bag): 3 topics, 9 messages"), out
    assert "2 LaserScan topics: pick one with --topic T" in out[-1], out
    # The topic picked as replay and convert pick it: its scans summarised as a log.
    assert main(["info", str(path), "--topic", "rear"]) == 0
    out = capsys.readouterr().out
    assert f"{path} (a {'ROS 1' if kind == 'ros1' else 'ROS 2'} bag): 3 scans × 6 beams" in out, out
    assert "topic /rear (sensor_msgs/LaserScan)" in out and "intensities yes" in out


def test_info_on_a_bag_without_laserscans_lists_it_and_exits_2(tmp_path, capsys):
    bag = write_bag(tmp_path / "talk.bag", "ros1", {"/chatter": 3})
    capsys.readouterr()
    assert main(["info", str(bag)]) == 2
    out, err = capsys.readouterr()
    assert "  topic /chatter: std_msgs/msg/String, 3 messages" in out.splitlines()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gtsjax: {bag}: has no sensor_msgs/LaserScan topic"), lines


def _write_gtd(path, n_scans=40, seed=3):
    """Rows as another program would write them (csv module, not gtsjax's writer): tracks coming and
    going, two classes, stamps since 1970."""
    rng = np.random.default_rng(seed)
    header = ["stamp", "track_id", "class", "x", "y", "theta", "var_x", "var_y", "var_theta"]
    spans = {1: ("robot", 0, 30), 2: ("robot", 5, 40), 4: ("ball", 12, 20), 7: ("robot", 33, 34)}
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for k in range(n_scans):
            for tid, (cls, a, b) in spans.items():
                if a <= k < b and rng.random() > 0.1:
                    w.writerow([repr(1.7e9 + 0.1 * k), tid, cls, *rng.normal(size=3), 1e-4, 1e-4, 1e-3])


def test_info_summarises_a_ground_truth_csv(tmp_path, capsys):
    path = tmp_path / "run1.csv"
    _write_gtd(path)
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    per: dict[int, list[float]] = {}
    for r in rows:
        per.setdefault(int(r["track_id"]), []).append(float(r["stamp"]))
    classes = {int(r["track_id"]): r["class"] for r in rows}
    stamps = [float(r["stamp"]) for r in rows]
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == (f"{path}: ground-truth CSV, {len(rows)} rows in {len(set(stamps))} scans, {min(stamps):.3f} … "
                      f"{max(stamps):.3f} s ({max(stamps) - min(stamps):.1f} s), {len(per)} tracks"), out
    for cls in sorted(set(classes.values())):
        ids = sorted(t for t, c in classes.items() if c == cls)
        assert any(line.startswith(f"  {cls}: {len(ids)} track") and line.endswith(", ".join(map(str, ids)))
                   for line in out), (cls, out)
    for tid, ts in sorted(per.items()):
        n = len(ts)
        assert f"  track {tid} ({classes[tid]}): {n} row{'s' * (n != 1)}, {min(ts):.3f} … {max(ts):.3f} s" in out, out


def test_info_reads_a_csv_by_its_header_and_refuses_another_header(tmp_path, capsys):
    named = tmp_path / "run1.txt"  # not .csv, but the GTD header: summarised, not taken for a log
    _write_gtd(named, n_scans=3)
    empty = tmp_path / "none.csv"
    empty.write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n")
    capsys.readouterr()
    assert main(["info", str(named), str(empty)]) == 0
    out = capsys.readouterr().out
    assert f"{named}: ground-truth CSV, " in out and f"{empty}: ground-truth CSV, no rows" in out, out
    other = tmp_path / "other.csv"
    other.write_text("time,id,x,y\n1.0,1,2.0,3.0\n")
    assert main(["info", str(other)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gtsjax: {other}: header must be stamp,track_id,"), lines
