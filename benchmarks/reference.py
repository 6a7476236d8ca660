"""The pipeline of Fig. 1 written a second time, the way a careful NumPy user would write it: the
reference that gtsjax's jitted step is timed against, and a second implementation its tracks are
checked against (``tests/test_reference.py``).

What "a careful NumPy user" means here:

* one scan at a time, in float64; segmentation vectorised over the beams; a Python loop over the
  segments, each segment's ORS and profiles vectorised over its points; ragged lists instead of
  padded slots (only the candidates that exist are processed, only the kept ones classified);
* every GP is a scikit-learn ``GaussianProcessRegressor`` (``ConstantKernel × RBF`` with the
  model's hyperparameters, ``optimizer=None``), predicting in batch for the scan's candidates;
* one filterpy ``KalmanFilter`` per track, with the same constant-velocity model, Mahalanobis gating,
  heading gate, greedy one-to-one assignment and track life cycle as ``gtsjax._track``;
* the map transformation as centred OLS with NumPy's ``eigvalsh`` and ``solve``.

Everything is read from a trained :class:`gtsjax.Model` (front-end settings, GP hyperparameters and
predictor arrays, tracker tuning, site), so the reference follows the model when it is retrained.

**How a model GP becomes a scikit-learn GPR.** An exact :class:`gtsjax.gp.GP` stores its
standardised training inputs and centred targets: the GPR is fitted on those with ``alpha`` equal
to the GP's effective noise ``σn² + jitter σf²``, which reproduces its mean and variance. A
:class:`gtsjax.gp.SparseGP` (the DTC predictor the shipped models hold) stores only its ``M``
inducing inputs ``Z``, the weights ``w`` of its mean ``k_Z(x)ᵀ w``, ``L_m⁻¹`` (``K_ZZ + a I = L_m
L_mᵀ``, ``a = jitter σf²``) and ``L_b⁻¹ L_m⁻¹``. The GPR is fitted on ``Z`` with ``alpha = a`` and
targets ``(K_ZZ + a I) w``, so that its ``alpha_`` is ``w`` and its mean is the DTC mean; its
variance ``σf² − k_Zᵀ (K_ZZ + a I)⁻¹ k_Z`` is the first two terms of the DTC variance, to which the
third, ``‖L_b⁻¹ L_m⁻¹ k_Z‖²``, is added from the stored matrix (``a`` is recovered as the stored
effective noise minus ``σn²``).
"""

import dataclasses
import math
import warnings

import numpy as np
from filterpy.kalman import KalmanFilter
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel

__all__ = ["ReferencePipeline", "RefOutput", "SklearnGP", "compare_tracks", "scans_to_numpy"]

NX = 6
_MAX_THETA_VAR = math.pi**2 / 3  # as gtsjax._pose: the heading variance where sin/cos carry nothing


