"""Training's front end and labels: stages a–c over the logs, each scan's map transformation (stage
f), and the labelled examples of the classifier (stage d) and the pose regressors (stage e).

The rules are those of ``shared/spec/formats.md``: a candidate near a labelled object is an example
of that object's class, with the object's pose in the candidate's ORS as its pose target (eq. 9, 16
inverted); a candidate near a site landmark is an example of the landmark's class; every other
candidate that passes the binary filters is ``background``.

"Near" needs each scan's map transformation (eq. 10), which is estimated as stage f does at run time
(the core's own ``update_transform``), from the candidates near the site's landmarks, seeded by the
site's rough sensor pose. Two passes: the first (:func:`first_pass`) places each landmark candidate at
the centre of a circle through its points (its ORS origin sits on the visible surface, a few cm in
front of a post's centre), of the radius that leaves the map rigid; it gives the landmark classes'
position targets, whose GPs then move each landmark candidate to its centre for the second
pass (:func:`second_pass`), as the step does at run time. All targets come from the second pass.

Every frame change goes through the core's geometry (:mod:`gtsjax.core.geometry`), on float64 host
arrays: the labels are the step's own maths, not a copy of it.

The held-out split (:func:`holdout_groups`) is by blocks of one second of scans, so that
near-identical consecutive scans do not sit on both sides of it. Background logs (recorded with no
robot in view, :func:`background_examples`) give background examples: every candidate the binary
filters keep in them, in one-second blocks as well.
"""

import dataclasses
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..core.c_filters import shape_quantities
from ..core.d_classify import gp_inputs
from ..core.e_pose import PoseRegressor, regress_one_class
from ..core.f_maptransform import Transform, update_transform
from ..core.frontend import FrontEndConfig, front_end_batch
from ..core.geometry import affine_heading, compose, field_to_sensor, in_bounds, relative, sensor_to_field, wrap
from ..drivers.batch import pad_chunk
from ..errors import InputError
from ..io.logs import ScanLog, fit_geometry, to_scans
from ..io.site import Site
from ..sensors import get_model
from .bounds import LANDMARK_RADIUS, MAP_SCALE_WARN
from .config import TrainConfig

BACKGROUND = "background"


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
    # [E, 4] where each example's points are: log index (among the labelled logs; -1: not kept), scan,
    # first beam and beam count of its segment (the outline's training data, ``train.outline``).
    where: np.ndarray | None = None
    # [E] the labelled object each example is, an index into its log's truth (-1: background, a
    # landmark, or not known): which robot, for the tags' calibration (``train.tags``).
    obj: np.ndarray | None = None

    def take(self, idx) -> "Examples":
        return Examples(*(None if getattr(self, f.name) is None else getattr(self, f.name)[idx]
                          for f in dataclasses.fields(self)))

    @staticmethod
    def concat(exs: "Sequence[Examples]") -> "Examples":
        def field(e, name):
            v = getattr(e, name)
            if v is None and name == "where":
                return np.full((len(e.cls), 4), -1, np.int64)
            return np.full(len(e.cls), -1, np.int64) if v is None and name == "obj" else v

        return Examples(*(np.concatenate([field(e, f.name) for e in exs]) for f in dataclasses.fields(Examples)))


# ------------------------------------------------------------------------------------------ the logs


def class_list(logs: Sequence[ScanLog], site: Site) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """All classes (background first, then landmark classes, then mobile classes), landmarks, mobiles."""
    landmarks = tuple(sorted(set(site.landmark_classes)))
    mobiles = tuple(sorted({str(c) for log in logs for c in log.truth_classes}))
    clash = set(landmarks) & set(mobiles)
    if clash or BACKGROUND in landmarks or BACKGROUND in mobiles:
        raise InputError("training data", f"class name(s) {sorted(clash or {BACKGROUND})} used for both landmarks "
                                          "and labelled objects, or reserved")
    return (BACKGROUND, *landmarks, *mobiles), landmarks, mobiles


def check_logs(logs: Sequence[ScanLog], names: Sequence[str]) -> None:
    """Labelled logs of one scanner: each labelled, all with the first one's beams, angles and model."""
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


