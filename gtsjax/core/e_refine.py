"""Stage e′, outline refinement: each posed candidate's points aligned to its class's learnt outline,
from the GP's pose, from the GP's heading turned to each of the outline's other sides, and from it
turned every 45° (a search over every side).

The GP of stage e reads a pose from a characteristic vector, a summary of the points; where two sides
of a robot give similar vectors it reads the wrong side (3–6 % of scans on the SPL field, the bulk of
the heading's RMSE). The points themselves say more: only one side of the outline fits them. So
every candidate of a class with an outline (:class:`Outline`, learnt by ``gtsjax train``:
:mod:`gtsjax.train.outline`) gets a fixed number of Gauss–Newton steps (Levenberg–Marquardt damped,
iteratively reweighted), per start ``h``, from ``(x̂, ŷ, θ̂ + o_h)``: ``o_h`` the class's learnt
sides (the GP's held-out misreads), then every 45° not within 30° of one (:data:`SEARCH_DEG`). The
learnt sides are where the GP misreads views like those it was trained on; a view of a side the
labels rarely showed (a robot recorded walking, seen side-on) is misread by any angle, which only a
search over the whole turn finds. Each point and the fit:

* each point ``p`` (in S) costs the outline's signed distance at ``Rot(θ)ᵀ (p − t)`` (bilinear in a
  grid of distances and gradients, Cauchy-weighted so that a leg merged into the segment does not pull);
* each point moved ``free_gap`` back towards the sensor must lie outside the outline: a pose that puts
  the body between the laser and what it saw is charged for it (otherwise one flat face would fit
  its own mirror image, body towards the sensor, as well as the truth).

What comes out per candidate and start: the refined pose, the fit's robust cost, and from the costs
the posterior probability of each (``-temperature · cost`` plus a prior: that the GP read the right
side, ``prior_right``, and of the rest the searched turns' share, ``prior_search``, all calibrated on
held-out examples at training). Fits that end within 30° of a more probable one are that side (it
takes their probability); the ``SIDES`` most probable sides go on to the tracker (stage g), whose
heading is a mixture over them, best first. The most probable side gives the candidate's heading;
the Gauss–Newton Hessian, scaled by the residual and a calibrated factor, its heading's variance.
Positions stay the GP's, but where a fit leaves the side the GP read and the class was calibrated to
take the fit's position there (``side_position``; see :func:`refine` for why). A candidate with fewer
than ``min_points`` points or a fit whose residual is above its class's ``max_rms`` keeps the GP's
pose and variance, and its sides are the GP's heading turned by the offsets with the prior alone.

Fixed shapes throughout: ``cands × SEARCH × window`` points, ``ITERATIONS`` steps (a loop of a fixed trip
count), the ``SIDES`` best by one ``top_k``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .buckets import bucketed_rows, slots_of
from .e_tags import TagReader, read_tags
from .geometry import wrap

POINTS = 32  # points per candidate the fit uses: a longer segment is thinned evenly (a robot at 1.5–3.6 m
# from a URG-04LX has 12–30 points; a close one up to the window's 96)
ITERATIONS = 6  # Gauss–Newton steps per hypothesis (from 5 cm / 10° off, 80 % of views are within 1 mm / 0.1° by the 6th)
SIDES = 4  # side hypotheses per candidate that go on to the tracker (the most probable of those searched)
# Besides the class's learnt sides, every fit also starts from the GP's heading turned by each of these
# (degrees; those within ``_SEARCH_APART`` of a learnt side are left out): a view of a side the labels
# rarely showed is misread by any angle, not only by the learnt sides' (on a walk-trained Nao, 100–150°
# where the learnt sides were ±40°), and six steps from 45° off bring 98 % of views home.
SEARCH_DEG = (45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0)
_SEARCH_APART = 0.5235987755982988  # 30°
SEARCH = SIDES + len(SEARCH_DEG)  # fits per candidate
# A fit that ends within this of the GP's heading is on the side the GP read, and keeps the GP's
# position; one on another side takes its own (the GP's position was read for the wrong side).
GP_SIDE = 0.5235987755982988  # 30°
# Fits that end closer than this are one side (the most probable's heading, all their probability): the
# learnt sides are as far apart, and a second fit a few degrees from the best (a start that stopped short,
# a partial view's other minimum) would be the side nearest a track's heading that has drifted towards it,
# and the track would follow it.
_MERGE = 0.5235987755982988  # 30°
_MAX_STEP_XY = 0.05  # m per step
_MAX_STEP_TH = 0.35  # rad per step
_DAMPING = 1e-3  # Levenberg–Marquardt: relative to the Hessian's diagonal


class Outline(eqx.Module):
    """The learnt outlines of the classes, as signed distance fields in each object's own frame.

    ``field[c, i, j]`` holds the signed distance (m, negative inside) and its gradient at the point
    ``lo[c] + cell[c] · (i, j)`` of class ``c``'s ``G × G`` grid. ``has[c]``: the class has an outline
    (mobile classes with enough training views). ``sides[c]``: the heading offsets of its side
    hypotheses (``sides[c, 0] = 0``, the GP's own), used where ``side_mask``. The rest is calibrated
    at training (:mod:`gtsjax.train.outline`)."""

    field: Float[Array, "classes grid grid 3"]
    lo: Float[Array, "classes 2"]
    cell: Float[Array, " classes"]
    has: Bool[Array, " classes"]
    sides: Float[Array, "classes sides"]
    side_mask: Bool[Array, "classes sides"]
    temperature: Float[Array, " classes"]  # log-likelihood per unit of fit cost (per m² of robust residual)
    prior_right: Float[Array, " classes"]  # probability that the GP read the right side
    max_rms: Float[Array, " classes"]  # m: a fit with a larger RMS residual fails
    cov_scale: Float[Array, "classes 3"]  # multiplies the residual-scaled inverse Hessian
    robust: Float[Array, ""]  # m: the Cauchy weight's scale
    free_gap: Float[Array, ""]  # m: how far before each point the ray must be outside the outline
    min_points: Int[Array, ""]
    # Of the probability that the GP misread the side, the share of the searched turns (:data:`SEARCH_DEG`)
    # against the learnt sides (calibrated; None in models trained before the search: not searched).
    prior_search: Float[Array, " classes"] | None = None
    # Whether a fit on another side than the GP read takes its own position (calibrated: where that was
    # nearer the truth on held-out views than the GP's; None in models trained before: never).
    side_position: Bool[Array, " classes"] | None = None


class Refined(eqx.Module):
    """Stage e′ for the candidates it ran on: per candidate the chosen pose and covariance, per side
    hypothesis the pose and log-probability (``-inf`` for unused sides)."""

    pose: Float[Array, "cands 3"]
    cov: Float[Array, "cands 3 3"]
    side_pose: Float[Array, "cands sides 3"]
    side_logp: Float[Array, "cands sides"]
    fitted: Bool[Array, " cands"]  # the fit succeeded (else the GP's pose stands)
    rms: Float[Array, " cands"]  # the chosen side's RMS residual (m)


def compact(pts: Float[Array, "n window 2"], mask: Bool[Array, "n window"], size: int = POINTS
            ) -> tuple[Float[Array, "n size 2"], Bool[Array, "n size"]]:
    """At most ``size`` of each candidate's points, spread evenly over its segment (a candidate's
    points are the first ``length`` of its window)."""
    n_pts = jnp.sum(mask, -1, dtype=jnp.int32)
    stride = jnp.maximum((n_pts + size - 1) // size, 1)
    idx = jnp.minimum(jnp.arange(size, dtype=jnp.int32)[None, :] * stride[:, None], pts.shape[1] - 1)
    take = jnp.take_along_axis
    return take(pts, idx[..., None], 1), take(mask, idx, 1) & (idx < n_pts[:, None])


def _bilinear(outline: Outline, cls, mx, my, lo_x, lo_y, cell, inv_cell):
    """Signed distance and gradient ``(d, gx, gy)`` at object-frame points ``(mx, my)`` of classes
    ``cls``, all arguments broadcast to one shape (the grid corner ``lo``, the cell size and its inverse
    as already gathered per class): bilinear in the grid, one gather of each cell's four corners
    (distance and gradient at each, side by side); beyond the grid the distance grows with the
    distance from its edge, along the way out."""
    g = outline.field.shape[1]
    ux, uy = (mx - lo_x) * inv_cell, (my - lo_y) * inv_cell
    uxc, uyc = jnp.clip(ux, 0.0, g - 1.0), jnp.clip(uy, 0.0, g - 1.0)
    ix, iy = jnp.clip(jnp.floor(uxc), 0, g - 2), jnp.clip(jnp.floor(uyc), 0, g - 2)
    fx, fy = uxc - ix, uyc - iy
    fld = outline.field
    corners = jnp.concatenate([fld[:, :-1, :-1], fld[:, :-1, 1:], fld[:, 1:, :-1], fld[:, 1:, 1:]], -1)
    cv = corners.reshape(-1, 12)[cls * (g - 1) ** 2 + ix.astype(jnp.int32) * (g - 1) + iy.astype(jnp.int32)]
    w00, w01, w10, w11 = (1 - fx) * (1 - fy), (1 - fx) * fy, fx * (1 - fy), fx * fy
    interp = lambda k: (w00 * cv[..., k] + w01 * cv[..., 3 + k]  # noqa: E731
                        + w10 * cv[..., 6 + k] + w11 * cv[..., 9 + k])
    ox, oy = (ux - uxc) * cell, (uy - uyc) * cell  # metres beyond the grid, per axis
    out2 = ox * ox + oy * oy
    out = out2 > 0
    rinv = jax.lax.rsqrt(jnp.where(out, out2, 1.0))
    d = interp(0) + jnp.where(out, out2 * rinv, 0.0)
    return d, jnp.where(out, ox * rinv, interp(1)), jnp.where(out, oy * rinv, interp(2))


def lookup(outline: Outline, cls: Int[Array, "*n"], m: Float[Array, "*n 2"]
           ) -> tuple[Float[Array, "*n"], Float[Array, "*n 2"]]:
    """Signed distance and its gradient at object-frame points ``m`` of classes ``cls`` (bilinear;
    beyond the grid, the distance grows with the distance from its edge): :func:`_bilinear`."""
    lo, cell = outline.lo[cls], outline.cell[cls]
    d, gx, gy = _bilinear(outline, cls, m[..., 0], m[..., 1], lo[..., 0], lo[..., 1], cell, 1.0 / cell)
    return d, jnp.stack([gx, gy], -1)


def _gram(outline: Outline, cls: Int[Array, " n"], pose: Float[Array, "n sides 3"], trig: Float[Array, "n sides 2"],
          pts: Float[Array, "n 1 l 2"], is_free: Bool[Array, "1 1 l"], mask: Bool[Array, "n 1 l"], with_cost: bool = False):
    """One Gauss–Newton step's sums for every candidate and side: the weighted Gram matrix ``VᵀWV`` over
    the points of ``V = [J, r]`` (one row per point), whose top-left 3 × 3 block is ``JᵀWJ`` and whose
    fourth column holds ``JᵀWr``; ``with_cost`` adds the robust cost (Cauchy's ``c² log(1 + (r/c)²)``
    over the points, plus the free-space terms squared). ``pts`` holds the points then the
    free-space points (``is_free``).

    Each point's residual, Jacobian and weight are computed once on the ``[n, sides, l]`` domain,
    from scalars per pose (``trig``: its cosine and sine, computed in the step's small kernel) and the
    outline's bilinear lookup (:func:`_bilinear`); the sums are one product. Built as the
    obvious form (a gather of twelve columns sliced apart, one ``einsum`` per term), a step was 26
    kernels; this is about 11. Fewer is possible (everything on a ``[…, l, 4]`` domain is one fusion)
    but repeats the per-point arithmetic per channel, which on a CPU costs more than the kernels saved."""
    shape = pose.shape[:2] + (pts.shape[2],)
    per_pose = lambda a: jnp.broadcast_to(a[..., None], shape)  # noqa: E731  [n, sides] -> domain
    per_point = lambda a: jnp.broadcast_to(a, shape)  # noqa: E731  [n, 1, l] -> domain
    per_cand = lambda a: jnp.broadcast_to(a[:, None, None], shape)  # noqa: E731  [n] -> domain
    c, s = per_pose(trig[..., 0]), per_pose(trig[..., 1])
    dx = per_point(pts[..., 0]) - per_pose(pose[..., 0])
    dy = per_point(pts[..., 1]) - per_pose(pose[..., 1])
    mx, my = c * dx + s * dy, -s * dx + c * dy  # the point in the object's frame
    lo, cell = outline.lo[cls], outline.cell[cls]
    r, gx, gy = _bilinear(outline, per_cand(cls), mx, my, per_cand(lo[:, 0]), per_cand(lo[:, 1]), per_cand(cell),
                          per_cand(1.0 / cell))
    # ∂r/∂t = −(Rot g)ᵀ, ∂r/∂θ = g · (m_y, −m_x)
    jx, jy, jt = -(c * gx - s * gy), -(s * gx + c * gy), gx * my - gy * mx
    free, m = per_point(is_free), per_point(mask)
    z = r / outline.robust
    inside = m & (r < 0)
    # Points: Cauchy-weighted residuals; free-space points: their distance where inside, squared.
    w = jnp.where(free, jnp.where(inside, 1.0, 0.0), jnp.where(m, 1.0 / (1.0 + z * z), 0.0))
    res = jnp.where(free & ~inside, 0.0, r)
    v = jnp.stack([jx, jy, jt, res], -1)
    G = jnp.einsum("...li,...lj->...ij", v * w[..., None], v)
    if not with_cost:
        return G
    cost = jnp.where(free, w * res * res, jnp.where(m, outline.robust**2 * jnp.log1p(z * z), 0.0))
    return G, jnp.sum(cost, -1)


def _adjugate3(a, b, c, d, e, f):
    """The adjugate ``(A, B, C, D, E, F)`` (same layout) and determinant of the symmetric 3 × 3 matrix
    ``[[a, b, c], [b, d, e], [c, e, f]]``, elementwise over any batch; a zero determinant becomes 1."""
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    return (A, B, C, D, E, F), jnp.where(jnp.abs(det) > 0, det, 1.0)


def _solve3(H, b):
    """``H⁻¹ b`` for symmetric 3×3 ``H`` (closed-form adjugate), batched."""
    (A, B, C, D, E, F), det = _adjugate3(H[..., 0, 0], H[..., 0, 1], H[..., 0, 2], H[..., 1, 1], H[..., 1, 2],
                                         H[..., 2, 2])
    inv = jnp.stack([jnp.stack([A, B, C], -1), jnp.stack([B, D, E], -1), jnp.stack([C, E, F], -1)], -2)
    inv = inv / det[..., None, None]
    return inv, jnp.einsum("...ij,...j->...i", inv, b)


def _gn_step(pose: Float[Array, "n sides 3"], G: Float[Array, "n sides 4 4"]) -> Float[Array, "n sides 3"]:
    """One damped Gauss–Newton step from the sums of :func:`_gram`, clipped (elementwise: one kernel)."""
    d = 1.0 + _DAMPING
    (A, B, C, D, E, F), det = _adjugate3(G[..., 0, 0] * d + 1e-9, G[..., 0, 1], G[..., 0, 2],
                                         G[..., 1, 1] * d + 1e-9, G[..., 1, 2], G[..., 2, 2] * d + 1e-9)
    g0, g1, g2 = -G[..., 0, 3], -G[..., 1, 3], -G[..., 2, 3]
    step = jnp.stack([jnp.clip((A * g0 + B * g1 + C * g2) / det, -_MAX_STEP_XY, _MAX_STEP_XY),
                      jnp.clip((B * g0 + D * g1 + E * g2) / det, -_MAX_STEP_XY, _MAX_STEP_XY),
                      jnp.clip((C * g0 + E * g1 + F * g2) / det, -_MAX_STEP_TH, _MAX_STEP_TH)], -1)
    return pose + step


def fit(outline: Outline, cls: Int[Array, " n"], pts: Float[Array, "n window 2"], mask: Bool[Array, "n window"],
        start: Float[Array, "n sides 3"]) -> tuple[Float[Array, "n sides 3"], Float[Array, "n sides"],
                                                    Float[Array, "n sides 3 3"]]:
    """``ITERATIONS`` damped Gauss–Newton steps from each start, on at most ``POINTS`` of each
    candidate's points (:func:`compact`). Returns the poses, their robust costs (Cauchy's
    ``c² log(1 + (r/c)²)`` over the points, which grows with every residual, so that a fit that
    explains fewer points never looks better for it, plus the free-space terms squared) and their
    Hessians ``JᵀWJ``."""
    pts, mask = compact(pts, mask)
    rho = jnp.sqrt(jnp.sum(pts**2, -1, keepdims=True))
    free = pts * (1.0 - outline.free_gap / jnp.where(rho > 0, rho, 1.0))
    both = jnp.concatenate([pts, free], 1)[:, None]  # [n, 1, 2 POINTS, 2]: one lookup for both
    mask2 = jnp.concatenate([mask, mask], 1)[:, None]
    is_free = (jnp.arange(2 * pts.shape[1], dtype=jnp.int32) >= pts.shape[1])[None, None]
    trig = lambda p: jnp.stack([jnp.cos(p[..., 2]), jnp.sin(p[..., 2])], -1)  # noqa: E731
    # A loop of a fixed trip count, not the steps unrolled: XLA compiles one step's code, not six copies,
    # and knows the count, so nothing waits on a test (on a GPU too: a loop of known trip count runs its
    # body that many times without reading a predicate back). The whole step has about 50 kernels fewer
    # than with the steps unrolled, compiles faster, gives the same results bit for bit and runs as fast.
    step = lambda _, pose: _gn_step(pose, _gram(outline, cls, pose, trig(pose), both, is_free, mask2))  # noqa: E731
    pose = jax.lax.fori_loop(0, ITERATIONS, step, start)
    pose = jnp.concatenate([pose[..., :2], wrap(pose[..., 2:])], -1)
    G, cost = _gram(outline, cls, pose, trig(pose), both, is_free, mask2, with_cost=True)
    return pose, cost, G[..., :3, :3]


def refine(outline: Outline, cls: Int[Array, " n"], run: Bool[Array, " n"], pts: Float[Array, "n window 2"],
           mask: Bool[Array, "n window"], pose_gp: Float[Array, "n 3"], cov_gp: Float[Array, "n 3 3"]) -> Refined:
    """Stage e′ for ``n`` candidates in S (see the module docstring): ``run`` marks the candidates of a
    class with an outline. Where the fit fails (not run, too few points, every side's residual too
    high: ``fitted`` False) the GP's pose and covariance stand and the sides carry the prior alone."""
    dt = pts.dtype
    if outline.prior_search is None:  # a model calibrated before the search: its learnt sides only
        offsets, use_side = outline.sides[cls], outline.side_mask[cls]  # [n, SIDES]
    else:
        offsets, use_side = search_sides(outline.sides[cls], outline.side_mask[cls])  # [n, SEARCH]
    start = jnp.concatenate([jnp.broadcast_to(pose_gp[:, None, :2], offsets.shape + (2,)),
                             (pose_gp[:, 2:3] + offsets)[..., None]], -1)
    pose, cost, H = fit(outline, cls, pts, mask, start)
    n_pts = jnp.minimum(jnp.sum(mask, -1), POINTS).astype(dt)  # as many as the fit used (compact)
    # Side probabilities: the fit's evidence (calibrated temperature) and the prior that the GP was right.
    search = None if outline.prior_search is None else outline.prior_search[cls].astype(dt)
    prior = side_prior(use_side, outline.prior_right[cls].astype(dt), search)
    rms = jnp.sqrt(cost / jnp.maximum(n_pts, 1.0)[:, None])
    ok_fit = run & (n_pts >= outline.min_points.astype(dt))
    good = ok_fit[:, None] & (rms <= outline.max_rms[cls][:, None]) & use_side
    fitted = jnp.any(good, -1)
    loglik = jnp.where(good, -outline.temperature[cls][:, None] * cost, -jnp.inf)
    logp_fit = jax.nn.log_softmax(jnp.where(use_side, prior + jnp.where(fitted[:, None], loglik, 0.0), -jnp.inf), -1)
    # Headings are the fits'. Positions on the side the GP read stay the GP's: it reads positions in
    # the frame the labels were made in, the map transformation's, which differs from the points' own
    # geometry by the transformation's errors (on the SPL field up to 3 cm at 4 m): on held-out views a
    # fit's position, or the GP's moved by the difference of two fits, was further from the truth than
    # the GP's (1.7–2.0 cm RMSE against 1.5), while the fit's heading was four times as good as the
    # GP's. On another side the GP's position is that of a misread (4.7 cm off on a walk-trained Nao's
    # held-out views, the fit's 3.0 cm; on a cart's, 1.5 and 2.0 cm): there the class takes whichever
    # was nearer on its held-out views (``side_position``).
    on_gp = jnp.abs(wrap(pose[..., 2] - pose_gp[:, None, 2])) < GP_SIDE
    if outline.side_position is None:
        on_gp = jnp.ones_like(on_gp)
    else:
        on_gp = on_gp | ~outline.side_position[cls][:, None]
    fitted_pose = jnp.concatenate([jnp.where(on_gp[..., None], pose_gp[:, None, :2], pose[..., :2]), pose[..., 2:]], -1)
    # Where nothing fitted, the sides are the GP's heading turned, with the prior alone.
    start_sides = start.at[..., 2].set(wrap(start[..., 2]))
    side_pose = jnp.where(good[..., None], fitted_pose, start_sides)
    side_logp = merge_sides(side_pose[..., 2], jnp.where(use_side, logp_fit, -jnp.inf))
    top_logp, top = jax.lax.top_k(side_logp, SIDES)  # the SIDES most probable go on, best first
    best = top[:, 0]
    take = lambda a: jnp.take_along_axis(a, best.reshape((-1,) + (1,) * (a.ndim - 1)), 1)[:, 0]  # noqa: E731
    # Heading variance: the residual variance times the inverse Hessian's heading entry, calibrated;
    # the position's stays the GP's.
    H_best, cost_best = take(H), take(cost)
    s2 = cost_best / jnp.maximum(n_pts - 3.0, 1.0)
    inv, _ = _solve3(H_best + 1e-9 * jnp.eye(3, dtype=dt)[None], jnp.zeros(H_best.shape[:-1], dt))
    var_th = s2 * inv[:, 2, 2] * outline.cov_scale[cls][:, 2]
    cov_fit = cov_gp.at[:, 2, :].set(0.0).at[:, :, 2].set(0.0).at[:, 2, 2].set(var_th)
    fit_ok = take(good)
    pose_out = jnp.where(fit_ok[:, None], take(side_pose), pose_gp)
    cov_out = jnp.where(fit_ok[:, None, None], cov_fit, cov_gp)
    return Refined(pose_out, cov_out, jnp.take_along_axis(side_pose, top[..., None], 1), top_logp, fit_ok,
                   jnp.where(fit_ok, take(rms), 0.0))


