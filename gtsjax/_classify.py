"""Stage d, object classifier (eq. 13–14): one GP regressor per class on 1/0 targets, argmax, and a
threshold on the winning score.

The paper's classifier is GP *regression* per class (class-vs-rest), not a GP classifier; its score
is not a calibrated probability, so the threshold is per class and chosen on held-out data. Class 0
is always ``background``: a candidate whose best class is background, or whose winning score is
below its class's threshold, is dropped. Prediction uses each GP's bounded-cost form (a fixed number
of inducing points), so the cost per candidate does not grow with the training set.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._gp import GP, SparseGP, predict_mean

BACKGROUND = 0


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


class Classifier(eqx.Module):
    """One score GP per class (index 0 is background) and a score threshold per class."""

    gps: tuple[SparseGP | GP, ...]
    threshold: Float[Array, " classes"]

    @property
    def n_classes(self) -> int:
        return len(self.gps)


def class_scores(clf: Classifier, vectors: Float[Array, "cands features"]) -> Float[Array, "cands classes"]:
    """``p_{j,k} = f_k(v_j)`` (eq. 13) for every candidate and class: each GP's predictive mean."""
    return jnp.stack([predict_mean(gp, vectors).astype(vectors.dtype) for gp in clf.gps], axis=-1)


def classify(
    clf: Classifier, vectors: Float[Array, "cands features"], keep: Bool[Array, " cands"]
) -> tuple[Float[Array, "cands classes"], Int[Array, " cands"], Bool[Array, " cands"]]:
    """Scores, the argmax class of each candidate, and which candidates survive: kept by the binary
    filters, not background, and with a winning score at or above the class's threshold."""
    scores = class_scores(clf, vectors)
    cls = jnp.argmax(scores, axis=-1).astype(jnp.int32)
    best = jnp.take_along_axis(scores, cls[:, None], axis=-1)[:, 0]
    ok = keep & (cls != BACKGROUND) & (best >= clf.threshold[cls])
    return scores, cls, ok
