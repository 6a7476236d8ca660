"""Calibration of the pose GPs' variances (stage e), training only, on the host in float64.

The GPs' predictive variances (eq. 7, noise included) become the tracker's measurement noise (stage
g); :func:`calibrate` scales them so that held-out errors are those of a calibrated Gaussian, gross
misreads aside (:func:`robust_variance_scale`), and sets the largest heading variance the tracker
trusts (``PoseRegressor.heading_var_max``). The step only applies what is stored here
(:func:`gtsjax.core.e_pose.regress_one_class`, :func:`gtsjax.core.e_pose.vague_headings`).
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.e_pose import MAX_THETA_VAR, PoseRegressor, regress_one_class
from ..drivers.evaluation import heading_error

# Median of χ² with one degree of freedom, and its 0.999 quantile: the tracker's heading gate.
_CHI2_1_MEDIAN = 0.45493642311957283
_CHI2_1_GATE = 10.827566170662733


def _trimmed_chi2_mean(gate: float) -> float:
    """``E[z² | z² < gate]`` for a standard normal ``z``."""
    a = math.sqrt(gate)
    tail = math.erfc(a / math.sqrt(2))  # P(|z| > a)
    phi = math.exp(-0.5 * gate) / math.sqrt(2 * math.pi)
    return (1.0 - 2 * a * phi - tail) / (1.0 - tail)


def robust_variance_scale(z2, iterations: int = 10) -> float:
    """The factor ``s`` by which variances must grow so that normalised squared errors ``z2`` are
    those of a calibrated Gaussian, outliers aside: starting from the median, repeatedly take as
    inliers the errors inside the 0.999 gate (``z2 / s < 10.83``, the tracker's heading gate) and set
    ``s`` so that their mean is that of a Gaussian truncated at the gate. A plain median is biased
    by contamination (10 % of misreads raise it by a quarter); this is not, while the outliers lie
    beyond the gate."""
    z2 = np.asarray(z2, np.float64)
    s = float(np.median(z2) / _CHI2_1_MEDIAN)
    m = _trimmed_chi2_mean(_CHI2_1_GATE)
    for _ in range(iterations):
        inl = z2 < _CHI2_1_GATE * s
        s = float(np.mean(z2[inl]) / m)
    return s


def calibrate(reg: PoseRegressor, vectors, target, *, good_deg: float = 15.0,
              vague_quantile: float = 0.99) -> PoseRegressor:
    """Scale the variances of a class's pose GPs so that, on held-out examples, the normalised
    squared errors of ``x̃``, ``ỹ`` and ``θ̃`` are those of a calibrated Gaussian, gross misreads aside
    (:func:`robust_variance_scale`).

    Why: the pose GPs' noise is homoscedastic, so the rare scan that sees a side of the robot as
    another (a heading off by 90° or more) inflates the noise estimate, and with it the variance of
    every prediction: typical headings, good to 2°, came with a σ of 25°. The tracker weighs and gates
    measurements by these variances; calibrated, typical errors get their true size and the misreads
    fall outside the heading gate. ``target`` [n, 3] holds the held-out ``(x̃, ỹ, θ̃)`` (θ̃ NaN for a
    class without heading).

    Also sets ``heading_var_max``: the ``vague_quantile`` (99 %) of the calibrated heading variances
    of the held-out examples read within ``good_deg`` (15°) of their heading. The rare read above it
    is far more often a misread than not (on the SPL field, simulated: 91 of 175 misreads and 34 of
    3 211 good reads have a σ above its 5°), and the tracker takes only its position: a misread with a
    large variance passes a heading gate widened by a few missed scans, and took the track with it."""
    rel, var = regress_one_class(eqx.tree_at(lambda r: r.var_scale, reg, None, is_leaf=lambda v: v is None),
                                 jnp.asarray(vectors, jnp.float32))
    rel, var, target = np.asarray(rel, np.float64), np.asarray(var, np.float64), np.asarray(target, np.float64)
    err = rel - target
    err[:, 2] = heading_error(err[:, 2], 1 if reg.turns is None else int(reg.turns))  # modulo 2π/turns
    scale = np.ones(3)
    for j in range(3 if reg.has_heading else 2):
        ok = np.isfinite(err[:, j]) & (var[:, j] > 0)
        if ok.sum() >= 10:
            scale[j] = robust_variance_scale(err[ok, j] ** 2 / var[ok, j])
    var_max = None
    if reg.has_heading:
        vt = np.minimum(var[:, 2] * scale[2], MAX_THETA_VAR)
        good = np.isfinite(err[:, 2]) & (np.abs(err[:, 2]) <= np.radians(good_deg))
        if good.sum() >= 20:
            var_max = jnp.asarray(np.quantile(vt[good], vague_quantile), jnp.float32)
    return eqx.tree_at(lambda r: (r.var_scale, r.heading_var_max), reg, (jnp.asarray(scale, jnp.float32), var_max),
                       is_leaf=lambda v: v is None)


# A class's mean pose error is learnt from this many held-out detections read on the right side; past
# these bounds it says the labels or the site are wrong, not the outline (the shipped model's is about
# 2 mm, docs/accuracy.md): training warns and takes nothing off.
MIN_BIAS_DETECTIONS = 30
BIAS_RANGE_M = 0.03
BIAS_RANGE_DEG = 3.0
WRONG_SIDE_DEG = 30.0


def pose_bias(errors: "dict[str, np.ndarray]", classes: "tuple[str, ...]"
              ) -> "tuple[np.ndarray | None, list[dict], list[str]]":
    """Each tracked class's mean pose error in its own frame (ahead, left, heading) on the tracking
    check's detections of the labelled logs' held-out scans (``errors``: per class ``[n, 3]``,
    :func:`~gtsjax.train.check.detection_errors`; those more than 30° off, a misread side, left out).
    Returns the ``[classes, 3]`` offsets the tracker takes off its rows
    (``TrackerParams.pose_offset``; None if no class has one), rows of the learnt-parameter table
    (with the detections and the standard error; from :data:`MIN_BIAS_DETECTIONS` on), and a warning
    per class whose mean lies past the sanity bounds (then not taken off).

    Why: the learnt outline is not quite the robot's (learnt from labelled poses that carry the map
    transformation's errors, it comes out smaller) and every view's refined pose carries part of that
    mismatch the same way: the same millimetres on every held-out scene, what no filter removes and
    every clock ``grade`` estimates inherits. The view-dependent rest is not a function of where the
    laser stands (``scripts/view_bias.py``) and is left alone."""
    offsets = np.zeros((len(classes), 3), np.float32)
    rows, warnings, any_set = [], [], False
    for name, err in errors.items():
        err = np.asarray(err, np.float64).reshape(-1, 3)
        err = err[np.abs(np.degrees(err[:, 2])) <= WRONG_SIDE_DEG]
        n = len(err)
        if n < MIN_BIAS_DETECTIONS:
            continue
        mean = err.mean(axis=0)
        se = err.std(axis=0, ddof=1) / np.sqrt(n)
        inside = (abs(mean[0]) <= BIAS_RANGE_M and abs(mean[1]) <= BIAS_RANGE_M
                  and abs(math.degrees(mean[2])) <= BIAS_RANGE_DEG)
        if inside:
            offsets[classes.index(name)] = mean
            any_set = True
        else:
            warnings.append(f"{name}: its detections on the held-out scans are off by {1e3 * mean[0]:+.0f} mm ahead, "
                            f"{1e3 * mean[1]:+.0f} mm left and {math.degrees(mean[2]):+.1f}° on average, past what an "
                            "outline explains: check the labels' poses and the site; not taken off")
        for j, (part, unit, scale, bound) in enumerate((("ahead", "mm", 1e3, 1e3 * BIAS_RANGE_M),
                                                        ("left", "mm", 1e3, 1e3 * BIAS_RANGE_M),
                                                        ("heading", "°", math.degrees(1.0), BIAS_RANGE_DEG))):
            rows.append({"class": name, "parameter": f"pose bias {part}", "unit": unit,
                         "value": round(float(mean[j]) * scale, 3 if unit == "°" else 2),
                         "source": "learnt" if inside else "measured",
                         "evidence": f"mean error of {n} held-out detections in its own frame (right side only), "
                                     f"standard error {scale * se[j]:.2g} {unit}; "
                                     + ("taken off the rows" if inside else "not taken off"),
                         "hard_range": None, "plausible": [-bound, bound]})
    return (offsets if any_set else None), rows, warnings