def step_beams(log: ScanLog) -> int:
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
    geometry = dict(angle_min=first.angle_min, angle_increment=first.angle_increment, n_beams=step_beams(first),
                    range_min=first.range_min, range_max=first.range_max)
    return [fit_geometry(log, **geometry, where=name, crop=True, sensor_model=first.sensor_model)
            for log, name in zip(background, names, strict=True)]


def _block_scans(log: ScanLog) -> int:
    """Scans in one second of ``log``: the size of a held-out block."""
    period = np.median(np.diff(log.stamps)) if log.n_scans > 1 else 0.1
    return max(1, int(round(1.0 / max(period, 1e-3))))


def scan_groups(log: ScanLog, *, moved: float = 0.05, jump: float = 0.25, block_s: float = 1.0) -> np.ndarray:
    """Each scan's held-out group within ``log`` (``[T]``, from 0): scans that see the labelled objects
    where they were are one group, so that no held-out view has a near-copy in the training set.

    A robot put down for seconds at a pose (or turned on the spot there) is one group for as long as it
    stays: held out, it is a pose the model never saw, as the poses of a live run are. Where the labels
    move (walking, carried), a group is one second of scans, as a log without labels is cut: a new group
    starts once the group is ``block_s`` old and an object has moved ``moved`` from where it was at the
    group's start. A jump (an object ``jump`` away from its last scan's pose: put down at the next grid
    pose) or an object appearing or leaving starts a new group at once."""
    block = _block_scans(log)
    poses = log.truth_poses
    if poses is None or poses.shape[1] == 0:
        return np.arange(log.n_scans) // block
    xy = poses[..., :2]
    present = ~np.isnan(xy[..., 0])
    out = np.zeros(log.n_scans, np.int64)
    g, start = 0, 0
    for t in range(1, log.n_scans):
        new = bool(np.any(present[t] != present[t - 1]))
        both = present[t] & present[t - 1]
        if not new and both.any():
            step = np.linalg.norm(xy[t, both] - xy[t - 1, both], axis=-1)
            new = bool(np.any(step > jump))
            if not new and t - start >= block:
                since = present[t] & present[start]
                new = bool(np.any(np.linalg.norm(xy[t, since] - xy[start, since], axis=-1) > moved))
        elif not present[t].any() and t - start >= block:
            new = True  # nobody in view: one-second blocks, as a log without labels
        if new:
            g, start = g + 1, t
        out[t] = g
    return out


# ---------------------------------------------------------------------------- stages a–c over the logs


_front_end_batch = jax.jit(front_end_batch, static_argnames=("chunk", "windows"))


def padded_size(n: int, cap: int, least: int = 64) -> int:
    """The leading size a program is compiled for when it gets ``n`` rows (at most ``cap``): the
    smallest power of two that holds them, at least ``least``, at most ``cap``. Logs and example sets
    of every length then share a few compiled programs (a log's last chunk was a program of its own,
    compiled afresh for each length), at a cost of less than twice the rows of that last chunk."""
    size = least
    while size < n:
        size *= 2
    return min(size, cap) if n <= cap else n


def run_front_end(log: ScanLog, cfg: FrontEndConfig, n_beams: int, chunk: int = 1024):
    """Stages a–c over a log, chunk by chunk; returns host arrays ``[T, K, …]``: origin, heading,
    keep, ``vector`` (the GP inputs of each candidate, :func:`~gtsjax.core.d_classify.gp_inputs`),
    ``shape`` (:func:`~gtsjax.core.c_filters.shape_quantities`), ``rng`` (the ORS origin's range) and
    ``occluded``, and each candidate's ``start`` beam and ``length``. A last chunk shorter than
    ``chunk`` is padded to :func:`padded_size` and its padding dropped."""
    outs = {"origin": [], "heading": [], "vector": [], "keep": [], "shape": [], "rng": [], "occluded": [],
            "start": [], "length": []}
    for start in range(0, log.n_scans, chunk):
        scans = to_scans(log.slice(start, start + chunk), n_beams)
        n = int(scans.dt.shape[0])
        fe = jax.tree.map(lambda a, n=n: a[:n], _front_end_batch(cfg, pad_chunk(scans, 0, n, padded_size(n, chunk))))
        f = fe.features
        rng = jnp.sqrt(jnp.sum(f.origin**2, axis=-1))
        outs["origin"].append(np.asarray(f.origin, np.float64))
        outs["heading"].append(np.asarray(f.heading, np.float64))
        outs["vector"].append(np.asarray(gp_inputs(f.vector, f.origin, f.height), np.float64))
        outs["keep"].append(np.asarray(fe.keep))
        outs["shape"].append(np.asarray(shape_quantities(f.width, f.height, f.n_points, rng), np.float64))
        outs["rng"].append(np.asarray(rng, np.float64))
        outs["occluded"].append(np.asarray(fe.candidates.occluded))
        outs["start"].append(np.asarray(fe.candidates.start))
        outs["length"].append(np.asarray(fe.candidates.length))
    return {k: np.concatenate(v) for k, v in outs.items()}