def merge_sides(heading: Float[Array, "n search"], logp: Float[Array, "n search"]) -> Float[Array, "n search"]:
    """Fits from several starts that end on one heading (within :data:`_MERGE`) are one side: the most
    probable of them keeps the probability of all (``-inf`` for the others), so that the sides that go
    on are distinct headings and not one heading several times over."""
    k = logp.shape[-1]
    ok = jnp.isfinite(logp)
    same = (jnp.abs(wrap(heading[:, :, None] - heading[:, None, :])) < _MERGE) & ok[:, :, None] & ok[:, None, :]
    first = (jnp.arange(k)[:, None] < jnp.arange(k)[None, :])[None]
    ahead = (logp[:, :, None] > logp[:, None, :]) | ((logp[:, :, None] == logp[:, None, :]) & first)  # [n, i, j]
    twin = jnp.any(same & ahead, 1)  # j has a more probable twin
    merged = jax.nn.logsumexp(jnp.where(same, logp[:, None, :], -jnp.inf), -1)  # [n, i]: over its twins j
    return jnp.where(twin | ~ok, -jnp.inf, merged)


def search_sides(offsets: Float[Array, "*n sides"], use: Bool[Array, "*n sides"]
                 ) -> tuple[Float[Array, "*n search"], Bool[Array, "*n search"]]:
    """The turns of the GP's heading every fit starts from: the class's learnt sides (``offsets``, used
    where ``use``), then :data:`SEARCH_DEG`'s, each used unless within 30° of a used learnt side."""
    fill = jnp.broadcast_to(jnp.radians(jnp.asarray(SEARCH_DEG, offsets.dtype)), offsets.shape[:-1] + (len(SEARCH_DEG),))
    near = jnp.abs(wrap(fill[..., :, None] - offsets[..., None, :])) < _SEARCH_APART
    return (jnp.concatenate([offsets, fill], -1),
            jnp.concatenate([use, ~jnp.any(use[..., None, :] & near, -1)], -1))


