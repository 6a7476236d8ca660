"""The learnt outline of each mobile class (stage e′'s data), its side hypotheses and the calibration
of the refinement on held-out examples.

**The outline.** Every labelled training example's points, moved into the object's own frame by its
truth pose, land on the object's outline at the laser's height. They are summarised as a closed
polyline, dense and star-shaped about the object's centre: in each of ``BEARING_BINS`` bearing bins
about the centre, the median range of the points that fall in it (bins no view reached are
interpolated from their neighbours). The step needs a signed distance, so the polyline becomes a
signed distance field (and its gradient) on a ``GRID × GRID`` grid around it.

Why a polyline of medians and not an occupancy grid accumulated directly: the median sits on the
surface whatever the range noise and the label's error, where an accumulated band of hits is as
thick as the noise and its edge (where a grid's inside would end) lies outside the true surface by
half that thickness, a centimetre of bias in every refined position. The price is the star shape:
an outline that a ray from the centre crosses twice (a deep notch) is filled in; a robot's body at
the height of a laser, a convex or nearly convex shape, is not affected.

**Side hypotheses.** The outline turned by α is compared with itself (the mean distance of the
turned polyline from the outline, the best translation within ±6 cm): the turns where that is a local
minimum, at least 30° from 0 and from one another, up to three, are the sides a partial view may
be taken for, and the hypotheses stage e′ tests besides the GP's heading (in practice the GP's
held-out misreads give them: :func:`fit_outlines`). Stage e′ also starts fits every 45° around the
GP's heading (``e_refine.SEARCH_DEG``), for the sides the labels rarely showed.

**Calibration** (held-out examples of the class, refined from the GP's poses from every start as the
step does; a class whose refined headings are less precise there than the GP's, by the median error,
keeps the GP's: its outline is not used):
``max_rms`` (a fit with a larger residual fails: 1.5 × the 99th percentile of the right side's
residual), the temperature and the priors of the side posterior (that the GP read the right side,
and the searched turns' share of the rest, never below 5 %: :data:`SEARCH_SHARES`; maximum
likelihood of the true side), whether a fit on another side than the GP read takes its own position
(where on these views it was nearer the truth than the GP's, with at least :data:`MIN_OFF_SIDE` of
them), and the factors that calibrate the covariance ``s² H⁻¹`` (as the GP variances are calibrated).
"""

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.e_pose import PoseRegressor, regress_one_class, to_sensor_frame
from ..core.e_refine import DEFAULT_PRIOR_RIGHT, DEFAULT_SIDES, GP_SIDE, POINTS, SIDES, Outline, fit, search_sides
from ..core.geometry import compose, relative, wrap
from ..drivers.evaluation import heading_error
from ..io.logs import ScanLog
from .calibrate import robust_variance_scale
from .labels import Examples, window_points

BEARING_BINS = 128
GRID = 64
MIN_POINTS = 5
ROBUST = 0.015  # m: Cauchy scale of the residuals (a URG-04LX's range noise is about 1 cm)
FREE_GAP = 0.03  # m
_F32 = jnp.float32


def candidate_points(logs: Sequence[ScanLog], ex: Examples, window: int, intensities: bool = False):
    """The points in S ``[n, window, 2]`` (float32) and their mask of the examples ``ex`` (all from the
    labelled logs: ``ex.where[:, 0] >= 0``), as the step's candidate windows hold them; with
    ``intensities``, also their intensities ``[n, window]`` (0 where a log has none)."""
    n = len(ex.cls)
    pts = np.zeros((n, window, 2), np.float32)
    mask = np.zeros((n, window), bool)
    inten = np.zeros((n, window), np.float32)
    for li, log in enumerate(logs):
        rows = np.flatnonzero(ex.where[:, 0] == li)
        if rows.size == 0:
            continue
        scan = ex.where[rows, 1]
        pts[rows], mask[rows], beam = window_points(log, scan, ex.where[rows, 2], ex.where[rows, 3], window, np.float32)
        if intensities and log.intensities is not None:
            inten[rows] = np.where(mask[rows], np.nan_to_num(log.intensities[scan[:, None], beam]), 0.0)
    return (pts, mask, inten) if intensities else (pts, mask)


def truth_in_sensor(ex: Examples) -> np.ndarray:
    """Each example's object pose in S ``[n, 3]`` from its ORS and its ORS-relative target."""
    return compose(np.concatenate([ex.origin, ex.heading[:, None]], -1), ex.target)


