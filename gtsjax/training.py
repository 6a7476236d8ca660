"""Training from labelled logs (``gtsjax train``): examples for the classifier (stage d) and the pose
regressors (stage e), GP fits, held-out evaluation, and the :class:`~gtsjax.model.Model` they make.

The rules are those of ``shared/spec/formats.md``: a candidate near a labelled object is an example
of that object's class, with the object's pose in the candidate's ORS as its pose target; a candidate
near a site landmark is an example of the landmark's class; every other candidate that passes the
binary filters is ``background``.

"Near" needs each scan's map transformation, which is estimated as stage f does at run time, from the
candidates near the site's landmarks, seeded by the site's rough sensor pose. Two passes: the first
uses the candidates' ORS origins (which sit on the visible surface, a few cm in front of a post's
centre); it gives the landmark classes' position targets, whose GPs then move each landmark candidate
to its centre for the second pass, as the step does at run time. All targets come from the second
pass.

Examples per class are balanced and capped (``max_per_class``): landmarks, in view in every scan,
would otherwise swamp the robots. The held-out split (``holdout``) is by blocks of one second of
scans, so that near-identical consecutive scans do not sit on both sides of it.

**What the model must reject** (issue 13). Background logs (recorded anywhere with no robot in view,
any format ``convert`` reads) add background examples: every candidate the binary filters keep in
them, except look-alikes of a landmark class (a post in view while recording). With them the
classifier sees many more background examples, shared evenly between their sources, and more of
each mobile class. From the labelled examples come each class's shape envelope
(:func:`fit_envelope`), its open-set examples and threshold (:func:`fit_support`, the threshold from
held-out examples) and each tracked class's motion limits (:func:`motion_limits`). A class with no
examples at all (a clean field has no background) is a warning in the report, not an error.
"""

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._classify import DEFAULT_THRESHOLD, Classifier, Support, classify, gp_inputs, nearest_d2
from ._filters import Envelope, envelope_pass, shape_quantities
from ._frontend import FrontEndConfig, front_end_batch
from ._geometry import affine_heading, compose, field_to_sensor, in_bounds, relative, sensor_to_field, wrap
from ._maptransform import Transform, update_transform
from ._pose import PoseRegressor, regress_one_class
from ._precision import exact_products
from ._track import DEFAULT_MAX_SPEED, DEFAULT_MAX_TURN_RATE, TrackerParams
from .errors import InputError
from .gp import GPArgumentError, fit
from .io.logs import ScanLog, fit_geometry, to_scans
from .io.site import Site
from .model import DEFAULT_MAP_GATE, DEFAULT_MAP_MIN_SPREAD, DEFAULT_MAX_TRACKS, DEFAULT_MEAS_VAR_FLOOR, Model
from .sensors import get_model
from .train.calibrate import calibrate

