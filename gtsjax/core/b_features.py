"""Stages a (ORS) and b (characterisation): each candidate's object reference system (eq. 8–9) and
characteristic vector ``v = (w, d_0 … d_{N_d−1}, I_0 … I_{N_I−1})`` (eq. 11–12).

Written for one candidate (a window of ``L`` beams and its mask) and vmapped over the ``K`` slots.

**ORS** (eq. 8 as corrected in READING-NOTES): ``r_j`` and ``θ_j`` are the midpoints of the
candidate's range and bearing extents; the origin in S is ``o′_j = (r_j cos θ_j, r_j sin θ_j)`` and
the heading ``θ_j``. A point's ORS coordinates (eq. 9) are computed as ``Rot(−θ_j)(p_i − o′_j) =
Rot(−θ_j) p_i − (r_j, 0)``, from the points in S that segmentation computed once per beam (float32:
about ``r · 1e-7`` of rounding, a few µm on a field). The window's valid entries are its first
``n_points``, in beam order, as segmentation makes them.

**Profiles** (eq. 11–12): cell ``k`` of ``N`` has centre ``c_k`` and value
``Σ_i q_i exp(−dist(k,i)) / Σ_i exp(−dist(k,i))`` with ``dist(k,i) = (c_k − y′_i)² / (2σ²)`` and ``q``
the ORS depth ``x′`` (distance profile) or the intensity (intensity profile). The weights are
rescaled per cell (see :func:`profile`) so that a cell far outside the candidate never divides 0 by
0: its value tends to the nearest point's value, the defined fallback. A cell whose total weight
still underflows (only possible for a gap of some 26σ inside a candidate) and a candidate with no
points (a dead slot, or a too-long segment) get 0.
Scans without intensity carry zero intensities, so their intensity profile is zero.

**Cell span** (left open by the paper): with ``cells_on_bbox`` False (the default) the cells tile a
fixed physical span ``[−cell_span/2, cell_span/2]`` of y′ centred on the ORS origin; with it True they
tile the candidate's own ``[min y′, max y′]``. ``σ = sigma_cells × cell width``, floored at
``sigma_min``. See ``FrontEndConfig`` for why the fixed span is the default.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .a_segment import Candidates

_F32 = jnp.float32
_I32 = jnp.int32


class Features(eqx.Module):
    """ORS and characteristic vector of the ``K`` candidate slots of one scan (or of one candidate,
    without the ``cands`` axis; a stack of scans adds a leading ``scans`` axis). Zero for empty slots."""

    origin: Float[Array, "*cands 2"]  # ORS origin o′_j in S (eq. 8)
    heading: Float[Array, "*cands"]  # ORS heading θ_j in S (eq. 8)
    points: Float[Array, "*cands window 2"] | None  # (x′, y′) of each measurement (eq. 9), 0 where masked
    vector: Float[Array, "*cands features"]  # (w, d_0 … d_{N_d−1}, I_0 … I_{N_I−1}) (eq. 11–12)
    n_points: Int[Array, "*cands"]
    width: Float[Array, "*cands"]  # bounding box along y′: max y′ − min y′
    height: Float[Array, "*cands"]  # bounding box along x′: max x′ − min x′


def _extents(a: Float[Array, "window n"], mask: Bool[Array, " window"], anyp: Bool[Array, ""]):
    """Masked ``(min, max)`` of each column, 0 for an empty candidate: one reduction for all columns."""
    m = jnp.min(jnp.where(mask[:, None], jnp.concatenate([a, -a], axis=-1), jnp.inf), axis=0)
    m = jnp.where(anyp, m, 0.0)
    n = a.shape[-1]
    return m[:n], -m[n:]


def _ors_box(
    ranges: Float[Array, " window"],
    angles: Float[Array, " window"],
    xy: Float[Array, "window 2"],
    mask: Bool[Array, " window"],
):
    """ORS origin, heading and points (eq. 8–9) and the bounding box ``(x′_lo, y′_lo), (x′_hi, y′_hi)``.

    A candidate's beams are consecutive, so its bearing extent is its first and last beam's angles
    (in either order): ``θ_j`` needs no reduction. Rotating the points by ``−θ_j`` first lets one
    masked reduction give the range extent and the bounding box together, since
    ``x′ = (Rot(−θ_j) p)_x − r_j`` (``Rot(−θ_j)(p − o′_j) = Rot(−θ_j) p − (r_j, 0)``).
    """
    anyp = jnp.any(mask)
    last = jnp.maximum(jnp.sum(mask, dtype=_I32) - 1, 0)
    th_j = jnp.where(anyp, 0.5 * (angles[0] + angles[last]), 0.0)
    c, s = jnp.cos(th_j), jnp.sin(th_j)
    u = c * xy[:, 0] + s * xy[:, 1]
    v = c * xy[:, 1] - s * xy[:, 0]
    lo, hi = _extents(jnp.stack([ranges, u, v], axis=-1), mask, anyp)
    r_j = 0.5 * (lo[0] + hi[0])
    pts = jnp.where(mask[:, None], jnp.stack([u - r_j, v], axis=-1), 0.0)
    box_lo = jnp.where(anyp, jnp.stack([lo[1] - r_j, lo[2]]), 0.0)
    box_hi = jnp.where(anyp, jnp.stack([hi[1] - r_j, hi[2]]), 0.0)
    return jnp.stack([r_j * c, r_j * s]), th_j, pts, box_lo, box_hi


def ors(
    ranges: Float[Array, " window"],
    angles: Float[Array, " window"],
    xy: Float[Array, "window 2"],
    mask: Bool[Array, " window"],
) -> tuple[Float[Array, "2"], Float[Array, ""], Float[Array, "window 2"]]:
    """``(o′_j, θ_j, points)``: the ORS origin and heading in S (eq. 8, midpoints of the range and
    bearing extents) and each measurement's ``(x′, y′) = Rot(−θ_j)(p_i − o′_j)`` (eq. 9), from the
    measurements' polar (``ranges``, ``angles``) and Cartesian (``xy``) coordinates in S. The
    window's valid entries must be its first ``sum(mask)`` (as segmentation makes them)."""
    origin, heading, pts, _, _ = _ors_box(ranges, angles, xy, mask)
    return origin, heading, pts


