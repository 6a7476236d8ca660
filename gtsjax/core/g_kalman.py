"""Stage g's Kalman algebra: each track's extended Kalman filter over ``(x, y, θ, vx, vy, ω)``, its
motion model, time update and measurement update (Joseph form), and the distances that gate a
detection against a track. The filter is the same for every slot and knows nothing of the track table
around it; :mod:`~gtsjax.core.g_track` describes the model and when an update keeps a detection's
heading.

The observation is linear (``H = [I₃ 0]``); what makes the filter "extended" is the heading:
innovations are wrapped to (−π, π], and the state's heading is re-wrapped after each update. Small
matrices are inverted by their adjugates and multiplied as sums of outer products, elementwise work
that XLA fuses with its neighbours instead of running a solve or a dot of its own.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .g_types import _F32, NX, TrackerParams, TrackerState
from .geometry import wrap


def motion_model(dt: Float[Array, ""], params: TrackerParams) -> tuple[Float[Array, "6 6"], Float[Array, "6 6"]]:
    """Transition ``F`` and process noise ``Q`` over ``dt`` seconds.

    Constant velocity: per axis ``F = [[1, dt], [0, 1]]`` and ``Q = q [[dt³/3, dt²/2], [dt²/2, dt]]``.
    Inflate-only (the paper's): ``F = I`` and ``Q = q dt`` on the pose, velocities untouched.
    """
    z3, i3 = jnp.zeros((3, 3), _F32), jnp.eye(3, dtype=_F32)
    q = jnp.stack([params.q_pos, params.q_pos, params.q_theta])
    F_cv = jnp.block([[i3, dt * i3], [z3, i3]])
    Q_cv = jnp.block(
        [
            [jnp.diag(q * dt**3 / 3), jnp.diag(q * dt**2 / 2)],
            [jnp.diag(q * dt**2 / 2), jnp.diag(q * dt)],
        ]
    )
    F_in = jnp.eye(NX, dtype=_F32)
    Q_in = jnp.block([[jnp.diag(q * dt), z3], [z3, z3]])
    cv = params.constant_velocity
    return jnp.where(cv, F_cv, F_in), jnp.where(cv, Q_cv, Q_in)


def predict(state: TrackerState, dt: Float[Array, ""], params: TrackerParams) -> TrackerState:
    """Time update of every slot (dead slots too: they are masked everywhere else and stay finite)."""
    F, Q = motion_model(dt, params)
    mean = jnp.einsum("ij,mj->mi", F, state.mean)
    mean = jnp.where(jnp.arange(NX, dtype=jnp.int32) == 2, wrap(mean), mean)
    cov = jnp.einsum("ij,mjk,lk->mil", F, state.cov, F) + Q[None]
    # The heading hypotheses turn with the state's heading, and grow as uncertain as it does.
    turn = mean[:, 2:3] - state.mean[:, 2:3]
    side_heading = wrap(state.side_heading + wrap(turn))
    side_var = state.side_var + (cov[:, 2:3, 2] - state.cov[:, 2:3, 2])
    return eqx.tree_at(
        lambda s: (s.mean, s.cov, s.side_heading, s.side_var), state, (mean, cov, side_heading, side_var)
    )


def innovation(mean: Float[Array, "6"], cov: Float[Array, "6 6"], z: Float[Array, "3"], R: Float[Array, "3 3"]):
    """Innovation (heading wrapped) and its covariance ``S = H P Hᵀ + R`` with ``H = [I₃ 0]``."""
    nu = z - mean[:3]
    nu = nu.at[2].set(wrap(nu[2]))
    S = cov[:3, :3] + R
    return nu, S


def inv3(S: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3 3"]:
    """Inverse of a symmetric positive definite 3×3 matrix by its adjugate: a handful of multiplies,
    where a general LU solve on such small batched matrices dominates the step's cost."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    d, e, f = S[..., 1, 1], S[..., 1, 2], S[..., 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    det = a * A + b * B + c * C
    adj = jnp.stack([jnp.stack([A, B, C], -1), jnp.stack([B, D, E], -1), jnp.stack([C, E, F], -1)], -2)
    return adj / det[..., None, None]


def inv2(S: Float[Array, "2 2"]) -> Float[Array, "2 2"]:
    """Inverse of a symmetric positive definite 2×2 matrix."""
    a, b, d = S[0, 0], S[0, 1], S[1, 1]
    return jnp.stack([jnp.stack([d, -b]), jnp.stack([-b, a])]) / (a * d - b * b)


def mahalanobis(mean, cov, z, R) -> Float[Array, ""]:
    """Squared Mahalanobis distance of a detection's position from a track's (2 dof): association
    ignores the heading, which a misread side of the robot can throw off by 90° or more."""
    nu, S = innovation(mean, cov, z, R)
    return nu[:2] @ inv2(S[:2, :2]) @ nu[:2]


def _mm(a, b):
    """``a @ b`` over the last two axes (batched, broadcast) as a sum of outer products, one per index
    of the contracted axis: elementwise, so XLA fuses it with its neighbours instead of running a dot."""
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for c in range(1, a.shape[-1]):
        out = out + a[..., :, c : c + 1] * b[..., c : c + 1, :]
    return out


def kalman_update(
    mean: Float[Array, "*#b 6"],
    cov: Float[Array, "*#b 6 6"],
    z: Float[Array, "*#b 3"],
    R: Float[Array, "*#b 3 3"],
    use_heading: Bool[Array, "*#b"] | bool = True,
):
    """Measurement update with ``H = [I₃ 0]``: gain ``K = P Hᵀ S⁻¹``, Joseph-form covariance
    ``(I − KH) P (I − KH)ᵀ + K R Kᵀ``, which stays symmetric positive definite in float32.

    With ``use_heading`` False the update is position-only (``H = [I₂ 0]``): the heading row of the
    gain is zero, which is the 3-row update with the heading's innovation zeroed and the heading's
    row and column of ``S⁻¹`` removed.

    Batched over leading axes (broadcast against each other), in whole-array form: the products with
    ``H`` are the first three rows or columns, ``(I − KH) P = P − K P₃`` and ``A (I − KH)ᵀ = A − A₃ Kᵀ``,
    each product a sum of three outer products."""
    i3 = jnp.arange(3, dtype=jnp.int32)
    i6 = jnp.arange(NX, dtype=jnp.int32)
    nu = z - mean[..., :3]
    nu = jnp.where(i3 == 2, wrap(nu), nu)
    S = cov[..., :3, :3] + R
    a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
    zero = jnp.zeros_like(a)
    pos_only = (
        jnp.stack([jnp.stack([d, -b, zero], -1), jnp.stack([-b, a, zero], -1), jnp.stack([zero, zero, zero], -1)], -2)
        / (a * d - b * b)[..., None, None]
    )
    s_inv = jnp.where(jnp.asarray(use_heading)[..., None, None], inv3(S), pos_only)
    K = _mm(cov[..., :, :3], s_inv)  # S is symmetric
    mean = mean + _mm(K, nu[..., :, None])[..., 0]
    mean = jnp.where(i6 == 2, wrap(mean), mean)
    A = cov - _mm(K, cov[..., :3, :])
    Kt = jnp.swapaxes(K, -1, -2)
    cov = A - _mm(A[..., :, :3], Kt) + _mm(_mm(K, R), Kt)
    return mean, 0.5 * (cov + jnp.swapaxes(cov, -1, -2))
