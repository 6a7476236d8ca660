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
from ..core.geometry import compose, relative, wrap
from ..drivers.evaluation import CHI2_95, heading_error

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
        err = _right_side(err)
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


# The rows' variance floor is learnt from this many held-out rows (consecutive rows are alike: a few
# seconds of a robot's track); past these bounds the rows err by
# more than a ground truth may (a misread side in more than one row of twenty, or a wrong outline):
# training warns and the floor stops there.
MIN_FLOOR_ROWS = 100
FLOOR_RANGE_MM = 30.0
FLOOR_RANGE_DEG = 5.0
COVERAGE = 0.95


def _with_offset(e: np.ndarray, offset: "np.ndarray | None") -> np.ndarray:
    """Rows' errors ``e`` [n, 8] (:func:`~gtsjax.train.check.row_errors`) as they are once the class's
    ``offset`` (ahead, left, heading) is taken off the rows as ``TrackerParams.off`` takes it: each row
    (its position relative to the truth's, its heading) composed with the offset's inverse."""
    if offset is None or not np.any(offset):
        return e
    row = np.column_stack([e[:, :2], e[:, 7] + e[:, 2]])
    back = compose(row, relative(np.asarray(offset, np.float64), np.zeros(3)))
    e = e.copy()
    e[:, :2], e[:, 2] = back[:, :2], wrap(back[:, 2] - e[:, 7])
    return e


def _right_side(err: np.ndarray) -> np.ndarray:
    """The rows of ``err`` (heading error, rad, in column 2) within :data:`WRONG_SIDE_DEG`: a side read
    wrong is a misread, counted apart, never part of a bias or a spread."""
    return err[np.abs(np.degrees(err[:, 2])) <= WRONG_SIDE_DEG]


def needed_floors(e: np.ndarray) -> np.ndarray:
    """Per row of ``e`` [n, 8], the least variance (position m² added to var_x and var_y, heading rad²)
    that puts its error inside its 95 % ellipse (χ²₂) and interval (χ²₁): ``[n, 2]``, 0 where it is
    inside already. Position: the root of ``dᵀ(Σ + fI)⁻¹d = k``, a quadratic in ``f``."""
    dx, dy, eth, vx, vy, cxy, vth, _ = e.T
    k = CHI2_95[2]
    b = k * (vx + vy) - (dx**2 + dy**2)
    c = k * (vx * vy - cxy**2) - (vy * dx**2 - 2 * cxy * dx * dy + vx * dy**2)
    pos = np.where(c < 0, (-b + np.sqrt(np.maximum(b**2 - 4 * k * c, 0.0))) / (2 * k), 0.0)
    head = np.maximum(eth**2 / CHI2_95[1] - vth, 0.0)
    return np.column_stack([pos, head])


def within_95(e: np.ndarray, floor=(0.0, 0.0)) -> tuple[float, float]:
    """The shares of rows ``e`` [n, 8] whose position error lies inside the 95 % ellipse and heading
    error inside the 95 % interval of their variances with ``floor`` (position, heading) added."""
    need = needed_floors(e)
    return float(np.mean(need[:, 0] <= floor[0])), float(np.mean(need[:, 1] <= floor[1]))


def _detection_variance(err: "np.ndarray | None") -> np.ndarray:
    """The variance of one detection's error (position: the mean of ahead's and left's; heading) from
    errors ``[n, 3]`` in the object's own frame, right side only; unbounded without
    :data:`MIN_BIAS_DETECTIONS` of them."""
    if err is None:
        return np.array([np.inf, np.inf])
    err = np.asarray(err, np.float64).reshape(-1, 3)
    err = _right_side(err)
    if len(err) < MIN_BIAS_DETECTIONS:
        return np.array([np.inf, np.inf])
    v = err.var(axis=0, ddof=1)
    return np.array([(v[0] + v[1]) / 2, v[2]])


