"""Stage e, pose regression (eq. 15–17): per class, GPs for the object's position ``(x̃, ỹ)`` in the
candidate's object reference system and, for mobile classes, its heading as ``(sin θ̃, cos θ̃)``.

The paper regresses θ̃ directly, which breaks at ±π; regressing the sine and cosine and taking
``atan2`` does not (READING-NOTES). Landmark classes get position regressors too: the centre of a
post lies behind the surface the laser sees, and the map transformation is better fed with centres.

The GPs' predictive variances (noise included) become the measurement noise of the tracker:
position variances rotated from ORS into S, heading variance propagated through ``atan2``.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ._gp import GP, SparseGP

# Heading variance is capped where the sine and cosine predictions carry no information.
_MAX_THETA_VAR = float(jnp.pi**2 / 3)


class PoseRegressor(eqx.Module):
    """GPs of one class: ``x``, ``y`` (ORS-relative position) and, if the class has a heading, ``sin``, ``cos``."""

    x: SparseGP | GP
    y: SparseGP | GP
    sin: SparseGP | GP | None = None
    cos: SparseGP | GP | None = None


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
    vt = jnp.minimum(vt, _MAX_THETA_VAR)
    return jnp.stack([mx, my, theta], -1), jnp.stack([vx, vy, vt], -1)


def regress(
    regressors: tuple[PoseRegressor | None, ...], vectors: Float[Array, "cands features"], cls: Int[Array, " cands"]
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3"]]:
    """Each candidate's ORS-relative pose and variances under the regressors of its own class. Every
    class's GPs run on every candidate (fixed shapes); the class picks the row. A class without
    regressors (background) gives zeros."""
    rel = jnp.zeros(vectors.shape[:1] + (3,), vectors.dtype)
    var = jnp.zeros_like(rel)
    for k, reg in enumerate(regressors):
        if reg is None:
            continue
        r, v = regress_one_class(reg, vectors)
        sel = (cls == k)[:, None]
        rel = jnp.where(sel, r, rel)
        var = jnp.where(sel, v, var)
    return rel, var


def to_sensor_frame(
    origin: Float[Array, "cands 2"],
    heading: Float[Array, " cands"],
    rel: Float[Array, "cands 3"],
    var: Float[Array, "cands 3"],
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3 3"]]:
    """From each candidate's ORS to S: ``p = o′ + Rot(θ_j)(x̃, ỹ)``, heading ``θ_j + θ̃`` (eq. 16 with
    the ORS in place of O), and the covariance ``Rot diag(vx, vy) Rotᵀ`` ⊕ ``vθ``."""
    c, s = jnp.cos(heading), jnp.sin(heading)
    px = origin[:, 0] + c * rel[:, 0] - s * rel[:, 1]
    py = origin[:, 1] + s * rel[:, 0] + c * rel[:, 1]
    pose = jnp.stack([px, py, heading + rel[:, 2]], -1)
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
