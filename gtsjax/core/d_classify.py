"""Stage d, object classifier (eq. 13–14): one GP regressor per class on 1/0 targets, argmax, a
threshold on the winning score, and an open-set test against the winning class's own examples.

The paper's classifier is GP *regression* per class (class-vs-rest), not a GP classifier; its score
is not a calibrated probability, so the threshold is per class and chosen on held-out data. Class 0
is always ``background``: a candidate whose best class is background, or whose winning score is
below its class's threshold, is dropped. Prediction uses each GP's bounded-cost form (a fixed number
of inducing points), so the cost per candidate does not grow with the training set.

**Open set**. A regression score says which training class a candidate is *most* like,
not whether it is like any: far from every training example each GP's mean falls back to its prior
(the class's share of the examples), and in between it extrapolates, so clutter the model never saw
(a table, a chair, a person's legs in another building) can win as "robot". So a candidate is also
background when it is unlike every training example of its winning class: when its squared distance
to the nearest of them, in that class's own scale (each input divided by the class's spread in it),
exceeds the class's threshold. The examples kept for the test (:class:`Support`, a fixed number per
class) and the thresholds (a high quantile of the distances of held-out examples of the class,
with a margin) come from training and are stored in the model. Before the argmax, each class's
shape envelope (stage c, :class:`~gtsjax.core.c_filters.Envelope`) removes the classes a candidate cannot
be, so a leg is never "robot" because of its size.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..gp import GP, SparseGP
from ..gp.sparse import predict_many
from .buckets import bucketed, slots_of

BACKGROUND = 0
# Winning class score needed to keep a candidate, every class's until training says otherwise: the
# scores are GP means on 1/0 targets, not probabilities (``Classifier.threshold``).
DEFAULT_THRESHOLD = 0.35


def gp_inputs(
    vector: Float[Array, "*cands features"],
    origin: Float[Array, "*cands 2"],
    height: Float[Array, "*cands"],
    columns: tuple[int, ...] = (),
) -> Float[Array, "*cands inputs"]:
    """What the GPs of stages d and e see: the characteristic vector (eq. 11–12) plus the candidate's
    depth (its bounding box along x′) and its range from the sensor; of these, the ``columns`` a model
    was trained on (all if empty; see ``Model.gp_columns``).

    The paper's vector is scale-free along the beam: a flat 0.27 m stretch of wall and a robot's chest
    seen face on give the same width and distance profile. The depth separates flat from angular
    shapes, and the range tells the GPs how dense and how noisy the points are (so that the pose
    regressors can learn how far behind the visible surface the centre lies at each distance).
    """
    rng = jnp.sqrt(jnp.sum(origin**2, axis=-1))
    x = jnp.concatenate([vector, height[..., None], rng[..., None]], axis=-1)
    return x[..., list(columns)] if columns else x


class Support(eqx.Module):
    """The open-set test's examples: per class up to ``P`` training inputs, each class in its own scale
    (``(x − mean) · inv_scale``), and the largest squared distance to the nearest of them that a
    candidate of the class may have. A class with no examples (the background, or a class trained
    without any) has an all-False mask and an infinite threshold: no test."""

    x: Float[Array, "classes support inputs"]  # scaled examples, 0 where masked
    mask: Bool[Array, "classes support"]
    mean: Float[Array, "classes inputs"]
    inv_scale: Float[Array, "classes inputs"]
    threshold: Float[Array, " classes"]

    @classmethod
    def none(cls, n_classes: int, n_inputs: int) -> "Support":
        """No open-set test (every class's threshold infinite)."""
        f32 = jnp.float32
        return cls(jnp.zeros((n_classes, 1, n_inputs), f32), jnp.zeros((n_classes, 1), bool),
                   jnp.zeros((n_classes, n_inputs), f32), jnp.ones((n_classes, n_inputs), f32),
                   jnp.full((n_classes,), jnp.inf, f32))


def nearest_d2(sup: Support, x: Float[Array, "cands inputs"]) -> Float[Array, "cands classes"]:
    """Squared distance from each candidate to the nearest support example of each class, in the
    class's scale (``inf`` for a class without examples). One batched matrix product,
    ``|u|² + |s|² − 2 u·s``, then a masked minimum over the examples."""
    u = (x[None, :, :] - sup.mean[:, None, :]) * sup.inv_scale[:, None, :]  # [classes, cands, inputs]
    ss = jnp.sum(sup.x * sup.x, axis=-1)  # [classes, support]
    d2 = jnp.sum(u * u, axis=-1)[:, :, None] + ss[:, None, :] - 2.0 * jnp.einsum("cki,cpi->ckp", u, sup.x)
    d2 = jnp.where(sup.mask[:, None, :], jnp.maximum(d2, 0.0), jnp.inf)
    return jnp.min(d2, axis=-1).T


class Classifier(eqx.Module):
    """One score GP per class (index 0 is background), a score threshold per class, and the open-set
    test's examples and thresholds."""

    gps: tuple[SparseGP | GP, ...]
    threshold: Float[Array, " classes"]
    support: Support

    @property
    def n_classes(self) -> int:
        return len(self.gps)


def class_scores(clf: Classifier, vectors: Float[Array, "cands features"]) -> Float[Array, "cands classes"]:
    """``p_{j,k} = f_k(v_j)`` (eq. 13) for every candidate and class: each GP's predictive mean (the
    classes' GPs batched, :func:`~gtsjax.gp.sparse.predict_many`)."""
    (means,) = predict_many(clf.gps, vectors, mean_only=True)
    return means.T.astype(vectors.dtype)


def _kept_only(clf: Classifier, vectors: Float[Array, "cands features"], keep: Bool[Array, " cands"], axis_name
               ) -> tuple[Float[Array, "cands classes"], Float[Array, "cands classes"]]:
    """Scores and nearest-example distances of the kept candidates only (zeros elsewhere): the kept
    rows gathered to the front, bucketed, and put back by comparison with their slots (no scatter)."""
    n = vectors.shape[0]
    order = jnp.argsort(~keep, stable=True).astype(jnp.int32)  # the kept candidates first, in slot order

    scores, d2 = bucketed(lambda v: (class_scores(clf, v), nearest_d2(clf.support, v)), vectors[order],
                          jnp.sum(keep, dtype=jnp.int32), clf.n_classes, axis_name)
    _, back = slots_of(order, jnp.ones((n,), bool), n)
    rows = jnp.concatenate([scores, d2], -1)[back]
    return rows[:, :clf.n_classes], rows[:, clf.n_classes:]


class Decision(eqx.Module):
    """Stage d's verdict on each candidate slot of one scan."""

    scores: Float[Array, "cands classes"]
    cls: Int[Array, " cands"]  # the winning class among those whose envelope the candidate lies in
    ok: Bool[Array, " cands"]  # kept, not background, score at or above threshold, like its class's examples
    unlike: Bool[Array, " cands"]  # would be ok, but unlike every training example of its class
    off_envelope: Bool[Array, " cands"]  # kept, and its best score is a class whose envelope it lies outside
    # Not ok, yet within the shape envelope of a tracked class and like its training examples: where a
    # confirmed track of that class (``guess_cls``, the best scoring such class) expects its object, it
    # is that object seen from a side the classifier takes for something else (see ``classify``).
    guess: Bool[Array, " cands"]
    guess_cls: Int[Array, " cands"]


def classify(
    clf: Classifier,
    vectors: Float[Array, "cands features"],
    keep: Bool[Array, " cands"],
    in_envelope: Bool[Array, "cands classes"] | None = None,
    bucket: bool = False,
    axis_name=None,
    tracked: Bool[Array, " classes"] | None = None,
) -> Decision:
    """Scores; each candidate's class, the best score among the classes whose shape envelope it lies
    in (``in_envelope``; background always qualifies); and which candidates survive: kept by the
    binary filters, not background, a winning score at or above its class's threshold, and like the
    training examples of its class (the open-set test, see the module docstring).

    With ``bucket`` only the kept candidates are scored, at the smallest of a few fixed counts that
    holds them (:func:`~gtsjax.core.buckets.bucketed`; ``axis_name`` under ``vmap``, as there): the
    score GPs over all candidate slots were the step's largest arithmetic. The others' scores are then
    zeros and their class background; nothing downstream reads them.

    **Guesses.** A robot's flat side at 3.5 m and a flat stretch of a box beside the field at the same
    range give the same characteristic vector: where the background holds such an object, seen in every
    scan of the recording, the classifier learns that view as background, and a robot walking past
    side-on is lost for seconds. Shape cannot settle it; where the robot is can. So a kept candidate
    that is not ok but lies within the shape envelope of a ``tracked`` class and passes that class's
    open-set test is a *guess* of that class: it gets a pose and the outline refinement (after the
    candidates the classifier took for the class), is kept where the outline fit succeeds, and may
    update a confirmed track close to its prediction, never start or confirm one
    (``g_track.GUESS_RADIUS``)."""
    if bucket:
        scores, nearest = _kept_only(clf, vectors, keep, axis_name)
    else:
        scores, nearest = class_scores(clf, vectors), nearest_d2(clf.support, vectors)
    n = scores.shape[-1]
    if in_envelope is None:
        in_envelope = jnp.ones(scores.shape, bool)
    allowed = in_envelope | (jnp.arange(n) == BACKGROUND)[None, :]
    cls = jnp.argmax(jnp.where(allowed, scores, -jnp.inf), axis=-1).astype(jnp.int32)
    best = jnp.take_along_axis(scores, cls[:, None], axis=-1)[:, 0]
    d2 = jnp.take_along_axis(nearest, cls[:, None], axis=-1)[:, 0]
    scored = keep & (cls != BACKGROUND) & (best >= clf.threshold[cls])
    like = d2 <= clf.support.threshold[cls]
    top = jnp.argmax(scores, axis=-1)
    off = keep & (top != BACKGROUND) & ~jnp.take_along_axis(in_envelope, top[:, None], axis=-1)[:, 0]
    if tracked is None:
        guess, guess_cls = jnp.zeros_like(keep), cls
    else:
        could = in_envelope & (nearest <= clf.support.threshold[None, :]) & tracked[None, :]
        guess_cls = jnp.argmax(jnp.where(could, scores, -jnp.inf), axis=-1).astype(jnp.int32)
        guess = keep & ~(scored & like) & jnp.any(could, axis=-1)
    return Decision(scores, cls, scored & like, scored & ~like, off, guess, guess_cls)
