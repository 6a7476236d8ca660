"""Held-out evaluation for the training report: stage d on held-out examples exactly as the step
decides it (the core's :func:`~gtsjax.core.d_classify.classify` with the shape envelopes of stage c,
:func:`decide`), and the pose errors of the mobile classes' regressors (stage e, eq. 15), in
:func:`evaluate_examples`.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ..core.c_filters import envelope_pass
from ..core.d_classify import classify
from ..core.e_pose import regress_one_class
from ..core.geometry import wrap
from ..core.model import Model
from ..drivers.batch import pad_chunk
from .labels import Examples, padded_size


@jax.jit
def _decide(clf, env, vectors, shape, rng):
    dec = classify(clf, vectors, jnp.ones(vectors.shape[0], bool), envelope_pass(env, shape, rng))
    return jnp.where(dec.ok, dec.cls, 0), dec.unlike, dec.off_envelope


def decide(model: Model, ex: Examples, chunk: int = 4096):
    """Stage d as the step decides it, on examples: each one's class (0 where dropped), and whether
    it was dropped as unlike its class's examples, or outside its best class's envelope."""
    outs = [[], [], []]
    for s in range(0, len(ex.cls), chunk):
        part = slice(s, s + chunk)
        n = len(ex.cls[part])
        args = pad_chunk((ex.vectors[part].astype(np.float32), ex.shape[part].astype(np.float32),
                          ex.rng[part].astype(np.float32)), 0, n, padded_size(n, chunk))  # one program for every set
        res = _decide(model.classifier, model.envelope, *args)
        for o, r in zip(outs, res, strict=True):
            o.append(np.asarray(r)[:n])
    if not outs[0]:
        return np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, bool)
    return tuple(np.concatenate(o) for o in outs)


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
        if reg is None or not reg.has_heading or not sel.any():
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
