"""GTD CSV per the spec, read by the csv module alone; TUM export; read-back validation."""

import csv

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.io.gtd import HEADER, GTDWriter, read_gtd, rows_from_output, tracks_of, write_tum


def test_csv_rows_only_for_confirmed_tracks_in_id_order(tmp_path):
    path = tmp_path / "out" / "gtd.csv"
    with GTDWriter(path) as w:
        for k in range(3):
            rows = rows_from_output(
                1.7e9 + 0.1 * k, track_id=[5, 2, -1], cls_index=[1, 1, 0],
                pose=[[1.0, 2.0, 4.0], [3.0, 1.0, -0.5], [0, 0, 0]], var=[[1e-4, 2e-4, 3e-3]] * 3,
                mask=[True, True, False], class_names=("background", "robot"))
            w.write(rows)
    with open(path, newline="") as f:
        recs = list(csv.reader(f))
    assert tuple(recs[0]) == HEADER
    assert len(recs) == 1 + 3 * 2
    assert [r[1] for r in recs[1:3]] == ["2", "5"]
    assert float(recs[1][0]) == 1.7e9 and recs[1][2] == "robot"
    assert abs(float(recs[2][5]) - (4.0 - 2 * np.pi)) < 1e-6  # wrapped
    back = read_gtd(path)
    assert len(back) == 6 and back[0].track_id == 2
    tracks = list(tracks_of(back))
    assert [t[0] for t in tracks] == [2, 5] and tracks[0][2].shape == (3, 4)


def test_tum_export(tmp_path):
    track = np.array([[0.0, 1.0, 2.0, np.pi / 2], [0.1, 1.1, 2.0, -np.pi / 2]])
    write_tum(tmp_path / "t.txt", track)
    vals = np.loadtxt(tmp_path / "t.txt")
    assert vals.shape == (2, 8)
    # Quaternion (0, 0, sin θ/2, cos θ/2) is unit and gives back the heading.
    np.testing.assert_allclose(np.linalg.norm(vals[:, 4:], axis=1), 1.0)
    np.testing.assert_allclose(2 * np.arctan2(vals[:, 6], vals[:, 7]), track[:, 3])


@pytest.mark.parametrize("text, match", [
    ("a,b\n", "header must be"),
    (",".join(HEADER) + "\n1.0,2,robot,1,2\n", "line 2 has 5 fields"),
    (",".join(HEADER) + "\n1.0,x,robot,1,2,3,4,5,6\n", "non-numeric"),
    (",".join(HEADER) + "\n1.0,1,robot,nan,2,3,4,5,6\n", "non-finite"),
])
def test_bad_gtd_is_one_line(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        read_gtd(p)


def test_writer_text_is_what_csv_writer_writes(tmp_path):
    """The writer's text equals ``csv.writer``'s for the same fields (the obvious form: a list per
    row, the numbers formatted as the format says), class names that need quoting among them, and
    reads back as the rows written."""
    import io

    from gtsjax.io.gtd import TrackRow

    rng = np.random.default_rng(3)
    names = ["robot", "post", "", "a,b", 'say "hi"', "line\nbreak", "tab\there", "naïve"]
    rows = [TrackRow(float(1.7e9 + rng.uniform(0, 100)), int(rng.integers(0, 10**6)), names[i % len(names)],
                     *rng.normal(0, 5, 3).tolist(), *(10.0 ** rng.uniform(-12, 2, 3)).tolist())
            for i in range(40)]
    rows.append(TrackRow(0.1, 7, "robot", float("nan"), float("inf"), -0.0, 0.0, 1e-300, float("-inf")))
    want = io.StringIO()
    w = csv.writer(want, lineterminator="\n")
    w.writerow(HEADER)
    for r in rows:
        w.writerow([repr(r.stamp), r.track_id, r.cls, f"{r.x:.6f}", f"{r.y:.6f}", f"{r.theta:.6f}",
                    f"{r.var_x:.6e}", f"{r.var_y:.6e}", f"{r.var_theta:.6e}"])
    with GTDWriter(tmp_path / "g.csv") as gw:
        gw.write(rows[:3])
        gw.write([])
        gw.write(rows[3:])
    assert (tmp_path / "g.csv").read_text() == want.getvalue()
    plain = [r for r in rows[:-1] if "\n" not in r.cls]
    with GTDWriter(tmp_path / "h.csv") as gw:
        gw.write(plain)
    back = read_gtd(tmp_path / "h.csv")
    assert [(r.track_id, r.cls) for r in back] == [(r.track_id, r.cls) for r in plain]
    np.testing.assert_allclose([r.x for r in back], [r.x for r in plain], atol=1e-6)


def test_units_form_is_what_csv_writer_writes_and_reads_back(tmp_path):
    """``--csv-units``: the header with units and the ``cov_xy_m2`` column, each row what
    ``csv.writer`` writes for the same fields; the reader takes it, the spec's header, and the spec's
    header followed by ``cov_xy`` (a file another program extended), with the covariance back."""
    import io

    from gtsjax.io.gtd import UNITS_HEADER, TrackRow

    rng = np.random.default_rng(4)
    rows = [TrackRow(float(1.7e9 + k * 0.1), k % 3, "robot", *rng.normal(0, 3, 3).tolist(),
                     *(10.0 ** rng.uniform(-6, -2, 3)).tolist(), float(rng.normal(0, 1e-4))) for k in range(20)]
    want = io.StringIO()
    w = csv.writer(want, lineterminator="\n")
    w.writerow(UNITS_HEADER)
    for r in rows:
        w.writerow([repr(r.stamp), r.track_id, r.cls, f"{r.x:.6f}", f"{r.y:.6f}", f"{r.theta:.6f}",
                    f"{r.var_x:.6e}", f"{r.var_y:.6e}", f"{r.var_theta:.6e}", f"{r.cov_xy:.6e}"])
    with GTDWriter(tmp_path / "u.csv", units=True) as gw:
        gw.write(rows)
    assert (tmp_path / "u.csv").read_text() == want.getvalue()
    back = read_gtd(tmp_path / "u.csv")
    np.testing.assert_allclose([r.cov_xy for r in back], [r.cov_xy for r in rows], rtol=1e-6)
    # The spec's header and a trailing cov_xy; and the spec's header alone reads cov_xy as 0.
    lines = want.getvalue().splitlines()
    (tmp_path / "x.csv").write_text("\n".join([",".join(HEADER) + ",cov_xy", *lines[1:]]) + "\n")
    assert [r.cov_xy for r in read_gtd(tmp_path / "x.csv")] == [r.cov_xy for r in back]
    (tmp_path / "s.csv").write_text("\n".join([",".join(HEADER), *(ln.rsplit(",", 1)[0] for ln in lines[1:])]) + "\n")
    assert {r.cov_xy for r in read_gtd(tmp_path / "s.csv")} == {0.0}
    (tmp_path / "bad.csv").write_text(",".join(UNITS_HEADER) + "\n" + lines[1].rsplit(",", 1)[0] + "\n")
    with pytest.raises(InputError, match="line 2 has 9 fields, expected 10"):
        read_gtd(tmp_path / "bad.csv")