def informative_columns(vectors: np.ndarray) -> tuple[int, ...]:
    """Indices of the columns of ``vectors`` [n, d] that vary (relative spread above 1e-9)."""
    if len(vectors) == 0:
        return tuple(range(vectors.shape[-1]))
    spread = vectors.max(axis=0) - vectors.min(axis=0)
    scale = np.maximum(np.abs(vectors).max(axis=0), 1.0)
    return tuple(int(c) for c in np.flatnonzero(spread > 1e-9 * scale))


def front_end_logs(logs: Sequence[ScanLog], cfg: FrontEndConfig, n_beams: int) -> tuple[list[dict], tuple[int, ...]]:
    """:func:`run_front_end` over every log, and the GP input columns the model keeps: those that
    vary over the kept candidates (the intensity profile of a scanner without intensity never does);
    the others are dropped from each log's ``vector``."""
    per_log = [run_front_end(log, cfg, n_beams) for log in logs]
    columns = informative_columns(np.concatenate([fe["vector"][fe["keep"]] for fe in per_log]))
    for fe in per_log:
        fe["vector"] = fe["vector"][..., list(columns)]
    return per_log, columns


# ------------------------------------------------------------------------- stage f, scan by scan


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
    """Each scan's map transformation (eq. 10, 18) from the points ``det_s`` ``[T, K, 2]`` in S (where
    ``keep``), seeded by the site's sensor pose: host arrays ``A``, ``mu_s``, ``mu_o``, ``degraded``
    and ``n`` (landmarks associated), one per scan."""
    tf0 = Transform.from_sensor_pose(jnp.asarray(site.sensor_pose, jnp.float32))
    tfs = _transforms(tf0, jnp.asarray(det_s, jnp.float32), jnp.asarray(keep), jnp.asarray(site.landmark_xy, jnp.float32),
                      jnp.asarray(cfg.map_gate, jnp.float32), jnp.asarray(cfg.map_min_spread, jnp.float32))
    return {"A": np.asarray(tfs.A, np.float64), "mu_s": np.asarray(tfs.mu_s, np.float64),
            "mu_o": np.asarray(tfs.mu_o, np.float64), "degraded": np.asarray(tfs.degraded),
            "n": np.asarray(tfs.n_landmarks)}




def map_scale(tf: dict, min_landmarks: int = 3) -> float:
    """The median scale ``sqrt(|det A|)`` of the transforms ``tf`` fitted on ``min_landmarks`` or more
    landmarks (1 for a rigid map); NaN where none was."""
    ok = ~tf["degraded"] & (tf["n"] >= min_landmarks)
    if not ok.any():
        return math.nan
    return float(np.median(np.sqrt(np.abs(np.linalg.det(tf["A"][ok])))))


