"""Scanner geometry (issue 13, item 5): a log, a live sensor or a background log is taken by a model
only with the model's angular step (within 1 %) and with its beams inside the model's field of view;
``crop`` cuts a wider one (and the range window) to the model's. Cropping is checked against a plain
loop over the beams; the commands against real logs of other scanners (SICK CARMEN, a 270° ROS bag)."""

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.io import ScanLog, save_log
from gtsjax.io.logs import fit_geometry, fit_to_model
from gtsjax.sensors import URG_04LX
from tests._utils import run_cli

DEMO_MODEL = Path(__file__).resolve().parents[1] / "gtsjax" / "data" / "demo-model.npz"
SPL_SITE = ('{"landmarks": [{"class": "post", "x": 0.0, "y": 1.3}, {"class": "post", "x": 0.0, "y": 2.7},'
            ' {"class": "post", "x": 6.0, "y": 1.3}, {"class": "post", "x": 6.0, "y": 2.7}],'
            ' "sensor_pose": [3.0, 4.0, -1.5708], "bounds": [0.0, 0.0, 6.0, 4.0]}')
# The geometry of a model trained on a URG-04LX (the shipped model's).
URG = dict(angle_min=URG_04LX.angle_min, angle_increment=URG_04LX.angle_increment, n_beams=URG_04LX.n_beams,
           range_min=URG_04LX.range_min, range_max=URG_04LX.range_max)
STEP = URG_04LX.angle_increment


def make_log(angle_min: float, angle_increment: float, n: int, *, scans: int = 4, range_max: float = 11.0,
             seed: int = 0) -> ScanLog:
    """A small log with ranges spread over [0, 12] m (some no-return zeros, NaNs and values outside
    every window), intensities, and one labelled object."""
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.0, 12.0, (scans, n)).astype(np.float32)
    ranges[rng.random((scans, n)) < 0.05] = 0.0
    ranges[0, :3] = (np.nan, 0.01, 0.025)
    return ScanLog(ranges=ranges, stamps=np.arange(scans) * 0.1, angle_min=angle_min, angle_increment=angle_increment,
                   intensities=rng.uniform(0, 1000, (scans, n)).astype(np.float32), range_min=0.02, range_max=range_max,
                   truth_classes=np.array(["robot"]), truth_poses=np.zeros((scans, 1, 3)))


def fit(log, crop=False, hint="", **geometry):
    return fit_geometry(log, **{**URG, **geometry}, where="x.log", crop=crop, hint=hint, sensor_model="URG-04LX")


def one_line(err: pytest.ExceptionInfo, *fragments):
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("x.log: "), msg
    for f in fragments:
        assert f in msg, msg
    return msg


# ------------------------------------------------------------------------------------------ angular step


def test_another_angular_step_is_refused():
    carmen = make_log(math.radians(-90.0), math.radians(1.0), 180)  # a SICK LMS as CARMEN logs it
    for crop in (False, True):  # no cropping mends another step
        with pytest.raises(InputError) as err:
            fit(carmen, crop=crop)
        one_line(err, "angular step 1.000° differs from the model's 0.352° (URG-04LX) by more than 1 %")
    with pytest.raises(InputError) as err:
        fit(make_log(math.radians(-120), math.radians(0.5), 481))  # a ROS bag at 0.5°
    one_line(err, "angular step 0.500°")


@pytest.mark.parametrize("factor", [1.008, 0.992])
def test_a_step_within_one_percent_is_accepted(factor):
    log = make_log(URG["angle_min"] + 5 * STEP, STEP * factor, 660)
    assert fit(log) is log  # untouched


@pytest.mark.parametrize("factor", [1.012, 0.988])
def test_a_step_beyond_one_percent_is_refused(factor):
    with pytest.raises(InputError) as err:
        fit(make_log(URG["angle_min"] + 5 * STEP, STEP * factor, 660))
    one_line(err, "angular step", "by more than 1 %")


# ------------------------------------------------------------------------------------------ field of view