def object_points(pts: np.ndarray, mask: np.ndarray, pose_s: np.ndarray) -> np.ndarray:
    """The masked points of every example in its object's frame, stacked ``[m, 2]``."""
    rel = relative(np.broadcast_to(pose_s[:, None, :], pts.shape[:2] + (3,)), pts.astype(np.float64))
    return rel[mask]


def outline_radii(points: np.ndarray, bins: int = BEARING_BINS) -> np.ndarray:
    """The star-shaped outline: the median range of the points in each bearing bin (bin ``i`` centred
    on ``2π (i + ½) / bins − π``), empty bins interpolated around the circle."""
    bearing = np.arctan2(points[:, 1], points[:, 0])
    rho = np.hypot(points[:, 0], points[:, 1])
    b = np.clip(((bearing + math.pi) / (2 * math.pi) * bins).astype(int), 0, bins - 1)
    radii = np.full(bins, np.nan)
    for i in range(bins):
        sel = rho[b == i]
        if sel.size >= 3:
            radii[i] = np.median(sel)
    ok = np.isfinite(radii)
    if ok.sum() < 3:
        raise ValueError("too few views of the object for an outline")
    centres = np.arange(bins)
    return np.interp(centres, centres[ok], radii[ok], period=bins)


def polyline(radii: np.ndarray) -> np.ndarray:
    """The outline's vertices ``[bins, 2]`` in the object's frame."""
    phi = 2 * math.pi * (np.arange(radii.size) + 0.5) / radii.size - math.pi
    return np.stack([radii * np.cos(phi), radii * np.sin(phi)], -1)


