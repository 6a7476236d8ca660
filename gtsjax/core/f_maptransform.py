"""Stage f, map transformation: the affine map from the sensor frame S to the field frame O,
re-estimated every scan from the detected landmarks (eq. 2, 18), and its use (eq. 10).

The map is ``p_O = μo + A (p_S − μs)`` with a general 2×2 ``A``: a tilted scan plane stretches and
shears what the sensor sees, and a general linear map absorbs that where a rigid transform cannot.

Association is not described in the paper. Here each site landmark takes the nearest detected
landmark candidate of its class, mapped into O with the previous transform, if it lies within a gate
and the landmark is also that candidate's nearest landmark of the class (mutual nearest neighbour, so
one candidate never serves two landmarks). At least three associated landmarks, spread in 2-D, are
needed; otherwise the previous transform is kept and the scan is marked degraded.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .geometry import affine_heading, field_to_sensor, rot, sensor_pose, sensor_to_field, wrap

_F32 = jnp.float32


class Transform(eqx.Module):
    """``p_O = mu_o + A (p_S − mu_s)`` (eq. 10), with what the last estimate was based on."""

    A: Float[Array, "2 2"]
    mu_s: Float[Array, "2"]
    mu_o: Float[Array, "2"]
    degraded: Bool[Array, ""]  # True when this scan's landmarks could not support a new estimate
    n_landmarks: Int[Array, ""]  # landmarks associated in this scan

    @classmethod
    def from_sensor_pose(cls, pose: Float[Array, "3"]) -> "Transform":
        """The first iteration (READING-NOTES): ``A = Rot(s′θ)``, ``μs = 0``, ``μo = (s′x, s′y)``."""
        pose = jnp.asarray(pose, dtype=_F32)
        return cls(
            A=rot(pose[2]),
            mu_s=jnp.zeros(2, _F32),
            mu_o=pose[:2],
            degraded=jnp.asarray(False),
            n_landmarks=jnp.asarray(0, jnp.int32),
        )

    def apply(self, p: Float[Array, "*n 2"]) -> Float[Array, "*n 2"]:
        """Points from S to O (eq. 10)."""
        return sensor_to_field(self.A, self.mu_s, self.mu_o, p)

    def to_sensor(self, p: Float[Array, "*n 2"]) -> Float[Array, "*n 2"]:
        """Points from O to S (eq. 10 inverted)."""
        return field_to_sensor(self.A, self.mu_s, self.mu_o, p)

    def heading(self) -> Float[Array, ""]:
        """The rotation part of ``A``, ``atan2(A10, A00)``: added to headings measured in S (eq. 10)."""
        return affine_heading(self.A)

    def sensor_pose(self) -> Float[Array, "3"]:
        """The sensor's pose in O as this transform sees it: where S's origin lands, and the heading.
        Also for a stack of transforms (NumPy or JAX arrays with a leading axis)."""
        return sensor_pose(self.A, self.mu_s, self.mu_o)


def associate(
    prev: Transform,
    det_s: Float[Array, "dets 2"],
    det_class: Int[Array, " dets"],
    det_mask: Bool[Array, " dets"],
    map_o: Float[Array, "landmarks 2"],
    map_class: Int[Array, " landmarks"],
    gate: Float[Array, ""],
    slack: Float[Array, ""] | float = 0.0,
) -> tuple[Int[Array, " landmarks"], Bool[Array, " landmarks"]]:
    """Each map landmark's detection: index into the candidates and whether it is associated.

    Mutual nearest neighbour of the same class within ``gate + slack · r`` metres (``r`` the
    detection's range from the sensor), after mapping the detections into O with ``prev``.
    """
    det_o = prev.apply(det_s)
    d2 = jnp.sum((map_o[:, None, :] - det_o[None, :, :]) ** 2, axis=-1)  # [L, K]
    ok = (map_class[:, None] == det_class[None, :]) & det_mask[None, :]
    d2 = jnp.where(ok, d2, jnp.inf)
    best_det = jnp.argmin(d2, axis=1)  # per landmark
    best_map = jnp.argmin(d2, axis=0)  # per detection
    mutual = best_map[best_det] == jnp.arange(map_o.shape[0])
    r = jnp.sqrt(jnp.sum(det_s[best_det] ** 2, axis=-1))
    hit = mutual & (jnp.min(d2, axis=1) <= (gate + slack * r) ** 2)
    return best_det, hit


# While the transform rests on no landmarks (the user's rough sensor pose, or a scan whose fit
# failed), association also allows for a heading this far off (radians, about 3.4°): the error of a
# guessed laser heading moves a landmark 8 m away by half a metre, beyond the gate.
GUESS_HEADING_SLACK = 0.06


def fit_transform(
    det_s: Float[Array, "landmarks 2"], map_o: Float[Array, "landmarks 2"], weight: Bool[Array, " landmarks"], min_spread: Float[Array, ""]
) -> tuple[Transform, Bool[Array, ""]]:
    """OLS with centring (eq. 18, 2): ``μs, μo`` the means of the associated pairs, ``Aᵀ = (XᵀX)⁻¹XᵀY``
    solved as a 2×2 linear system, never inverted. Also whether the fit is supported: at least three
    pairs, and the detections spread in 2-D (the smaller eigenvalue of ``XᵀX / n`` above
    ``min_spread²``), so that ``XᵀX`` is well conditioned."""
    w = weight.astype(det_s.dtype)
    n = jnp.sum(w)
    n_safe = jnp.maximum(n, 1.0)
    mu_s = jnp.sum(w[:, None] * det_s, axis=0) / n_safe
    mu_o = jnp.sum(w[:, None] * map_o, axis=0) / n_safe
    X = w[:, None] * (det_s - mu_s[None])
    Y = w[:, None] * (map_o - mu_o[None])
    XtX = X.T @ X
    XtY = X.T @ Y
    # Smallest eigenvalue of the symmetric 2x2 XtX / n, in closed form.
    a, b, c = XtX[0, 0] / n_safe, XtX[0, 1] / n_safe, XtX[1, 1] / n_safe
    lam_min = 0.5 * (a + c) - jnp.sqrt(jnp.maximum(0.25 * (a - c) ** 2 + b**2, 0.0))
    ok = (n >= 3) & (lam_min > min_spread**2)
    # Keep the solve well posed when the fit is rejected, so no NaN leaks into gradients or outputs.
    XtX_safe = jnp.where(ok, XtX, jnp.eye(2, dtype=XtX.dtype))
    # The 2×2 system in closed form (Cramer's rule): well conditioned whenever ``ok``.
    p, q, r = XtX_safe[0, 0], XtX_safe[0, 1], XtX_safe[1, 1]
    det = p * r - q * q
    inv = jnp.stack([jnp.stack([r, -q]), jnp.stack([-q, p])]) / det
    At = inv @ XtY
    tf = Transform(A=At.T, mu_s=mu_s, mu_o=mu_o, degraded=~ok, n_landmarks=n.astype(jnp.int32))
    return tf, ok


# Associations a rigid motion must explain (metres): a scan plane tilted by a few degrees stretches
# what the sensor sees by a percent or two, centimetres across a field; a candidate taken for a
# landmark it is not (a robot beside a post, a post hidden behind it) sits decimetres off.
RIGID_TOLERANCE = 0.15
# Wrong associations dropped per scan, worst first (a fixed, unrolled count).
RIGID_DROPS = 2


def rigid_inliers(det_s: Float[Array, "landmarks 2"], map_o: Float[Array, "landmarks 2"], hit: Bool[Array, " landmarks"],
                  tol: float = RIGID_TOLERANCE, drops: int = RIGID_DROPS) -> Bool[Array, " landmarks"]:
    """The associations (``hit``) that one rigid motion of S onto O explains within ``tol``: up to
    ``drops`` times, the closed-form least-squares rotation and translation (2-D Procrustes) of the
    pairs still kept, and the pair furthest from it dropped if it is further than ``tol``.

    The affine fit (:func:`fit_transform`) has six degrees of freedom: three pairs determine it
    exactly, whatever they are, so a single wrong pair among three or four bends it to fit and the
    next scan's association starts from the bent transform (on a crowded field a robot walking past
    a goal post took a laser's transform metres off, for good). A rigid motion has three: three pairs
    over-determine it and a wrong one shows as a residual. (The tilt the affine map absorbs stays far
    inside ``tol``.) With fewer than three pairs left the fit is unsupported anyway."""
    sx, sy, ox, oy = det_s[:, 0], det_s[:, 1], map_o[:, 0], map_o[:, 1]
    # Per pair, the products whose sums the fit needs (raw moments: one reduction per pass).
    terms = jnp.stack([jnp.ones_like(sx), sx, sy, ox, oy, sx * ox + sy * oy, sx * oy - sy * ox], -1)
    for _ in range(drops):
        mom = hit.astype(terms.dtype) @ terms
        # Means, then the Procrustes rotation's cosine and sine (unnormalised: (Σ a·b, Σ a×b)); written
        # with one reciprocal and one rsqrt so that XLA fuses the scalar arithmetic into the residuals.
        n = mom[0]
        mean = mom[1:5] * (1.0 / jnp.maximum(n, 1.0))  # μs_x, μs_y, μo_x, μo_y
        dot = mom[5] - n * (mean[0] * mean[2] + mean[1] * mean[3])  # Σ (s − μs)·(o − μo)
        cross = mom[6] - n * (mean[0] * mean[3] - mean[1] * mean[2])  # Σ (s − μs) × (o − μo)
        norm2 = dot * dot + cross * cross
        inv = jax.lax.rsqrt(jnp.where(norm2 > 0, norm2, 1.0))
        c, s = jnp.where(norm2 > 0, dot * inv, 1.0), cross * inv
        ax, ay = sx - mean[0], sy - mean[1]
        ex, ey = c * ax - s * ay - (ox - mean[2]), s * ax + c * ay - (oy - mean[3])
        r2 = jnp.where(hit, ex * ex + ey * ey, -1.0)
        worst = jnp.max(r2)
        hit = hit & ~((r2 >= worst) & (worst > tol * tol) & (n >= 3))
    return hit


def update_transform(
    prev: Transform,
    det_s: Float[Array, "dets 2"],
    det_class: Int[Array, " dets"],
    det_mask: Bool[Array, " dets"],
    map_o: Float[Array, "landmarks 2"],
    map_class: Int[Array, " landmarks"],
    gate: Float[Array, ""],
    min_spread: Float[Array, ""],
) -> tuple[Transform, Float[Array, "landmarks 2"], Bool[Array, " landmarks"]]:
    """Stage f for one scan: associate, fit, and keep ``prev`` (marked degraded) if the fit is not
    supported. While ``prev`` rests on no landmarks, the gate widens with range
    (``GUESS_HEADING_SLACK``). Returns the transform, each landmark's residual in O (detected minus
    map position, under the new transform; 0 where not associated), and the association mask."""
    unsupported = prev.degraded | (prev.n_landmarks == 0)
    slack = GUESS_HEADING_SLACK * unsupported.astype(gate.dtype)
    idx, hit = associate(prev, det_s, det_class, det_mask, map_o, map_class, gate, slack)
    matched_s = det_s[idx]
    hit = rigid_inliers(matched_s, map_o, hit)
    new, ok = fit_transform(matched_s, map_o, hit, min_spread)
    tf = jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, prev)
    tf = eqx.tree_at(lambda t: (t.degraded, t.n_landmarks), tf, (~ok, jnp.sum(hit).astype(jnp.int32)))
    residual = jnp.where(hit[:, None], tf.apply(matched_s) - map_o, 0.0)
    return tf, residual, hit


def poses_to_field(
    tf: Transform, pose_s: Float[Array, "dets 3"], cov_s: Float[Array, "dets 3 3"]
) -> tuple[Float[Array, "dets 3"], Float[Array, "dets 3 3"]]:
    """Poses from S to O (eq. 10, 16): position through the affine map, heading plus
    ``atan2(A10, A00)``, position covariance ``A Σ Aᵀ``.

    Mapping the whole regressed position through ``A``, rather than rotating the ORS-relative offset
    by ``θ̂`` as eq. 16 prints, is the same for a rigid ``A`` and keeps the offset consistent with the
    stretch of a tilted scan plane otherwise.
    """
    xy = tf.apply(pose_s[:, :2])
    theta = pose_s[:, 2] + tf.heading()
    theta = wrap(theta)
    A3 = jnp.zeros((3, 3), tf.A.dtype).at[:2, :2].set(tf.A).at[2, 2].set(1.0)
    cov = jnp.einsum("ij,njk,lk->nil", A3, cov_s, A3)
    return jnp.concatenate([xy, theta[:, None]], -1), cov
