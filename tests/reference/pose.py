"""Stage e: each kept candidate's pose relative to its ORS, ``(x̃, ỹ, θ̃)`` with θ̃ from the sine and
cosine GPs (eq. 15), and the variances: the GPs' predictive variances, the heading's propagated
through ``atan2``, scaled by the class's calibration. Of a mobile class only the ``max_objects``
candidates with the highest class score get a pose, of a landmark class the ``max_landmarks`` best."""

import math

import numpy as np

from .gp import _f, sklearn_gp

MAX_THETA_VAR = math.pi**2 / 3  # as gtsjax.core.e_pose: the heading variance where sin/cos carry nothing


class PoseRegressors:
    """Stage e from a trained model's ``pose`` regressors (one per class, ``None`` for a class
    without a pose)."""

    def __init__(self, model, max_landmarks: int):
        self.pose = [None if r is None else _ClassGPs(r) for r in model.pose]
        self.var_scale = [None if r is None or r.var_scale is None else _f(r.var_scale) for r in model.pose]
        self.heading_var_max = np.array(
            [np.inf if r is None or r.heading_var_max is None else float(r.heading_var_max) for r in model.pose]
        )
        self.max_objects = model.max_objects
        self.max_landmarks = max_landmarks

    def regress(self, x, cls, ok, scores):
        """ORS-relative pose and variances under each candidate's class's GPs; the candidates beyond
        their class's cap are dropped (the third output is False for them)."""
        rel = np.zeros((len(x), 3))
        var = np.zeros((len(x), 3))
        ok = ok.copy()
        for k, reg in enumerate(self.pose):
            rows = np.flatnonzero(ok & (cls == k))
            if reg is None or rows.size == 0:
                continue
            cap = self.max_objects if reg.heading else self.max_landmarks
            if rows.size > cap:
                keep = rows[np.argsort(-scores[rows, k], kind="stable")[:cap]]
                ok[np.setdiff1d(rows, keep)] = False
                rows = np.sort(keep)
            mean, var_all = reg.predict(x[rows])
            (mx, my), (vx, vy) = mean[:, :2].T, var_all[:, :2].T
            if not reg.heading:
                rel[rows, :2] = np.stack([mx, my], 1)
                var[rows, :2] = np.stack([vx, vy], 1)
                continue
            (ms, mc), (vs, vc) = mean[:, 2:].T, var_all[:, 2:].T
            r2 = ms**2 + mc**2
            with np.errstate(divide="ignore", invalid="ignore"):
                vt = np.where(r2 > 1e-6, (mc**2 * vs + ms**2 * vc) / r2**2, MAX_THETA_VAR)
            v3 = np.stack([vx, vy, vt], 1)
            if self.var_scale[k] is not None:
                v3 = v3 * self.var_scale[k]
            rel[rows] = np.stack([mx, my, np.arctan2(ms, mc)], 1)
            var[rows] = np.minimum(v3, [np.inf, np.inf, MAX_THETA_VAR])
        return rel, var, ok

    def vague(self, var, cls):
        """Headings read with a variance above their class's ``heading_var_max`` (good reads rarely have one)."""
        return var[:, 2] > self.heading_var_max[cls]


class _ClassGPs:
    """One class's pose GPs in scikit-learn: each GP on its own (:func:`~.gp.sklearn_gp`), or each
    group of one kernel as one multi-output GPR (:class:`~.gp.SklearnSharedGP`: one kernel row per
    group, as a careful scikit-learn user would predict GPs of one kernel)."""

    def __init__(self, reg):
        if reg.shared is not None:
            self.parts = [sklearn_gp(g) for g in reg.shared]
        else:
            self.parts = [sklearn_gp(g) for g in reg.outputs()]
        self.heading = reg.has_heading

    def predict(self, x):
        """Means and variances ``[n, outputs]`` of ``x``, ``y`` (, ``sin``, ``cos``)."""
        outs = [p.predict(x) for p in self.parts]
        return (np.column_stack([m for m, _ in outs]), np.column_stack([v for _, v in outs]))