# The side hypotheses of a class with no learnt outline (and of every class of a model trained before
# outlines): the GP's heading and its quarter turns, the GP's side nine times in ten.
DEFAULT_SIDES = (0.0, 0.5 * 3.141592653589793, 3.141592653589793, -0.5 * 3.141592653589793)
DEFAULT_PRIOR_RIGHT = 0.9


def side_prior(use: Bool[Array, "n sides"], p_right: Float[Array, " n"], search: Float[Array, " n"] | None = None
               ) -> Float[Array, "n sides"]:
    """The prior log-probability of each side: the GP's (side 0) ``p_right``; the rest shared by the
    other used learnt sides (columns below ``SIDES``) and, with ``search``, the used searched turns
    (the columns after): those get ``search`` of it, the learnt sides the rest (each group all of it
    where the other has none). Unnormalised where sides are unused."""
    dt = p_right.dtype
    k = use.shape[1]
    col = np.arange(k)[None, :]
    # The used learnt sides and searched turns counted as sums of columns, which fuse with what uses
    # them (a reduction would be a kernel of its own on a CPU).
    u = use.astype(dt)
    k_l = sum((u[:, j:j + 1] for j in range(1, min(k, SIDES))), jnp.zeros_like(u[:, :1]))
    k_s = sum((u[:, j:j + 1] for j in range(SIDES, k)), jnp.zeros_like(u[:, :1]))
    f = jnp.zeros_like(p_right) if search is None else search
    f = jnp.where(k_s > 0, jnp.where(k_l > 0, f[:, None], 1.0), 0.0)
    rest = jnp.log1p(-p_right)[:, None]
    # Where a group is empty, its (unused) columns get any value: the caller masks them.
    return jnp.where(col == 0, jnp.log(p_right)[:, None],
                     jnp.where(col < SIDES, rest + jnp.log1p(-f) - jnp.log(jnp.maximum(k_l, 1.0)),
                               rest + jnp.log(jnp.maximum(f, 1e-30)) - jnp.log(jnp.maximum(k_s, 1.0))))


