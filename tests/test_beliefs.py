"""A robot's own poses read for grading (``gtsjax.io.beliefs``): TUM and CSV written here by hand, with
the values typed in, read back; and each way a team's file goes wrong refused in one line naming the
file, the line and what to do."""

import math

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.io.beliefs import read_beliefs
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
