"""Stage e, pose regression (eq. 15–17): per class, GPs for the object's position ``(x̃, ỹ)`` in the
candidate's object reference system and, for mobile classes, its heading as ``(sin θ̃, cos θ̃)``.

The paper regresses θ̃ directly, which breaks at ±π; regressing the sine and cosine and taking
``atan2`` does not (READING-NOTES). Landmark classes get position regressors too: the centre of a
post lies behind the surface the laser sees, and the map transformation is better fed with centres.

The GPs' predictive variances (noise included) become the measurement noise of the tracker:
position variances rotated from ORS into S, heading variance propagated through ``atan2``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._buckets import bucketed
from ._geometry import compose, wrap
from .gp import GP, SparseGP

# Heading variance is capped where the sine and cosine predictions carry no information.
_MAX_THETA_VAR = float(jnp.pi**2 / 3)


class PoseRegressor(eqx.Module):
    """GPs of one class: ``x``, ``y`` (ORS-relative position) and, if the class has a heading, ``sin``, ``cos``.

    ``var_scale`` multiplies the predictive variances of ``(x̃, ỹ, θ̃)`` (see :func:`calibrate`).
    ``heading_var_max``: the largest (calibrated) heading variance of a read the tracker trusts for the
    heading; a candidate above it is *vague* and updates a track's position only (see :func:`calibrate`;
    ``None``: every heading is used)."""

    x: SparseGP | GP
    y: SparseGP | GP
    sin: SparseGP | GP | None = None
    cos: SparseGP | GP | None = None
    var_scale: Float[Array, "3"] | None = None
    heading_var_max: Float[Array, ""] | None = None


def _predict(gp, v):
    mean, var = gp.predict(v, include_noise=True)
    return mean.astype(v.dtype), var.astype(v.dtype)


def regress_one_class(
    reg: PoseRegressor, vectors: Float[Array, "cands features"]
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3"]]:
    """ORS-relative pose ``(x̃, ỹ, θ̃)`` and its variances for every candidate under one class's GPs
    (eq. 15). A class without heading GPs reports θ̃ = 0 with zero variance."""
    mx, vx = _predict(reg.x, vectors)
    my, vy = _predict(reg.y, vectors)
    if reg.sin is None or reg.cos is None:
        zero = jnp.zeros_like(mx)
        return jnp.stack([mx, my, zero], -1), jnp.stack([vx, vy, zero], -1)
    ms, vs = _predict(reg.sin, vectors)
    mc, vc = _predict(reg.cos, vectors)
    theta = jnp.arctan2(ms, mc)
    # dθ = (c ds − s dc) / (s² + c²): first-order propagation of the two predictive variances.
    r2 = ms**2 + mc**2
    r2_safe = jnp.where(r2 > 1e-6, r2, 1.0)
    vt = jnp.where(r2 > 1e-6, (mc**2 * vs + ms**2 * vc) / r2_safe**2, _MAX_THETA_VAR)
    var = jnp.stack([vx, vy, vt], -1)
    if reg.var_scale is not None:
        var = var * reg.var_scale.astype(var.dtype)[None, :]
    cap = jnp.asarray([jnp.inf, jnp.inf, _MAX_THETA_VAR], var.dtype)
    return jnp.stack([mx, my, theta], -1), jnp.minimum(var, cap[None, :])


# Median of χ² with one degree of freedom, and its 0.999 quantile: the tracker's heading gate.
_CHI2_1_MEDIAN = 0.45493642311957283
_CHI2_1_GATE = 10.827566170662733


def _trimmed_chi2_mean(gate: float) -> float:
    """``E[z² | z² < gate]`` for a standard normal ``z``."""
    import math

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
    import numpy as np

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
    import numpy as np

    rel, var = regress_one_class(eqx.tree_at(lambda r: r.var_scale, reg, None, is_leaf=lambda v: v is None),
                                 jnp.asarray(vectors, jnp.float32))
    rel, var, target = np.asarray(rel, np.float64), np.asarray(var, np.float64), np.asarray(target, np.float64)
    err = rel - target
    err[:, 2] = wrap(err[:, 2])
    scale = np.ones(3)
    for j in range(3 if reg.sin is not None else 2):
        ok = np.isfinite(err[:, j]) & (var[:, j] > 0)
        if ok.sum() >= 10:
            scale[j] = robust_variance_scale(err[ok, j] ** 2 / var[ok, j])
    var_max = None
    if reg.sin is not None:
        vt = np.minimum(var[:, 2] * scale[2], _MAX_THETA_VAR)
        good = np.isfinite(err[:, 2]) & (np.abs(err[:, 2]) <= np.radians(good_deg))
        if good.sum() >= 20:
            var_max = jnp.asarray(np.quantile(vt[good], vague_quantile), jnp.float32)
    return eqx.tree_at(lambda r: (r.var_scale, r.heading_var_max), reg, (jnp.asarray(scale, jnp.float32), var_max),
                       is_leaf=lambda v: v is None)


def vague_headings(regressors: "tuple[PoseRegressor | None, ...]", cls: Int[Array, " cands"],
                   var: Float[Array, "cands 3"]) -> Bool[Array, " cands"]:
    """Candidates whose heading variance exceeds their class's ``heading_var_max`` (never, for a class
    without one)."""
    vmax = jnp.stack([jnp.asarray(jnp.inf if r is None or r.heading_var_max is None else r.heading_var_max,
                                  var.dtype) for r in regressors])
    return var[:, 2] > vmax[cls]


def _top(sel: Bool[Array, " cands"], score: Float[Array, " cands"], k: int) -> tuple[Int[Array, " k"], Bool[Array, " k"]]:
    """Indices of the ``k`` selected candidates with the highest scores, and which of them are selected."""
    _, idx = jax.lax.top_k(jnp.where(sel, score, -jnp.inf), k)
    return idx, sel[idx]


def regress(
    regressors: tuple[PoseRegressor | None, ...],
    vectors: Float[Array, "cands features"],
    cls: Int[Array, " cands"],
    ok: Bool[Array, " cands"],
    scores: Float[Array, "cands classes"],
    max_objects: int,
    max_landmarks: int,
    bucket: bool = True,
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3"], Bool[Array, " cands"]]:
    """Each kept candidate's ORS-relative pose and variances under the regressors of its own class,
    and which candidates got one.

    Fixed shapes, and no GP runs on a candidate that cannot use it: per class, the candidates of the
    class with the highest class scores are gathered (``top_k``), regressed and scattered back; the
    ``max_objects`` best of a mobile class get the mean and variance GPs, the ``max_landmarks`` best
    of a landmark class the position means only (stage f reads no variance). With ``bucket`` each
    runs at the smallest of a few fixed sizes that holds the candidates present
    (:func:`~gtsjax._buckets.bucketed`: a scan with one robot pays for one, not eight); leave it off
    under ``vmap``, which turns the branches into selects that all run. A candidate beyond its
    class's cap gets no pose and must be dropped (the third output is False for it). Background and
    unkept candidates give zeros."""
    n = vectors.shape[0]
    run = bucketed if bucket else (lambda fn, v, _n, _w: tuple(fn(v)))
    rel = jnp.zeros((n, 3), vectors.dtype)
    var = jnp.zeros_like(rel)
    posed = jnp.zeros((n,), bool)
    for k, reg in enumerate(regressors):
        if reg is None:
            continue
        sel = ok & (cls == k)
        if reg.sin is None or reg.cos is None:
            idx, chosen = _top(sel, scores[:, k], min(max_landmarks, n))

            def means(v, reg=reg):
                mx = reg.x.predict_mean(v).astype(vectors.dtype)
                my = reg.y.predict_mean(v).astype(vectors.dtype)
                return (jnp.stack([mx, my, jnp.zeros_like(mx)], -1),)

            (r,) = run(means, vectors[idx], jnp.sum(chosen), 3)
            rel = rel.at[idx].set(jnp.where(chosen[:, None], r, rel[idx]))
        else:
            idx, chosen = _top(sel, scores[:, k], min(max_objects, n))
            r, v = run(lambda v, reg=reg: regress_one_class(reg, v), vectors[idx], jnp.sum(chosen), 3)
            rel = rel.at[idx].set(jnp.where(chosen[:, None], r, rel[idx]))
            var = var.at[idx].set(jnp.where(chosen[:, None], v, var[idx]))
        posed = posed.at[idx].max(chosen)
    return rel, var, posed


def to_sensor_frame(
    origin: Float[Array, "cands 2"],
    heading: Float[Array, " cands"],
    rel: Float[Array, "cands 3"],
    var: Float[Array, "cands 3"],
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3 3"]]:
    """From each candidate's ORS to S: ``p = o′ + Rot(θ_j)(x̃, ỹ)``, heading ``θ_j + θ̃`` (eq. 16 with
    the ORS in place of O), and the covariance ``Rot diag(vx, vy) Rotᵀ`` ⊕ ``vθ``."""
    pose = compose(jnp.concatenate([origin, heading[:, None]], -1), rel)
    c, s = jnp.cos(heading), jnp.sin(heading)
    cxx = c**2 * var[:, 0] + s**2 * var[:, 1]
    cyy = s**2 * var[:, 0] + c**2 * var[:, 1]
    cxy = c * s * (var[:, 0] - var[:, 1])
    zero = jnp.zeros_like(cxx)
    cov = jnp.stack([
        jnp.stack([cxx, cxy, zero], -1),
        jnp.stack([cxy, cyy, zero], -1),
        jnp.stack([zero, zero, var[:, 2]], -1),
    ], -2)
    return pose, cov