def _segment_distance(p: np.ndarray, verts: np.ndarray) -> np.ndarray:
    a, b = verts, np.roll(verts, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("pvi,vi->pv", p[:, None, :] - a[None], ab) / np.sum(ab**2, -1)[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(p[:, None, :] - closest, axis=-1), axis=1)


def _inside(p: np.ndarray, radii: np.ndarray) -> np.ndarray:
    bins = radii.size
    phi = np.arctan2(p[:, 1], p[:, 0])
    pos = (phi + math.pi) / (2 * math.pi) * bins - 0.5
    r_at = np.interp(pos, np.arange(bins), radii, period=bins)
    return np.hypot(p[:, 0], p[:, 1]) < r_at


def distance_field(radii: np.ndarray, grid: int = GRID, margin: float = 0.12) -> tuple[np.ndarray, np.ndarray, float]:
    """The signed distance (negative inside) of the outline and its gradient on a ``grid × grid`` grid
    ``[grid, grid, 3]``, its lower corner and cell size."""
    half = float(np.max(radii)) + margin
    cell = 2 * half / (grid - 1)
    lo = np.array([-half, -half])
    ax = lo[0] + cell * np.arange(grid)
    gx, gy = np.meshgrid(ax, ax, indexing="ij")
    p = np.stack([gx.ravel(), gy.ravel()], -1)
    d = _segment_distance(p, polyline(radii))
    sdf = np.where(_inside(p, radii), -d, d).reshape(grid, grid)
    ddx, ddy = np.gradient(sdf, cell)
    return np.stack([sdf, ddx, ddy], -1), lo, cell


def _lookup_np(field, lo, cell, m):
    g = field.shape[0]
    u = np.clip((m - lo) / cell, 0, g - 1)
    i0 = np.clip(np.floor(u).astype(int), 0, g - 2)
    f = u - i0
    v = lambda di, dj: field[i0[..., 0] + di, i0[..., 1] + dj, 0]  # noqa: E731
    fx, fy = f[..., 0], f[..., 1]
    return (1 - fx) * ((1 - fy) * v(0, 0) + fy * v(0, 1)) + fx * ((1 - fy) * v(1, 0) + fy * v(1, 1))


def self_match(radii: np.ndarray, field, lo, cell, step_deg: float = 1.0, shift: float = 0.06) -> np.ndarray:
    """For each turn ``α = 0, 1, …, 359°``: the mean |distance| from the outline of the outline turned
    by α, at the best translation within ±``shift`` (1 cm grid)."""
    verts = polyline(radii)
    ts = np.arange(-shift, shift + 1e-9, 0.01)
    tx, ty = np.meshgrid(ts, ts, indexing="ij")
    t = np.stack([tx.ravel(), ty.ravel()], -1)  # [T, 2]
    out = []
    for a in np.radians(np.arange(0.0, 360.0, step_deg)):
        c, s = math.cos(a), math.sin(a)
        turned = verts @ np.array([[c, s], [-s, c]])  # rows: Rot(a) v
        m = turned[None] + t[:, None]  # [T, V, 2]
        out.append(np.min(np.mean(np.abs(_lookup_np(field, lo, cell, m)), -1)))
    return np.asarray(out)


def side_offsets(match: np.ndarray, most: int = SIDES - 1, apart_deg: float = 30.0) -> list[float]:
    """The turns (degrees, in (−180, 180]) of the ``most`` lowest local minima of ``match`` (one value
    per degree), at least ``apart_deg`` from 0 and from one another."""
    n = match.size
    minima = [i for i in range(n) if match[i] <= match[(i - 1) % n] and match[i] <= match[(i + 1) % n]]
    chosen: list[int] = []
    for i in sorted(minima, key=lambda i: match[i]):
        deg = ((i + 180) % 360) - 180
        if abs(deg) < apart_deg or any(abs(((i - j + 180) % 360) - 180) < apart_deg for j in chosen):
            continue
        chosen.append(i)
        if len(chosen) == most:
            break
    return [float(((i + 180) % 360) - 180) for i in chosen]


# An outline whose half-turn lies within this of itself (mean distance, m, at the best shift) looks the
# same from the front and the back: a 36 × 24 cm box is within 0.1 mm (1–1.5 mm as learnt from labelled
# views, their labels' errors blurring it), a base with its front corners
# cut off 6 cm is 6 mm away, the Nao-like outline 18 mm.
HALF_TURN_M = 0.003
# Training views of a class the symmetry is judged on (evenly spaced: no random draw).
SYMMETRY_VIEWS = 2000
# The sides of a class alike turned half a turn where no outline is used: the GP's heading and its
# half-turn, as likely.
HALF_TURN_SIDES = (0.0, math.pi, 0.0, 0.0)
HALF_TURN_MASK = (True, True, False, False)


def half_turn_distance(radii: np.ndarray) -> float:
    """How far (m) the outline turned by 180° lies from itself: :func:`self_match` at 180° alone."""
    f, lo, cell = distance_field(radii)
    verts = polyline(radii)
    ts = np.arange(-0.06, 0.06 + 1e-9, 0.01)
    tx, ty = np.meshgrid(ts, ts, indexing="ij")
    m = -verts[None] + np.stack([tx.ravel(), ty.ravel()], -1)[:, None]  # Rot(π) v, shifted
    return float(np.min(np.mean(np.abs(_lookup_np(f, lo, cell, m)), -1)))


def half_turn_symmetry(logs: Sequence[ScanLog], ex: Examples, is_held: np.ndarray, classes: tuple[str, ...],
                       mobiles: tuple[str, ...], window: int, given: "dict[str, int] | None" = None
                       ) -> tuple[dict[str, int], dict[str, float], list[dict]]:
    """Which mobile classes look the same turned by half a turn (their outline from the training views
    at their labelled poses, :func:`outline_radii`, within :data:`HALF_TURN_M` of its half-turn), or
    as ``given`` (``--heading-turns``: 1 or 2 per class): the heading's symmetry order per class (2
    for those; the rest are left out), the distance per class (mm) and the rows of the training
    report's table of learnt values (:func:`~gtsjax.train.bounds.entry`). A view of such a class tells
    its heading only up to a half-turn, so its heading is regressed modulo π
    (:func:`~gtsjax.train.pose.fit_pose_regressors`) and the other half-turn kept as a side
    hypothesis as likely as the read (:func:`fit_outlines`)."""
    from . import bounds

    given = given or {}
    turns, dist, rows = {}, {}, []
    own = ex.where[:, 0] >= 0
    for name in mobiles:
        idx = np.flatnonzero((ex.cls == classes.index(name)) & ~is_held & own)
        d = math.nan
        if idx.size >= 50:
            idx = idx[np.linspace(0, idx.size - 1, min(idx.size, SYMMETRY_VIEWS)).astype(int)]
            sub = ex.take(idx)
            pts, mask = candidate_points(logs, sub, window)
            d = half_turn_distance(outline_radii(object_points(pts, mask, truth_in_sensor(sub))))
            dist[name] = round(1000 * d, 2)
        n = given.get(name, 2 if d <= HALF_TURN_M else 1)
        if n == 2:
            turns[name] = 2
        decided = "heading read modulo 180°" if n == 2 else "front told from back"
        if name in given:
            rows.append(bounds.entry(bounds.HALF_TURN, name, round(1000 * d, 2) if math.isfinite(d) else 0.0,
                                     "set", f"--heading-turns {name}={n}: {decided}"))
        elif math.isfinite(d):
            rows.append(bounds.entry(bounds.HALF_TURN, name, round(1000 * d, 2), "learnt",
                                     f"its outline from {idx.size} labelled views: {decided} "
                                     f"({'within' if n == 2 else 'over'} {1000 * HALF_TURN_M:g} mm)"))
    return turns, dist, rows


_fit = jax.jit(fit)


def _single_outline(radii: np.ndarray) -> Outline:
    """One class's outline (class 0) with nothing calibrated: what the fits of :func:`learn_outline`
    run against."""
    f, lo, cell = distance_field(radii)
    one = lambda v, dt=_F32: jnp.asarray(np.asarray(v)[None], dt)  # noqa: E731
    return Outline(field=one(f), lo=one(lo), cell=one(cell), has=jnp.ones(1, bool), sides=jnp.zeros((1, SIDES), _F32),
                   side_mask=jnp.zeros((1, SIDES), bool).at[0, 0].set(True), temperature=jnp.zeros(1, _F32),
                   prior_right=jnp.ones(1, _F32), max_rms=jnp.full(1, 1.0, _F32), cov_scale=jnp.ones((1, 3), _F32),
                   robust=jnp.asarray(ROBUST, _F32), free_gap=jnp.asarray(FREE_GAP, _F32),
                   min_points=jnp.asarray(MIN_POINTS, jnp.int32))


def learn_outline(pts: np.ndarray, mask: np.ndarray, truth: np.ndarray, iterations: int = 2) -> np.ndarray:
    """The outline's radii from views ``pts``/``mask`` of the object at poses ``truth`` (in S).

    The labels' poses in S come through the scan's estimated map transformation, whose errors move the
    object by a centimetre or more, more with range: points accumulated in those frames blur the
    outline (by 2–3 cm on the SPL field). So the outline is re-estimated ``iterations`` times with each
    view aligned to the previous outline (stage e′'s own fit, started from the label), the views that
    converge within 5 cm and 10° of their label only, in the frame of their mean label (the
    alignment's own drift taken out)."""
    radii = outline_radii(object_points(pts, mask, truth))
    for _ in range(iterations):
        outline = _single_outline(radii)
        start = np.concatenate([truth[:, None, :], np.repeat(truth[:, None, :], SIDES - 1, 1)], 1)
        poses, _, _ = refine_examples(outline, 0, pts, mask, start[:, 0], offsets=np.zeros(SIDES))
        fitted = poses[:, 0]
        off = relative(truth, fitted)  # the fit in the label's frame
        ok = (np.hypot(off[:, 0], off[:, 1]) < 0.05) & (np.abs(off[:, 2]) < math.radians(10))
        if ok.sum() < 50:
            break
        drift = np.mean(off[ok], 0)
        frame = compose(fitted[ok], relative(drift, np.zeros(3)))  # the fit, less the mean drift
        radii = outline_radii(object_points(pts[ok], mask[ok], frame))
    return radii


def misread_modes(err: np.ndarray, most: int = SIDES - 1, apart_deg: float = 30.0, width_deg: float = 15.0,
                  min_count: int = 5) -> list[float]:
    """The headings (degrees) that the GP's misreads cluster at: up to ``most`` peaks of the held-out
    heading errors beyond ``apart_deg``, each the mean of the errors within ``width_deg`` of the densest
    1°-spaced window, at least ``apart_deg`` from 0 and the others, with ``min_count`` errors or more."""
    deg = np.degrees(wrap(np.asarray(err, np.float64)))
    deg = deg[np.abs(deg) > apart_deg]
    chosen: list[float] = []
    for _ in range(most):
        centres = np.arange(-180.0, 180.0, 1.0)
        dist = np.abs(((deg[None, :] - centres[:, None]) + 180) % 360 - 180)
        count = np.sum(dist <= width_deg, 1)
        for c in chosen:
            count[np.abs(((centres - c) + 180) % 360 - 180) < apart_deg] = 0
        count[np.abs(centres) < apart_deg] = 0
        i = int(np.argmax(count))
        if count[i] < min_count:
            break
        near = deg[dist[i] <= width_deg]
        chosen.append(float(np.degrees(np.angle(np.mean(np.exp(1j * np.radians(near)))))))
    return chosen




def searched_sides(outline: Outline, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Class ``k``'s turns of the GP's heading that stage e′'s fits start from, and which are used
    (:func:`gtsjax.core.e_refine.search_sides`)."""
    offs, use = search_sides(outline.sides[k], outline.side_mask[k])
    return np.asarray(offs, np.float64), np.asarray(use, bool)


def refine_examples(outline: Outline, k: int, pts, mask, pose_gp, chunk: int = 1024, offsets=None):
    """Stage e′'s fit on examples of class ``k`` from their GP poses turned by ``offsets`` (default:
    the turns the step searches, :func:`searched_sides`): every start's pose, cost and Hessian (host arrays)."""
    offsets = searched_sides(outline, k)[0] if offsets is None else np.asarray(offsets)
    starts = np.concatenate([np.broadcast_to(pose_gp[:, None, :2], (len(pose_gp), len(offsets), 2)),
                             (pose_gp[:, 2:3] + offsets[None, :])[..., None]], -1)
    poses, costs, hs = [], [], []
    for i in range(0, len(pts), chunk):
        sl = slice(i, i + chunk)
        n = len(pts[sl])
        pad = chunk - n
        args = [np.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1)) for a in (pts[sl], mask[sl], starts[sl])]
        p, c, h = _fit(outline, jnp.full((chunk,), k, jnp.int32), jnp.asarray(args[0]), jnp.asarray(args[1]),
                       jnp.asarray(args[2], _F32))
        poses.append(np.asarray(p, np.float64)[:n])
        costs.append(np.asarray(c, np.float64)[:n])
        hs.append(np.asarray(h, np.float64)[:n])
    return np.concatenate(poses), np.concatenate(costs), np.concatenate(hs)


