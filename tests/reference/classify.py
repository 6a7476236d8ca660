"""Stages c–d: the per-class shape envelopes (which classes a candidate's ``(width, depth, n · r)``
allows in its range bin), then one GP score per class (eq. 13–14), the best allowed class, its
threshold, and the open-set test (no farther from the nearest training example of its class, in the
class's scale, than the class's threshold)."""

import math

import numpy as np

from .gp import _f, sklearn_gp


class Classifier:
    """Stages c (envelopes) and d from a trained model's ``envelope`` and ``classifier``."""

    def __init__(self, model):
        self.gps = [sklearn_gp(g) for g in model.classifier.gps]
        self.threshold = _f(model.classifier.threshold)
        sup = model.classifier.support  # the open-set test: per class its examples, scale, threshold
        self.support = [
            (_f(sup.x[k])[np.asarray(sup.mask[k])], _f(sup.mean[k]), _f(sup.inv_scale[k]), float(sup.threshold[k]))
            for k in range(len(self.gps))
        ]
        env = model.envelope
        self.bin_width, self.lo, self.hi = float(env.bin_width), _f(env.lo), _f(env.hi)
        self.whole = np.asarray(env.whole, bool)  # classes seen whole only: an occluded view is partial

    def in_envelope(self, shape, rng):
        """Which classes each candidate may be (a loop over candidates)."""
        lo, hi = self.lo, self.hi
        out = np.zeros((len(shape), lo.shape[0]), bool)
        for i, (q, r) in enumerate(zip(shape, rng, strict=True)):
            b = min(max(int(math.floor(r / self.bin_width)), 0), lo.shape[1] - 1)
            out[i] = np.all((q >= lo[:, b]) & (q <= hi[:, b]), axis=1)
        return out

    def like(self, x, k) -> np.ndarray:
        """Whether each candidate passes class ``k``'s open-set test."""
        examples, mean, inv, thr = self.support[k]
        if not np.isfinite(thr):
            return np.ones(len(x), bool)
        if len(examples) == 0:
            return np.zeros(len(x), bool)
        u = (x - mean) * inv
        return np.array([float(np.min(np.sum((examples - ui) ** 2, axis=1))) <= thr for ui in u], bool)

    def guesses(self, x, envelope, ok, scores, tracked):
        """Which candidates that are not ok could be a tracked class (within its envelope, like its
        examples), and the best scoring such class: ``(guess, guess_cls)``."""
        could = np.zeros(scores.shape, bool)
        for k in np.flatnonzero(tracked):
            could[:, k] = envelope[:, k] & self.like(x, k)
        guess_cls = np.where(could, scores, -np.inf).argmax(axis=1)
        return ~ok & could.any(axis=1), guess_cls

    def classify(self, x, allowed):
        """Class of each candidate (the best score among the classes its envelope allows, and
        background) and whether it survives: not background, score ≥ threshold, and like the training
        examples of its class. Returns ``(cls, ok, scores)``."""
        if len(x) == 0:
            return np.zeros(0, int), np.zeros(0, bool), np.zeros((0, len(self.gps)))
        scores = np.stack([g.predict_mean(x) for g in self.gps], axis=1)
        allowed = allowed.copy()
        allowed[:, 0] = True
        cls = np.where(allowed, scores, -np.inf).argmax(axis=1)
        best = scores[np.arange(len(cls)), cls]
        like = np.ones(len(cls), bool)
        for i, k in enumerate(cls):
            examples, mean, inv, thr = self.support[k]
            if np.isfinite(thr):
                u = (x[i] - mean) * inv
                like[i] = len(examples) > 0 and float(np.min(np.sum((examples - u) ** 2, axis=1))) <= thr
        return cls, (cls != 0) & (best >= self.threshold[cls]) & like, scores
