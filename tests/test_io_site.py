"""Site files: the spec's example loads; every broken rule is one line naming the file."""

import json
from pathlib import Path

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


def _moved(key, i, value):
    doc = json.loads(json.dumps(SPL))
    if key == "landmarks":
        doc["landmarks"][1]["y"] = value
    else:
        doc[key][i] = value
    return doc


@pytest.mark.parametrize(
    "key, i, value, match",
    [
        ("landmarks", None, 1e39, "landmark 1: 'y' is 1e+39"),
        ("landmarks", None, -2e4, "landmark 1: 'y' is -20000"),
        ("sensor_pose", 0, 1e39, "'sensor_pose' x is 1e+39"),
        ("sensor_pose", 2, 1e39, "'sensor_pose' theta is 1e+39"),
        ("bounds", 3, 1e39, "'bounds' ymax is 1e+39"),
    ],
)
def test_absurd_coordinates_are_refused_naming_the_field(tmp_path, key, i, value, match):
    """A coordinate of 1e39 is finite in JSON and float64 but infinite in the float32 step: beyond
    10 km from the origin is refused, naming the field (``1e39`` written as JSON reads that way)."""
    bad(tmp_path, doc=_moved(key, i, value), match=match)


def test_a_large_but_real_field_loads(tmp_path):
    doc = json.loads(json.dumps(SPL))
    for lm in doc["landmarks"]:
        lm["x"] += 9000.0
    doc["sensor_pose"][0] += 9000.0
    doc["bounds"] = [9000.0, 0.0, 9006.0, 4.0]
    assert load_site(write(tmp_path, doc)).landmarks[2].x == 9006.0


def test_replay_refuses_a_site_at_1e39_in_one_line(tmp_path, capsys):
    from gtsjax.cli import main
    from gtsjax.io import save_log
    from gtsjax.sim import simulate

    log, _ = simulate("spl-eval", seed=1, n_scans=3)
    save_log(log, tmp_path / "log.npz")
    site = write(tmp_path, _moved("landmarks", None, 1e39))
    demo = Path(__file__).resolve().parents[1] / "gtsjax" / "data" / "demo-model.npz"
    code = main(["replay", str(tmp_path / "log.npz"), "--site", str(site), "--model", str(demo),
                 "--out", str(tmp_path / "o.csv")])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"gtsjax: {site}: landmark 1: 'y'"), lines
    assert not (tmp_path / "o.csv").exists()


# ----------------------------------------------------------------------------- several sensors (issue 18)

TWO = {
    "landmarks": SPL["landmarks"],
    "sensors": [{"name": "north", "sensor_pose": [3.0, 4.3, -1.5708], "model": "URG-04LX"},
                {"name": "south", "sensor_pose": [3.0, -0.3, 1.5708]}],
    "bounds": SPL["bounds"],
}


def test_site_without_sensors_is_one_sensor_and_writes_as_before(tmp_path):
    site = load_site(write(tmp_path, SPL))
    assert site.sensors == () and [(s.name, s.pose, s.model) for s in site.sensor_list] == [
        ("laser", (3.0, 4.0, -1.5708), None)]
    save_site(site, tmp_path / "again.json")
    assert json.loads((tmp_path / "again.json").read_text()) == SPL  # no key added


def test_site_with_sensors_loads_round_trips_and_keeps_a_sensor_pose_for_old_readers(tmp_path):
    site = load_site(write(tmp_path, TWO))
    assert [(s.name, s.pose, s.model) for s in site.sensor_list] == [
        ("north", (3.0, 4.3, -1.5708), "URG-04LX"), ("south", (3.0, -0.3, 1.5708), None)]
    assert site.sensor_pose == (3.0, 4.3, -1.5708)  # the first sensor's
    save_site(site, tmp_path / "again.json")
    doc = json.loads((tmp_path / "again.json").read_text())
    assert doc["sensor_pose"] == [3.0, 4.3, -1.5708] and doc["sensors"] == TWO["sensors"]
    assert load_site(tmp_path / "again.json") == site
    south = site.for_sensor("south")
    assert south.sensor_pose == (3.0, -0.3, 1.5708) and south.sensors == () and south.landmarks == site.landmarks
    with pytest.raises(InputError, match="no sensor named 'east'"):
        site.for_sensor("east")


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: d.pop("sensors"), "missing required key 'sensor_pose' (or a 'sensors' list)"),
    (lambda d: d.update(sensors=[]), "missing required key 'sensor_pose' (or a 'sensors' list)"),
    (lambda d: d["sensors"][1].update(name="north"), "the name 'north' is used twice"),
    (lambda d: d["sensors"][1].pop("sensor_pose"), "sensor 1 is missing 'sensor_pose'"),
    (lambda d: d["sensors"][0].update(sensor_pose=[0, 0]), "sensor 'north': 'sensor_pose' must be [x, y, theta]"),
    (lambda d: d["sensors"][0].update(sensor_pose=[1e39, 0, 0]), "beyond ±10000 m"),
    (lambda d: d["sensors"][1].update(model="LMS-100"), "sensor 'south': unknown scanner model 'LMS-100'"),
    (lambda d: d["sensors"][1].update(name="a=b"), "'name' must be a non-empty string without '=' or ','"),
    (lambda d: d.update(sensors="north"), "'sensors' must be a non-empty list"),
])
def test_bad_sensors_list_is_one_line(tmp_path, change, message):
    doc = json.loads(json.dumps(TWO))
    change(doc)
    with pytest.raises(InputError) as err:
        load_site(write(tmp_path, doc))
    assert str(err.value).startswith(str(tmp_path / "site.json")) and message in str(err.value)