def side_prior_np(usable: np.ndarray, prior_right: float, search: float) -> np.ndarray:
    """:func:`gtsjax.core.e_refine.side_prior` for one class's used sides (NumPy; ``-inf`` where unused)."""
    col = np.arange(len(usable))
    k_l = int(np.sum(usable & (col > 0) & (col < SIDES)))
    k_s = int(np.sum(usable & (col >= SIDES)))
    f = (search if k_l else 1.0) if k_s else 0.0
    with np.errstate(divide="ignore"):
        out = np.where(col == 0, math.log(prior_right), np.where(
            col < SIDES, np.log1p(-prior_right) + np.log1p(-f) - math.log(max(k_l, 1)),
            np.log1p(-prior_right) + np.log(max(f, 1e-30)) - math.log(max(k_s, 1))))
    return np.where(usable, out, -np.inf)


def side_logp(cost, usable, temperature, prior_right, search=0.0):
    """The side posterior ``[n, sides]`` of :func:`gtsjax.core.e_refine.refine` (NumPy, before the
    fits that end on one heading are merged)."""
    ll = np.where(usable[None], side_prior_np(usable, prior_right, search)[None] - temperature * cost, -np.inf)
    ll = ll - ll.max(1, keepdims=True)
    return ll - np.log(np.sum(np.exp(ll), 1, keepdims=True))