def expected_crop(log: ScanLog, n_beams=URG["n_beams"]):
    """The beams to keep, by walking them: those within half a model beam of the model's field of
    view, the first ``n_beams`` of them."""
    lo = URG["angle_min"] - 0.5 * STEP
    hi = URG["angle_min"] + (n_beams - 1) * STEP + 0.5 * STEP
    keep = []
    for i in range(log.n_beams):
        a = log.angle_min + i * log.angle_increment
        if lo <= a <= hi and len(keep) < n_beams:
            keep.append(i)
    return keep


@pytest.mark.parametrize("angle_min,factor,n", [
    (math.radians(-135.0), 1.0, 768),  # the leg_tracker bags: 270° at the URG-04LX's step
    (math.radians(-135.0) + 0.3 * STEP, 1.0, 768),  # beams between the model's
    (math.radians(-135.0) - 0.5 * STEP, 1.0, 768),  # exactly half a beam off
    (math.radians(-10.0), 1.0, 700),  # sticking out on one side only
    (math.radians(-125.0), 0.995, 760),  # a slightly finer step: more beams fit than the model has
    (math.radians(-130.0), 1.007, 740),
])
def test_crop_keeps_exactly_the_beams_inside(angle_min, factor, n):
    log = make_log(angle_min, STEP * factor, n)
    with pytest.raises(InputError) as err:
        fit(log, hint="; crop it with --crop-fov")
    one_line(err, "field of view", "is not inside the model's -119.5° … 119.9° (URG-04LX); crop it with --crop-fov")

    out = fit(log, crop=True)
    keep = expected_crop(log)
    assert 0 < len(keep) <= URG["n_beams"] and keep == list(range(keep[0], keep[-1] + 1))
    assert out.n_beams == len(keep)
    assert out.angle_min == pytest.approx(log.angle_min + keep[0] * log.angle_increment, abs=1e-12)
    assert out.angle_increment == log.angle_increment  # not resampled
    kept = log.ranges[:, keep]
    outside = np.isfinite(kept) & (kept > 0) & ((kept < URG["range_min"]) | (kept > URG["range_max"]))
    np.testing.assert_array_equal(out.ranges, np.where(outside, 0.0, kept).astype(np.float32))
    np.testing.assert_array_equal(out.intensities, np.where(outside, 0.0, log.intensities[:, keep]))
    assert outside.any() and np.all(out.ranges[np.isfinite(out.ranges)] <= URG["range_max"])
    assert (out.range_min, out.range_max) == (URG["range_min"], URG["range_max"])  # the overlap of both windows
    np.testing.assert_array_equal(out.truth_poses, log.truth_poses)
    # What is left fits the model as it is: fitting again changes nothing.
    again = fit(out)
    assert again is out
    model_max = URG["angle_min"] + (URG["n_beams"] - 1) * STEP
    assert URG["angle_min"] - 0.5 * STEP <= out.angles()[0] and out.angles()[-1] <= model_max + 0.5 * STEP


def test_crop_leaves_too_few_beams():
    log = make_log(math.radians(117.0), STEP, 200)  # 9 of its beams overlap the model's field of view
    assert len(expected_crop(log)) == 9
    with pytest.raises(InputError) as err:
        fit(log, crop=True)
    one_line(err, "is not inside the model's", "only 9 of its beams lie inside (at least 69 needed)")


def test_more_beams_than_the_model_is_refused_unless_cropped():
    log = make_log(URG["angle_min"], STEP * 0.992, 687)  # within the field of view and the 1 %, but 687 beams
    with pytest.raises(InputError) as err:
        fit(log)
    one_line(err, "has 687 beams per scan, more than the 682 of the model (URG-04LX)")
    out = fit(log, crop=True)
    assert out.n_beams == 682 and out.angle_min == log.angle_min


def test_crop_applies_the_range_window_to_a_log_that_fits():
    log = make_log(URG["angle_min"], STEP, 682, range_max=30.0)
    assert fit(log) is log  # without crop, ranges are left as they are
    out = fit(log, crop=True)
    assert out.n_beams == 682 and out.range_max == URG["range_max"]
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(out.valid(), log.valid() & (log.ranges <= URG["range_max"]))
    assert np.nanmax(out.ranges) <= URG["range_max"]
    with pytest.raises(InputError) as err:
        fit(dataclasses.replace(log, range_min=6.0, range_max=30.0), crop=True)
    one_line(err, "does not overlap the model's [0.02, 5.6] m")


