"""Stage e′, outline refinement, written out plainly from the module docstring of
``gtsjax.core.e_refine``: per candidate and per side hypothesis a fixed number of damped Gauss–Newton
steps on the outline's signed distance field (bilinear, ``scipy.ndimage.map_coordinates`` of order 1),
Cauchy-weighted, with a free-space hinge for each point moved ``free_gap`` back towards the sensor;
the side posterior from the fits' robust costs; the heading's variance from the Hessian; and which
candidates are refined. Float64, one candidate and one side at a time."""

import dataclasses
import math

import numpy as np
from scipy.ndimage import map_coordinates

from .track import wrap

# gtsjax: ``e_refine.ITERATIONS``, ``POINTS``, ``SIDES``, ``_MAX_STEP_XY``, ``_MAX_STEP_TH``, ``_DAMPING``,
# ``DEFAULT_SIDES``, ``DEFAULT_PRIOR_RIGHT`` (tests/test_refine.py checks that they agree).
ITERATIONS = 6
POINTS = 32  # a candidate's points the fit uses: every ceil(n / 32)-th
SIDES = 4
MAX_STEP_XY = 0.05  # m per step, per axis
MAX_STEP_TH = 0.35  # rad per step
DAMPING = 1e-3  # times the diagonal of the normal matrix
RIDGE = 1e-9  # added to the normal matrix's diagonal (every solve)
DEFAULT_SIDES = (0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi)
DEFAULT_PRIOR_RIGHT = 0.9


@dataclasses.dataclass
class Outline:
    """A model's ``e_refine.Outline`` as float64 NumPy arrays."""

    field: np.ndarray  # [classes, G, G, 3]: signed distance, d/dx, d/dy at lo + cell * (i, j)
    lo: np.ndarray  # [classes, 2]
    cell: np.ndarray  # [classes]
    has: np.ndarray  # [classes] bool
    sides: np.ndarray  # [classes, sides]
    side_mask: np.ndarray  # [classes, sides] bool
    temperature: np.ndarray  # [classes]
    prior_right: np.ndarray  # [classes]
    max_rms: np.ndarray  # [classes]
    cov_scale: np.ndarray  # [classes, 3]
    robust: float
    free_gap: float
    min_points: int

    @classmethod
    def of(cls, outline) -> "Outline":
        f = lambda v: np.asarray(v, np.float64)  # noqa: E731
        return cls(
            field=f(outline.field), lo=f(outline.lo), cell=f(outline.cell), has=np.asarray(outline.has, bool),
            sides=f(outline.sides), side_mask=np.asarray(outline.side_mask, bool),
            temperature=f(outline.temperature), prior_right=f(outline.prior_right), max_rms=f(outline.max_rms),
            cov_scale=f(outline.cov_scale), robust=float(outline.robust), free_gap=float(outline.free_gap),
            min_points=int(outline.min_points),
        )