def prior_sides(pose: Float[Array, "n 3"], offsets: Float[Array, "n sides"], use: Bool[Array, "n sides"],
                p_right: Float[Array, " n"]) -> tuple[Float[Array, "n sides 3"], Float[Array, "n sides"]]:
    """Side hypotheses from the GP's pose alone: its heading turned by each offset, the GP's side with
    probability ``p_right`` and the others sharing the rest."""
    logp = jax.nn.log_softmax(jnp.where(use, side_prior(use, p_right), -jnp.inf), -1)
    side = jnp.broadcast_to(pose[:, None, :], offsets.shape + (3,))
    side = side.at[..., 2].set(wrap(pose[:, 2:3] + offsets))
    return side, logp


class Sides(eqx.Module):
    """Every candidate's pose and covariance after stage e′ and its side hypotheses (in S)."""

    pose: Float[Array, "cands 3"]
    cov: Float[Array, "cands 3 3"]
    side_pose: Float[Array, "cands sides 3"]
    side_logp: Float[Array, "cands sides"]
    refined: Bool[Array, " cands"]
    # Stage e″'s identity log-likelihoods where a tag reader was given (0 for candidates not read),
    # read on the fits' own rows (:func:`refine_candidates`); None without a reader.
    tag_ll: Float[Array, "cands ids"] | None = None