def cell_centres(
    n_cells: int,
    y_lo: Float[Array, ""],
    y_hi: Float[Array, ""],
    cells_on_bbox: Bool[Array, ""],
    cell_span: Float[Array, ""],
) -> tuple[Float[Array, " cells"], Float[Array, ""]]:
    """Centres of ``n_cells`` profile cells and their width: tiling ``[y_lo, y_hi]`` (bounding box)
    or ``[−cell_span/2, cell_span/2]`` (fixed span)."""
    lo = jnp.where(cells_on_bbox, y_lo, -0.5 * cell_span)
    hi = jnp.where(cells_on_bbox, y_hi, 0.5 * cell_span)
    cw = (hi - lo) / n_cells
    k = jnp.arange(n_cells, dtype=lo.dtype)
    return lo + (k + 0.5) * cw, cw


def profile(
    centres: Float[Array, " cells"],
    sigma: Float[Array, ""],
    y: Float[Array, " window"],
    q: Float[Array, "window n"],
    mask: Bool[Array, " window"],
    y_lo: Float[Array, ""],
    y_hi: Float[Array, ""],
) -> Float[Array, "cells n"]:
    """Kernel-weighted mean of each column of ``q`` per cell (eq. 11, and eq. 12 with intensities):
    weights ``exp(−(c_k − y′_i)² / (2σ²))`` over the masked points; ``sigma`` must be positive.

    The weights are scaled by ``exp(dist(c_k, [y_lo, y_hi]))``, the distance from the cell's centre to
    the candidate's y′ extent: the ratio is unchanged, and for a cell outside the extent this is the
    distance to the nearest point, so the weights cannot all underflow and the value tends to the
    nearest point's. Inside the extent, consecutive points are no farther apart than the
    segmentation's break distance, so underflow would need a gap of some 26σ; if the total weight
    does underflow to 0 (or the candidate is empty) the value is 0.
    """
    inv = 0.5 / (sigma * sigma)
    shift = (centres - jnp.clip(centres, y_lo, y_hi)) ** 2 * inv
    dist = (centres[:, None] - y[None, :]) ** 2 * inv  # [cells, window]
    w = jnp.where(mask[None, :], jnp.exp(shift[:, None] - dist), 0.0)
    acc = w @ jnp.concatenate([jnp.ones_like(q[:, :1]), q], axis=-1)  # the total weight, then the sums
    total = acc[:, :1]
    ok = total > 0
    return jnp.where(ok, acc[:, 1:] / jnp.where(ok, total, 1.0), 0.0)


def characterise(
    ranges: Float[Array, " window"],
    angles: Float[Array, " window"],
    xy: Float[Array, "window 2"],
    intensities: Float[Array, " window"],
    mask: Bool[Array, " window"],
    *,
    n_dist: int,
    n_intensity: int,
    cells_on_bbox: Bool[Array, ""],
    cell_span: Float[Array, ""],
    sigma_cells: Float[Array, ""],
    sigma_min: Float[Array, ""],
) -> Features:
    """ORS (eq. 8–9) and characteristic vector (eq. 11–12) of one candidate."""
    origin, heading, pts, (xlo, ylo), (xhi, yhi) = _ors_box(ranges, angles, xy, mask)
    xp, y = pts[:, 0], pts[:, 1]
    width = yhi - ylo

    def prof(n, q):
        c, cw = cell_centres(n, ylo, yhi, cells_on_bbox, cell_span)
        return profile(c, jnp.maximum(sigma_cells * cw, sigma_min), y, q, mask, ylo, yhi)

    if n_dist == n_intensity:  # same cells: one set of weights serves both profiles
        both = prof(n_dist, jnp.stack([xp, intensities], axis=-1))
        d, i = both[:, 0], both[:, 1]
    else:
        d = prof(n_dist, xp[:, None])[:, 0]
        i = prof(n_intensity, intensities[:, None])[:, 0]
    return Features(
        origin=origin,
        heading=heading,
        points=pts,
        vector=jnp.concatenate([width[None], d, i]),
        n_points=jnp.sum(mask, dtype=_I32),
        width=width,
        height=xhi - xlo,
    )


def characterise_all(cands: Candidates, **kwargs) -> Features:
    """:func:`characterise` vmapped over the candidate slots of one scan (keyword arguments as there)."""
    return jax.vmap(lambda r, a, p, i, m: characterise(r, a, p, i, m, **kwargs))(
        cands.ranges, cands.angles, cands.xy, cands.intensities, cands.mask
    )
