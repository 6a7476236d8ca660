"""Each class's mean pose error in its own frame (issue 55, lever 5): measured by training's tracking
check on held-out detections (``train.check.frame_error``), learnt within bounds and listed with its
evidence (``train.calibrate.pose_bias``), taken off the tracks' rows (``TrackerParams.off``; in the
step against the reference in ``tests/test_reference.py``). Checked against complex arithmetic and
plain means."""

import math

import jax.numpy as jnp
import numpy as np

from gtsjax.core.g_types import TrackerParams
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
    offsets, rows, warnings = pose_bias({"robot": np.concatenate([good, wrong])}, ("post", "robot"))
    assert not warnings
    np.testing.assert_allclose(offsets[1], good.mean(axis=0), rtol=1e-5)
    assert np.all(offsets[0] == 0)
    assert [r["parameter"] for r in rows] == ["pose bias ahead", "pose bias left", "pose bias heading"]
    assert all(r["source"] == "learnt" and r["class"] == "robot" for r in rows)
    mean = good.mean(axis=0)
    se = good.std(axis=0, ddof=1) / np.sqrt(len(good))
    np.testing.assert_allclose([r["value"] for r in rows], [1e3 * mean[0], 1e3 * mean[1], math.degrees(mean[2])],
                               atol=0.006)
    assert "200 held-out detections" in rows[0]["evidence"] and f"{1e3 * se[0]:.2g} mm" in rows[0]["evidence"]


def test_pose_bias_needs_detections_and_takes_nothing_off_past_its_bounds():
    assert pose_bias({"robot": np.full((MIN_BIAS_DETECTIONS - 1, 3), 0.001)}, ("robot",)) == (None, [], [])
    far = np.tile([0.08, 0.0, 0.0], (100, 1))  # 8 cm ahead: the labels or the site, not an outline
    offsets, rows, warnings = pose_bias({"robot": far}, ("robot",))
    assert offsets is None and len(warnings) == 1 and "+80 mm ahead" in warnings[0] and "check the labels" in warnings[0]
    assert rows[0]["value"] == 80.0 and rows[0]["source"] == "measured" and "not taken off" in rows[0]["evidence"]


def test_off_undoes_an_error_made_in_the_objects_frame():
    """Poses made by adding a known error in the object's own frame to the truth come back to it,
    per class (a class without an offset untouched); without offsets nothing moves."""
    rng = np.random.default_rng(5)
    offset = np.array([[0.0, 0.0, 0.0], [0.02, -0.01, math.radians(4.0)]], np.float32)
    params = TrackerParams.default([False, True])
    cls = np.array([1, 0, 1, 1, 1])
    truth = np.stack([rng.uniform(-3, 3, 5), rng.uniform(-3, 3, 5), rng.uniform(-math.pi, math.pi, 5)], 1)

    def made(p, o):  # the error added: position along the true heading's axes, then the heading
        z = complex(p[0], p[1]) + complex(o[0], o[1]) * np.exp(1j * p[2])
        return np.array([z.real, z.imag, math.remainder(p[2] + o[2], 2 * math.pi)])

    est = np.stack([made(truth[i], offset[c]) for i, c in enumerate(cls)]).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(params.off(jnp.asarray(cls), jnp.asarray(est))), est)
    shifted = TrackerParams(**{**vars(params), "pose_offset": jnp.asarray(offset)})
    back = np.asarray(shifted.off(jnp.asarray(cls), jnp.asarray(est)))
    np.testing.assert_allclose(back[:, :2], truth[:, :2], atol=2e-6)
    np.testing.assert_allclose(np.remainder(back[:, 2] - truth[:, 2] + math.pi, 2 * math.pi) - math.pi, 0, atol=2e-6)


def test_a_model_file_keeps_the_offset_and_refuses_one_of_the_wrong_shape(tmp_path):
    """The offset is an optional leaf of the model file: kept to the bit, loaded as absent from a file
    without it, and a leaf that does not fit the classes is named."""
    import equinox as eqx
    import pytest

    from gtsjax.cli.demo import demo_model_path
    from gtsjax.errors import InputError
    from gtsjax.io.modelfile import load_model, save_model

    model = load_model(demo_model_path())
    without = eqx.tree_at(lambda m: m.tracker.pose_offset, model, None, is_leaf=lambda x: x is None)
    save_model(without, tmp_path / "none.npz")
    assert load_model(tmp_path / "none.npz").tracker.pose_offset is None
    offset = np.arange(3 * len(model.classes), dtype=np.float32).reshape(-1, 3) * 1e-3
    for leaf, path in ((offset, tmp_path / "m.npz"), (np.zeros((len(model.classes) + 2, 3), np.float32), tmp_path / "bad.npz")):
        save_model(eqx.tree_at(lambda m: m.tracker.pose_offset, without, jnp.asarray(leaf), is_leaf=lambda x: x is None), path)
    np.testing.assert_array_equal(np.asarray(load_model(tmp_path / "m.npz").tracker.pose_offset), offset)
    with pytest.raises(InputError, match="tracker.pose_offset has shape"):
        load_model(tmp_path / "bad.npz")
