"""Ray casting against vertical prisms cut by the scan plane, vectorised over scans and beams.

A scene at the laser's height is a set of circles (posts, legs) and line segments (polygon edges,
walls). Every function here works on whole arrays: ``[T, N]`` rays (T scans, N beams) against
``[T, P]`` primitives whose positions may change from scan to scan (moving robots). The nearest hit
along each ray wins, so a polygon's far edges, and anything behind an object, are never seen.
"""

import numpy as np


def ray_circles(ox, oy, dx, dy, cx, cy, r):
    """Distance along rays to circles. Rays: origins ``[T, 1]``, unit directions ``[T, N]``;
    circles: centres ``[T, C]``, radii ``[C]``. Returns ``t [T, N, C]`` (inf for a miss) and the
    cosine of the incidence angle ``[T, N, C]``."""
    ex = cx[:, None, :] - ox[:, :, None]  # [T, 1, C]
    ey = cy[:, None, :] - oy[:, :, None]
    b = dx[..., None] * ex + dy[..., None] * ey  # [T, N, C] projection of the centre on the ray
    c = ex * ex + ey * ey - r * r
    disc = b * b - c
    hit = (disc >= 0) & (c > 0)  # the origin outside the circle
    sq = np.sqrt(np.where(hit, disc, 0.0))
    t = b - sq
    hit &= t > 0
    # cos(incidence) = distance from the chord's midpoint to the hit point / r, i.e. sqrt(disc)/r.
    cos_inc = np.where(hit, sq / r, 0.0)
    return np.where(hit, t, np.inf), cos_inc


def ray_segments(ox, oy, dx, dy, x0, y0, x1, y1):
    """Distance along rays to segments ``(x0, y0)–(x1, y1)`` ``[T, S]``. Returns ``t [T, N, S]``
    (inf for a miss) and the cosine of the incidence angle. Both faces of a segment are seen: a
    closed polygon hides its back faces by occlusion alone."""
    ux, uy = (x1 - x0)[:, None, :], (y1 - y0)[:, None, :]
    wx, wy = (x0[:, None, :] - ox[:, :, None]), (y0[:, None, :] - oy[:, :, None])
    ddx, ddy = dx[..., None], dy[..., None]
    den = ddx * uy - ddy * ux  # cross(d, u)
    ok = np.abs(den) > 1e-12
    den_s = np.where(ok, den, 1.0)
    t = (wx * uy - wy * ux) / den_s  # cross(w, u) / cross(d, u)
    s = (wx * ddy - wy * ddx) / den_s  # cross(w, d) / cross(d, u)
    hit = ok & (t > 0) & (s >= 0) & (s <= 1)
    seg_len = np.sqrt(ux * ux + uy * uy)
    cos_inc = np.abs(den) / np.where(seg_len > 0, seg_len, 1.0)
    return np.where(hit, t, np.inf), np.where(hit, cos_inc, 0.0)


def polygon_edges(vertices: np.ndarray, poses: np.ndarray):
    """Edges in O of a polygon given in its body frame (``vertices [V, 2]``, counter-clockwise) at
    ``poses [T, 3]``: ``x0, y0, x1, y1`` each ``[T, V]``. NaN poses (absent object) give NaN edges,
    which no ray hits."""
    c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
    vx, vy = vertices[None, :, 0], vertices[None, :, 1]
    wx = poses[:, 0:1] + c * vx - s * vy
    wy = poses[:, 1:2] + s * vx + c * vy
    return wx, wy, np.roll(wx, -1, axis=1), np.roll(wy, -1, axis=1)


def beam_directions(angles: np.ndarray, yaw: np.ndarray, roll: np.ndarray, pitch: np.ndarray):
    """Horizontal unit directions in O ``[T, N]`` of beams at ``angles`` in a scan plane tilted by
    ``roll`` and ``pitch`` (sensor frame, radians ``[T]``), and the stretch factor ``[T, N]`` from a
    horizontal distance to the range along the tilted beam (``1 / |horizontal part|``).

    The beam's 3-D direction is ``R_y(pitch) R_x(roll) (cos φ, sin φ, 0)``; vertical prisms are cut by
    its horizontal projection, so only that projection's heading and length matter."""
    ca, sa = np.cos(angles)[None, :], np.sin(angles)[None, :]
    cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
    cp, sp = np.cos(pitch)[:, None], np.sin(pitch)[:, None]
    # R_x(roll) (ca, sa, 0) = (ca, sa cr, sa sr); then R_y(pitch): x' = x cp + z sp, z' = -x sp + z cp.
    hx = ca * cp + sa * sr * sp
    hy = sa * cr
    norm = np.sqrt(hx * hx + hy * hy)
    hx, hy = hx / norm, hy / norm
    cy_, sy_ = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return cy_ * hx - sy_ * hy, sy_ * hx + cy_ * hy, 1.0 / norm
