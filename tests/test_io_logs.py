"""Scan logs: every rule of the format rejected with one line naming the file, round trips exact."""

import io
import zipfile

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.io import ScanLog, from_scans, load_log, save_log, to_scans
from gtsjax.sensors import URG_04LX
from tests._utils import assert_allclose


def good_log(t=5, n=682, labelled=True, intensities=False, seed=0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = {
        "ranges": rng.uniform(0.1, 5.0, (t, n)).astype(np.float32),
        "stamps": np.arange(t, dtype=np.float64) * 0.1 + 1.7e9,
        "angle_min": np.float64(URG_04LX.angle_min),
        "angle_increment": np.float64(URG_04LX.angle_increment),
        "range_min": np.float64(0.02),
        "range_max": np.float64(5.6),
        "sensor_model": np.str_("URG-04LX"),
    }
    if intensities:
        d["intensities"] = rng.uniform(0, 1000, (t, n)).astype(np.float32)
    if labelled:
        d["truth_classes"] = np.array(["robot", "robot"])
        poses = rng.uniform(0, 4, (t, 2, 3))
        poses[1:3, 1] = np.nan  # object 1 absent in scans 1-2
        d["truth_poses"] = poses
    return d


def write(tmp_path, d, name="log.npz"):
    p = tmp_path / name
    np.savez(p, **d)
    return p


def one_line_error(path, match):
    with pytest.raises(InputError) as exc:
        load_log(path)
    msg = str(exc.value)
    assert "\n" not in msg
    assert str(path) in msg
    assert match in msg, msg
    return msg


def test_good_log_loads_and_keeps_unknown_keys(tmp_path):
    d = good_log()
    d["my_extra_key"] = np.arange(3)
    log = load_log(write(tmp_path, d))
    assert log.n_scans == 5 and log.n_beams == 682
    assert log.sensor_model == "URG-04LX"
    assert np.array_equal(log.extra["my_extra_key"], np.arange(3))
    np.testing.assert_array_equal(log.ranges, d["ranges"])
    np.testing.assert_array_equal(log.truth_poses, d["truth_poses"])


def test_minimal_log_defaults(tmp_path):
    d = {k: good_log(labelled=False)[k] for k in ("ranges", "stamps", "angle_min", "angle_increment")}
    log = load_log(write(tmp_path, d))
    assert log.range_min == 0.02 and log.range_max == 30.0
    assert log.intensities is None and log.sensor_model is None and not log.labelled


@pytest.mark.parametrize("key", ["ranges", "stamps", "angle_min", "angle_increment"])
def test_missing_required_key(tmp_path, key):
    d = good_log()
    del d[key]
    one_line_error(write(tmp_path, d), f"missing required key(s) '{key}'")


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d.update(ranges=d["ranges"].astype(np.int32)), "'ranges' must be float32"),
        (lambda d: d.update(ranges=d["ranges"][0]), "'ranges' must have shape [T, N]"),
        (lambda d: d.update(ranges=np.zeros((0, 5), np.float32), stamps=np.zeros(0)), "'ranges' is empty"),
        (lambda d: d.update(stamps=d["stamps"][:-1]), "'stamps' must have shape [5]"),
        (lambda d: d.update(stamps=d["stamps"].astype(np.int64)), "'stamps' must be float64"),
        (lambda d: d["stamps"].__setitem__(2, np.nan), "'stamps' has a non-finite value at scan 2"),
        (lambda d: d["stamps"].__setitem__(3, 0.0), "'stamps' decrease at scan 3"),
        (lambda d: d.update(angle_increment=np.float64(-0.1)), "'angle_increment' must be > 0"),
        (lambda d: d.update(angle_min=np.zeros(3)), "'angle_min' must be a float64 scalar"),
        (lambda d: d.update(angle_min=np.float64(np.inf)), "'angle_min' is not finite"),
        (lambda d: d.update(range_min=np.float64(6.0)), "range window"),
        (lambda d: d.update(intensities=np.ones((5, 3), np.float32)), "'intensities' must have the shape"),
        (lambda d: d.update(intensities=-np.ones((5, 682), np.float32)), "'intensities' must be finite and >= 0"),
        (lambda d: d.update(sensor_model=np.float64(1.0)), "'sensor_model' must be a string scalar"),
        (lambda d: d.pop("truth_classes"), "must come together"),
        (lambda d: d.update(truth_poses=d["truth_poses"][:, :, :2]), "'truth_poses' must have shape [5, 2, 3]"),
        (lambda d: d.update(truth_classes=np.array([1, 2])), "'truth_classes' must be a 1-D string array"),
        (lambda d: d["truth_poses"].__setitem__((0, 0, 2), np.nan), "partly NaN"),
    ],
)
def test_bad_log_rejected_with_one_line(tmp_path, mutate, match):
    d = good_log()
    mutate(d)
    one_line_error(write(tmp_path, d), match)


def test_not_an_npz(tmp_path):
    """A file of another kind is named as ``gtsjax info`` names it (issue 54: "not a NumPy .npz archive
    (ValueError)" for a PNG, a CSV, a BreezySLAM log); a damaged zip archive as what zipfile found."""
    p = tmp_path / "scan.npz"
    p.write_text("this is not a log\n")
    one_line_error(p, "a text file, not a .npz scan log")
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    one_line_error(p, "a PNG image, not a .npz scan log")
    p = tmp_path / "walk.dat"
    p.write_text("1000 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0\n")
    one_line_error(p, "a BreezySLAM log, not a .npz scan log: convert it first (gtsjax convert")
    p = tmp_path / "cut.npz"
    p.write_bytes(b"PK\x03\x04 a truncated zip")
    one_line_error(p, "not a NumPy .npz archive")