def _side_nll(cost, right, usable, temperature, prior_right, search=0.0):
    """Mean negative log-probability of the right heading: of the sides whose fit lands on it."""
    p = np.exp(side_logp(cost, usable, temperature, prior_right, search))
    return -np.mean(np.log(np.maximum(np.sum(np.where(right, p, 0.0), 1), 1e-12)))


# The share of a misread's prior that the searched turns get (``Outline.prior_search``), chosen on
# held-out views among these. Never below 5 %: the held-out views come from the recording the GP
# was trained on, and cannot show how often it misreads a side that recording rarely showed.
SEARCH_SHARES = (0.05, 0.2, 0.5, 0.8)
# Held-out views whose fit left the GP's side that the choice of their position is made on: with fewer,
# the GP's position stands.
MIN_OFF_SIDE = 10


def calibrate_outline(outline: Outline, k: int, pts, mask, pose_gp, truth, right_deg: float = 20.0,
                      turns: int = 1) -> tuple[Outline, dict]:
    """Calibrate class ``k``'s refinement on held-out examples (see the module docstring); returns the
    outline and a summary: GP and refined errors side by side (headings modulo ``2π/turns``: a class
    alike turned half a turn is judged on what its views can tell)."""
    poses, cost, H = refine_examples(outline, k, pts, mask, pose_gp)
    usable = searched_sides(outline, k)[1]
    n_pts = np.minimum(mask.sum(1), POINTS).astype(float)  # as many as the fit uses (e_refine.compact)
    err_th = np.abs(wrap(poses[..., 2] - truth[:, None, 2]))  # [n, sides]
    err_th = np.where(usable[None], err_th, np.inf)
    label = np.argmin(err_th, 1)
    has_right = (err_th[np.arange(len(label)), label] < math.radians(right_deg)) & (n_pts >= MIN_POINTS)
    rms = np.sqrt(cost / np.maximum(n_pts, 1)[:, None])
    rms_right = rms[np.arange(len(label)), label][has_right]
    max_rms = 1.5 * float(np.quantile(rms_right, 0.99)) if rms_right.size >= 20 else 0.05
    good = has_right & (rms[np.arange(len(label)), label] <= max_rms)
    right = (err_th < math.radians(right_deg)) & (rms <= max_rms)
    best = (math.inf, 1.0, 0.9, SEARCH_SHARES[0])
    c_good, r_good = np.where(rms <= max_rms, cost, 1e3)[good], right[good]
    for temp in np.geomspace(1.0, 1e6, 61):
        for pr in (0.3, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98, 0.99):
            for sh in SEARCH_SHARES:
                nll = _side_nll(c_good, r_good, usable, temp, pr, sh) if good.any() else 0.0
                if nll < best[0]:
                    best = (nll, float(temp), pr, sh)
    _, temperature, prior_right, search = best
    # The side each example would get, its pose and covariance factor s² H⁻¹.
    prior = side_prior_np(usable, prior_right, search)
    score = np.where(usable[None] & (rms <= max_rms), prior[None] - temperature * cost, -np.inf)
    fitted = np.isfinite(score).any(1) & (n_pts >= MIN_POINTS)
    chosen = np.argmax(score, 1)
    idx = np.arange(len(chosen))
    # Where the fit left the side the GP read, whose position is nearer the truth there: the GP's (read
    # for a side it misread) or the fit's? The step takes the fit's where it was nearer on these views.
    off_gp = fitted & (np.abs(wrap(poses[idx, chosen, 2] - pose_gp[:, 2])) >= GP_SIDE)
    rmse = lambda p: float(np.sqrt(np.mean(np.sum((p[off_gp] - truth[off_gp, :2]) ** 2, 1)))) if off_gp.any() else math.nan  # noqa: E731
    off_rmse = {"gp": rmse(pose_gp[:, :2]), "fit": rmse(poses[idx, chosen, :2])}
    side_position = bool(off_gp.sum() >= MIN_OFF_SIDE and off_rmse["fit"] < off_rmse["gp"])
    pose_r = np.concatenate([np.where((off_gp & side_position)[:, None], poses[idx, chosen, :2], pose_gp[:, :2]),
                             np.where(fitted, poses[idx, chosen, 2], pose_gp[:, 2])[:, None]], -1)
    s2 = cost[idx, chosen] / np.maximum(n_pts - 3, 1)
    cov = s2[:, None, None] * np.linalg.inv(H[idx, chosen] + 1e-9 * np.eye(3))
    err = pose_r - truth
    err[:, 2] = wrap(err[:, 2])
    right = fitted & (np.abs(err[:, 2]) < math.radians(right_deg))
    scale = np.ones(3)
    v = cov[right, 2, 2]
    ok = v > 0
    if ok.sum() >= 20:
        scale[2] = robust_variance_scale(err[right][ok, 2] ** 2 / v[ok])
    upd = lambda a, v: a.at[k].set(v)  # noqa: E731
    outline = Outline(
        field=outline.field, lo=outline.lo, cell=outline.cell, has=outline.has, sides=outline.sides,
        side_mask=outline.side_mask, temperature=upd(outline.temperature, temperature),
        prior_right=upd(outline.prior_right, prior_right), max_rms=upd(outline.max_rms, max_rms),
        cov_scale=upd(outline.cov_scale, jnp.asarray(scale, _F32)), robust=outline.robust,
        free_gap=outline.free_gap, min_points=outline.min_points,
        prior_search=upd(outline.prior_search, search), side_position=upd(outline.side_position, side_position))
    e_gp = pose_gp - truth
    e_gp[:, 2] = wrap(e_gp[:, 2])

    def summary(e):
        th = np.degrees(np.abs(heading_error(e[:, 2], turns)))
        return {"position_rmse_cm": round(100 * float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, 1)))), 2),
                "heading_median_deg": round(float(np.median(th)), 2),
                "heading_rmse_deg": round(float(np.sqrt(np.mean(th**2))), 2),
                "misread_fraction": round(float(np.mean(th > 30)), 4)}

    return outline, {"examples": int(len(truth)), "fitted_fraction": round(float(fitted.mean()), 4),
                     "max_rms_mm": round(1000 * max_rms, 2), "temperature": round(temperature, 1),
                     "prior_right": prior_right, "prior_search": search,
                     "off_side": {"examples": int(off_gp.sum()), "min_examples": MIN_OFF_SIDE,
                                  "position_from": "fit" if side_position else "gp",
                                  **{f"{k}_rmse_cm": round(100 * v, 2) for k, v in off_rmse.items() if math.isfinite(v)}}, "cov_scale": [round(float(v), 3) for v in scale],
                     "gp": summary(e_gp), "refined": summary(err)}