def test_a_model_without_geometry_takes_logs_as_before():
    carmen = make_log(math.radians(-90.0), math.radians(1.0), 180)
    assert fit(carmen, angle_increment=float("nan")) is carmen
    with pytest.raises(InputError) as err:
        fit(make_log(0.0, STEP, 768), angle_increment=float("nan"))
    one_line(err, "has 768 beams per scan; the model (URG-04LX) takes at most 682")


def test_fit_to_model_reads_the_models_geometry():
    model = SimpleNamespace(**URG, sensor_model="URG-04LX")
    with pytest.raises(InputError) as err:
        fit_to_model(make_log(math.radians(-90.0), math.radians(1.0), 180), model, "x.log")
    one_line(err, "(URG-04LX)")
    assert fit_to_model(make_log(math.radians(-135.0), STEP, 768), model, "x.log", crop=True).n_beams == 682


# ------------------------------------------------------------------------------------------ live sensor


@pytest.fixture(scope="module")
def demo_model():
    from gtsjax.io.modelfile import load_model

    return load_model(DEMO_MODEL)


def test_live_check_refuses_another_step_or_a_wider_field(demo_model):
    from gtsjax.drivers.live import check_sensor

    check_sensor(demo_model, URG_04LX, "/dev/ttyACM0")  # the scanner it was trained for
    finer = dataclasses.replace(URG_04LX, ares=2048, amin=88, amax=769, afrt=768)  # same name, 0.176° steps
    with pytest.raises(InputError) as err:
        check_sensor(demo_model, finer, "/dev/ttyACM0")
    msg = str(err.value)
    assert msg.startswith("/dev/ttyACM0 (URG-04LX): angular step 0.176° differs from the model's 0.352°"), msg
    wider = dataclasses.replace(URG_04LX, amin=20, amax=700)  # 681 beams from -128°: cannot be cropped live
    with pytest.raises(InputError, match=r"field of view -128\.0° … 111\.1° is not inside the model's"):
        check_sensor(demo_model, wider, "/dev/ttyACM0")


# ------------------------------------------------------------------------------------------ commands


def run(*args):
    return run_cli(*args, timeout=300)


def one_line_exit_2(res, path, *fragments):
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"gtsjax: {path}: ") and "Traceback" not in res.stderr, lines[0]
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def real_logs(shared_file):
    for name in ("leg_tracker_positive_1.bag", "carmen_intel-corrected.log.gz"):
        shared_file("data", "logs", name)
    return shared_file("data", "logs")


@pytest.fixture()
def site(tmp_path):
    p = tmp_path / "site.json"
    p.write_text(SPL_SITE)
    return p


def test_replay_refuses_a_sick_carmen_log(real_logs, site, tmp_path):
    log, out = real_logs / "carmen_intel-corrected.log.gz", tmp_path / "gtd.csv"
    res = run("replay", log, "--site", site, "--model", DEMO_MODEL, "--out", out)
    one_line_exit_2(res, log, "angular step 1.000° differs from the model's 0.352° (URG-04LX) by more than 1 %")
    assert not out.exists() and list(tmp_path.iterdir()) == [site]


def test_replay_crops_a_270_degree_bag_only_when_asked(real_logs, site, tmp_path):
    bag, out = real_logs / "leg_tracker_positive_1.bag", tmp_path / "gtd.csv"
    res = run("replay", bag, "--site", site, "--model", DEMO_MODEL, "--out", out)
    one_line_exit_2(res, bag, "field of view -135.0° … 134.6° is not inside the model's -119.5° … 119.9° (URG-04LX)",
                    "crop it with --crop-fov")
    assert not out.exists()
    res = run("replay", bag, "--site", site, "--model", DEMO_MODEL, "--out", out, "--crop-fov")
    assert res.returncode == 0, res.stderr
    assert "cropped to the model's field of view: 682 of 768 beams (-119.5° … 119.9°), returns in [0.03, 5.6] m" \
        in " ".join(res.stderr.split())
    lines = out.read_text().splitlines()
    assert lines[0] == "stamp,track_id,class,x,y,theta,var_x,var_y,var_theta"