def lookup(ol: Outline, k: int, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance ``[n]`` and gradient ``[n, 2]`` of class ``k``'s outline at object-frame points
    ``m`` ``[n, 2]``: the grid's three channels interpolated bilinearly at the point moved onto the
    grid; a point beyond the grid adds its distance from the grid's edge to the distance there, and
    its gradient is the unit vector from the edge point out to it."""
    m = np.asarray(m, np.float64).reshape(-1, 2)
    g = ol.field.shape[1]
    u = (m - ol.lo[k]) / ol.cell[k]  # grid coordinates
    uc = np.clip(u, 0.0, g - 1.0)
    v = np.stack([map_coordinates(ol.field[k, :, :, ch], uc.T, order=1, mode="nearest") for ch in range(3)], -1)
    d = v[:, 0].copy()
    grad = v[:, 1:].copy()
    for i in range(len(m)):
        out = (u[i] - uc[i]) * ol.cell[k]
        beyond = math.hypot(out[0], out[1])
        if beyond > 0:
            d[i] += beyond
            grad[i] = out / beyond
    return d, grad


def residuals(ol: Outline, k: int, pose, p: np.ndarray):
    """Residuals (signed distances) ``[n]`` of points ``p`` ``[n, 2]`` (in S) at ``pose`` and their
    Jacobians ``[n, 3]`` with respect to ``(x, y, θ)``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    R = np.array([[c, -s], [s, c]])
    dR = np.array([[-s, -c], [c, -s]])  # dR/dθ
    q = p - np.asarray(pose[:2])[None]
    m = q @ R  # rows: Rᵀ (p − t)
    r, g = lookup(ol, k, m)
    J = np.zeros((len(p), 3))
    J[:, :2] = -(g @ R.T)  # ∂m/∂t = −Rᵀ, so ∂r/∂t = −gᵀ Rᵀ
    J[:, 2] = np.einsum("ni,ni->n", g, q @ dR)  # ∂m/∂θ = dRᵀ/dθ (p − t)
    return r, J


def free_points(ol: Outline, pts: np.ndarray) -> np.ndarray:
    """Each point moved ``free_gap`` back along its beam towards the sensor (S's origin)."""
    out = np.zeros_like(pts)
    for i, p in enumerate(pts):
        rho = math.hypot(p[0], p[1])
        out[i] = p * (1.0 - ol.free_gap / rho) if rho > 0 else p * (1.0 - ol.free_gap)
    return out


def normal_equations(ol: Outline, k: int, pose, pts: np.ndarray, free: np.ndarray):
    """``H = Σ w J Jᵀ``, ``b = Σ w J r`` and the robust cost of the (masked) points ``pts`` at ``pose``:
    Cauchy weights ``1 / (1 + (r/c)²)`` and cost ``c² log(1 + (r/c)²)`` on the points, weight 1 and
    cost ``r²`` on the free-space points inside the outline (``r < 0``), nothing on the others."""
    H, b, cost = np.zeros((3, 3)), np.zeros(3), 0.0
    c = ol.robust
    if len(pts):
        r, J = residuals(ol, k, pose, pts)
        rf, Jf = residuals(ol, k, pose, free)
        for i in range(len(pts)):
            w = 1.0 / (1.0 + (r[i] / c) ** 2)
            H += w * np.outer(J[i], J[i])
            b += w * J[i] * r[i]
            cost += c * c * math.log1p((r[i] / c) ** 2)
            if rf[i] < 0:
                H += np.outer(Jf[i], Jf[i])
                b += Jf[i] * rf[i]
                cost += rf[i] ** 2
    return H, b, cost


def fit_one(ol: Outline, k: int, pts: np.ndarray, start) -> tuple[np.ndarray, float, np.ndarray]:
    """``ITERATIONS`` Levenberg–Marquardt-damped, reweighted Gauss–Newton steps of class ``k``'s outline
    against the points ``pts`` ``[n, 2]`` (in S) from ``start``, each step clipped per axis; the
    heading wrapped at the end. Returns the pose, its robust cost and its ``H``."""
    free = free_points(ol, pts)
    pose = np.asarray(start, np.float64).copy()
    for _ in range(ITERATIONS):
        H, b, _ = normal_equations(ol, k, pose, pts, free)
        A = H + DAMPING * np.diag(np.diag(H)) + RIDGE * np.eye(3)
        delta = np.linalg.solve(A, -b)
        delta[:2] = np.clip(delta[:2], -MAX_STEP_XY, MAX_STEP_XY)
        delta[2] = np.clip(delta[2], -MAX_STEP_TH, MAX_STEP_TH)
        pose = pose + delta
    pose[2] = wrap(pose[2])
    H, _, cost = normal_equations(ol, k, pose, pts, free)
    return pose, cost, H


def thin(p: np.ndarray) -> np.ndarray:
    """At most ``POINTS`` of a candidate's points, every ``ceil(n / POINTS)``-th from the first."""
    return p[:: max(1, -(-len(p) // POINTS))][:POINTS]


def fit(ol: Outline, cls, pts, mask, start):
    """:func:`fit_one` for candidates ``[n]`` (points ``[n, window, 2]`` under ``mask``) and starts
    ``[n, sides, 3]``: poses ``[n, sides, 3]``, costs ``[n, sides]``, Hessians ``[n, sides, 3, 3]``."""
    pts, start = np.asarray(pts, np.float64), np.asarray(start, np.float64)
    n, h = start.shape[:2]
    poses, costs, hs = np.zeros((n, h, 3)), np.zeros((n, h)), np.zeros((n, h, 3, 3))
    for i in range(n):
        p = thin(pts[i][np.asarray(mask[i], bool)])
        for j in range(h):
            poses[i, j], costs[i, j], hs[i, j] = fit_one(ol, int(cls[i]), p, start[i, j])
    return poses, costs, hs


def side_prior(p_right: float, use) -> np.ndarray:
    """Log-prior of each side: ``log p_right`` for the GP's own (side 0), the rest shared equally by
    the other used sides; ``-inf`` for unused sides."""
    k = max(int(np.sum(use)) - 1, 1)
    with np.errstate(divide="ignore"):
        out = np.array([math.log(p_right) if p_right > 0 else -math.inf] + [
            math.log((1.0 - p_right) / k) if p_right < 1 else -math.inf for _ in range(len(use) - 1)])
    return np.where(use, out, -np.inf)


def log_normalise(a: np.ndarray) -> np.ndarray:
    top = np.max(a)
    if not np.isfinite(top):
        return np.full_like(a, -np.inf)
    return a - (top + math.log(np.sum(np.exp(a - top))))


@dataclasses.dataclass
class Refined:
    pose: np.ndarray  # [n, 3]
    cov: np.ndarray  # [n, 3, 3]
    side_pose: np.ndarray  # [n, sides, 3]
    side_logp: np.ndarray  # [n, sides]
    fitted: np.ndarray  # [n]
    rms: np.ndarray  # [n]
    fit_pose: np.ndarray  # [n, sides, 3] every side's fit (position included)
    cost: np.ndarray  # [n, sides]


def refine(ol: Outline, cls, run, pts, mask, pose_gp, cov_gp) -> Refined:
    """Stage e′ (``e_refine.refine``) candidate by candidate: a fit per used side from the GP's pose
    turned by the side's offset; a side is good where the candidate is run, has ``min_points`` points
    or more and the side's RMS residual ``sqrt(cost / points)`` is at most the class's ``max_rms``.
    With a good side, the side posterior is the prior plus ``-temperature · cost`` over the good sides
    (the others impossible), each good side's pose is the GP's position with the fit's heading, and the
    most probable side gives the candidate's heading and heading variance ``cost / (points − 3) ·
    (H + 10⁻⁹ I)⁻¹_θθ · cov_scale_θ`` (uncorrelated with the GP's position). Without, the GP's pose and
    covariance stand and the sides are the GP's heading turned, with the prior alone."""
    pose_gp, cov_gp = np.asarray(pose_gp, np.float64), np.asarray(cov_gp, np.float64)
    n, h = len(cls), ol.sides.shape[1]
    out = Refined(pose_gp.copy(), cov_gp.copy(), np.zeros((n, h, 3)), np.full((n, h), -np.inf), np.zeros(n, bool),
                  np.zeros(n), np.zeros((n, h, 3)), np.zeros((n, h)))
    for i in range(n):
        k = int(cls[i])
        use = ol.side_mask[k]
        p = thin(np.asarray(pts[i], np.float64)[np.asarray(mask[i], bool)])
        n_pts = len(p)
        starts = [np.array([pose_gp[i, 0], pose_gp[i, 1], pose_gp[i, 2] + ol.sides[k, j]]) for j in range(h)]
        fits = [fit_one(ol, k, p, s) for s in starts]
        good = np.zeros(h, bool)
        for j in range(h):
            out.fit_pose[i, j], out.cost[i, j] = fits[j][0], fits[j][1]
            rms = math.sqrt(fits[j][1] / max(n_pts, 1))
            good[j] = bool(run[i]) and n_pts >= ol.min_points and rms <= ol.max_rms[k] and use[j]
        prior = side_prior(ol.prior_right[k], use)
        if good.any():
            logp = log_normalise(np.where(good, prior - ol.temperature[k] * out.cost[i], -np.inf))
        else:
            logp = log_normalise(prior)
        out.side_logp[i] = np.where(use, logp, -np.inf)
        for j in range(h):
            heading = fits[j][0][2] if good[j] else wrap(starts[j][2])
            out.side_pose[i, j] = [pose_gp[i, 0], pose_gp[i, 1], heading]
        best = int(np.argmax(out.side_logp[i]))
        if good[best]:
            out.fitted[i] = True
            out.rms[i] = math.sqrt(fits[best][1] / max(n_pts, 1))
            out.pose[i] = out.side_pose[i, best]
            s2 = fits[best][1] / max(n_pts - 3.0, 1.0)
            var_th = s2 * np.linalg.inv(fits[best][2] + RIDGE * np.eye(3))[2, 2] * ol.cov_scale[k, 2]
            cov = cov_gp[i].copy()
            cov[2, :] = 0.0
            cov[:, 2] = 0.0
            cov[2, 2] = var_th
            out.cov[i] = cov
    return out


def prior_sides(pose, offsets, use, p_right) -> tuple[np.ndarray, np.ndarray]:
    """Side hypotheses from the GP's pose alone: per candidate its heading turned by each offset,
    log-probabilities from :func:`side_prior` (normalised over the used sides)."""
    pose = np.asarray(pose, np.float64)
    n, h = np.shape(offsets)
    side = np.zeros((n, h, 3))
    logp = np.full((n, h), -np.inf)
    for i in range(n):
        logp[i] = log_normalise(side_prior(float(p_right[i]), np.asarray(use[i], bool)))
        for j in range(h):
            side[i, j] = [pose[i, 0], pose[i, 1], wrap(pose[i, 2] + offsets[i][j])]
    return side, logp


@dataclasses.dataclass
class Sides:
    pose: np.ndarray  # [n, 3]
    cov: np.ndarray  # [n, 3, 3]
    side_pose: np.ndarray  # [n, sides, 3]
    side_logp: np.ndarray  # [n, sides]
    refined: np.ndarray  # [n]


def refine_candidates(ol: Outline | None, max_objects: int, cls, ok, scores, pts, mask, pose, cov) -> Sides:
    """Stage e′ on a scan's candidates: of the candidates ``ok`` whose class has an outline, the
    ``max_objects`` with the highest score for their own class (ties: the earlier) are refined; a
    refined candidate whose fit succeeded takes its pose, covariance and sides from :func:`refine`,
    every other one keeps the GP's pose and covariance with the sides of :func:`prior_sides` (its
    class's offsets and prior; without an outline ``DEFAULT_SIDES`` and ``DEFAULT_PRIOR_RIGHT``)."""
    cls = np.asarray(cls, int)
    n = len(cls)
    pose, cov = np.asarray(pose, np.float64).copy(), np.asarray(cov, np.float64).copy()
    if ol is None:
        side_pose, side_logp = prior_sides(pose, np.tile(DEFAULT_SIDES, (n, 1)), np.ones((n, SIDES), bool),
                                           np.full(n, DEFAULT_PRIOR_RIGHT))
        return Sides(pose, cov, side_pose, side_logp, np.zeros(n, bool))
    side_pose, side_logp = prior_sides(pose, ol.sides[cls], ol.side_mask[cls], ol.prior_right[cls])
    refined = np.zeros(n, bool)
    eligible = [i for i in range(n) if ok[i] and ol.has[cls[i]]]
    chosen = sorted(eligible, key=lambda i: -float(scores[i][cls[i]]))[:max_objects]  # stable: ties keep order
    if chosen:
        idx = np.array(chosen)
        r = refine(ol, cls[idx], np.ones(len(idx), bool), np.asarray(pts)[idx], np.asarray(mask)[idx], pose[idx],
                   cov[idx])
        for a, i in enumerate(idx):
            if r.fitted[a]:
                pose[i], cov[i] = r.pose[a], r.cov[a]
                side_pose[i], side_logp[i] = r.side_pose[a], r.side_logp[a]
                refined[i] = True
    return Sides(pose, cov, side_pose, side_logp, refined)