def window_points(log: ScanLog, scan: np.ndarray, start: np.ndarray, length: np.ndarray, window: int,
                  dtype=np.float64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points in S ``[n, window, 2]`` of candidate windows of ``log`` (scan, first beam, length; as
    the front end gives them), their mask and beams: as the step's candidate windows hold them, the
    arithmetic in ``dtype`` (the step's float32 where what is learnt from them must match it)."""
    lane = np.arange(window)
    inside = (lane[None, :] < np.minimum(length, window)[:, None]) & (start[:, None] + lane[None, :] < log.n_beams)
    beam = np.minimum(start[:, None] + lane[None, :], log.n_beams - 1)
    valid = log.valid()[scan[:, None], beam] & inside
    r = np.where(valid, log.ranges[scan[:, None], beam], 0.0).astype(dtype)
    a = (dtype(log.angle_min) + beam.astype(dtype) * dtype(log.angle_increment)).astype(dtype)
    return np.stack([r * np.cos(a), r * np.sin(a)], -1), valid, beam


def circle_centres(pts: np.ndarray, mask: np.ndarray, origin: np.ndarray, radius: float, iterations: int = 8,
                   robust: float = 0.01) -> np.ndarray:
    """The centres ``[n, 2]`` of circles of ``radius`` through each candidate's points ``pts`` ``[n, w, 2]``
    (where ``mask``): Gauss-Newton on the points' distances to the circle, Cauchy-weighted (scale
    ``robust``, metres) against a mixed pixel at an edge, started ``radius`` behind the ORS ``origin``
    along its line of sight."""
    u = origin / np.maximum(np.linalg.norm(origin, axis=-1, keepdims=True), 1e-9)
    q = origin + radius * u
    for _ in range(iterations):
        d = pts - q[:, None]
        n = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
        r = n - radius
        w = mask / (1.0 + (r / robust) ** 2)
        J = -d / n[..., None]
        JtJ = np.einsum("kni,knj,kn->kij", J, J, w) + 1e-9 * np.eye(2)
        Jtr = np.einsum("kni,kn,kn->ki", J, r, w)
        q = q - np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
    return q


def landmark_centres(log: ScanLog, fe: dict, site: Site, cfg: TrainConfig, steps: int = 4) -> tuple[dict, dict]:
    """The first pass's map transformations, from each landmark candidate's centre: ``(transforms,
    evidence)`` (``evidence["radius"]`` the landmarks' radius found, NaN where none was).

    A candidate's ORS origin (eq. 8: the midpoints of its range and bearing extents) lies in front of a
    post's centre, by 0.7-0.8 of its radius and more with range as fewer beams reach its edges; the site
    gives the centres. Fitted to the origins, the affine map (eq. 10) takes that shortfall up as a scale
    (1.012 for a 5 cm post at 3-4 m), and the labels through it sit that share of their range too close
    to the laser: the landmark GPs learn centres short by that much, the run-time map keeps the scale,
    and every robot's label and learnt outline shrink with it (the outline 1.5 cm small in radius on the
    tests' Nao recording). So the candidates that the map from their origins puts near a landmark are
    placed at the centre of a circle through their points, and the circle's radius is the one that
    leaves the map rigid (a horizontal laser's geometry is): the secant method on the median scale. The
    radius cannot come from the points alone: four points on a short arc fit a smaller circle nearly as
    well (millimetres short, centimetres of map). Without three landmarks in view in any scan, or where
    no radius within :data:`~gtsjax.train.bounds.LANDMARK_RADIUS` brings the scale within
    :data:`~gtsjax.train.bounds.MAP_SCALE_WARN` of 1 (landmarks that are not round), the map from the
    origins, as before."""
    tf0 = estimate_transforms(fe["origin"], fe["keep"], site, cfg)
    s0 = map_scale(tf0)
    evidence = {"radius": math.nan, "scale_before": s0, "scale_after": s0, "candidates": 0}
    if not math.isfinite(s0):  # never three landmarks in view (a site without landmarks included)
        return tf0, evidence
    origin_o = sensor_to_field(*_per_scan(tf0), fe["origin"])
    gap = np.linalg.norm(origin_o[:, :, None] - site.landmark_xy[None, None], axis=-1).min(-1)
    t, k = np.nonzero(fe["keep"] & (gap < cfg.landmark_radius))
    length = fe["length"][t, k]
    pts, mask, _ = window_points(log, t, fe["start"][t, k], length, int(min(cfg.frontend.window, length.max(initial=1))))
    evidence["candidates"] = int(t.size)

    def fitted(radius: float) -> tuple[dict, float]:
        det = fe["origin"].copy()
        det[t, k] = circle_centres(pts, mask, fe["origin"][t, k], radius)
        tf = estimate_transforms(det, fe["keep"], site, cfg)
        return tf, map_scale(tf)

    lo, hi = 1e-3 * LANDMARK_RADIUS.floor, 1e-3 * LANDMARK_RADIUS.ceiling
    r0, r1 = 0.03, 0.06
    tf_a, sa = fitted(r0)
    best = (abs(sa - 1.0), r0, tf_a, sa)
    for _ in range(steps):
        tf_b, sb = fitted(r1)
        if not (math.isfinite(sa) and math.isfinite(sb)):
            break
        if abs(sb - 1.0) < best[0]:
            best = (abs(sb - 1.0), r1, tf_b, sb)
        if sb == sa or best[0] < 1e-5:
            break
        r2 = float(np.clip(r1 - (sb - 1.0) * (r1 - r0) / (sb - sa), lo, hi))
        r0, sa, r1 = r1, sb, r2
    off, radius, tf, s = best
    if off > MAP_SCALE_WARN:
        return tf0, evidence
    return tf, {**evidence, "radius": radius, "scale_after": s}


def _per_scan(tf):
    """A log's transforms ``[T]`` as arguments of ``geometry``'s S ↔ O maps for points ``[T, n, 2]``."""
    return tf["A"][:, None], tf["mu_s"][:, None], tf["mu_o"][:, None]


def _ors(origin, heading):
    """Candidates' ORS frames ``[..., 3]`` (eq. 9) from their origins and headings."""
    return np.concatenate([origin, heading[..., None]], -1)


# ------------------------------------------------------------------------------------------ labels


def label_log(log: ScanLog, fe: dict, tf: dict, site: Site, classes: tuple[str, ...], cfg: TrainConfig,
              group_offset: int, log_index: int = -1) -> tuple[Examples, np.ndarray]:
    """Label one log's candidates (spec rules) and compute their ORS-relative pose targets. Also
    returns the class of every candidate slot ``[T, K]`` (0 where not an example or background).
    ``log_index``: the log's place among the labelled logs, recorded in ``Examples.where``."""
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
    obj = np.full((T, K), -1, np.int64)
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
        obj[hit] = m
        best[hit] = d[hit]

    # A scan whose transform could not be estimated gives no labels worth having. With bounds, the
    # background is what the step could confuse with an object on the field: candidates inside the
    # bounds (plus a margin), not the walls and furniture around it, which the step drops anyway.
    use = fe["keep"] & ~tf["degraded"][:, None] & ~(ambiguous & (cls == 0))
    if site.bounds is not None and cfg.bounds_margin is not None:
        use &= in_bounds(origin_o, np.asarray(site.bounds), cfg.bounds_margin) | (cls != 0)
    t_idx, k_idx = np.nonzero(use)
    return Examples(
        vectors=fe["vector"][t_idx, k_idx],
        cls=cls[t_idx, k_idx],
        target=target[t_idx, k_idx],
        group=group_offset + scan_groups(log)[t_idx],
        origin=origin[t_idx, k_idx],
        heading=heading[t_idx, k_idx],
        shape=fe["shape"][t_idx, k_idx],
        rng=fe["rng"][t_idx, k_idx],
        occluded=fe["occluded"][t_idx, k_idx],
        where=np.stack([np.full(t_idx.shape, log_index), t_idx, fe["start"][t_idx, k_idx],
                        fe["length"][t_idx, k_idx]], -1).astype(np.int64),
        obj=obj[t_idx, k_idx],
    ), np.where(use, cls, 0)


def per_log_sites(site: "Site | Sequence[Site]", n: int) -> list[Site]:
    """One site per log: ``site`` for each, or the sequence given (the laser each log is from, on a
    field of several: each log's own rough sensor pose)."""
    sites = [site] * n if isinstance(site, Site) else list(site)
    if len(sites) != n:
        raise ValueError(f"{len(sites)} sites for {n} logs")
    return sites


def first_pass(logs: Sequence[ScanLog], per_log: Sequence[dict], site: "Site | Sequence[Site]",
               classes: tuple[str, ...], cfg: TrainConfig) -> tuple[Examples, list[np.ndarray], int, list[dict]]:
    """Pass 1: transforms from the landmark candidates' circle centres (:func:`landmark_centres`; from
    the raw ORS origins where the landmarks are not round), and the labels they give. Returns the
    examples of all logs, each log's class per candidate slot ``[T, K]``, the next free held-out group
    id, and each log's evidence of :func:`landmark_centres`. ``site``: one for every log, or one per log
    (:func:`per_log_sites`)."""
    offset = 0
    exs, cls_slots, centres = [], [], []
    for log, fe, log_site in zip(logs, per_log, per_log_sites(site, len(logs)), strict=True):
        tf, evidence = landmark_centres(log, fe, log_site, cfg)
        ex, cls_tk = label_log(log, fe, tf, log_site, classes, cfg, offset)
        cls_slots.append(cls_tk)
        centres.append(evidence)
        offset = int(ex.group.max(initial=offset)) + 1
        exs.append(ex)
    return Examples.concat(exs), cls_slots, offset, centres


def _relabel(logs, per_log, cls_slots, pose, site, classes, landmarks, cfg) -> tuple[Examples, int, int]:
    degraded = 0
    n_scans = 0
    offset = 0
    exs = []
    sites = per_log_sites(site, len(logs))
    for i, (log, fe, cls_tk, log_site) in enumerate(zip(logs, per_log, cls_slots, sites, strict=True)):
        det_s = fe["origin"].copy()
        T, K, D = fe["vector"].shape
        for name in landmarks:
            k = classes.index(name)
            rel, _ = regress_one_class(pose[k], jnp.asarray(fe["vector"].reshape(T * K, D), jnp.float32))
            rel = np.asarray(rel, np.float64).reshape(T, K, 3)
            moved = compose(_ors(fe["origin"], fe["heading"]), rel[..., :2])
            det_s = np.where((cls_tk == k)[..., None], moved, det_s)
        tf = estimate_transforms(det_s, fe["keep"], log_site, cfg)
        degraded += int(tf["degraded"].sum())
        n_scans += log.n_scans
        ex, _ = label_log(log, fe, tf, log_site, classes, cfg, offset, log_index=i)
        offset = int(ex.group.max(initial=offset)) + 1
        exs.append(ex)
    return Examples.concat(exs), degraded, n_scans


def second_pass(logs: Sequence[ScanLog], per_log: Sequence[dict], cls_slots: Sequence[np.ndarray],
                pose: Sequence[PoseRegressor | None], site: Site, classes: tuple[str, ...],
                landmarks: tuple[str, ...], cfg: TrainConfig) -> tuple[Examples, int, int]:
    """Pass 2: each landmark candidate of pass 1 (``cls_slots``) moved to its centre as its class's
    position GPs (``pose``) predict it (eq. 16), transforms again, all labels and targets. Returns the
    examples, the scans whose transform was degraded, and the scans in all. A field with nothing but
    objects on it gives no background inside the bounds: then the background is taken from around
    it (walls, furniture)."""
    ex, degraded, n_scans = _relabel(logs, per_log, cls_slots, pose, site, classes, landmarks, cfg)
    if not np.any(ex.cls == 0) and cfg.bounds_margin is not None:
        ex, degraded, n_scans = _relabel(logs, per_log, cls_slots, pose, site, classes, landmarks,
                                         dataclasses.replace(cfg, bounds_margin=None))
    return ex, degraded, n_scans


def background_examples(logs: Sequence[ScanLog], names: Sequence[str], cfg: TrainConfig, n_beams: int,
                        columns: tuple[int, ...], group_offset: int) -> tuple[Examples, list[dict]]:
    """Every candidate that the binary filters keep in a background log (recorded with no robot in view)
    is a background example; one-second blocks of scans are the held-out groups, as for labelled logs."""
    exs, info = [], []
    for log, name in zip(logs, names, strict=True):
        fe = run_front_end(log, cfg.frontend, n_beams)
        t_idx, k_idx = np.nonzero(fe["keep"])
        n = t_idx.size
        exs.append(Examples(
            vectors=fe["vector"][t_idx, k_idx][:, list(columns)],
            cls=np.zeros(n, np.int64),
            target=np.full((n, 3), np.nan),
            group=group_offset + t_idx // _block_scans(log),
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
    return Examples.concat(exs), info


def holdout_groups(rng: np.random.Generator, groups: np.ndarray, fraction: float) -> list:
    """The held-out split: a ``fraction`` (at least one) of the distinct one-second blocks ``groups``."""
    groups = np.unique(groups)
    return list(set(rng.choice(groups, max(1, int(round(fraction * groups.size))), replace=False).tolist()))