def fit_outlines(logs: Sequence[ScanLog], ex: Examples, is_held: np.ndarray, classes: tuple[str, ...],
                 mobiles: tuple[str, ...], pose: Sequence[PoseRegressor | None], window: int,
                 rng: np.random.Generator, *, max_examples: int = 6000,
                 max_calibration: int = 4000, turns: "dict[str, int] | None" = None) -> tuple[Outline | None, dict]:
    """Outline, side hypotheses and calibration of each mobile class (see the module docstring).
    Returns the :class:`Outline` (``None`` if no class has enough views) and a summary per class. A
    mobile class without an outline gets the default side hypotheses (the GP's heading's quarter
    turns, ``e_refine.DEFAULT_SIDES``).

    The side hypotheses of a class are the headings its GP's held-out misreads cluster at
    (:func:`misread_modes`): the sides a view is taken for in fact. With fewer than five misreads to
    go by, the outline's own near-symmetries (:func:`self_match`) stand in.

    A class alike turned half a turn (``turns``, :func:`half_turn_symmetry`) has its half-turn as a side
    hypothesis, as likely as the read (its GP reads the heading modulo π); its held-out heading errors
    are judged modulo π. Where no class has an outline but such a class exists, the outline is kept,
    used by none, for its side hypotheses."""
    turns = turns or {}
    arrays = _OutlineArrays.blank(len(classes))
    report, held = {}, {}
    own = ex.where[:, 0] >= 0
    for name in mobiles:
        k = classes.index(name)
        arrays.sides[k], arrays.side_mask[k] = DEFAULT_SIDES, True
        if name in turns:
            arrays.sides[k], arrays.side_mask[k], arrays.prior_right[k] = HALF_TURN_SIDES, HALF_TURN_MASK, 0.5
        idx = np.flatnonzero((ex.cls == k) & ~is_held & own)
        if idx.size < 50 or pose[k] is None:
            report[name] = {"outline": False, "why": f"only {idx.size} labelled views"}
            continue
        sub = ex.take(rng.choice(idx, min(idx.size, max_examples), replace=False))
        radii = learn_outline(*candidate_points(logs, sub, window), truth_in_sensor(sub))
        f, lo_k, cell_k = distance_field(radii)
        csub, pose_gp, truth = _held_out_poses(ex, k, is_held, own, pose[k], rng, max_calibration)
        offs, source = _side_hypotheses(pose_gp, truth, radii, f, lo_k, cell_k)
        if name in turns:  # the half-turn first, then the misreads' other sides
            offs, source = [180.0] + [o for o in offs if abs(abs(o) - 180.0) >= 30.0][:SIDES - 2], "half-turn symmetry"
        arrays.set_class(k, f, lo_k, cell_k, offs)
        held[k] = (*candidate_points(logs, csub, window), pose_gp, truth)
        verts = polyline(radii)
        report[name] = {"outline": True, "views": int(len(sub.cls)),
                        "size_m": [round(float(np.ptp(verts[:, j])), 3) for j in range(2)],
                        "sides_deg": [round(o, 1) for o in offs], "sides_from": source}
    if not arrays.has.any():
        return (arrays.outline() if turns else None), report
    outline = _calibrate_classes(arrays.outline(), held, classes, report,
                                 {classes.index(n): t for n, t in turns.items()})
    if not bool(jnp.any(outline.has)) and not turns:
        return None, report
    return outline, report


