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
"""

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._classify import Classifier, class_scores, gp_inputs
from ._frontend import FrontEndConfig, front_end_log
from ._gp import fit
from ._maptransform import Transform, update_transform
from ._pose import PoseRegressor, calibrate, regress_one_class
from ._track import TrackerParams
from .errors import InputError
from .io.logs import ScanLog, to_scans
from .io.site import Site
from .model import Model
from .sensors import get_model

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
    n_inducing_class: int = 512
    n_inducing_var: int = 64
    restarts: int = 3  # optimiser starts per GP fit
    holdout: float = 0.2  # fraction of one-second blocks held out for evaluation
    label_radius: float = 0.3  # m: a candidate this close to a labelled object is that object
    landmark_radius: float = 0.25  # m: a candidate this close to a site landmark is that landmark
    bounds_margin: float | None = 0.5  # m: background examples only this far outside the site's bounds
    threshold: float = 0.35  # winning class score needed to keep a candidate (scores are GP means, not probabilities)
    map_gate: float = 0.4  # m: landmark association gate of stage f
    map_min_spread: float = 0.3  # m: associated landmarks must spread this much in 2-D
    meas_var_floor: tuple[float, float, float] = (2.5e-5, 2.5e-5, 3e-4)  # (5 mm)², (5 mm)², (1°)²
    # Noise floor of every GP, relative to its signal variance. Many scans of one static pose give
    # near-duplicate inputs with equal targets; without a floor the likelihood is maximised by
    # interpolating them (σn² → 0, tiny length scales), which generalises badly to new poses.
    noise_floor: float = 1e-2
    max_tracks: int = 8
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

    def take(self, idx) -> "Examples":
        return Examples(*(getattr(self, f.name)[idx] for f in dataclasses.fields(self)))


def wrap(a):
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def class_list(logs: Sequence[ScanLog], site: Site) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """All classes (background first, then landmark classes, then mobile classes), landmarks, mobiles."""
    landmarks = tuple(sorted(set(site.landmark_classes)))
    mobiles = tuple(sorted({str(c) for log in logs for c in log.truth_classes}))
    clash = set(landmarks) & set(mobiles)
    if clash or BACKGROUND in landmarks or BACKGROUND in mobiles:
        raise InputError("training data", f"class name(s) {sorted(clash or {BACKGROUND})} used for both landmarks "
                                          "and labelled objects, or reserved")
    return (BACKGROUND, *landmarks, *mobiles), landmarks, mobiles


def run_front_end(log: ScanLog, cfg: FrontEndConfig, n_beams: int, chunk: int = 1024):
    """Stages a–c over a log, chunk by chunk; returns host arrays origin, heading, keep and ``vector``,
    the GP inputs of each candidate (:func:`~gtsjax._classify.gp_inputs`)."""
    outs = {"origin": [], "heading": [], "vector": [], "keep": []}
    for start in range(0, log.n_scans, chunk):
        scans = to_scans(log.slice(start, start + chunk), n_beams)
        fe = front_end_log(cfg, scans)
        outs["origin"].append(np.asarray(fe.features.origin, np.float64))
        outs["heading"].append(np.asarray(fe.features.heading, np.float64))
        f = fe.features
        outs["vector"].append(np.asarray(gp_inputs(f.vector, f.origin, f.height), np.float64))
        outs["keep"].append(np.asarray(fe.keep))
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


def _to_s(tf, p_o):
    """Points [T, n, 2] in O to S under per-scan transforms (inverse of eq. 10, solved)."""
    d = p_o - tf["mu_o"][:, None, :]
    return np.linalg.solve(tf["A"][:, None], d[..., None])[..., 0] + tf["mu_s"][:, None, :]


def _to_o(tf, p_s):
    return np.einsum("tij,tnj->tni", tf["A"], p_s - tf["mu_s"][:, None, :]) + tf["mu_o"][:, None, :]


def _rel(origin, heading, p_s):
    """Points in S [T, K, 2] into each candidate's ORS (eq. 9)."""
    d = p_s - origin
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def label_log(log: ScanLog, fe: dict, tf: dict, site: Site, classes: tuple[str, ...], cfg: TrainConfig,
              group_offset: int) -> tuple[Examples, np.ndarray]:
    """Label one log's candidates (spec rules) and compute their ORS-relative pose targets. Also
    returns the class of every candidate slot ``[T, K]`` (0 where not an example or background)."""
    T, K = fe["keep"].shape
    origin, heading = fe["origin"], fe["heading"]
    origin_o = _to_o(tf, origin)  # [T, K, 2]
    rot_s = np.arctan2(tf["A"][:, 1, 0], tf["A"][:, 0, 0])  # [T]
    cls = np.zeros((T, K), np.int64)
    target = np.full((T, K, 3), np.nan)
    best = np.full((T, K), np.inf)

    lm_xy = site.landmark_xy
    lm_s = _to_s(tf, np.broadcast_to(lm_xy, (T,) + lm_xy.shape))  # [T, L, 2]
    for j, lm in enumerate(site.landmarks):
        d = np.linalg.norm(origin_o - lm_xy[j], axis=-1)
        hit = (d < cfg.landmark_radius) & (d < best)
        rel = _rel(origin, heading, np.broadcast_to(lm_s[:, j : j + 1], origin.shape))
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
        p_s = _to_s(tf, np.nan_to_num(p[:, None, :2]))  # [T, 1, 2]
        rel = _rel(origin, heading, np.broadcast_to(p_s, origin.shape))
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
        x0, y0, x1, y1 = site.bounds
        mg = cfg.bounds_margin
        inside = ((origin_o[..., 0] >= x0 - mg) & (origin_o[..., 0] <= x1 + mg)
                  & (origin_o[..., 1] >= y0 - mg) & (origin_o[..., 1] <= y1 + mg))
        use &= inside | (cls != 0)
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


