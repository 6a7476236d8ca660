"""What training learns for stages c and d: each class's shape envelope (:func:`fit_envelope`), the
open-set test's examples and thresholds (:func:`fit_support`), and the classifier's GPs, one per
class on 1/0 targets (eq. 14; :func:`fit_classifier`), on balanced and capped examples.

**What the model must reject**. Background logs (recorded anywhere with no robot in view)
add background examples: every candidate the binary filters keep in them, except look-alikes of a
landmark class (a post in view while recording, :func:`landmark_lookalikes`). With them the
classifier sees many more background examples, shared evenly between their sources
(:func:`share`), and more of each mobile class. A class with no examples at all (a clean field has
no background) is a warning in the report, not an error.
"""

import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..core.c_filters import Envelope
from ..core.d_classify import Classifier, Support, nearest_d2
from .config import TrainConfig
from .fit import GPFits, sample
from .labels import BACKGROUND, Examples


def fit_envelope(ex: Examples, n_classes: int, beam_step: float, *, n_bins: int = 8, quantile: float = 0.01,
                 min_per_bin: int = 20, whole_fraction: float = 0.95) -> tuple[Envelope, dict]:
    """Per-class shape envelopes (:class:`~gtsjax.core.c_filters.Envelope`) from labelled examples: in each
    range bin, the ``quantile`` and ``1 − quantile`` quantiles of the class's width, depth and
    ``n · r``, widened by a tenth of their spread plus what one beam more or less and the range noise
    can add at the bin's far edge (a beam's spacing for width, 1 cm for depth, one point for
    ``n · r``). Bins with fewer than ``min_per_bin`` examples of the class take the limits of the
    nearest bin that has enough (the quantities depend on range only through noise and spacing), and no
    bin is narrower than the class's limits over all its examples (a range seen from few placements shows
    few of the class's views); a
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
        # No bin narrower than the class over all ranges: width, depth and n · r of a rigid object do
        # not depend on range but through noise and beam spacing, and a bin seen from a few placements
        # only (a robot put down at a handful of poses) shows few of its views, not all it has.
        all_lo, all_hi = limits(ex.shape[sel], r_max)
        lo[k], hi[k] = np.minimum(lo[k], all_lo), np.maximum(hi[k], all_hi)
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
    """Squared Euclidean distance from each row of ``x`` to the nearest row of ``s`` (host, float64:
    the thresholds are set on these, the step tests them with :func:`~gtsjax.core.d_classify.nearest_d2`)."""
    out = np.full(len(x), np.inf)
    if len(s) == 0:
        return out
    ss = np.sum(s * s, axis=1)
    for i in range(0, len(x), chunk):
        a = x[i : i + chunk]
        d2 = np.sum(a * a, axis=1)[:, None] + ss[None, :] - 2.0 * a @ s.T
        out[i : i + chunk] = np.maximum(d2.min(axis=1), 0.0)
    return out


def fit_support(ex: Examples, is_held: np.ndarray, n_classes: int, rng, *, size: int = 512,
                quantile: float = 0.995, margin: float = 1.5, min_held: int = 50) -> tuple[Support, dict]:
    """The open-set test's examples and thresholds (:class:`~gtsjax.core.d_classify.Support`).

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


def landmark_lookalikes(support: Support, bg_ex: Examples, bg_info: Sequence[dict], classes: tuple[str, ...],
                        landmarks: tuple[str, ...]) -> np.ndarray:
    """Which background-log examples pass a landmark class's open-set test (a post in view while
    recording): as background they would teach the classifier that the landmark is background, so
    they are left out. Notes in each background log's ``bg_info`` entry how many of its were."""
    lookalike = np.zeros(len(bg_ex.cls), bool)
    if len(bg_ex.cls):
        d2 = np.asarray(nearest_d2(support, jnp.asarray(bg_ex.vectors, jnp.float32)))
        for name in landmarks:
            k = classes.index(name)
            lookalike |= d2[:, k] <= float(support.threshold[k])
    per_log = np.bincount(np.searchsorted(np.cumsum([i["candidates"] for i in bg_info]), np.flatnonzero(lookalike),
                                          side="right"), minlength=len(bg_info))
    for item, n_look in zip(bg_info, per_log, strict=True):
        item["landmark_lookalikes_left_out"] = int(n_look)
    return lookalike


def share(rng: np.random.Generator, pools: Sequence[np.ndarray], cap: int) -> np.ndarray:
    """Up to ``cap`` indices drawn from ``pools`` as evenly as they allow (a pool smaller than its
    share gives all it has, and the rest is shared among the others)."""
    sizes = np.array([p.size for p in pools])
    take = np.zeros(len(pools), int)
    left, open_ = cap, sizes > 0
    while left > 0 and open_.any():
        portion = max(1, left // int(open_.sum()))
        for i in np.flatnonzero(open_):
            t = min(portion, sizes[i] - take[i], left)
            take[i] += t
            left -= t
            open_[i] = take[i] < sizes[i]
    return np.sort(np.concatenate([sample(rng, p, int(t)) for p, t in zip(pools, take, strict=True)]
                                  + [np.zeros(0, int)]))


def fit_classifier(ex: Examples, is_held: np.ndarray, source: np.ndarray, n_sources: int, support: Support,
                   classes: tuple[str, ...], mobiles: tuple[str, ...], cfg: TrainConfig, rng: np.random.Generator,
                   gps: GPFits) -> tuple[Classifier, np.ndarray, list[str]]:
    """The classifier (stage d): balanced, capped training examples; one GP per class on 1/0 targets
    (eq. 14), every class's threshold ``cfg.threshold``, and the open-set ``support``.

    The background, as varied as the world, may get more examples than the other classes
    (``max_background``) and each mobile class more than a landmark class (``max_mobile``) when there
    are ``n_sources`` background logs. The background examples are shared out evenly between their
    sources (``source``: −1 for the labelled logs' own background, else the background log's index;
    what one source cannot fill goes to the others), so that a long log of one office does not crowd
    out the field's own clutter. Returns the classifier, the indices of its training examples in
    ``ex``, and warnings (a class without examples)."""
    n_bg = cfg.max_per_class if not n_sources else (cfg.max_background or 12 * cfg.max_per_class)
    n_mobile = cfg.max_per_class if not n_sources else (cfg.max_mobile or 4 * cfg.max_per_class)
    pools = [np.flatnonzero((ex.cls == 0) & ~is_held & (source == s)) for s in range(-1, n_sources)]
    bg_idx = share(rng, pools, n_bg)
    caps = [n_mobile if c in mobiles else cfg.max_per_class for c in classes]
    train_idx = np.concatenate([bg_idx] + [
        sample(rng, np.flatnonzero((ex.cls == k) & ~is_held), caps[k]) for k in range(1, len(classes))])
    warnings = []
    missing = [c for k, c in enumerate(classes) if not np.any(ex.cls[train_idx] == k)]
    if missing:
        warnings.append(f"no training examples of class(es) {', '.join(missing)}: "
                        + ("only the open-set test and the shape envelopes reject clutter; record the field with "
                           "people walking and no robot, and pass it with --background"
                           if missing == [BACKGROUND] else "it is never detected"))
    x_cls = ex.vectors[train_idx]
    clf_gps = tuple(gps(x_cls, (ex.cls[train_idx] == k).astype(np.float64), f"class.{name}", cfg.n_inducing_class,
                        cfg.max_class_fit) for k, name in enumerate(classes))
    return Classifier(clf_gps, jnp.full(len(classes), cfg.threshold, jnp.float32), support), train_idx, warnings