@dataclasses.dataclass
class _OutlineArrays:
    """The per-class arrays of an :class:`Outline` (host side) as :func:`fit_outlines` fills them
    class by class, before the calibration that needs the whole outline."""

    field: np.ndarray
    lo: np.ndarray
    cell: np.ndarray
    has: np.ndarray
    sides: np.ndarray
    side_mask: np.ndarray
    prior_right: np.ndarray

    @classmethod
    def blank(cls, n_c: int) -> "_OutlineArrays":
        """No class with an outline: a flat field and the GP's heading as the one side hypothesis."""
        field = np.zeros((n_c, GRID, GRID, 3), np.float32)
        field[..., 0] = 1.0
        side_mask = np.zeros((n_c, SIDES), bool)
        side_mask[:, 0] = True
        return cls(field=field, lo=np.zeros((n_c, 2), np.float32), cell=np.full(n_c, 0.01, np.float32),
                   has=np.zeros(n_c, bool), sides=np.zeros((n_c, SIDES), np.float32), side_mask=side_mask,
                   prior_right=np.full(n_c, DEFAULT_PRIOR_RIGHT, np.float32))

    def set_class(self, k: int, field: np.ndarray, lo: np.ndarray, cell: float, offs: list[float]) -> None:
        """Class ``k``'s distance field, and its side hypotheses: the GP's heading, then ``offs`` (degrees)."""
        self.field[k], self.lo[k], self.cell[k], self.has[k] = field, lo, cell, True
        self.sides[k], self.side_mask[k] = 0.0, False
        self.sides[k, 1:1 + len(offs)] = np.radians(offs)
        self.side_mask[k, :1 + len(offs)] = True

    def outline(self) -> Outline:
        """The :class:`Outline` with the calibration's figures at their neutral values (set by
        :func:`calibrate_outline`, class by class)."""
        n_c = len(self.has)
        return Outline(
            field=jnp.asarray(self.field), lo=jnp.asarray(self.lo), cell=jnp.asarray(self.cell),
            has=jnp.asarray(self.has), sides=jnp.asarray(self.sides), side_mask=jnp.asarray(self.side_mask),
            temperature=jnp.zeros(n_c, _F32), prior_right=jnp.asarray(self.prior_right),
            max_rms=jnp.full(n_c, 0.05, _F32), cov_scale=jnp.ones((n_c, 3), _F32),
            robust=jnp.asarray(ROBUST, _F32), free_gap=jnp.asarray(FREE_GAP, _F32),
            min_points=jnp.asarray(MIN_POINTS, jnp.int32), prior_search=jnp.full(n_c, SEARCH_SHARES[0], _F32),
            side_position=jnp.zeros(n_c, bool))