def test_evaluate_refuses_a_log_of_another_step(site, tmp_path):
    from gtsjax.sim import simulate

    log, _ = simulate("spl-eval", seed=1, n_scans=5)
    wide = dataclasses.replace(log, angle_min=math.radians(-90.0), angle_increment=math.radians(0.5),
                               ranges=log.ranges[:, :361].copy(), intensities=None)
    path = tmp_path / "half-degree.npz"
    save_log(wide, path)
    res = run("evaluate", "--model", DEMO_MODEL, path, "--site", site, "--out-dir", tmp_path / "eval")
    one_line_exit_2(res, path, "angular step 0.500° differs from the model's 0.352° (URG-04LX)")
    assert not (tmp_path / "eval").exists()


def _reading_intensities(model):
    """``model`` as if trained on scans with intensities: its GPs' columns include the intensity profile
    (eq. 12's cells follow the distance profile's in the characteristic vector)."""
    first = 1 + model.frontend.n_dist
    return dataclasses.replace(model, gp_columns=tuple(sorted({*model.gp_columns, first, first + 1})))


def test_a_model_reading_intensities_refuses_inputs_without_them(demo_model):
    """Issue 17: a model whose GPs read the intensity profile refuses, in one line, a log without
    intensities and a live sensor that gives none (or a stream asked for without them); the shipped
    URG-04LX model reads none and takes both."""
    from gtsjax.drivers.live import check_sensor

    assert not demo_model.uses_intensity  # trained on a scanner without intensity
    needy = _reading_intensities(demo_model)
    assert needy.uses_intensity
    rng = np.random.default_rng(3)
    ranges = rng.uniform(0.5, 4.0, (2, URG_04LX.n_beams)).astype(np.float32)
    bare = ScanLog(ranges=ranges, stamps=np.arange(2.0), angle_min=URG_04LX.angle_min,
                   angle_increment=URG_04LX.angle_increment, sensor_model="URG-04LX")
    fit_to_model(bare, demo_model, "bare.npz")
    with pytest.raises(InputError, match=r"^bare\.npz: has no intensities, but the model was trained on scans with"):
        fit_to_model(bare, needy, "bare.npz")
    fit_to_model(dataclasses.replace(bare, intensities=np.ones_like(ranges)), needy, "with.npz")
    check_sensor(demo_model, URG_04LX, "/dev/ttyACM0")
    with pytest.raises(InputError, match=r"^/dev/ttyACM0 \(URG-04LX\): has no intensities"):
        check_sensor(needy, URG_04LX, "/dev/ttyACM0")  # a URG-04LX reports none
    bright = dataclasses.replace(URG_04LX, has_intensity=True)
    check_sensor(needy, bright, "/dev/ttyACM0")
    with pytest.raises(InputError, match="has no intensities"):
        check_sensor(needy, bright, "/dev/ttyACM0", intensity=False)  # run --no-intensity


def test_train_drops_intensities_a_scanner_cannot_have(tmp_path):
    """Issue 17: ``train`` on a URG-04LX log that carries intensities (a converter filled them in)
    warns in one line and trains without them, so the model runs on a real URG-04LX stream."""
    import warnings

    from gtsjax import InputWarning
    from gtsjax.sim import simulate
    from gtsjax.train import TrainConfig, train

    log, site = simulate("spl-train", seed=11, n_scans=200)
    assert log.sensor_model == "URG-04LX" and log.intensities is None
    lit = dataclasses.replace(log, intensities=np.random.default_rng(4).uniform(0, 1, log.ranges.shape).astype(np.float32))
    config = dataclasses.replace(TrainConfig(), max_per_class=40, max_pose_examples=50, n_inducing=16, restarts=1,
                                 check_pipeline=False)  # a model to run; training's tracking check is tested apart
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model, _ = train([lit], site, config, names=["lit.npz"])
    said = [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    assert said == ["lit.npz: carries intensities, but a URG-04LX reports none: trained without them"]
    assert not model.uses_intensity
