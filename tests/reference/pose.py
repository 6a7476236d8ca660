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
        self.pose = [
            None
            if r is None
            else dict(zip(("x", "y", "sin", "cos"), ([sklearn_gp(g) for g in r.outputs()] + [None, None])[:4], strict=True))
            for r in model.pose
        ]
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
            cap = self.max_objects if reg["sin"] is not None else self.max_landmarks
            if rows.size > cap:
                keep = rows[np.argsort(-scores[rows, k], kind="stable")[:cap]]
                ok[np.setdiff1d(rows, keep)] = False
                rows = np.sort(keep)
            v = x[rows]
            mx, vx = reg["x"].predict(v)
            my, vy = reg["y"].predict(v)
            if reg["sin"] is None or reg["cos"] is None:
                rel[rows, :2] = np.stack([mx, my], 1)
                var[rows, :2] = np.stack([vx, vy], 1)
                continue
            ms, vs = reg["sin"].predict(v)
            mc, vc = reg["cos"].predict(v)
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
