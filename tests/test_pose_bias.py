"""Each class's mean pose error in its own frame (issue 55, lever 5), measured by training's tracking
check on held-out detections (``train.check.frame_error``) and listed with its evidence
(``train.calibrate.pose_bias``). Checked against complex arithmetic and plain means."""

import math

import numpy as np

from gtsjax.train.calibrate import MIN_BIAS_DETECTIONS, pose_bias
from gtsjax.train.check import frame_error


def _complex_error(est, truth):
    """``est − truth`` in the truth's frame, as complex numbers: (z_e − z_t)·e^{−iθ_t}."""
    d = (complex(est[0], est[1]) - complex(truth[0], truth[1])) * np.exp(-1j * truth[2])
    return d.real, d.imag, math.remainder(est[2] - truth[2], 2 * math.pi)


def test_frame_error_is_the_error_in_the_objects_own_frame():
    rng = np.random.default_rng(3)
    for _ in range(50):
        truth = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)])
        est = truth + np.array([*rng.normal(0, 0.05, 2), rng.normal(0, 0.1)])
        np.testing.assert_allclose(frame_error(est, truth, 1), _complex_error(est, truth), atol=1e-12)
        # an object alike turned half a turn, read on its other side: the error is to the turned truth
        flipped = est + np.array([0.0, 0.0, math.pi])
        turned = truth + np.array([0.0, 0.0, math.pi])
        np.testing.assert_allclose(frame_error(flipped, truth, 2), _complex_error(flipped, turned), atol=1e-12)


def test_pose_bias_is_the_mean_of_the_right_side_detections():
    rng = np.random.default_rng(4)
    want = np.array([-0.002, 0.001, math.radians(0.3)])
    good = want + rng.normal(0, [0.005, 0.005, math.radians(1.0)], (200, 3))
    wrong = np.array([[0.01, 0.0, math.radians(120.0)], [0.0, 0.02, math.radians(-90.0)]])  # misread sides
    rows, warnings = pose_bias({"robot": np.concatenate([good, wrong])})
    assert not warnings
    assert [r["parameter"] for r in rows] == ["pose bias ahead", "pose bias left", "pose bias heading"]
    assert all(r["source"] == "measured" and r["class"] == "robot" for r in rows)
    mean = good.mean(axis=0)
    se = good.std(axis=0, ddof=1) / np.sqrt(len(good))
    np.testing.assert_allclose([r["value"] for r in rows], [1e3 * mean[0], 1e3 * mean[1], math.degrees(mean[2])],
                               atol=0.006)
    assert "200 held-out detections" in rows[0]["evidence"] and f"{1e3 * se[0]:.2g} mm" in rows[0]["evidence"]


def test_pose_bias_needs_detections_and_warns_past_its_bounds():
    assert pose_bias({"robot": np.full((MIN_BIAS_DETECTIONS - 1, 3), 0.001)}) == ([], [])
    far = np.tile([0.08, 0.0, 0.0], (100, 1))  # 8 cm ahead: the labels or the site, not an outline
    rows, warnings = pose_bias({"robot": far})
    assert len(warnings) == 1 and "+80 mm ahead" in warnings[0] and "check the labels" in warnings[0]
    assert rows[0]["value"] == 80.0