def _held_out_poses(ex: Examples, k: int, is_held: np.ndarray, own: np.ndarray, pose_k: PoseRegressor,
                    rng: np.random.Generator, most: int) -> tuple[Examples, np.ndarray, np.ndarray]:
    """Class ``k``'s held-out views (the training ones if fewer than 20 are held out), the GP's poses
    of them and their truth in S: what both the side hypotheses and the calibration are judged on."""
    cal = np.flatnonzero((ex.cls == k) & is_held & own)
    cal = cal if cal.size >= 20 else np.flatnonzero((ex.cls == k) & own)
    csub = ex.take(rng.choice(cal, min(cal.size, most), replace=False))
    rel, var = regress_one_class(pose_k, jnp.asarray(csub.vectors, _F32))
    pose_gp, _ = to_sensor_frame(jnp.asarray(csub.origin, _F32), jnp.asarray(csub.heading, _F32), rel, var)
    return csub, np.asarray(pose_gp, np.float64), truth_in_sensor(csub)


def _side_hypotheses(pose_gp: np.ndarray, truth: np.ndarray, radii: np.ndarray, field, lo, cell
                     ) -> tuple[list[float], str]:
    """The turns (degrees) a view of the class is taken for, and where they come from: the GP's
    misreads where there are enough of them, else the outline's own near-symmetries."""
    offs = misread_modes(pose_gp[:, 2] - truth[:, 2])
    if offs:
        return offs, "misreads"
    return side_offsets(self_match(radii, field, lo, cell)), "outline symmetry"


def _calibrate_classes(outline: Outline, held: dict, classes: tuple[str, ...], report: dict,
                       turns: "dict[int, int] | None" = None) -> Outline:
    """Each class's refinement calibrated on its held-out views (:func:`calibrate_outline`), and the
    outline left unused for a class whose refined headings are less precise there than the GP's
    (modulo π for a class alike turned half a turn, ``turns``)."""
    turns = turns or {}
    for k, (pts, mask, pose_gp, truth) in held.items():
        outline, rep = calibrate_outline(outline, k, pts, mask, pose_gp, truth, turns=turns.get(k, 1))
        report[classes[k]]["calibration"] = rep
        # The outline is used only where its headings are at least as precise as the GP's on held-out
        # views (the median error: the tracker's mixture takes care of the gross misreads either way).
        # A blurred outline (too few distinct views to sharpen it) reads every heading a little off.
        if rep["refined"]["heading_median_deg"] > rep["gp"]["heading_median_deg"]:
            report[classes[k]]["used"] = False
            report[classes[k]]["why"] = (f"held-out heading median {rep['refined']['heading_median_deg']:.2f}° "
                                         f"against the GP's {rep['gp']['heading_median_deg']:.2f}°")
            half = k in turns
            outline = eqx.tree_at(lambda o: (o.has, o.sides, o.side_mask, o.prior_right), outline, (
                outline.has.at[k].set(False),
                outline.sides.at[k].set(jnp.asarray(HALF_TURN_SIDES if half else DEFAULT_SIDES, _F32)),
                outline.side_mask.at[k].set(jnp.asarray(HALF_TURN_MASK) if half else True),
                outline.prior_right.at[k].set(0.5 if half else DEFAULT_PRIOR_RIGHT)))
        else:
            report[classes[k]]["used"] = True
    return outline