def _f(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


_FITTED: dict[tuple[int, ...], tuple[list, "SklearnGP"]] = {}


def sklearn_gp(gp) -> "SklearnGP":
    """:class:`SklearnGP` of ``gp``, built once per set of arrays: carrying a pose GP over 6 000 examples
    into scikit-learn costs seconds (two Cholesky factorisations), and a model changed elsewhere
    (``eqx.tree_at`` on its tracker) keeps the same GP arrays. Keyed by the identity of the arrays,
    which the entry keeps alive, so a key is never reused by other arrays."""
    import jax

    leaves = jax.tree_util.tree_leaves(gp)
    key = tuple(id(x) for x in leaves)
    hit = _FITTED.get(key)
    if hit is None:
        hit = _FITTED[key] = (leaves, SklearnGP(gp))
    return hit[1]


def wrap(a):
    """Angle to (−π, π]."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


# ------------------------------------------------------------------------------------------------ GPs


class SklearnGP:
    """One of the model's GPs (exact or DTC) as a fitted scikit-learn ``GaussianProcessRegressor``
    (see the module docstring for how the DTC predictor is carried over)."""

    def __init__(self, gp):
        p = gp.params
        sf2 = float(np.exp(_f(p.log_signal_var)))
        self.noise_var = float(np.exp(_f(p.log_noise_var)))
        with np.errstate(over="ignore"):  # a feature BFGS switched off (log l ~ 1e3): l = inf, as w = 0 in gtsjax
            lengthscale = np.exp(_f(p.log_lengthscale))
        kernel = ConstantKernel(sf2, constant_value_bounds="fixed") * RBF(lengthscale, length_scale_bounds="fixed")
        self.x_mean = _f(gp.x_mean)
        self.x_scale = _f(gp.x_scale)
        self.y_mean = float(gp.y_mean)
        self.var_gpr = None
        if hasattr(gp, "z"):  # SparseGP (DTC)
            use = np.asarray(gp.z_mask, bool)
            z = _f(gp.z)[use]
            w = _f(gp.weights)[use]
            a = max(float(_f(gp.noise)) - self.noise_var, 1e-12 * sf2)
            targets = (kernel(z) + a * np.eye(len(z))) @ w
            mv = int(gp.proj_m.shape[0])  # the variance uses the first mv inducing points only
            use_v = np.asarray(gp.z_mask, bool)[:mv]
            self.proj_b = _f(gp.proj_b)[np.ix_(use_v, use_v)]
            zv = _f(gp.z)[:mv][use_v]
            self.var_gpr = GaussianProcessRegressor(kernel, alpha=a, optimizer=None, normalize_y=False,
                                                    copy_X_train=False).fit(zv, np.zeros(len(zv)))
        else:  # exact GP
            use = np.asarray(gp.mask, bool)
            z = _f(gp.x)[use]
            targets = _f(gp.y)[use]
            a = float(np.exp(_f(p.log_noise_var)) + _f(gp.jitter) * sf2)
            self.proj_b = None
        self.gpr = GaussianProcessRegressor(kernel, alpha=a, optimizer=None, normalize_y=False, copy_X_train=False)
        self.gpr.fit(z, targets)
        self.var_gpr = self.var_gpr or self.gpr

    def _std(self, x: np.ndarray) -> np.ndarray:
        return (x - self.x_mean) / self.x_scale

    def predict_mean(self, x: np.ndarray) -> np.ndarray:
        """Predictive mean (eq. 7) of raw inputs ``x`` [n, d]."""
        return self.gpr.predict(self._std(x)) + self.y_mean

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and variance, observation noise included (what pose regression uses)."""
        xs = self._std(x)
        mean = self.gpr.predict(xs)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # sklearn warns when it clips a variance of -1e-17 at 0
            _, std = self.var_gpr.predict(xs, return_std=True)
        var = std**2
        if self.proj_b is not None:
            t2 = self.var_gpr.kernel_(xs, self.var_gpr.X_train_) @ self.proj_b.T
            var = var + np.sum(t2 * t2, axis=1)
        return mean + self.y_mean, np.maximum(var, 0.0) + self.noise_var


# ------------------------------------------------------------------------------------------ tracker


@dataclasses.dataclass
class _Track:
    kf: KalmanFilter
    cls: int
    track_id: int
    confirmed: bool
    hits: int = 1
    misses: int = 0
    contrary: int = 0
    rival: float = 0.0
    support: float = 1.0
    rival_support: float = 0.0


class _Tracker:
    """Stage g with one filterpy ``KalmanFilter`` per track (same model and life cycle as gtsjax).

    Gating follows the model's tracker: on position (2 dof), with an assigned detection's heading used
    only if its own innovation passes ``heading_gate`` (otherwise a position-only update, and the
    turn rate is forgotten); ``|ω| ≤ max_turn_rate`` of the track's class; a rival heading with fading
    support that takes over when more detections agree with it; leftover detections within
    ``birth_exclusion`` of a leftover track recaptured by it; confirmation after ``n_confirm`` hits, if
    more than the tentative scans with no detection but an "other" candidate within
    ``birth_exclusion`` of the prediction (``contrary``), and if the motion is plausible: speed at most
    ``max_speed + 2 σ_v`` (``σ_v²`` the largest eigenvalue of the velocity covariance, from
    ``eigvalsh``), turn rate before clipping at most ``max_turn_rate + 2 σ_ω``; an implausible scan
    takes the confirmation away and restarts ``hits`` and ``contrary`` at 0; tracks reported while
    confirmed and missed fewer than ``m_report`` scans (written out plainly from the module docstring
    of ``gtsjax._track``)."""

    def __init__(self, params, max_tracks: int):
        g = {f.name: np.asarray(getattr(params, f.name)) for f in dataclasses.fields(params)}
        self.q_pos, self.q_theta = float(g["q_pos"]), float(g["q_theta"])
        self.vel_var0, self.omega_var0 = float(g["vel_var0"]), float(g["omega_var0"])
        self.gate = g["gate"].astype(np.float64)
        self.heading_gate = float(g["heading_gate"])
        self.heading_memory = float(g["heading_memory"])
        self.max_speed = np.broadcast_to(g["max_speed"], g["tracked"].shape).astype(np.float64)
        self.max_turn_rate = np.broadcast_to(g["max_turn_rate"], g["tracked"].shape).astype(np.float64)
        self.m_report = int(g["m_report"])
        self.tracked = g["tracked"].astype(bool)
        self.n_confirm, self.m_tentative, self.m_delete = int(g["n_confirm"]), int(g["m_tentative"]), int(g["m_delete"])
        self.birth_exclusion = float(g["birth_exclusion"])
        self.constant_velocity = bool(g["constant_velocity"])
        self.max_tracks = max_tracks
        self.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        self.reset()

    def reset(self):
        self.slots: list[_Track | None] = [None] * self.max_tracks
        self.next_id = 0

    def motion_model(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """``F`` and ``Q`` over ``dt``: constant velocity (piecewise white acceleration) or inflate-only."""
        q = np.array([self.q_pos, self.q_pos, self.q_theta])
        if self.constant_velocity:
            F = np.eye(NX)
            F[:3, 3:] = dt * np.eye(3)
            Q = np.block([[np.diag(q * dt**3 / 3), np.diag(q * dt**2 / 2)],
                          [np.diag(q * dt**2 / 2), np.diag(q * dt)]])
        else:
            F = np.eye(NX)
            Q = np.zeros((NX, NX))
            Q[:3, :3] = np.diag(q * dt)
        return F, Q

    def plausible(self, t: _Track, omega: float) -> bool:
        """Whether the track's speed and turn rate (``omega``, before clipping) are its class's, within
        twice their standard deviations."""
        v = t.kf.x[3:5, 0]
        sigma_v = math.sqrt(max(np.linalg.eigvalsh(t.kf.P[3:5, 3:5])[-1], 0.0))
        sigma_w = math.sqrt(max(t.kf.P[5, 5], 0.0))
        return bool(math.hypot(v[0], v[1]) <= self.max_speed[t.cls] + 2.0 * sigma_v
                    and abs(omega) <= self.max_turn_rate[t.cls] + 2.0 * sigma_w)

    def step(self, z: np.ndarray, R: np.ndarray, cls: np.ndarray, dt: float, other: np.ndarray | None = None,
             partial: np.ndarray | None = None, vague: np.ndarray | None = None) -> None:
        """Predict, gate, assign, update, and start, confirm and end tracks, for detections ``z`` [n, 3]
        with covariances ``R`` [n, 3, 3] and classes ``cls`` [n] (all of tracked classes); ``other``
        [n_o, 2]: positions of the scan's other candidates (not detections of a tracked class);
        ``partial`` [n]: occluded views of a class seen whole, which only a confirmed track may take;
        ``vague`` [n]: headings read with a variance above the class's ``heading_var_max``. Neither
        kind's heading is used or rejected: the track takes its position only."""
        other = np.zeros((0, 2)) if other is None else np.asarray(other, np.float64).reshape(-1, 2)
        partial = np.zeros(len(z), bool) if partial is None else np.asarray(partial, bool)
        vague = np.zeros(len(z), bool) if vague is None else np.asarray(vague, bool)
        F, Q = self.motion_model(dt)
        live = [i for i, t in enumerate(self.slots) if t is not None]
        for i in live:
            kf = self.slots[i].kf
            kf.predict(F=F, Q=Q)
            kf.x[2] = wrap(kf.x[2])
        # whether an "other" candidate lies near each track's prediction
        other_near = {i: bool(np.any(np.hypot(other[:, 0] - self.slots[i].kf.x[0, 0],
                                              other[:, 1] - self.slots[i].kf.x[1, 0]) < self.birth_exclusion))
                      for i in live}
        n = len(z)
        cost = np.full((n, self.max_tracks), np.inf)
        for i in live:
            t = self.slots[i]
            x, P = t.kf.x[:3, 0], t.kf.P[:3, :3]
            for j in np.flatnonzero(cls == t.cls):
                if partial[j] and not t.confirmed:
                    continue
                nu = z[j] - x
                nu[2] = wrap(nu[2])
                S = P + R[j]
                d2 = nu[:2] @ np.linalg.solve(S[:2, :2], nu[:2])  # position only: 2 dof
                if d2 <= self.gate[cls[j]]:
                    cost[j, i] = d2
        # Greedy one-to-one: repeatedly the globally closest gated pair.
        det_of = {}
        while n and np.isfinite(cost).any():
            j, i = np.unravel_index(np.argmin(cost), cost.shape)
            det_of[i] = j
            cost[j, :] = np.inf
            cost[:, i] = np.inf
        # Recapture: a leftover detection within birth_exclusion of a leftover track of its class.
        near = np.full((n, self.max_tracks), np.inf)
        for i in live:
            t = self.slots[i]
            if i in det_of:
                continue
            for j in np.flatnonzero(cls == t.cls):
                d = math.hypot(z[j, 0] - t.kf.x[0, 0], z[j, 1] - t.kf.x[1, 0])
                if j not in det_of.values() and d < self.birth_exclusion and (t.confirmed or not partial[j]):
                    near[j, i] = d
        while n and np.isfinite(near).any():
            j, i = np.unravel_index(np.argmin(near), near.shape)
            det_of[i] = j
            near[j, :] = np.inf
            near[:, i] = np.inf
        fade = math.exp(-dt / self.heading_memory)
        for i in live:
            t = self.slots[i]
            t.support *= fade
            t.rival_support *= fade
            omega = t.kf.x[5, 0]  # a coasting track's turn rate: clipped at its last update
            if i in det_of:
                j = det_of[i]
                zj = z[j].copy()
                zj[2] = t.kf.x[2, 0] + wrap(zj[2] - t.kf.x[2, 0])  # innovation wrapped
                r_theta = R[j][2, 2]
                head_ok = (zj[2] - t.kf.x[2, 0]) ** 2 <= self.heading_gate * (t.kf.P[2, 2] + r_theta)
                w_max = self.max_turn_rate[t.cls]
                position_only = partial[j] or vague[j]
                if head_ok and t.confirmed and not position_only:
                    # a heading that would turn a confirmed track faster than its class can is a misread
                    x0, P0 = t.kf.x.copy(), t.kf.P.copy()
                    t.kf.update(zj, R=R[j])
                    head_ok = abs(t.kf.x[5, 0]) <= w_max + 2.0 * math.sqrt(max(t.kf.P[5, 5], 0.0))
                    t.kf.x, t.kf.P = x0, P0
                if position_only:  # a cut outline or a vague heading: the position only, the heading neither used nor rejected
                    t.kf.update(zj[:2, None], R=R[j][:2, :2], H=self.H[:2])
                    omega = t.kf.x[5, 0]
                    t.kf.x[5] = min(max(omega, -w_max), w_max)
                elif head_ok:
                    t.kf.update(zj, R=R[j])
                    omega = t.kf.x[5, 0]
                    t.kf.x[5] = min(max(omega, -w_max), w_max)
                    t.support += 1.0
                else:  # position-only update; a turn rate learnt from headings is forgotten
                    learnt = t.kf.P[5, 5] < self.omega_var0  # predicted covariance, before this update
                    t.kf.update(zj[:2, None], R=R[j][:2, :2], H=self.H[:2])
                    if learnt:
                        t.kf.P[5, :] = 0.0
                        t.kf.P[:, 5] = 0.0
                        t.kf.P[5, 5] = self.omega_var0
                        t.kf.x[5] = omega = 0.0
                    else:
                        omega = t.kf.x[5, 0]
                        t.kf.x[5] = min(max(omega, -w_max), w_max)
                    # the rejected heading joins an agreeing rival, or replaces a faded one
                    nu = wrap(z[j, 2] - t.rival)
                    if nu**2 <= self.heading_gate * 2.0 * r_theta:
                        t.rival_support += 1.0
                        t.rival = wrap(t.rival + nu / t.rival_support)
                    elif t.rival_support < 1.0:
                        t.rival, t.rival_support = z[j, 2], 1.0
                t.kf.x[2] = wrap(t.kf.x[2])
                t.kf.P = 0.5 * (t.kf.P + t.kf.P.T)
                if t.rival_support > t.support + 0.5:  # the rival takes over
                    theta = t.kf.x[2, 0]
                    t.kf.x[2] = t.rival
                    t.kf.P[2, :] = 0.0
                    t.kf.P[:, 2] = 0.0
                    t.kf.P[2, 2] = r_theta
                    t.rival, t.support, t.rival_support = theta, t.rival_support, t.support
                t.hits += 1
                t.misses = 0
            else:
                t.misses += 1
                if not t.confirmed and other_near[i]:
                    t.contrary += 1
            if self.plausible(t, omega):
                t.confirmed = t.confirmed or (t.hits >= self.n_confirm and t.hits > t.contrary)
            else:  # confirmation restarts, as for a new track
                t.confirmed, t.hits, t.contrary = False, 0, 0
            if t.misses >= (self.m_delete if t.confirmed else self.m_tentative):
                self.slots[i] = None
        # Births: the i-th free slot takes the i-th unused detection not near a live track of its class.
        used = set(det_of.values())
        may_start = []
        for j in range(n):
            if j in used or partial[j]:
                continue
            near = any(t is not None and t.cls == cls[j]
                       and math.hypot(z[j, 0] - t.kf.x[0, 0], z[j, 1] - t.kf.x[1, 0]) < self.birth_exclusion
                       for t in self.slots)
            if not near:
                may_start.append(j)
        # of detections closer than birth_exclusion, only the first may start a track
        born = [j for j in may_start
                if not any(i < j and cls[i] == cls[j] and math.hypot(*(z[j, :2] - z[i, :2])) < self.birth_exclusion
                           for i in may_start)]
        free = [i for i, t in enumerate(self.slots) if t is None]
        for rank, (i, j) in enumerate(zip(free, born, strict=False)):
            kf = KalmanFilter(dim_x=NX, dim_z=3)
            kf.H = self.H
            kf.x = np.concatenate([z[j], np.zeros(3)])[:, None]
            P = np.zeros((NX, NX))
            P[:3, :3] = R[j]
            P[3, 3] = P[4, 4] = self.vel_var0
            P[5, 5] = self.omega_var0
            kf.P = P
            self.slots[i] = _Track(kf, int(cls[j]), self.next_id + rank, self.n_confirm <= 1)
        self.next_id += min(len(free), len(born))


# ------------------------------------------------------------------------------------------ pipeline


@dataclasses.dataclass
class RefOutput:
    """One scan's confirmed tracks (ids ascending by slot, as gtsjax's table) and the transform."""

    track_id: np.ndarray  # [n]
    track_class: np.ndarray  # [n]
    track_pose: np.ndarray  # [n, 3]
    track_var: np.ndarray  # [n, 3]
    A: np.ndarray
    mu_s: np.ndarray
    mu_o: np.ndarray
    degraded: bool
    n_detections: int


class ReferencePipeline:
    """Stages a–g of one scan at a time, from a trained :class:`gtsjax.Model` with its site attached."""

    def __init__(self, model):
        if model.site is None:
            raise ValueError("attach a site first (Model.with_site)")
        fe = model.frontend
        self.K, self.L = fe.max_candidates, fe.window
        self.n_dist, self.n_intensity = fe.n_dist, fe.n_intensity
        scalar = {f.name: float(np.asarray(getattr(fe, f.name))) for f in dataclasses.fields(fe)
                  if f.name not in ("max_candidates", "window", "n_dist", "n_intensity")}
        self.fe = scalar
        self.cells_on_bbox = bool(scalar["cells_on_bbox"])
        self.classifier = [sklearn_gp(g) for g in model.classifier.gps]
        self.threshold = _f(model.classifier.threshold)
        sup = model.classifier.support  # the open-set test: per class its examples, scale, threshold
        self.support = [(_f(sup.x[k])[np.asarray(sup.mask[k])], _f(sup.mean[k]), _f(sup.inv_scale[k]),
                         float(sup.threshold[k])) for k in range(len(self.classifier))]
        env = model.envelope  # the per-class shape envelopes of stage c
        self.env = (float(env.bin_width), _f(env.lo), _f(env.hi), np.asarray(env.whole, bool))
        self.pose = [None if r is None else {c: (None if getattr(r, c) is None else sklearn_gp(getattr(r, c)))
                                             for c in ("x", "y", "sin", "cos")} for r in model.pose]
        self.var_scale = [None if r is None or r.var_scale is None else _f(r.var_scale) for r in model.pose]
        self.heading_var_max = np.array([np.inf if r is None or r.heading_var_max is None else float(r.heading_var_max)
                                         for r in model.pose])
        self.max_objects = model.max_objects
        self.max_landmarks = int(model.site.landmark_xy.shape[0]) + self.max_objects  # the site's posts + look-alikes
        self.gp_columns = model.gp_columns
        self.landmark_mask = np.asarray(model.landmark_mask, bool)
        self.map_gate = float(model.map_gate)
        self.map_min_spread = float(model.map_min_spread)
        self.meas_var_floor = _f(model.meas_var_floor)
        s = model.site
        self.landmark_xy = _f(s.landmark_xy)
        self.landmark_class = np.asarray(s.landmark_class, int)
        self.sensor_pose = _f(s.sensor_pose)
        self.bounds = _f(s.bounds) if bool(s.has_bounds) else None
        self.tracker = _Tracker(model.tracker, model.max_tracks)
        self.reset()

    def reset(self) -> None:
        """Before the first scan: the site's rough sensor pose as the transform, no tracks."""
        x, y, th = self.sensor_pose
        self.A = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        self.mu_s = np.zeros(2)
        self.mu_o = np.array([x, y])
        self.supported = False  # no fit from landmarks yet: the gate allows for a guessed heading
        self.tracker.reset()

    # ---- stages a–c
    def segments(self, ranges, valid, angles):
        """Stage a: ``(start, end)`` beam indices of the first ``K`` segments and the points in S."""
        valid = valid & np.isfinite(ranges) & (ranges > 0)
        r = np.where(valid, ranges, 0.0)
        x, y = r * np.cos(angles), r * np.sin(angles)
        d2 = np.diff(x) ** 2 + np.diff(y) ** 2
        thr = self.fe["break_distance"] + self.fe["break_growth"] * np.minimum(r[1:], r[:-1])
        joined = valid[1:] & valid[:-1] & (d2 <= thr * thr)
        starts = np.flatnonzero(valid & ~np.concatenate([[False], joined]))
        ends = np.flatnonzero(valid & ~np.concatenate([joined, [False]]))
        return list(zip(starts[: self.K], ends[: self.K], strict=True)), r, x, y

    def _profile(self, n, ylo, yhi, y, q):
        """Eq. 11–12: Gaussian-weighted mean of the columns of ``q`` in each of ``n`` cells."""
        if self.cells_on_bbox:
            lo, hi = ylo, yhi
        else:
            lo, hi = -0.5 * self.fe["cell_span"], 0.5 * self.fe["cell_span"]
        cw = (hi - lo) / n
        c = lo + (np.arange(n) + 0.5) * cw
        sigma = max(self.fe["sigma_cells"] * cw, self.fe["sigma_min"])
        dist = (c[:, None] - y[None, :]) ** 2 / (2 * sigma * sigma)
        w = np.exp(-(dist - dist.min(axis=1, keepdims=True)))  # scaled per cell: no underflow
        return (w @ q) / w.sum(axis=1, keepdims=True)

    def candidates(self, ranges, intensities, valid, angles):
        """Stages a–c: GP inputs, ORS origins and headings of the candidates that pass the filters, and
        what the shape envelopes read: ``(width, depth, n · r)``, the range, whether occluded."""
        segs, r, x, y = self.segments(ranges, valid, angles)
        ok_beam = valid & np.isfinite(ranges) & (ranges > 0)
        inten = np.where(valid & np.isfinite(intensities), intensities, 0.0)
        vecs, origins, headings, shape, occluded = [], [], [], [], []
        for s, e in segs:
            n = e - s + 1
            if n > self.L or n < self.fe["min_points"]:
                continue
            sl = slice(s, e + 1)
            rr, px, py = r[sl], x[sl], y[sl]
            th = 0.5 * (angles[s] + angles[e])
            c, sn = math.cos(th), math.sin(th)
            u = c * px + sn * py
            v = c * py - sn * px
            r_j = 0.5 * (rr.min() + rr.max())
            xp = u - r_j
            ylo, yhi = v.min(), v.max()
            width = yhi - ylo
            if not (self.fe["width_min"] <= width <= self.fe["width_max"]):
                continue
            height = xp.max() - xp.min()
            if self.n_dist == self.n_intensity:
                both = self._profile(self.n_dist, ylo, yhi, v, np.stack([xp, inten[sl]], 1))
                d, i = both[:, 0], both[:, 1]
            else:
                d = self._profile(self.n_dist, ylo, yhi, v, xp[:, None])[:, 0]
                i = self._profile(self.n_intensity, ylo, yhi, v, inten[sl][:, None])[:, 0]
            vecs.append(np.concatenate([[width], d, i, [height, abs(r_j)]]))
            origins.append((r_j * c, r_j * sn))
            headings.append(th)
            shape.append((width, height, n * abs(r_j)))
            # a nearer return just beside either end: something stands in front of it there
            occluded.append(any(0 <= b < len(r) and ok_beam[b] and r[b] < r[end]
                                for b, end in ((s - 1, s), (e + 1, e))))
        d = 1 + self.n_dist + self.n_intensity + 2
        x = np.array(vecs).reshape(-1, d)
        if self.gp_columns:  # the inputs the model was trained on
            x = x[:, list(self.gp_columns)]
        origins = np.array(origins).reshape(-1, 2)
        return x, origins, np.array(headings), np.array(shape).reshape(-1, 3), np.array(occluded, bool)

    # ---- stages d–e
    def in_envelope(self, shape, rng):
        """Stage c's shape envelopes: which classes each candidate may be (a loop over candidates)."""
        bin_width, lo, hi, _ = self.env
        out = np.zeros((len(shape), lo.shape[0]), bool)
        for i, (q, r) in enumerate(zip(shape, rng, strict=True)):
            b = min(max(int(math.floor(r / bin_width)), 0), lo.shape[1] - 1)
            out[i] = np.all((q >= lo[:, b]) & (q <= hi[:, b]), axis=1)
        return out

    def classify(self, x, allowed):
        """Stage d: class of each candidate (the best score among the classes its envelope allows, and
        background) and whether it survives: not background, score ≥ threshold, and no farther from the
        nearest training example of its class (in the class's scale) than the class's threshold."""
        if len(x) == 0:
            return np.zeros(0, int), np.zeros(0, bool), np.zeros((0, len(self.classifier)))
        scores = np.stack([g.predict_mean(x) for g in self.classifier], axis=1)
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

    def regress(self, x, cls, ok, scores):
        """Stage e: ORS-relative pose and variances under each candidate's class's GPs; of a mobile
        class, the ``max_objects`` candidates with the highest class score only, of a landmark class the
        ``landmark_cap`` best (the others are dropped: the second output is False for them)."""
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
                vt = np.where(r2 > 1e-6, (mc**2 * vs + ms**2 * vc) / r2**2, _MAX_THETA_VAR)
            v3 = np.stack([vx, vy, vt], 1)
            if self.var_scale[k] is not None:
                v3 = v3 * self.var_scale[k]
            rel[rows] = np.stack([mx, my, np.arctan2(ms, mc)], 1)
            var[rows] = np.minimum(v3, [np.inf, np.inf, _MAX_THETA_VAR])
        return rel, var, ok

    # ---- stage f
    def update_transform(self, det_s, det_cls):
        """Associate landmark detections (mutual nearest neighbour within the gate, after mapping them
        with the previous transform), then centred OLS (eq. 18) if at least three spread in 2-D."""
        if len(det_s) == 0:
            return False
        det_o = self.mu_o + (det_s - self.mu_s) @ self.A.T
        d2 = np.sum((self.landmark_xy[:, None] - det_o[None]) ** 2, axis=-1)
        d2[self.landmark_class[:, None] != det_cls[None, :]] = np.inf
        best_det = d2.argmin(axis=1)
        best_map = d2.argmin(axis=0)
        # while the transform rests on no landmarks, the gate allows a guessed heading 0.06 rad off
        slack = 0.0 if self.supported else 0.06
        gate = self.map_gate + slack * np.linalg.norm(det_s[best_det], axis=1)
        hit = (best_map[best_det] == np.arange(len(self.landmark_xy))) & (d2.min(axis=1) <= gate**2)
        n = int(hit.sum())
        if n < 3:
            return False
        ps, po = det_s[best_det[hit]], self.landmark_xy[hit]
        mu_s, mu_o = ps.mean(0), po.mean(0)
        X, Y = ps - mu_s, po - mu_o
        XtX = X.T @ X
        if np.linalg.eigvalsh(XtX / n)[0] <= self.map_min_spread**2:
            return False
        self.A = np.linalg.solve(XtX, X.T @ Y).T
        self.mu_s, self.mu_o = mu_s, mu_o
        return True

    def step(self, ranges, intensities, valid, angle_min, angle_increment, dt) -> RefOutput:
        """The whole pipeline for one scan (NumPy arrays of the padded scan, as gtsjax's ``Scan``)."""
        ranges, intensities = _f(ranges), _f(intensities)
        valid = np.asarray(valid, bool)
        angles = float(angle_min) + np.arange(ranges.shape[0]) * float(angle_increment)
        x, origin, heading, shape, occluded = self.candidates(ranges, intensities, valid, angles)
        cls, ok, scores = self.classify(x, self.in_envelope(shape, np.hypot(origin[:, 0], origin[:, 1])))
        partial = occluded & self.env[3][cls]  # occluded views of a class seen whole
        rel, var, ok = self.regress(x, cls, ok, scores)
        vague = var[:, 2] > self.heading_var_max[cls]  # headings read with a variance good reads rarely have
        # ORS -> S (eq. 16 with the ORS in place of O)
        c, s = np.cos(heading), np.sin(heading)
        pose_s = np.stack([origin[:, 0] + c * rel[:, 0] - s * rel[:, 1],
                           origin[:, 1] + s * rel[:, 0] + c * rel[:, 1], heading + rel[:, 2]], 1)
        cov_s = np.zeros((len(x), 3, 3))
        cov_s[:, 0, 0] = c**2 * var[:, 0] + s**2 * var[:, 1]
        cov_s[:, 1, 1] = s**2 * var[:, 0] + c**2 * var[:, 1]
        cov_s[:, 0, 1] = cov_s[:, 1, 0] = c * s * (var[:, 0] - var[:, 1])
        cov_s[:, 2, 2] = var[:, 2]
        lm = ok & self.landmark_mask[cls]
        degraded = not self.update_transform(pose_s[lm, :2], cls[lm])
        self.supported = not degraded
        # S -> O (eq. 10) and tracking of the mobile classes inside the bounds.
        trk = ok & self.tracker.tracked[cls]
        ps, cs, kc = pose_s[trk], cov_s[trk], cls[trk]
        xy = self.mu_o + (ps[:, :2] - self.mu_s) @ self.A.T
        theta = wrap(ps[:, 2] + math.atan2(self.A[1, 0], self.A[0, 0]))
        A3 = np.eye(3)
        A3[:2, :2] = self.A
        cov_o = A3 @ cs @ A3.T + np.diag(self.meas_var_floor)
        if self.bounds is not None:
            b = self.bounds
            inside = (xy[:, 0] >= b[0]) & (xy[:, 1] >= b[1]) & (xy[:, 0] <= b[2]) & (xy[:, 1] <= b[3])
        else:
            inside = np.ones(len(xy), bool)
        z = np.column_stack([xy, theta])[inside]
        # Every other candidate kept by the filters (stage c) counts against the confirmation of a
        # tentative track it lies near: background, rejected, landmarks, objects outside the bounds
        # or without a pose, at its pose in O (its ORS origin where it got none: rel = 0).
        det_idx = np.flatnonzero(trk)[inside]
        is_other = np.ones(len(x), bool)
        is_other[det_idx] = False
        other_xy = self.mu_o + (pose_s[is_other, :2] - self.mu_s) @ self.A.T
        self.tracker.step(z, cov_o[inside], kc[inside], float(dt), other_xy, partial[trk][inside], vague[trk][inside])
        b = self.bounds
        tracks = [t for t in self.tracker.slots
                  if t is not None and t.confirmed and t.misses < self.tracker.m_report
                  and (b is None or b[0] <= t.kf.x[0, 0] <= b[2] and b[1] <= t.kf.x[1, 0] <= b[3])
                  and (t.misses == 0 or not self.seen_through(t.kf.x[:2, 0], ranges, valid, angle_min, angle_increment))]
        return RefOutput(
            track_id=np.array([t.track_id for t in tracks], int),
            track_class=np.array([t.cls for t in tracks], int),
            track_pose=np.array([t.kf.x[:3, 0] for t in tracks]).reshape(-1, 3),
            track_var=np.array([np.diag(t.kf.P)[:3] for t in tracks]).reshape(-1, 3),
            A=self.A.copy(), mu_s=self.mu_s.copy(), mu_o=self.mu_o.copy(), degraded=degraded,
            n_detections=int(len(z)),
        )

    def seen_through(self, xy_o, ranges, valid, angle_min, angle_increment, margin=0.3) -> bool:
        """Whether the three beams nearest the bearing of field point ``xy_o`` show it empty: none
        returns before ``margin`` past it (no return counts as empty)."""
        x, y = self.mu_s + np.linalg.solve(self.A, np.asarray(xy_o, np.float64) - self.mu_o)
        rho = math.hypot(x, y)
        beam = int(np.round((math.atan2(y, x) - float(angle_min)) / float(angle_increment)))
        for i in (beam - 1, beam, beam + 1):
            if not 0 <= i < len(ranges):
                return False
            if valid[i] and ranges[i] <= rho + margin:
                return False
        return True

    def run(self, scans) -> list[RefOutput]:
        """Every scan of a stack (NumPy arrays from :func:`scans_to_numpy`), from a fresh state."""
        self.reset()
        return [self.step(*(a[i] for a in scans)) for i in range(len(scans[0]))]


def scans_to_numpy(scans) -> tuple[np.ndarray, ...]:
    """A stacked gtsjax ``Scan`` as NumPy arrays ``(ranges, intensities, valid, angle_min,
    angle_increment, dt)``: the very numbers the jitted step receives."""
    return tuple(np.asarray(getattr(scans, f)) for f in
                 ("ranges", "intensities", "valid", "angle_min", "angle_increment", "dt"))


def compare_tracks(outputs, ref: list[RefOutput]) -> dict:
    """Agreement of gtsjax's stacked outputs (``process_log`` or stacked ``step`` outputs, NumPy) with
    the reference's, scan by scan: confirmed track ids, counts, and pose differences of equal ids."""
    mask = np.asarray(outputs.track_mask)
    ids = np.asarray(outputs.track_id)
    pose = np.asarray(outputs.track_pose, np.float64)
    n = len(ref)
    same_ids = 0
    dpos, dth = [], []
    all_g, all_r = set(), set()
    for t in range(n):
        g = {int(i): pose[t, m] for m, i in enumerate(ids[t]) if mask[t, m]}
        r = {int(i): p for i, p in zip(ref[t].track_id, ref[t].track_pose, strict=True)}
        all_g |= g.keys()
        all_r |= r.keys()
        same_ids += g.keys() == r.keys()
        for i in g.keys() & r.keys():
            dpos.append(float(np.hypot(*(g[i][:2] - r[i][:2]))))
            dth.append(abs(float(wrap(g[i][2] - r[i][2]))))
    dpos, dth = np.asarray(dpos), np.asarray(dth)
    return {
        "scans": n,
        "scans_same_ids": int(same_ids),
        "track_ids_gtsjax": sorted(all_g),
        "track_ids_reference": sorted(all_r),
        "track_scans_gtsjax": int(mask.sum()),
        "track_scans_reference": int(sum(len(o.track_id) for o in ref)),
        "pairs_compared": int(dpos.size),
        "max_pos_diff_m": float(dpos.max()) if dpos.size else 0.0,
        "p99_pos_diff_m": float(np.percentile(dpos, 99)) if dpos.size else 0.0,
        "max_heading_diff_deg": float(np.degrees(dth.max())) if dth.size else 0.0,
        "degraded_scans_reference": int(sum(o.degraded for o in ref)),
    }