def variance_floor(rows: "dict[str, np.ndarray]", classes: "tuple[str, ...]", offsets: "np.ndarray | None" = None,
                   detections: "dict[str, np.ndarray] | None" = None
                   ) -> "tuple[np.ndarray | None, list[dict], list[str]]":
    """Each tracked class's variance floor of the reported rows, from the tracking check's rows of the
    labelled logs' held-out scans (``rows``: per class ``[n, 8]``, :func:`~gtsjax.train.check.row_errors`;
    taken as they are once ``offsets``, :func:`pose_bias`'s, come off): the least position and heading
    variance which, added to every row's, puts 95 % of those rows' errors inside their 95 % ellipse and
    interval (the 95th percentile of each row's :func:`needed_floors`; rows more than 30° off, a misread
    side, left out), and no more than the variance of one detection's error (``detections``: per class
    ``[n, 3]`` errors in its own frame, :func:`pose_bias`'s; right side only): a row averages detections,
    so it may be as wrong as one of them, not more, and where the check's rows err by more, that is the
    recording's habit (a robot turned or carried by hand between scans) the rows of a real run do not
    share. Returns the ``[classes, 2]`` floors (``TrackerParams.var_floor``; None if no class has one), rows of the learnt-parameter table
    (as standard deviations, with the rows' coverage before and after) and a warning per class whose
    floor passes the sanity bounds (then held at them).

    Why: the tracker's variance is that of noise averaged over scans, and shrinks scan after scan; a
    robot's error on a new scene is mostly its view's bias, the same every scan (docs/accuracy.md),
    so the rows' ellipses became too sure. A floor added to every row's variance stands for that bias.
    Only the position's is added: on the held-out scenes of ``tests/test_recordings.py``'s recordings
    the position ellipses held 62–97 % of the errors, the heading intervals 93–100 %, and a heading
    floor learnt from a recording's rows (a robot carried and turned by hand between poses) made them
    several times too wide there (NEES 0.1). The heading's is listed, as measured."""
    floors = np.zeros((len(classes), 2), np.float32)
    table, warnings, any_set = [], [], False
    for name, e in rows.items():
        e = np.asarray(e, np.float64).reshape(-1, 8)
        e = e[np.all(np.isfinite(e), axis=1)]
        if len(e) < MIN_FLOOR_ROWS:
            continue
        c = classes.index(name)
        e = _with_offset(e, None if offsets is None else np.asarray(offsets[c], np.float64))
        # A row read on the wrong side is a misread no error bar should cover (evaluate counts those
        # apart, "reads more than 30° off"): a floor wide enough for it would make every other row's
        # ellipse useless.
        e = _right_side(e)
        if len(e) < MIN_FLOOR_ROWS:
            continue
        need = needed_floors(e)
        want = np.quantile(need, COVERAGE, axis=0, method="higher")
        bound = np.array([(FLOOR_RANGE_MM / 1e3) ** 2, math.radians(FLOOR_RANGE_DEG) ** 2])
        cap = _detection_variance(None if detections is None else detections.get(name))
        floor = np.minimum(np.minimum(want, bound), cap)
        floor[1] = 0.0  # the heading's measured and listed, not widened (see the docstring)
        before, after = within_95(e), within_95(e, floor)
        if want[0] > bound[0]:
            warnings.append(f"{name}: its rows' positions on the held-out scans err by more than their variances "
                            f"and {FLOOR_RANGE_MM:.0f} mm more would cover (needed {1e3 * math.sqrt(want[0]):.0f} mm): "
                            f"a wrong outline or labels; the rows' error bars stop there and hold "
                            f"{100 * after[0]:.0f} % of its position errors")
        floors[c] = floor
        any_set = any_set or bool(np.any(floor > 0))
        for j, (part, unit, scale, bound_u, share) in enumerate((
                ("position", "mm", 1e3, FLOOR_RANGE_MM, "ellipse"), ("heading", "°", math.degrees(1.0), FLOOR_RANGE_DEG,
                                                                    "interval"))):
            applied = j == 0
            table.append({"class": name, "parameter": f"row {part} sd floor", "unit": unit,
                          "value": round(float(math.sqrt(floor[j] if applied else min(want[j], bound[j]))) * scale,
                                         3 if unit == "°" else 2),
                          "source": "learnt" if applied else "measured",
                          "evidence": (f"added to the variance of every row: {len(e)} held-out rows (right side only), "
                                       f"{100 * before[j]:.1f} % inside their 95 % {share} before, "
                                       f"{100 * after[j]:.1f} % after"
                                       + (f" (held at one detection's error, {scale * math.sqrt(cap[j]):.3g} {unit})"
                                          if want[j] > cap[j] and cap[j] < bound[j] else ""))
                          if applied else
                          (f"what {len(e)} held-out rows (right side only) would need: {100 * before[j]:.1f} % inside "
                           f"their 95 % {share}; not added (the heading's intervals held 93–100 % on held-out scenes, "
                           "docs/accuracy.md)"),
                          "hard_range": [0.0, bound_u], "plausible": [0.0, bound_u]})
    return (floors if any_set else None), table, warnings
