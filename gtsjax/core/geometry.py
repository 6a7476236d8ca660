"""Plane geometry, the one home of it: angle wrap, rotations, and the paper's three frames.

* **ORS**, a candidate's own reference system (eq. 9): origin ``o′`` at the candidate, x′ along its
  heading ``θ_j``. Poses regressed in it are *relative* to the candidate.
* **S**, the sensor's frame: what the scan measures.
* **O**, the field's frame: ``p_O = μo + A (p_S − μs)`` (eq. 10), with a general 2×2 ``A`` (the map
  transformation, ``f_maptransform.Transform``).

Every function takes NumPy or JAX arrays and returns the same kind, so the jitted step (float32, on
the device), training's labels (float64), evaluation and the file writers (NumPy, on the host) share
one definition and nothing makes a trip to the device it does not need. Leading axes broadcast.
Headings are wrapped where they are subtracted (:func:`wrap`); sums are left as they are.
"""

import jax
import jax.numpy as jnp
import numpy as np


def _xp(*arrays):
    """``jax.numpy`` if any argument is a JAX array (or tracer), else ``numpy``."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def _lift(a, ndim: int):
    """``a`` with singleton axes in front up to ``ndim`` axes: broadcasting made explicit (the tests
    run JAX with ``jax_numpy_rank_promotion="raise"``)."""
    return a.reshape((1,) * (ndim - a.ndim) + a.shape)


def wrap(a):
    """Angle(s) to (−π, π]."""
    xp = _xp(a)
    return xp.pi - xp.mod(xp.pi - xp.asarray(a), 2 * xp.pi)


def rot(theta):
    """Rotation matrices ``[..., 2, 2]`` by ``theta`` ``[...]``."""
    xp = _xp(theta)
    c, s = xp.cos(theta), xp.sin(theta)
    return xp.stack([xp.stack([c, -s], -1), xp.stack([s, c], -1)], -2)


def compose(frame, rel):
    """A pose (or point) given relative to ``frame`` ``[..., 3]``, in the frame's parent:
    ``p = o + Rot(θ)(x̃, ỹ)``, heading ``θ + θ̃`` (not wrapped). ``rel`` is ``[..., 3]`` or ``[..., 2]``
    (a point: the result is a point). ORS → S is eq. 16 with the ORS in place of O."""
    xp = _xp(frame, rel)
    nd = max(frame.ndim, rel.ndim)
    frame, rel = _lift(frame, nd), _lift(rel, nd)
    c, s = xp.cos(frame[..., 2]), xp.sin(frame[..., 2])
    x = frame[..., 0] + c * rel[..., 0] - s * rel[..., 1]
    y = frame[..., 1] + s * rel[..., 0] + c * rel[..., 1]
    if rel.shape[-1] == 2:
        return xp.stack([x, y], -1)
    return xp.stack([x, y, frame[..., 2] + rel[..., 2]], -1)


def relative(frame, p):
    """The inverse of :func:`compose`: a pose or point ``p`` of the parent frame, seen from ``frame``:
    ``Rot(−θ)(p − o)`` and, for a pose, the wrapped heading difference (eq. 9 for a candidate's ORS)."""
    xp = _xp(frame, p)
    nd = max(frame.ndim, p.ndim)
    frame, p = _lift(frame, nd), _lift(p, nd)
    c, s = xp.cos(frame[..., 2]), xp.sin(frame[..., 2])
    dx, dy = p[..., 0] - frame[..., 0], p[..., 1] - frame[..., 1]
    x, y = c * dx + s * dy, -s * dx + c * dy
    if p.shape[-1] == 2:
        return xp.stack([x, y], -1)
    return xp.stack([x, y, wrap(p[..., 2] - frame[..., 2])], -1)


def sensor_to_field(A, mu_s, mu_o, p):
    """Points ``[..., 2]`` from S to O under the affine map (eq. 10): ``μo + A (p − μs)``. ``A``
    ``[..., 2, 2]``, ``μs``, ``μo`` ``[..., 2]`` broadcast against the points' leading axes."""
    nd = max(p.ndim, mu_s.ndim, mu_o.ndim, A.ndim - 1)
    A, mu_s, mu_o, p = _lift(A, nd + 1), _lift(mu_s, nd), _lift(mu_o, nd), _lift(p, nd)
    return mu_o + _xp(A, mu_s, mu_o, p).sum(A * (p - mu_s)[..., None, :], axis=-1)


def field_to_sensor(A, mu_s, mu_o, p):
    """Points ``[..., 2]`` from O to S: the inverse of :func:`sensor_to_field`, ``μs + A⁻¹ (p − μo)``
    (the 2×2 inverse in closed form, so that it broadcasts the same way)."""
    nd = max(p.ndim, mu_s.ndim, mu_o.ndim, A.ndim - 1)
    A, mu_s, mu_o, p = _lift(A, nd + 1), _lift(mu_s, nd), _lift(mu_o, nd), _lift(p, nd)
    d = p - mu_o
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    x = (A[..., 1, 1] * d[..., 0] - A[..., 0, 1] * d[..., 1]) / det
    y = (-A[..., 1, 0] * d[..., 0] + A[..., 0, 0] * d[..., 1]) / det
    return mu_s + _xp(A, mu_s, mu_o, p).stack([x, y], -1)


def affine_heading(A):
    """The rotation part of ``A``, ``atan2(A10, A00)``: what a heading measured in S gains in O."""
    return _xp(A).arctan2(A[..., 1, 0], A[..., 0, 0])


def sensor_pose(A, mu_s, mu_o):
    """The sensor's pose in O under the map: where S's origin lands, and :func:`affine_heading`."""
    xp = _xp(A, mu_s, mu_o)
    origin = sensor_to_field(A, mu_s, mu_o, xp.zeros_like(mu_s))
    return xp.concatenate([origin, affine_heading(A)[..., None]], -1)


def in_bounds(xy, bounds, margin=0.0):
    """Whether points ``[..., 2]`` lie inside ``bounds`` ``(x0, y0, x1, y1)`` grown by ``margin``
    (edges inside)."""
    x, y = xy[..., 0], xy[..., 1]
    return ((x >= bounds[0] - margin) & (y >= bounds[1] - margin)
            & (x <= bounds[2] + margin) & (y <= bounds[3] + margin))