def _fit32(x, y, key, cfg, progress, label, n_inducing: int, max_fit: int | None = None):
    t0 = time.perf_counter()
    # With max_fit the posterior takes every example given (the caller capped them); without, fit's
    # own cap applies to the fit and the posterior alike.
    cap = {} if max_fit is None else {"max_points": x.shape[0], "max_fit_points": max_fit}
    gp = fit(x, y, key=key, restarts=cfg.restarts, jitter=cfg.noise_floor, **cap)
    sparse = gp.sparse(n_inducing, cfg.n_inducing_var).astype(jnp.float32)
    p = gp.params
    info = {"gp": label, "n": int(x.shape[0]), "n_fit": int(min(x.shape[0], max_fit or x.shape[0])),
            "seconds": round(time.perf_counter() - t0, 2),
            "lml": float(gp.log_marginal_likelihood()),
            "signal_var": float(p.signal_var), "noise_var": float(p.noise_var),
            "lengthscale_median": float(np.median(np.asarray(p.lengthscale)))}
    if progress is not None:
        progress(info)
    return sparse, info


def train(logs: Sequence[ScanLog], site: Site, cfg: TrainConfig = TrainConfig(), *,
          progress: Callable[[dict], None] | None = None, names: Sequence[str] | None = None) -> tuple[Model, dict]:
    """Train a model from labelled logs of one site. Returns the model (float32 predictors, bounded
    cost) and a report: examples per class, GP fits, held-out accuracy and pose errors."""
    names = list(names) if names is not None else [f"log {i}" for i in range(len(logs))]
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
    n_beams = first.n_beams
    if first.sensor_model is not None:
        try:
            n_beams = max(n_beams, get_model(first.sensor_model).n_beams)
        except InputError:
            pass
    classes, landmarks, mobiles = class_list(logs, site)
    if not mobiles:
        raise InputError(names[0], "no labelled object classes in the logs")

    fe_cfg = cfg.frontend
    per_log = []
    for log in logs:
        fe = run_front_end(log, fe_cfg, n_beams)
        per_log.append(fe)
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
    groups = np.unique(ex_all.group)
    held = set(rng.choice(groups, max(1, int(round(cfg.holdout * groups.size))), replace=False).tolist())
    fits = []
    pose: list[PoseRegressor | None] = [None] * len(classes)
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
    is_held = np.isin(ex_all.group, list(held))

    # Classifier: balanced, capped examples; one GP per class on 1/0 targets (eq. 14).
    counts = {c: int(np.sum(ex_all.cls == k)) for k, c in enumerate(classes)}
    train_idx = np.concatenate([
        _sample(rng, np.flatnonzero((ex_all.cls == k) & ~is_held), cfg.max_per_class) for k in range(len(classes))])
    missing = [c for k, c in enumerate(classes) if not np.any(ex_all.cls[train_idx] == k)]
    if missing:
        raise InputError("training data", f"no training examples of class(es) {', '.join(missing)}")
    x_cls = ex_all.vectors[train_idx]
    clf_gps = []
    for k, name in enumerate(classes):
        key, sub = jax.random.split(key)
        gp, info = _fit32(x_cls, (ex_all.cls[train_idx] == k).astype(np.float64), sub, cfg, progress, f"class.{name}",
                          cfg.n_inducing_class)
        clf_gps.append(gp)
        fits.append(info)
    classifier = Classifier(tuple(clf_gps), jnp.full(len(classes), cfg.threshold, jnp.float32))

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

    rate = _rate(logs)
    tracked = [c in mobiles for c in classes]
    model = Model(
        frontend=fe_cfg,
        classifier=classifier,
        pose=tuple(pose),
        tracker=TrackerParams.default(tracked, rate_hz=rate),
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
    )
    report = {
        "classes": list(classes),
        "examples": counts,
        "examples_used": {c: int(np.sum(ex_all.cls[train_idx] == k)) for k, c in enumerate(classes)},
        "fits": fits,
        "variance_calibration": calibration,
        "scans": n_scans,
        "degraded_scans": degraded,
        "heldout": evaluate_examples(model, ex_all.take(np.flatnonzero(is_held))),
    }
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
            c, s = np.cos(fe["heading"]), np.sin(fe["heading"])
            moved = np.stack([fe["origin"][..., 0] + c * rel[..., 0] - s * rel[..., 1],
                              fe["origin"][..., 1] + s * rel[..., 0] + c * rel[..., 1]], -1)
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


def predict_classes(model: Model, vectors: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Class of each vector as the step decides it (argmax, then background below the threshold)."""
    out = []
    for s in range(0, len(vectors), chunk):
        v = jnp.asarray(vectors[s : s + chunk], jnp.float32)
        scores = np.asarray(class_scores(model.classifier, v))
        cls = scores.argmax(-1)
        best = scores[np.arange(len(cls)), cls]
        cls = np.where(best >= np.asarray(model.classifier.threshold)[cls], cls, 0)
        out.append(cls)
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def evaluate_examples(model: Model, ex: Examples) -> dict:
    """Held-out classification accuracy (overall and per class) and pose errors of the mobile classes."""
    if len(ex.cls) == 0:
        return {"n": 0}
    pred = predict_classes(model, ex.vectors)
    out = {"n": int(len(ex.cls)), "accuracy": float(np.mean(pred == ex.cls)), "per_class": {}, "pose": {}}
    for k, name in enumerate(model.classes):
        sel = ex.cls == k
        if sel.any():
            out["per_class"][name] = {"n": int(sel.sum()), "recall": float(np.mean(pred[sel] == k))}
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