def test_truncated_npz(tmp_path):
    buf = io.BytesIO()
    np.savez(buf, **good_log())
    p = tmp_path / "cut.npz"
    p.write_bytes(buf.getvalue()[: len(buf.getvalue()) // 2])
    one_line_error(p, "not a NumPy .npz archive")


def test_pickled_object_array_rejected(tmp_path):
    d = good_log()
    d["ranges"] = np.array([[object()]], dtype=object)
    p = tmp_path / "pickled.npz"
    np.savez(p, **d)  # np.savez pickles object arrays; the format forbids them
    one_line_error(p, "pickled")


def test_missing_file_and_directory(tmp_path):
    one_line_error(tmp_path / "nope.npz", "no such file")
    one_line_error(tmp_path, "is a directory")


def test_zip_that_is_not_a_log(tmp_path):
    p = tmp_path / "other.npz"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("hello.txt", "hi")
    with pytest.raises(InputError, match=str(p)):
        load_log(p)


def test_save_load_round_trip_exact(tmp_path):
    d = good_log(intensities=True)
    d["custom"] = np.array([1.5, 2.5])
    log = load_log(write(tmp_path, d))
    out = tmp_path / "again.npz"
    save_log(log, out)
    with np.load(out, allow_pickle=False) as z:
        for key, value in d.items():
            np.testing.assert_array_equal(z[key], value, err_msg=key)
            assert z[key].dtype == np.asarray(value).dtype or key == "truth_classes", key
    assert not (tmp_path / "again.npz.part").exists()


def test_save_refuses_a_bad_log(tmp_path):
    log = load_log(write(tmp_path, good_log()))
    log.stamps = log.stamps[::-1].copy()
    with pytest.raises(InputError, match="decrease"):
        save_log(log, tmp_path / "bad.npz")
    assert not (tmp_path / "bad.npz").exists()


def test_to_scans_pads_masks_and_round_trips(tmp_path):
    d = good_log(n=600, intensities=True, labelled=False)
    r = d["ranges"]
    r[0, :3] = [np.nan, 0.0, -1.0]  # no return, three ways
    r[1, 5] = 9.0  # beyond range_max
    r[1, 6] = 0.01  # below range_min
    r[2, 7] = np.inf
    log = load_log(write(tmp_path, d))
    scans = to_scans(log, n_beams=682)
    assert scans.ranges.shape == (5, 682) and scans.ranges.dtype == np.float32
    assert scans.valid.dtype == bool
    valid = np.asarray(scans.valid)
    # The obvious reference, beam by beam.
    for t in range(5):
        for i in range(682):
            v = i < 600 and np.isfinite(r[t, i]) and 0.02 <= r[t, i] <= 5.6 and r[t, i] > 0
            assert valid[t, i] == v, (t, i)
            if v:
                assert scans.ranges[t, i] == r[t, i]
            else:
                assert scans.ranges[t, i] == 0 and scans.intensities[t, i] == 0
    assert_allclose(np.asarray(scans.dt), np.r_[0.0, np.full(4, 0.1)])
    back = from_scans(scans, log.stamps, 600, angle_min=log.angle_min, angle_increment=log.angle_increment,
                      range_min=log.range_min, range_max=log.range_max, sensor_model=log.sensor_model)
    np.testing.assert_array_equal(back.ranges, np.where(log.valid(), log.ranges, 0))
    np.testing.assert_array_equal(back.intensities, np.where(log.valid(), log.intensities, 0))
    # A log whose "no return" is already 0 survives log -> arrays -> log exactly.
    clean = ScanLog(ranges=back.ranges, stamps=log.stamps, angle_min=log.angle_min,
                    angle_increment=log.angle_increment, range_min=0.02, range_max=5.6)
    again = from_scans(to_scans(clean), clean.stamps, 600, angle_min=clean.angle_min,
                       angle_increment=clean.angle_increment, with_intensities=False)
    np.testing.assert_array_equal(again.ranges, clean.ranges)
    assert_allclose(np.asarray(scans.angles()[0, :600]), log.angles())


def test_to_scans_refuses_too_many_beams(tmp_path):
    log = load_log(write(tmp_path, good_log(n=700, labelled=False)))
    with pytest.raises(InputError, match="700 beams"):
        to_scans(log, n_beams=682)


def test_a_slice_cuts_every_row_per_scan_and_keeps_the_rest(tmp_path):
    """``ScanLog.slice`` keeps the scans asked for, and with them each per-scan key (the simulator's
    sensor truth), row for row as indexing the saved file's arrays gives them; per-object and
    per-log keys (which robot each object is, where the log came from) stay whole."""
    from gtsjax.sim import simulate

    log, _ = simulate("spl-eval", seed=3, n_scans=30)
    log.extra["truth_names"] = np.asarray(["a"], np.str_)
    log.extra["source"] = np.asarray("made here", np.str_)
    save_log(log, tmp_path / "whole.npz")
    part = log.slice(5, 17)
    part.validate("part")  # raises on rows that do not match
    with np.load(tmp_path / "whole.npz", allow_pickle=False) as whole:
        for key in ("ranges", "stamps", "truth_poses", "truth_sensor_pose"):
            got = part.extra[key] if key in part.extra else getattr(part, key)
            np.testing.assert_array_equal(got, whole[key][5:17], err_msg=key)
        assert str(part.extra["source"]) == str(whole["source"]) and list(part.extra["truth_names"]) == ["a"]
    save_log(part, tmp_path / "part.npz")
    assert load_log(tmp_path / "part.npz").n_scans == 12
