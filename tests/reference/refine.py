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
# gtsjax: ``e_refine.SEARCH_DEG``, ``_SEARCH_APART``, ``_GP_SIDE``, ``_MERGE``: the turns every fit also
# starts from (those within 30° of a used learnt side left out); a fit within 30° of the GP's heading is
# on its side; fits that end within 30° of each other are one side.
SEARCH_DEG = (45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0)
SEARCH_APART = math.radians(30.0)
GP_SIDE = math.radians(30.0)
MERGE = math.radians(30.0)


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
    prior_search: np.ndarray | None = None  # [classes]: None, the searched turns are not used
    side_position: np.ndarray | None = None  # [classes] bool: None, never

    @classmethod
    def of(cls, outline) -> "Outline":
        f = lambda v: np.asarray(v, np.float64)  # noqa: E731
        return cls(
            field=f(outline.field), lo=f(outline.lo), cell=f(outline.cell), has=np.asarray(outline.has, bool),
            sides=f(outline.sides), side_mask=np.asarray(outline.side_mask, bool),
            temperature=f(outline.temperature), prior_right=f(outline.prior_right), max_rms=f(outline.max_rms),
            cov_scale=f(outline.cov_scale), robust=float(outline.robust), free_gap=float(outline.free_gap),
            min_points=int(outline.min_points),
            prior_search=None if outline.prior_search is None else f(outline.prior_search),
            side_position=None if outline.side_position is None else np.asarray(outline.side_position, bool),
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
    # the three channels at once: the grid's (row, column, channel) at each point and whole channel
    # indices, where bilinear in the first two and exact in the third
    at = np.concatenate([np.repeat(uc.T, 3, axis=1), np.tile(np.arange(3.0), len(m))[None]])
    v = map_coordinates(ol.field[k], at, order=1, mode="nearest").reshape(-1, 3)
    out = (u - uc) * ol.cell[k]  # from the grid's edge out to the point (zero on the grid)
    beyond = np.hypot(out[:, 0], out[:, 1])
    off = beyond > 0
    d = v[:, 0] + beyond
    grad = np.where(off[:, None], out / np.where(off, beyond, 1.0)[:, None], v[:, 1:])
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
        r, J = residuals(ol, k, pose, np.concatenate([pts, free]))  # the points, then their free-space points
        r, rf, J, Jf = r[: len(pts)], r[len(pts):], J[: len(pts)], J[len(pts):]
        w = 1.0 / (1.0 + (r / c) ** 2)
        inside = (rf < 0).astype(np.float64)  # free-space points inside the outline count, weight 1
        H = (J * w[:, None]).T @ J + (Jf * inside[:, None]).T @ Jf
        b = J.T @ (w * r) + Jf.T @ (inside * rf)
        cost = float(np.sum(c * c * np.log1p((r / c) ** 2)) + np.sum(inside * rf**2))
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


def fit_many(ol: Outline, k: int, pts: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_one` from each of ``starts`` ``[h, 3]`` at once, the same steps written over a leading
    axis of starts (each start's arithmetic is its own): poses ``[h, 3]``, costs ``[h]``, ``H``
    ``[h, 3, 3]``. The reference's time went into NumPy's per-call cost on a few dozen points, one
    start and one step at a time (``tests/test_reference.py`` checks it against :func:`fit_one`)."""
    free = free_points(ol, pts)
    both = np.concatenate([pts, free])
    n, c = len(pts), ol.robust
    pose = np.asarray(starts, np.float64).copy()

    def normal(pose):
        h = len(pose)
        if n == 0:
            return np.zeros((h, 3, 3)), np.zeros((h, 3)), np.zeros(h)
        cs, sn = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        R = np.stack([np.stack([cs, -sn], -1), np.stack([sn, cs], -1)], -2)  # [h, 2, 2]
        dR = np.stack([np.stack([-sn, -cs], -1), np.stack([cs, -sn], -1)], -2)
        q = both[None] - pose[:, None, :2]  # [h, m, 2]
        r, g = lookup(ol, k, np.einsum("hmi,hij->hmj", q, R))
        r, g = r.reshape(h, -1), g.reshape(h, -1, 2)
        J = np.concatenate([-np.einsum("hmi,hji->hmj", g, R),
                            np.einsum("hmi,hmi->hm", g, np.einsum("hmi,hij->hmj", q, dR))[..., None]], -1)
        r, rf, J, Jf = r[:, :n], r[:, n:], J[:, :n], J[:, n:]
        w = 1.0 / (1.0 + (r / c) ** 2)
        inside = (rf < 0).astype(np.float64)
        H = np.einsum("hm,hmi,hmj->hij", w, J, J) + np.einsum("hm,hmi,hmj->hij", inside, Jf, Jf)
        b = np.einsum("hmi,hm->hi", J, w * r) + np.einsum("hmi,hm->hi", Jf, inside * rf)
        cost = np.sum(c * c * np.log1p((r / c) ** 2), 1) + np.sum(inside * rf**2, 1)
        return H, b, cost

    eye = np.eye(3)
    for _ in range(ITERATIONS):
        H, b, _ = normal(pose)
        A = H + DAMPING * H * eye + RIDGE * eye
        delta = np.linalg.solve(A, -b[..., None])[..., 0]
        delta[:, :2] = np.clip(delta[:, :2], -MAX_STEP_XY, MAX_STEP_XY)
        delta[:, 2] = np.clip(delta[:, 2], -MAX_STEP_TH, MAX_STEP_TH)
        pose = pose + delta
    pose[:, 2] = wrap(pose[:, 2])
    H, _, cost = normal(pose)
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
        poses[i], costs[i], hs[i] = fit_many(ol, int(cls[i]), p, start[i])
    return poses, costs, hs


def side_prior(p_right: float, use, search: float | None = None) -> np.ndarray:
    """Log-prior of each side: ``log p_right`` for the GP's own (side 0); the rest to the other used
    learnt sides (the first ``SIDES``) and the used searched turns (after them): ``search`` of it
    shared by the searched turns, the remainder by the learnt sides, all of it to one group where the
    other has no used side; ``-inf`` for unused sides."""
    use = np.asarray(use, bool)
    learnt = [j for j in range(1, min(len(use), SIDES)) if use[j]]
    searched = [j for j in range(SIDES, len(use)) if use[j]]
    share = 0.0 if not searched else (1.0 if not learnt else float(search or 0.0))
    out = np.full(len(use), -np.inf)
    with np.errstate(divide="ignore"):
        out[0] = math.log(p_right) if p_right > 0 else -math.inf
        for j in learnt:
            out[j] = math.log((1.0 - p_right) * (1.0 - share) / len(learnt)) if (1.0 - p_right) * (1.0 - share) > 0 else -math.inf
        for j in searched:
            out[j] = math.log((1.0 - p_right) * share / len(searched)) if (1.0 - p_right) * share > 0 else -math.inf
    return np.where(use, out, -np.inf)


def searched_starts(ol: Outline, k: int) -> tuple[list[float], list[bool]]:
    """Class ``k``'s turns of the GP's heading that fits start from, and which are used: its learnt
    sides, then ``SEARCH_DEG``'s unless within ``SEARCH_APART`` of a used learnt side (none used in a
    model without ``prior_search``)."""
    offs = [float(o) for o in ol.sides[k]]
    use = [bool(u) for u in ol.side_mask[k]]
    for d in SEARCH_DEG:
        a = math.radians(d)
        near = any(use[j] and abs(wrap(a - offs[j])) < SEARCH_APART for j in range(len(offs)))
        offs.append(a)
        use.append(ol.prior_search is not None and not near)
    return offs, use


def merge(heading, logp) -> np.ndarray:
    """Fits that end within ``MERGE`` of a more probable one (ties: the earlier) are dropped (``-inf``);
    each kept one gets the probability of every fit within ``MERGE`` of it, its own included."""
    n = len(logp)
    out = np.full(n, -np.inf)
    for j in range(n):
        if not np.isfinite(logp[j]):
            continue
        twins = [i for i in range(n) if np.isfinite(logp[i]) and abs(wrap(heading[i] - heading[j])) < MERGE]
        if any(logp[i] > logp[j] or (logp[i] == logp[j] and i < j) for i in twins if i != j):
            continue
        top = max(logp[i] for i in twins)
        out[j] = top + math.log(sum(math.exp(logp[i] - top) for i in twins))
    return out


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
    """Stage e′ (``e_refine.refine``) candidate by candidate: a fit from the GP's pose turned by each
    start of :func:`searched_starts`; a start is good where the candidate is run, has ``min_points``
    points or more, the start is used and its fit's RMS residual ``sqrt(cost / points)`` is at most the
    class's ``max_rms``. With a good start, the posterior is the prior (:func:`side_prior`) plus
    ``-temperature · cost`` over the good starts (the others impossible); each good start's pose is
    the fit's heading with the GP's position, or the fit's position where the class's
    ``side_position`` says so and the fit ended ``GP_SIDE`` or more from the GP's heading. Without a
    good start, the starts' headings with the prior alone. The starts are merged (:func:`merge`) and
    the ``SIDES`` most probable (ties: the earlier) are the sides, best first; the best gives the
    candidate's pose where its start was good, and its heading variance ``cost / (points − 3) ·
    (H + 10⁻⁹ I)⁻¹_θθ · cov_scale_θ`` (uncorrelated with the GP's position). Otherwise the GP's pose and
    covariance stand."""
    pose_gp, cov_gp = np.asarray(pose_gp, np.float64), np.asarray(cov_gp, np.float64)
    n, h = len(cls), ol.sides.shape[1] + len(SEARCH_DEG)
    out = Refined(pose_gp.copy(), cov_gp.copy(), np.zeros((n, SIDES, 3)), np.full((n, SIDES), -np.inf),
                  np.zeros(n, bool), np.zeros(n), np.zeros((n, h, 3)), np.zeros((n, h)))
    for i in range(n):
        k = int(cls[i])
        offs, use = searched_starts(ol, k)
        p = thin(np.asarray(pts[i], np.float64)[np.asarray(mask[i], bool)])
        n_pts = len(p)
        starts = [np.array([pose_gp[i, 0], pose_gp[i, 1], pose_gp[i, 2] + offs[j]]) for j in range(h)]
        fits = list(zip(*fit_many(ol, k, p, np.asarray(starts)), strict=True))
        good = np.zeros(h, bool)
        for j in range(h):
            out.fit_pose[i, j], out.cost[i, j] = fits[j][0], fits[j][1]
            rms = math.sqrt(fits[j][1] / max(n_pts, 1))
            good[j] = bool(run[i]) and n_pts >= ol.min_points and rms <= ol.max_rms[k] and use[j]
        prior = side_prior(ol.prior_right[k], use, None if ol.prior_search is None else ol.prior_search[k])
        if good.any():
            logp = log_normalise(np.where(good, prior - ol.temperature[k] * out.cost[i], -np.inf))
        else:
            logp = log_normalise(prior)
        logp = np.where(use, logp, -np.inf)
        side_pose = np.zeros((h, 3))
        for j in range(h):
            if not good[j]:
                side_pose[j] = [pose_gp[i, 0], pose_gp[i, 1], wrap(starts[j][2])]
                continue
            fitted = fits[j][0]
            own_xy = (ol.side_position is not None and ol.side_position[k]
                      and abs(wrap(fitted[2] - pose_gp[i, 2])) >= GP_SIDE)  # another side than the GP read
            side_pose[j] = [*(fitted[:2] if own_xy else pose_gp[i, :2]), fitted[2]]
        logp = merge(side_pose[:, 2], logp)
        order = sorted(range(h), key=lambda j: (-logp[j], j))[:SIDES]  # the most probable, best first
        out.side_pose[i], out.side_logp[i] = side_pose[order], logp[order]
        best = order[0]
        if good[best]:
            out.fitted[i] = True
            out.rms[i] = math.sqrt(fits[best][1] / max(n_pts, 1))
            out.pose[i] = side_pose[best]
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
