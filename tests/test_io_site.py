"""Site files: the spec's example loads; every broken rule is one line naming the file."""

import json

import pytest

from gtsjax import InputError
from gtsjax.io import load_site, save_site

SPL = {
    "landmarks": [
        {"class": "post", "x": 0.0, "y": 1.3},
        {"class": "post", "x": 0.0, "y": 2.7},
        {"class": "post", "x": 6.0, "y": 1.3},
        {"class": "post", "x": 6.0, "y": 2.7},
    ],
    "sensor_pose": [3.0, 4.0, -1.5708],
    "bounds": [0.0, 0.0, 6.0, 4.0],
}


def write(tmp_path, doc, raw=None):
    p = tmp_path / "site.json"
    p.write_text(raw if raw is not None else json.dumps(doc))
    return p


def test_spl_site_loads_and_round_trips(tmp_path):
    doc = dict(SPL, comment="extra keys are accepted")
    site = load_site(write(tmp_path, doc))
    assert site.landmark_classes == ("post",) * 4
    assert site.landmark_xy.shape == (4, 2)
    assert site.sensor_pose == (3.0, 4.0, -1.5708)
    assert site.bounds == (0.0, 0.0, 6.0, 4.0)
    out = tmp_path / "again.json"
    save_site(site, out)
    assert json.loads(out.read_text()) == doc


def test_bounds_optional(tmp_path):
    doc = {k: v for k, v in SPL.items() if k != "bounds"}
    assert load_site(write(tmp_path, doc)).bounds is None


def bad(tmp_path, doc=None, raw=None, match=""):
    p = write(tmp_path, doc, raw)
    with pytest.raises(InputError) as exc:
        load_site(p)
    msg = str(exc.value)
    assert "\n" not in msg and str(p) in msg and match in msg, msg


def test_not_json(tmp_path):
    bad(tmp_path, raw="landmarks: [1, 2]", match="not a JSON site file")
    bad(tmp_path, raw="\xff\xfe binary", match="not a JSON site file")


def test_wrong_top_level(tmp_path):
    bad(tmp_path, doc=[1, 2, 3], match="top level must be a JSON object")


@pytest.mark.parametrize("key", ["landmarks", "sensor_pose"])
def test_missing_key(tmp_path, key):
    bad(tmp_path, doc={k: v for k, v in SPL.items() if k != key}, match=f"missing required key '{key}'")


def test_too_few_landmarks(tmp_path):
    bad(tmp_path, doc=dict(SPL, landmarks=SPL["landmarks"][:2]), match="at least 3 landmarks, got 2")


def test_collinear_landmarks(tmp_path):
    lms = [{"class": "post", "x": float(x), "y": 2.0 * x + 1.0} for x in range(5)]
    bad(tmp_path, doc=dict(SPL, landmarks=lms), match="on one line")


@pytest.mark.parametrize(
    "landmark, match",
    [
        ({"class": "post", "x": 1.0}, "landmark 0 is missing 'y'"),
        ({"class": "", "x": 1.0, "y": 2.0}, "'class' must be a non-empty string"),
        ({"class": "post", "x": "1", "y": 2.0}, "must be finite numbers"),
        ({"class": "post", "x": float("nan"), "y": 2.0}, "must be finite numbers"),
        ([1, 2], "landmark 0 must be an object"),
    ],
)
def test_bad_landmark(tmp_path, landmark, match):
    bad(tmp_path, doc=dict(SPL, landmarks=[landmark] + SPL["landmarks"]), match=match)


@pytest.mark.parametrize("pose", [[3.0, 4.0], [3.0, 4.0, "x"], "3,4,0", [3.0, 4.0, True]])
def test_bad_sensor_pose(tmp_path, pose):
    bad(tmp_path, doc=dict(SPL, sensor_pose=pose), match="'sensor_pose' must be [x, y, theta]")


@pytest.mark.parametrize("bounds, match", [([0, 0, 6], "four finite numbers"), ([6, 0, 0, 4], "xmin < xmax")])
def test_bad_bounds(tmp_path, bounds, match):
    bad(tmp_path, doc=dict(SPL, bounds=bounds), match=match)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_site(tmp_path / "absent.json")