BACKGROUND = "background"


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Settings of ``gtsjax train``; the defaults are those the shipped results use."""

    frontend: FrontEndConfig = dataclasses.field(default_factory=FrontEndConfig)
    max_per_class: int = 500  # classifier examples per class (balanced and capped)
    # Pose GPs of a mobile class: conditioned on up to max_pose_examples examples, their
    # hyperparameters fitted on a subsample of max_pose_fit of them (``gp.fit``'s max_fit_points).
    # Heading accuracy grows with the examples the posterior sees (on the SPL field, from 2 000 to
    # 6 000: held-out median 2.6° -> 1.9°, misreads 7.1 % -> 5.0 %), while the fit's cost grows with
    # the cube of the examples it sees; the step's cost grows linearly with max_pose_examples.
    max_pose_examples: int = 6000
    max_pose_fit: int = 2000
    max_landmark_examples: int = 500  # position-GP training examples per landmark class (simple shapes)
    # Inducing points of each GP's predictive mean: they bound the step's cost per candidate whatever
    # the training set, and a GP trained on this many examples or fewer predicts its exact mean. The
    # mobile classes' pose GPs run on a few candidates per scan (the model's max_objects) and get the
    # most, since heading accuracy depends on them; the classifier's GPs run on every candidate and
    # the landmark classes' position GPs learn a simple shape: they get fewer. The pose GPs' variance
    # (O(M^2) per candidate) uses the first n_inducing_var.
    n_inducing: int = 6144
    n_inducing_class: int = 2048
    n_inducing_var: int = 64
    restarts: int = 3  # optimiser starts per GP fit
    # Classifier: with background logs, the background class gets max_background examples (None: twelve
    # times max_per_class), as varied as real clutter is, and each mobile class max_mobile (None: four
    # times max_per_class): as many views of the robot as of clutter of its size keep a robot's score up
    # where clutter looks like it. Without background logs, both are max_per_class. With more than
    # max_class_fit examples in all, the hyperparameters are fitted on a subsample of that many and
    # the GPs conditioned on all of them.
    max_background: int | None = None
    max_mobile: int | None = None
    max_class_fit: int | None = 1500
    support_size: int = 512  # open-set test: training examples kept per class
    # Motion limits per class (m/s, rad/s) that override what labelled motion, or the default, gives.
    max_speed: dict[str, float] = dataclasses.field(default_factory=dict)
    max_turn_rate: dict[str, float] = dataclasses.field(default_factory=dict)
    holdout: float = 0.2  # fraction of one-second blocks held out for evaluation
    label_radius: float = 0.3  # m: a candidate this close to a labelled object is that object
    landmark_radius: float = 0.25  # m: a candidate this close to a site landmark is that landmark
    bounds_margin: float | None = 0.5  # m: background examples only this far outside the site's bounds
    threshold: float = DEFAULT_THRESHOLD  # every class's score threshold (``Classifier.threshold``)
    map_gate: float = DEFAULT_MAP_GATE  # m: landmark association gate of stage f (``Model.map_gate``)
    map_min_spread: float = DEFAULT_MAP_MIN_SPREAD  # m: associated landmarks must spread this much in 2-D
    meas_var_floor: tuple[float, float, float] = DEFAULT_MEAS_VAR_FLOOR  # m², m², rad² (``Model.meas_var_floor``)
    # Noise floor of every GP, relative to its signal variance. Many scans of one static pose give
    # near-duplicate inputs with equal targets; without a floor the likelihood is maximised by
    # interpolating them (σn² → 0, tiny length scales), which generalises badly to new poses.
    noise_floor: float = 1e-2
    max_tracks: int = DEFAULT_MAX_TRACKS  # track slots (``Model.max_tracks``)
    seed: int = 0


@dataclasses.dataclass
class Examples:
    """Labelled candidates from one or more logs (host arrays)."""

    vectors: np.ndarray  # [E, D] characteristic vectors
    cls: np.ndarray  # [E] class index
    target: np.ndarray  # [E, 3] ORS-relative (x̃, ỹ, θ̃); θ̃ NaN where the class has no heading
    group: np.ndarray  # [E] held-out block id
    origin: np.ndarray  # [E, 2] ORS origin in S
    heading: np.ndarray  # [E] ORS heading in S
    shape: np.ndarray  # [E, 3] width, depth, n_points · range (what the shape envelopes bound)
    rng: np.ndarray  # [E] range of the ORS origin
    occluded: np.ndarray  # [E] a nearer return beside either end (``Candidates.occluded``)

    def take(self, idx) -> "Examples":
        return Examples(*(getattr(self, f.name)[idx] for f in dataclasses.fields(self)))


def class_list(logs: Sequence[ScanLog], site: Site) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """All classes (background first, then landmark classes, then mobile classes), landmarks, mobiles."""
    landmarks = tuple(sorted(set(site.landmark_classes)))
    mobiles = tuple(sorted({str(c) for log in logs for c in log.truth_classes}))
    clash = set(landmarks) & set(mobiles)
    if clash or BACKGROUND in landmarks or BACKGROUND in mobiles:
        raise InputError("training data", f"class name(s) {sorted(clash or {BACKGROUND})} used for both landmarks "
                                          "and labelled objects, or reserved")
    return (BACKGROUND, *landmarks, *mobiles), landmarks, mobiles


_front_end_batch = jax.jit(front_end_batch, static_argnames=("chunk", "windows"))


def run_front_end(log: ScanLog, cfg: FrontEndConfig, n_beams: int, chunk: int = 1024):
    """Stages a–c over a log, chunk by chunk; returns host arrays ``[T, K, …]``: origin, heading,
    keep, ``vector`` (the GP inputs of each candidate, :func:`~gtsjax._classify.gp_inputs`),
    ``shape`` (:func:`~gtsjax._filters.shape_quantities`), ``rng`` (the ORS origin's range) and
    ``occluded``."""
    outs = {"origin": [], "heading": [], "vector": [], "keep": [], "shape": [], "rng": [], "occluded": []}
    for start in range(0, log.n_scans, chunk):
        scans = to_scans(log.slice(start, start + chunk), n_beams)
        fe = _front_end_batch(cfg, scans)
        f = fe.features
        rng = jnp.sqrt(jnp.sum(f.origin**2, axis=-1))
        outs["origin"].append(np.asarray(f.origin, np.float64))
        outs["heading"].append(np.asarray(f.heading, np.float64))
        outs["vector"].append(np.asarray(gp_inputs(f.vector, f.origin, f.height), np.float64))
        outs["keep"].append(np.asarray(fe.keep))
        outs["shape"].append(np.asarray(shape_quantities(f.width, f.height, f.n_points, rng), np.float64))
        outs["rng"].append(np.asarray(rng, np.float64))
        outs["occluded"].append(np.asarray(fe.candidates.occluded))
    return {k: np.concatenate(v) for k, v in outs.items()}


@jax.jit
def _transforms(tf0: Transform, det_s, keep, map_o, gate, min_spread):
    """Stage f over a whole log with class-agnostic association (training knows which points are
    landmarks only by where they are)."""
    zeros_d = jnp.zeros(det_s.shape[1], jnp.int32)
    zeros_m = jnp.zeros(map_o.shape[0], jnp.int32)

    def body(tf, inp):
        d, k = inp
        new, _, _ = update_transform(tf, d, zeros_d, k, map_o, zeros_m, gate, min_spread)
        return new, new

    return jax.lax.scan(body, tf0, (det_s, keep))[1]


def estimate_transforms(det_s: np.ndarray, keep: np.ndarray, site: Site, cfg: TrainConfig) -> dict[str, np.ndarray]:
    tf0 = Transform.from_sensor_pose(jnp.asarray(site.sensor_pose, jnp.float32))
    tfs = _transforms(tf0, jnp.asarray(det_s, jnp.float32), jnp.asarray(keep), jnp.asarray(site.landmark_xy, jnp.float32),
                      jnp.asarray(cfg.map_gate, jnp.float32), jnp.asarray(cfg.map_min_spread, jnp.float32))
    return {"A": np.asarray(tfs.A, np.float64), "mu_s": np.asarray(tfs.mu_s, np.float64),
            "mu_o": np.asarray(tfs.mu_o, np.float64), "degraded": np.asarray(tfs.degraded),
            "n": np.asarray(tfs.n_landmarks)}


def _per_scan(tf):
    """A log's transforms ``[T]`` as arguments of ``_geometry``'s S ↔ O maps for points ``[T, n, 2]``."""
    return tf["A"][:, None], tf["mu_s"][:, None], tf["mu_o"][:, None]


def _ors(origin, heading):
    """Candidates' ORS frames ``[..., 3]`` (eq. 9) from their origins and headings."""
    return np.concatenate([origin, heading[..., None]], -1)


def label_log(log: ScanLog, fe: dict, tf: dict, site: Site, classes: tuple[str, ...], cfg: TrainConfig,
              group_offset: int) -> tuple[Examples, np.ndarray]:
    """Label one log's candidates (spec rules) and compute their ORS-relative pose targets. Also
    returns the class of every candidate slot ``[T, K]`` (0 where not an example or background)."""
    T, K = fe["keep"].shape
    origin, heading = fe["origin"], fe["heading"]
    origin_o = sensor_to_field(*_per_scan(tf), origin)  # [T, K, 2]
    rot_s = affine_heading(tf["A"])  # [T]
    ors = _ors(origin, heading)
    cls = np.zeros((T, K), np.int64)
    target = np.full((T, K, 3), np.nan)
    best = np.full((T, K), np.inf)

    lm_xy = site.landmark_xy
    lm_s = field_to_sensor(*_per_scan(tf), np.broadcast_to(lm_xy, (T,) + lm_xy.shape))  # [T, L, 2]
    for j, lm in enumerate(site.landmarks):
        d = np.linalg.norm(origin_o - lm_xy[j], axis=-1)
        hit = (d < cfg.landmark_radius) & (d < best)
        rel = relative(ors, np.broadcast_to(lm_s[:, j : j + 1], origin.shape))
        cls[hit] = classes.index(lm.cls)
        target[hit, :2] = rel[hit]
        target[hit, 2] = np.nan
        best[hit] = d[hit]

    poses = log.truth_poses  # [T, M, 3]
    ambiguous = np.zeros((T, K), bool)
    for m, name in enumerate(log.truth_classes):
        p = poses[:, m]
        present = ~np.isnan(p[:, 0])
        d = np.linalg.norm(origin_o - np.nan_to_num(p[:, None, :2]), axis=-1)
        d = np.where(fe["keep"], d, np.inf)
        near = (d < cfg.label_radius) & present[:, None]
        # One example per object and scan: the candidate nearest its centre. Other pieces of it (a
        # robot the scan splits in two) are neither that class nor background: left out.
        nearest = np.arange(K)[None, :] == np.argmin(d, axis=1)[:, None]
        hit = near & nearest & (d < best)
        ambiguous |= near & ~nearest
        p_s = field_to_sensor(*_per_scan(tf), np.nan_to_num(p[:, None, :2]))  # [T, 1, 2]
        rel = relative(ors, np.broadcast_to(p_s, origin.shape))
        th = wrap(np.nan_to_num(p[:, 2])[:, None] - rot_s[:, None] - heading)
        cls[hit] = classes.index(str(name))
        target[hit, :2] = rel[hit]
        target[hit, 2] = th[hit]
        best[hit] = d[hit]

    # A scan whose transform could not be estimated gives no labels worth having. With bounds, the
    # background is what the step could confuse with an object on the field: candidates inside the
    # bounds (plus a margin), not the walls and furniture around it, which the step drops anyway.
    use = fe["keep"] & ~tf["degraded"][:, None] & ~(ambiguous & (cls == 0))
    if site.bounds is not None and cfg.bounds_margin is not None:
        use &= in_bounds(origin_o, np.asarray(site.bounds), cfg.bounds_margin) | (cls != 0)
    t_idx, k_idx = np.nonzero(use)
    period = np.median(np.diff(log.stamps)) if log.n_scans > 1 else 0.1
    block = max(1, int(round(1.0 / max(period, 1e-3))))
    return Examples(
        vectors=fe["vector"][t_idx, k_idx],
        cls=cls[t_idx, k_idx],
        target=target[t_idx, k_idx],
        group=group_offset + t_idx // block,
        origin=origin[t_idx, k_idx],
        heading=heading[t_idx, k_idx],
        shape=fe["shape"][t_idx, k_idx],
        rng=fe["rng"][t_idx, k_idx],
        occluded=fe["occluded"][t_idx, k_idx],
    ), np.where(use, cls, 0)


def informative_columns(vectors: np.ndarray) -> tuple[int, ...]:
    """Indices of the columns of ``vectors`` [n, d] that vary (relative spread above 1e-9)."""
    if len(vectors) == 0:
        return tuple(range(vectors.shape[-1]))
    spread = vectors.max(axis=0) - vectors.min(axis=0)
    scale = np.maximum(np.abs(vectors).max(axis=0), 1.0)
    return tuple(int(c) for c in np.flatnonzero(spread > 1e-9 * scale))


def _sample(rng, idx, cap):
    return idx if idx.size <= cap else np.sort(rng.choice(idx, cap, replace=False))


def _share(rng, pools: list[np.ndarray], cap: int) -> np.ndarray:
    """Up to ``cap`` indices drawn from ``pools`` as evenly as they allow (a pool smaller than its
    share gives all it has, and the rest is shared among the others)."""
    sizes = np.array([p.size for p in pools])
    take = np.zeros(len(pools), int)
    left, open_ = cap, sizes > 0
    while left > 0 and open_.any():
        share = max(1, left // int(open_.sum()))
        for i in np.flatnonzero(open_):
            t = min(share, sizes[i] - take[i], left)
            take[i] += t
            left -= t
            open_[i] = take[i] < sizes[i]
    return np.sort(np.concatenate([_sample(rng, p, int(t)) for p, t in zip(pools, take, strict=True)]
                                  + [np.zeros(0, int)]))


def _fit32(x, y, key, cfg, progress, label, n_inducing: int, max_fit: int | None = None):
    t0 = time.perf_counter()
    # With max_fit the posterior takes every example given (the caller capped them); without, fit's
    # own cap applies to the fit and the posterior alike.
    cap = {} if max_fit is None else {"max_points": x.shape[0], "max_fit_points": max_fit}
    try:
        gp = fit(x, y, key=key, restarts=cfg.restarts, jitter=cfg.noise_floor, **cap)
        sparse = gp.sparse(n_inducing, cfg.n_inducing_var).astype(jnp.float32)
    except GPArgumentError as err:  # the GP library is core code; to the user it is a bad setting
        raise InputError(err.where, err.problem) from None
    p = gp.params
    info = {"gp": label, "n": int(x.shape[0]), "n_fit": int(min(x.shape[0], max_fit or x.shape[0])),
            "seconds": round(time.perf_counter() - t0, 2),
            "lml": float(gp.log_marginal_likelihood()),
            "signal_var": float(p.signal_var), "noise_var": float(p.noise_var),
            "lengthscale_median": float(np.median(np.asarray(p.lengthscale)))}
    if progress is not None:
        progress(info)
    return sparse, info


# ------------------------------------------------------------------------------------- open set (issue 13)


def fit_envelope(ex: "Examples", n_classes: int, beam_step: float, *, n_bins: int = 8, quantile: float = 0.01,
                 min_per_bin: int = 20, whole_fraction: float = 0.95) -> tuple[Envelope, dict]:
    """Per-class shape envelopes (:class:`~gtsjax._filters.Envelope`) from labelled examples: in each
    range bin, the ``quantile`` and ``1 − quantile`` quantiles of the class's width, depth and
    ``n · r``, widened by a tenth of their spread plus what one beam more or less and the range noise
    can add at the bin's far edge (a beam's spacing for width, 1 cm for depth, one point for
    ``n · r``). Bins with fewer than ``min_per_bin`` examples of the class take the limits of the
    nearest bin that has enough (the quantities depend on range only through noise and spacing); a
    class with no examples at all is closed, and background (class 0) is open. A class is ``whole``
    (must be seen unoccluded) when at least ``whole_fraction`` of its examples were. The quantiles
    leave out the rarest views (1 % at each end: a robot's outline half lost to grazing beams), which
    a tracker coasts through. Returns the envelope and a summary per class for the training report."""
    non_bg = ex.cls != 0
    r_max = float(np.max(ex.rng[non_bg])) if non_bg.any() else 1.0
    bin_width = max(0.05, math.ceil(r_max * 1.1 / n_bins / 0.05) * 0.05)
    b = np.clip((ex.rng // bin_width).astype(int), 0, n_bins - 1)
    lo = np.full((n_classes, n_bins, 3), np.inf)
    hi = np.full((n_classes, n_bins, 3), -np.inf)
    lo[0], hi[0] = -np.inf, np.inf
    whole = np.zeros(n_classes, bool)
    report = {}

    def limits(q, far):
        a, z = np.quantile(q, quantile, axis=0), np.quantile(q, 1 - quantile, axis=0)
        slack = 0.1 * (z - a) + np.array([far * beam_step, 0.01, far])
        return np.maximum(a - slack, 0.0), z + slack

    for k in range(1, n_classes):
        sel = ex.cls == k
        if not sel.any():
            continue
        filled = []
        for j in range(n_bins):
            q = ex.shape[sel & (b == j)]
            if len(q) >= min_per_bin:
                lo[k, j], hi[k, j] = limits(q, (j + 1) * bin_width)
                filled.append(j)
        if not filled:  # too few examples for any bin: one interval over all of them
            lo[k, :], hi[k, :] = limits(ex.shape[sel], r_max)
            filled = list(range(n_bins))
        filled = np.asarray(filled)
        for j in range(n_bins):
            if j not in filled:
                near = filled[np.argmin(np.abs(filled - j))]
                lo[k, j], hi[k, j] = lo[k, near], hi[k, near]
        seen_whole = float(np.mean(~ex.occluded[sel]))
        whole[k] = seen_whole >= whole_fraction
        report[k] = {"width_m": [round(float(lo[k, :, 0].min()), 3), round(float(hi[k, :, 0].max()), 3)],
                     "depth_m": [round(float(lo[k, :, 1].min()), 3), round(float(hi[k, :, 1].max()), 3)],
                     "points_at_1m": [round(float(lo[k, :, 2].min()), 1), round(float(hi[k, :, 2].max()), 1)],
                     "range_bins_seen": [round(float(filled.min() * bin_width), 2),
                                         round(float((filled.max() + 1) * bin_width), 2)],
                     "seen_whole": round(seen_whole, 4), "whole_required": bool(whole[k])}
    f32 = jnp.float32
    env = Envelope(jnp.asarray(bin_width, f32), jnp.asarray(lo, f32), jnp.asarray(hi, f32), jnp.asarray(whole))
    return env, report


def _nearest_d2_np(x: np.ndarray, s: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Squared Euclidean distance from each row of ``x`` to the nearest row of ``s`` (host, float64)."""
    out = np.full(len(x), np.inf)
    if len(s) == 0:
        return out
    ss = np.sum(s * s, axis=1)
    for i in range(0, len(x), chunk):
        a = x[i : i + chunk]
        d2 = np.sum(a * a, axis=1)[:, None] + ss[None, :] - 2.0 * a @ s.T
        out[i : i + chunk] = np.maximum(d2.min(axis=1), 0.0)
    return out


def fit_support(ex: "Examples", is_held: np.ndarray, n_classes: int, rng, *, size: int = 512,
                quantile: float = 0.995, margin: float = 1.5, min_held: int = 50) -> tuple[Support, dict]:
    """The open-set test's examples and thresholds (:class:`~gtsjax._classify.Support`).

    Per non-background class: up to ``size`` of its training examples, drawn at random (so the
    examples keep the class's density; a farthest-point choice would keep its outliers first, and a
    leg near an odd example would pass), in the class's own scale: each input divided by the class's
    standard deviation in it, floored at a tenth of that input's spread over all classes (an input
    that is nearly constant within a class would otherwise make any difference in it "unlike"). The
    threshold is ``margin`` times the ``quantile`` of the squared distances from the class's
    held-out examples to their nearest support example (from the training examples left out of the
    support, or failing that the support itself leaving each one out, when fewer than ``min_held``
    are held out). Returns the support and, per class, the threshold, how many examples it rests on
    and how many held-out examples of the class and of the background it rejects."""
    d = ex.vectors.shape[1]
    pooled = np.std(ex.vectors, axis=0)
    per = []
    report = {}
    for k in range(n_classes):
        tr = np.flatnonzero((ex.cls == k) & ~is_held)
        if k == 0 or tr.size == 0:
            per.append(None)
            continue
        x = ex.vectors[tr]
        mean = x.mean(axis=0)
        scale = np.maximum(x.std(axis=0), np.maximum(0.1 * pooled, 1e-6))
        pick = tr if tr.size <= size else np.sort(rng.choice(tr, size, replace=False))
        sup = (ex.vectors[pick] - mean) / scale
        held = np.flatnonzero((ex.cls == k) & is_held)
        source = "held-out"
        if held.size >= min_held:
            d2 = _nearest_d2_np((ex.vectors[held] - mean) / scale, sup)
        else:
            rest = np.setdiff1d(tr, pick)
            source = "training (not in the support)"
            if rest.size >= min_held:
                d2 = _nearest_d2_np((ex.vectors[rest] - mean) / scale, sup)
            else:  # leave one out among the support itself
                source = "training (leave one out)"
                full = np.sum(sup * sup, 1)[:, None] + np.sum(sup * sup, 1)[None, :] - 2 * sup @ sup.T
                np.fill_diagonal(full, np.inf)
                d2 = np.maximum(full.min(axis=1), 0.0) if len(sup) > 1 else np.zeros(1)
        thr = float(margin * np.quantile(d2, quantile))
        per.append((sup, mean, scale, thr))
        bg_held = np.flatnonzero((ex.cls == 0) & is_held)
        bg_d2 = _nearest_d2_np((ex.vectors[bg_held] - mean) / scale, sup)
        report[k] = {"threshold_d2": round(thr, 3), "support": int(len(sup)), "threshold_from": f"{d2.size} {source}",
                     "class_rejected": float(np.mean(d2 > thr)),
                     "background_rejected": float(np.mean(bg_d2 > thr)) if bg_held.size else None}
    p_max = max([len(v[0]) for v in per if v is not None], default=1)
    xs = np.zeros((n_classes, p_max, d))
    mask = np.zeros((n_classes, p_max), bool)
    means = np.zeros((n_classes, d))
    inv = np.ones((n_classes, d))
    thr = np.full(n_classes, np.inf)
    for k, v in enumerate(per):
        if v is None:
            continue
        sup, mean, scale, t = v
        xs[k, : len(sup)], mask[k, : len(sup)], means[k], inv[k], thr[k] = sup, True, mean, 1.0 / scale, t
    f32 = jnp.float32
    return Support(jnp.asarray(xs, f32), jnp.asarray(mask), jnp.asarray(means, f32), jnp.asarray(inv, f32),
                   jnp.asarray(thr, f32)), report


def motion_limits(logs: Sequence[ScanLog], classes: tuple[str, ...], *, quantile: float = 0.995, margin: float = 1.25,
                  min_run: int = 5, min_steps: int = 50) -> dict[str, dict]:
    """Each labelled class's maximum speed (m/s) and turn rate (rad/s) from its labelled motion,
    where there is some: the ``quantile`` of its speeds and turn rates between consecutive scans, times
    ``margin``, over runs of at least ``min_run`` consecutive steps in which it moved. A training
    grid's robot is carried from pose to pose between scans: those jumps are single steps between
    scans where it stood still, never a run, so they do not count as motion; nor does a step of a run
    three times faster than the run's median (the jump to where a walk starts). A class with fewer than
    ``min_steps`` such steps gets no entry (the tracker's default applies)."""
    speeds: dict[str, list] = {}
    turns: dict[str, list] = {}
    for log in logs:
        if log.n_scans < 2:
            continue
        dt = np.diff(log.stamps)
        for m, name in enumerate(log.truth_classes):
            p = log.truth_poses[:, m]
            ok = ~np.isnan(p[:-1, 0]) & ~np.isnan(p[1:, 0]) & (dt > 0)
            step = np.hypot(*(p[1:, :2] - p[:-1, :2]).T)
            turn = np.abs(wrap(p[1:, 2] - p[:-1, 2]))
            moving = ok & ((step > 1e-4) | (turn > 1e-4))
            # Runs of consecutive moving steps, at least min_run long.
            edges = np.diff(np.concatenate([[0], moving.astype(int), [0]]))
            starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
            for a, b in zip(starts, ends, strict=True):
                if b - a >= min_run:
                    # A jump into or out of a run (put down, then walking) is not motion either: steps
                    # over three times the run's median speed are left out.
                    v = step[a:b] / dt[a:b]
                    smooth = v <= 3.0 * max(np.median(v), 1e-3)
                    speeds.setdefault(str(name), []).append(v[smooth])
                    turns.setdefault(str(name), []).append((turn[a:b] / dt[a:b])[smooth])
    out = {}
    for name in classes:
        if name not in speeds:
            continue
        v, w = np.concatenate(speeds[name]), np.concatenate(turns[name])
        if v.size >= min_steps:
            out[name] = {"max_speed": round(float(margin * np.quantile(v, quantile)), 3),
                         "max_turn_rate": round(float(margin * np.quantile(w, quantile)), 3), "steps": int(v.size)}
    return out


@jax.jit
def _decide(clf, env, vectors, shape, rng):
    dec = classify(clf, vectors, jnp.ones(vectors.shape[0], bool), envelope_pass(env, shape, rng))
    return jnp.where(dec.ok, dec.cls, 0), dec.unlike, dec.off_envelope


def decide(model: Model, ex: "Examples", chunk: int = 4096):
    """Stage d as the step decides it, on examples: each one's class (0 where dropped), and whether
    it was dropped as unlike its class's examples, or outside its best class's envelope."""
    outs = [[], [], []]
    for s in range(0, len(ex.cls), chunk):
        f32 = jnp.float32
        part = slice(s, s + chunk)
        res = _decide(model.classifier, model.envelope, jnp.asarray(ex.vectors[part], f32),
                      jnp.asarray(ex.shape[part], f32), jnp.asarray(ex.rng[part], f32))
        for o, r in zip(outs, res, strict=True):
            o.append(np.asarray(r))
    if not outs[0]:
        return np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, bool)
    return tuple(np.concatenate(o) for o in outs)


def background_examples(logs: Sequence[ScanLog], names: Sequence[str], cfg: "TrainConfig", n_beams: int,
                        columns: tuple[int, ...], group_offset: int) -> tuple["Examples", list[dict]]:
    """Every candidate that the binary filters keep in a background log (recorded with no robot in view)
    is a background example; one-second blocks of scans are the held-out groups, as for labelled logs."""
    exs, info = [], []
    for log, name in zip(logs, names, strict=True):
        fe = run_front_end(log, cfg.frontend, n_beams)
        t_idx, k_idx = np.nonzero(fe["keep"])
        period = np.median(np.diff(log.stamps)) if log.n_scans > 1 else 0.1
        block = max(1, int(round(1.0 / max(period, 1e-3))))
        n = t_idx.size
        exs.append(Examples(
            vectors=fe["vector"][t_idx, k_idx][:, list(columns)],
            cls=np.zeros(n, np.int64),
            target=np.full((n, 3), np.nan),
            group=group_offset + t_idx // block,
            origin=fe["origin"][t_idx, k_idx],
            heading=fe["heading"][t_idx, k_idx],
            shape=fe["shape"][t_idx, k_idx],
            rng=fe["rng"][t_idx, k_idx],
            occluded=fe["occluded"][t_idx, k_idx],
        ))
        group_offset = int(exs[-1].group.max(initial=group_offset)) + 1
        info.append({"log": str(name), "scans": int(log.n_scans), "candidates": int(n)})
    if not exs:
        z = np.zeros(0)
        return Examples(np.zeros((0, len(columns))), z.astype(np.int64), np.zeros((0, 3)), z.astype(np.int64),
                        np.zeros((0, 2)), z, np.zeros((0, 3)), z, z.astype(bool)), info
    return _concat(exs), info



def _n_beams(log: ScanLog) -> int:
    """The step's beam count for a model trained on ``log``: its own, or its scanner model's if more."""
    n = log.n_beams
    if log.sensor_model is not None:
        try:
            n = max(n, get_model(log.sensor_model).n_beams)
        except InputError:
            pass
    return n


def fit_background(first: ScanLog, background: Sequence[ScanLog], names: Sequence[str]) -> list[ScanLog]:
    """Background logs checked against the labelled logs' scanner (``first``): the same angular step
    within 1 %, cropped to its field of view and range window (:func:`~gtsjax.io.logs.fit_geometry`);
    another step is one :class:`InputError` naming the log."""
    geometry = dict(angle_min=first.angle_min, angle_increment=first.angle_increment, n_beams=_n_beams(first),
                    range_min=first.range_min, range_max=first.range_max)
    return [fit_geometry(log, **geometry, where=name, crop=True, sensor_model=first.sensor_model)
            for log, name in zip(background, names, strict=True)]


@exact_products
def train(logs: Sequence[ScanLog], site: Site, cfg: TrainConfig = TrainConfig(), *,
          progress: Callable[[dict], None] | None = None, names: Sequence[str] | None = None,
          background: Sequence[ScanLog] = (), background_names: Sequence[str] | None = None) -> tuple[Model, dict]:
    """Train a model from labelled logs of one site, and optional background logs (recorded anywhere,
    with no robot in view: every candidate in them is a background example; their beams are checked
    against the labelled logs' scanner and cropped to its field of view). Returns the model (float32
    predictors, bounded cost) and a report: examples per class, GP fits, shape envelopes, open-set
    thresholds, motion limits, held-out accuracy and pose errors, and warnings."""
    names = list(names) if names is not None else [f"log {i}" for i in range(len(logs))]
    bg_names = list(background_names) if background_names is not None else [
        f"background log {i}" for i in range(len(background))]
    if not logs:
        raise InputError("train", "no logs given")
    for log, name in zip(logs, names, strict=True):
        if not log.labelled:
            raise InputError(name, "not a labelled log (no truth_classes / truth_poses)")
    first = logs[0]
    for log, name in zip(logs[1:], names[1:], strict=True):
        if (log.n_beams, log.sensor_model) != (first.n_beams, first.sensor_model) or not math.isclose(
                log.angle_min, first.angle_min, abs_tol=1e-9) or not math.isclose(
                log.angle_increment, first.angle_increment, abs_tol=1e-12):
            raise InputError(name, f"scan geometry differs from {names[0]} (beams, angles or sensor model)")
    n_beams = _n_beams(first)
    background = fit_background(first, background, bg_names)
    classes, landmarks, mobiles = class_list(logs, site)
    if not mobiles:
        raise InputError(names[0], "no labelled object classes in the logs")
    warnings: list[str] = []

    fe_cfg = cfg.frontend
    per_log = [run_front_end(log, fe_cfg, n_beams) for log in logs]
    # GP inputs that never vary (the intensity profile of a scanner without intensity) are left out.
    columns = informative_columns(np.concatenate([fe["vector"][fe["keep"]] for fe in per_log]))
    for fe in per_log:
        fe["vector"] = fe["vector"][..., list(columns)]

    # Pass 1: transforms from raw ORS origins; landmark targets; landmark position GPs.
    rng = np.random.default_rng(cfg.seed)
    key = jax.random.PRNGKey(cfg.seed)
    offset = 0
    ex1, cls1 = [], []
    for log, fe in zip(logs, per_log, strict=True):
        tf = estimate_transforms(fe["origin"], fe["keep"], site, cfg)
        ex, cls_tk = label_log(log, fe, tf, site, classes, cfg, offset)
        cls1.append(cls_tk)
        offset = int(ex.group.max(initial=offset)) + 1
        ex1.append(ex)
    ex_all = _concat(ex1)
    fits = []
    pose: list[PoseRegressor | None] = [None] * len(classes)
    # Background logs' scans are split into held-out blocks with the labelled ones.
    bg_ex, bg_info = background_examples(background, bg_names, cfg, n_beams, columns, offset)
    groups = np.unique(np.concatenate([ex_all.group, bg_ex.group]))
    held = set(rng.choice(groups, max(1, int(round(cfg.holdout * groups.size))), replace=False).tolist())
    for name in landmarks:
        k = classes.index(name)
        idx = _sample(rng, np.flatnonzero((ex_all.cls == k) & ~np.isin(ex_all.group, list(held))),
                      cfg.max_landmark_examples)
        if idx.size < 3:
            raise InputError("training data", f"only {idx.size} examples of landmark class '{name}'; are the site's "
                                              "landmarks in view and sensor_pose roughly right?")
        gps = []
        for j, comp in enumerate(("x", "y")):
            key, sub = jax.random.split(key)
            gp, info = _fit32(ex_all.vectors[idx], ex_all.target[idx, j], sub, cfg, progress, f"{name}.{comp}",
                              cfg.n_inducing_class)
            gps.append(gp)
            fits.append(info)
        pose[k] = PoseRegressor(gps[0], gps[1])

    # Pass 2: landmark candidates moved to their predicted centres, transforms again, all targets.
    ex_all = _second_pass(logs, per_log, cls1, pose, site, classes, landmarks, cfg)
    if not np.any(ex_all.cls == 0) and cfg.bounds_margin is not None:
        # Nothing but objects on the field: take the background from around it (walls, furniture).
        ex_all = _second_pass(logs, per_log, cls1, pose, site, classes, landmarks,
                              dataclasses.replace(cfg, bounds_margin=None))
    degraded, n_scans = ex_all.degraded, ex_all.n_scans
    labelled_counts = {c: int(np.sum(ex_all.cls == k)) for k, c in enumerate(classes)}

    # Shape envelopes (stage c) and open-set supports (stage d) from the labelled logs' classes.
    is_held_lab = np.isin(ex_all.group, list(held))
    envelope, env_report = fit_envelope(ex_all.take(np.flatnonzero(~is_held_lab)), len(classes), first.angle_increment)
    # The background logs join the background class; a candidate in them that looks like a landmark
    # class's own examples (a post in view while recording) is left out: it would teach the classifier
    # that the landmark is background.
    support, sup_report = fit_support(_concat([ex_all, bg_ex]), np.isin(np.concatenate([ex_all.group, bg_ex.group]),
                                                                        list(held)), len(classes), rng,
                                      size=cfg.support_size)
    lookalike = np.zeros(len(bg_ex.cls), bool)
    if len(bg_ex.cls):
        d2 = np.asarray(nearest_d2(support, jnp.asarray(bg_ex.vectors, jnp.float32)))
        for name in landmarks:
            k = classes.index(name)
            lookalike |= d2[:, k] <= float(support.threshold[k])
    for item, n_look in zip(bg_info, np.bincount(np.searchsorted(np.cumsum([i["candidates"] for i in bg_info]),
                                                                np.flatnonzero(lookalike), side="right"),
                                                minlength=len(bg_info)), strict=True):
        item["landmark_lookalikes_left_out"] = int(n_look)
    ex_all = _concat([ex_all, bg_ex.take(np.flatnonzero(~lookalike))])
    is_held = np.isin(ex_all.group, list(held))

    # Classifier: balanced, capped examples; one GP per class on 1/0 targets (eq. 14). The background,
    # as varied as the world, may get more examples than the other classes (max_background).
    counts = {c: int(np.sum(ex_all.cls == k)) for k, c in enumerate(classes)}
    n_bg = cfg.max_per_class if not background else (cfg.max_background or 12 * cfg.max_per_class)
    n_mobile = cfg.max_per_class if not background else (cfg.max_mobile or 4 * cfg.max_per_class)
    # The background examples are shared out evenly between their sources (the labelled logs' own
    # background, then each background log; what one source cannot fill goes to the others), so that
    # a long log of one office does not crowd out the field's own clutter.
    source = np.concatenate([np.full(len(ex_all.cls) - int(np.sum(~lookalike)), -1),
                             np.repeat(np.arange(len(bg_info)), [i["candidates"] for i in bg_info])[~lookalike]])
    pools = [np.flatnonzero((ex_all.cls == 0) & ~is_held & (source == s)) for s in range(-1, len(bg_info))]
    bg_idx = _share(rng, pools, n_bg)
    caps = [n_mobile if c in mobiles else cfg.max_per_class for c in classes]
    train_idx = np.concatenate([bg_idx] + [
        _sample(rng, np.flatnonzero((ex_all.cls == k) & ~is_held), caps[k]) for k in range(1, len(classes))])
    missing = [c for k, c in enumerate(classes) if not np.any(ex_all.cls[train_idx] == k)]
    if missing:
        warnings.append(f"no training examples of class(es) {', '.join(missing)}: "
                        + ("only the open-set test and the shape envelopes reject clutter; record the field with "
                           "people walking and no robot, and pass it with --background"
                           if missing == [BACKGROUND] else "it is never detected"))
    x_cls = ex_all.vectors[train_idx]
    clf_gps = []
    for k, name in enumerate(classes):
        key, sub = jax.random.split(key)
        gp, info = _fit32(x_cls, (ex_all.cls[train_idx] == k).astype(np.float64), sub, cfg, progress, f"class.{name}",
                          cfg.n_inducing_class, cfg.max_class_fit)
        clf_gps.append(gp)
        fits.append(info)
    classifier = Classifier(tuple(clf_gps), jnp.full(len(classes), cfg.threshold, jnp.float32), support)

    # Pose regressors of the mobile classes: x̃, ỹ, sin θ̃, cos θ̃ (eq. 15, 17).
    calibration = {}
    for name in mobiles:
        k = classes.index(name)
        idx = _sample(rng, np.flatnonzero((ex_all.cls == k) & ~is_held), cfg.max_pose_examples)
        if idx.size < 3:
            raise InputError("training data", f"only {idx.size} examples of class '{name}'")
        tgt = ex_all.target[idx]
        comps = {"x": tgt[:, 0], "y": tgt[:, 1], "sin": np.sin(tgt[:, 2]), "cos": np.cos(tgt[:, 2])}
        gps = {}
        for comp, y in comps.items():
            key, sub = jax.random.split(key)
            gps[comp], info = _fit32(ex_all.vectors[idx], y, sub, cfg, progress, f"{name}.{comp}", cfg.n_inducing,
                                     cfg.max_pose_fit)
            fits.append(info)
        pose[k] = PoseRegressor(gps["x"], gps["y"], gps["sin"], gps["cos"])
        # Variances calibrated on the held-out examples (on the training ones if too few are held out).
        cal = np.flatnonzero((ex_all.cls == k) & is_held)
        cal = cal if cal.size >= 20 else idx
        pose[k] = calibrate(pose[k], ex_all.vectors[cal], ex_all.target[cal])
        calibration[name] = {"examples": int(cal.size), "held_out": bool(cal is not idx),
                             "var_scale": [round(float(v), 4) for v in np.asarray(pose[k].var_scale)]}
        if pose[k].heading_var_max is not None:
            calibration[name]["vague_heading_sigma_deg"] = round(math.degrees(math.sqrt(float(pose[k].heading_var_max))), 2)

    # Motion limits of the tracked classes: from labelled motion, else the user's or the defaults.
    learnt = motion_limits(logs, classes)
    motion = {}
    speed, turn = [], []
    for c in classes:
        if c in cfg.max_speed or c in cfg.max_turn_rate or c in learnt or c in mobiles:
            src = learnt.get(c, {})
            v = cfg.max_speed.get(c, src.get("max_speed", DEFAULT_MAX_SPEED))
            w = cfg.max_turn_rate.get(c, src.get("max_turn_rate", DEFAULT_MAX_TURN_RATE))
            how = "set" if c in cfg.max_speed else "labelled motion" if "max_speed" in src else "default"
            how_w = "set" if c in cfg.max_turn_rate else "labelled motion" if "max_turn_rate" in src else "default"
            motion[c] = {"max_speed": v, "max_speed_from": how, "max_turn_rate": w, "max_turn_rate_from": how_w,
                         "labelled_steps": src.get("steps", 0)}
        speed.append(motion.get(c, {}).get("max_speed", DEFAULT_MAX_SPEED))
        turn.append(motion.get(c, {}).get("max_turn_rate", DEFAULT_MAX_TURN_RATE))

    rate = _rate(logs)
    tracked = [c in mobiles for c in classes]
    model = Model(
        frontend=fe_cfg,
        classifier=classifier,
        envelope=envelope,
        pose=tuple(pose),
        tracker=TrackerParams.default(tracked, rate_hz=rate, max_speed=speed, max_turn_rate=turn),
        landmark_mask=jnp.asarray([c in landmarks for c in classes]),
        map_gate=jnp.asarray(cfg.map_gate, jnp.float32),
        map_min_spread=jnp.asarray(cfg.map_min_spread, jnp.float32),
        meas_var_floor=jnp.asarray(cfg.meas_var_floor, jnp.float32),
        site=None,
        classes=classes,
        max_tracks=cfg.max_tracks,
        sensor_model=first.sensor_model or "unknown",
        n_beams=n_beams,
        gp_columns=columns,
        angle_min=float(first.angle_min),
        angle_increment=float(first.angle_increment),
        range_min=float(first.range_min),
        range_max=float(first.range_max),
    )
    report = {
        "classes": list(classes),
        "examples": counts,
        "examples_labelled_logs": labelled_counts,
        "examples_used": {c: int(np.sum(ex_all.cls[train_idx] == k)) for k, c in enumerate(classes)},
        "background_logs": bg_info,
        "fits": fits,
        "variance_calibration": calibration,
        "envelopes": {classes[k]: v for k, v in env_report.items()},
        "open_set": {classes[k]: v for k, v in sup_report.items()},
        "motion_limits": motion,
        "scans": n_scans,
        "degraded_scans": degraded,
        "warnings": warnings,
        "heldout": evaluate_examples(model, ex_all.take(np.flatnonzero(is_held))),
    }
    if len(bg_ex.cls):
        report["heldout_background_logs"] = evaluate_examples(
            model, bg_ex.take(np.flatnonzero(np.isin(bg_ex.group, list(held)))))
    return model, report


def _second_pass(logs, per_log, cls1, pose, site, classes, landmarks, cfg) -> Examples:
    """Landmark candidates moved to their predicted centres, transforms again, all labels and targets."""
    ex2 = []
    offset = 0
    degraded = 0
    n_scans = 0
    for log, fe, cls_tk in zip(logs, per_log, cls1, strict=True):
        det_s = fe["origin"].copy()
        T, K, D = fe["vector"].shape
        for name in landmarks:
            k = classes.index(name)
            rel, _ = regress_one_class(pose[k], jnp.asarray(fe["vector"].reshape(T * K, D), jnp.float32))
            rel = np.asarray(rel, np.float64).reshape(T, K, 3)
            moved = compose(_ors(fe["origin"], fe["heading"]), rel[..., :2])
            det_s = np.where((cls_tk == k)[..., None], moved, det_s)
        tf = estimate_transforms(det_s, fe["keep"], site, cfg)
        degraded += int(tf["degraded"].sum())
        n_scans += log.n_scans
        ex, _ = label_log(log, fe, tf, site, classes, cfg, offset)
        offset = int(ex.group.max(initial=offset)) + 1
        ex2.append(ex)
    ex_all = _concat(ex2)
    ex_all.degraded, ex_all.n_scans = degraded, n_scans
    return ex_all


def _rate(logs):
    dts = np.concatenate([np.diff(log.stamps) for log in logs if log.n_scans > 1] or [np.array([0.1])])
    dts = dts[dts > 0]
    return float(1.0 / np.median(dts)) if dts.size else 10.0


def _concat(exs: list[Examples]) -> Examples:
    return Examples(*(np.concatenate([getattr(e, f.name) for e in exs]) for f in dataclasses.fields(Examples)))


def evaluate_examples(model: Model, ex: Examples) -> dict:
    """Held-out classification as the step decides it (envelopes, scores, thresholds, open set):
    accuracy overall and per class, what each class's examples were taken for, the share dropped as
    unlike their class's examples or outside its envelope, and the pose errors of the mobile classes."""
    if len(ex.cls) == 0:
        return {"n": 0}
    pred, unlike, off = decide(model, ex)
    out = {"n": int(len(ex.cls)), "accuracy": float(np.mean(pred == ex.cls)), "per_class": {}, "pose": {}}
    for k, name in enumerate(model.classes):
        sel = ex.cls == k
        if sel.any():
            taken = {c: float(np.mean(pred[sel] == j)) for j, c in enumerate(model.classes) if np.any(pred[sel] == j)}
            out["per_class"][name] = {"n": int(sel.sum()), "recall": float(np.mean(pred[sel] == k)), "taken_for": taken,
                                      "unlike": float(np.mean(unlike[sel])), "off_envelope": float(np.mean(off[sel]))}
        reg = model.pose[k]
        if reg is None or reg.sin is None or not sel.any():
            continue
        rel, _ = regress_one_class(reg, jnp.asarray(ex.vectors[sel], jnp.float32))
        rel = np.asarray(rel, np.float64)
        err_xy = np.linalg.norm(rel[:, :2] - ex.target[sel, :2], axis=1)
        err_th = wrap(rel[:, 2] - ex.target[sel, 2])
        out["pose"][name] = {"n": int(sel.sum()), "rmse_xy_m": float(np.sqrt(np.mean(err_xy**2))),
                             "rmse_theta_deg": float(np.degrees(np.sqrt(np.mean(err_th**2)))),
                             "median_theta_deg": float(np.degrees(np.median(np.abs(err_th)))),
                             "misread_fraction": float(np.mean(np.abs(err_th) > np.radians(30)))}
    return out