def refine_candidates(outline: "Outline | None", max_objects: int, cls: Int[Array, " cands"], ok: Bool[Array, " cands"],
                      scores: Float[Array, "cands classes"], xy: Float[Array, "cands window 2"],
                      mask: Bool[Array, "cands window"], pose: Float[Array, "cands 3"],
                      cov: Float[Array, "cands 3 3"], bucket: bool = False, axis_name=None, *,
                      reader: "TagReader | None" = None, ranges: Float[Array, "cands window"] | None = None,
                      intensities: Float[Array, "cands window"] | None = None) -> Sides:
    """Stage e′ on a scan's candidates: the ``max_objects`` kept candidates of classes with an outline
    that score highest for their class are refined (:func:`refine`); every other candidate keeps its
    GP pose and gets its class's side hypotheses from the GP's heading (:func:`prior_sides`). With
    ``bucket``, the fits run on the smallest of a few fixed counts of candidates that holds those
    present (:func:`~gtsjax.core.buckets.bucketed_rows`: a scan with one robot pays for one), as the
    pose GPs do (``e_pose.regress``; ``axis_name`` as there).

    With a tag ``reader`` (stage e″, :func:`~gtsjax.core.e_tags.read_tags`), the same chosen rows are
    read along their outlines from their sides (``ranges``, ``intensities``: the candidates' returns)
    in the same call, and come back with the fits' results by the same gather: the selection, the
    rows' gathers and their return to the scan's slots are shared, not done twice (each is a kernel
    of its own on a CPU)."""
    n = cls.shape[0]
    dt = pose.dtype
    if outline is None:
        offsets = jnp.broadcast_to(jnp.asarray(DEFAULT_SIDES, dt), (n, SIDES))
        side_pose, side_logp = prior_sides(pose, offsets, jnp.ones((n, SIDES), bool),
                                           jnp.full((n,), DEFAULT_PRIOR_RIGHT, dt))
        return Sides(pose, cov, side_pose, side_logp, jnp.zeros((n,), bool))
    side_pose, side_logp = prior_sides(pose, outline.sides[cls], outline.side_mask[cls], outline.prior_right[cls])
    sel = ok & outline.has[cls]
    own = jnp.take_along_axis(scores, cls[:, None], 1)[:, 0]
    k = min(max_objects, n)
    _, idx = jax.lax.top_k(jnp.where(sel, own, -jnp.inf), k)
    chosen = sel[idx]
    args = (cls[idx], chosen, xy[idx], mask[idx], pose[idx], cov[idx])
    if reader is not None:
        args = args + (ranges[idx], intensities[idx])

    def run(a):
        r = refine(outline, *a[:6])
        if reader is None:
            return r, None
        c, ch, pts, m, rr, it = a[0], a[1], a[2], a[3], a[6], a[7]
        return r, read_tags(reader, c, pts, rr, it, m & ch[:, None], r.side_pose, r.side_logp)[0]

    r, ll = bucketed_rows(run, args, jnp.sum(chosen, dtype=jnp.int32), axis_name) if bucket else run(args)
    # Every chosen row comes back (its reading does, fitted or not); a fit's results only where it fitted.
    back, src = slots_of(idx, chosen, n)
    parts = (r.pose, r.cov, r.side_pose, r.side_logp, r.fitted.astype(pose.dtype)[:, None]) + (
        () if ll is None else (ll.astype(pose.dtype),))
    rows = jnp.concatenate([a.reshape(k, -1) for a in parts], -1)[src]
    out, at = [], 0
    fitted_at = sum(a[0].size for a in parts[:4])
    got = back & (rows[:, fitted_at] > 0.5)
    for full, part in zip((pose, cov, side_pose, side_logp), parts[:4], strict=True):
        w = part[0].size
        out.append(jnp.where(got.reshape((-1,) + (1,) * (full.ndim - 1)), rows[:, at:at + w].reshape(full.shape), full))
        at += w
    tag_ll = None if ll is None else jnp.where(back[:, None], rows[:, fitted_at + 1:], 0.0)
    return Sides(*out, got, tag_ll)
