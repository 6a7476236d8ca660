"""Stage g, tracking: one filterpy ``KalmanFilter`` per track with gtsjax's motion model and track life
cycle, written out plainly from the module docstring of ``gtsjax.core.g_track``."""

import dataclasses
import math

import numpy as np
from filterpy.kalman import KalmanFilter

NX = 6


def wrap(a):
    """Angle to (−π, π]."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


@dataclasses.dataclass
class Track:
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


class Tracker:
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
    of ``gtsjax.core.g_track``)."""

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
        self.slots: list[Track | None] = [None] * self.max_tracks
        self.next_id = 0

    def motion_model(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """``F`` and ``Q`` over ``dt``: constant velocity (piecewise white acceleration) or inflate-only."""
        q = np.array([self.q_pos, self.q_pos, self.q_theta])
        if self.constant_velocity:
            F = np.eye(NX)
            F[:3, 3:] = dt * np.eye(3)
            Q = np.block([[np.diag(q * dt**3 / 3), np.diag(q * dt**2 / 2)], [np.diag(q * dt**2 / 2), np.diag(q * dt)]])
        else:
            F = np.eye(NX)
            Q = np.zeros((NX, NX))
            Q[:3, :3] = np.diag(q * dt)
        return F, Q

    def plausible(self, t: Track, omega: float) -> bool:
        """Whether the track's speed and turn rate (``omega``, before clipping) are its class's, within
        twice their standard deviations."""
        v = t.kf.x[3:5, 0]
        sigma_v = math.sqrt(max(np.linalg.eigvalsh(t.kf.P[3:5, 3:5])[-1], 0.0))
        sigma_w = math.sqrt(max(t.kf.P[5, 5], 0.0))
        return bool(
            math.hypot(v[0], v[1]) <= self.max_speed[t.cls] + 2.0 * sigma_v
            and abs(omega) <= self.max_turn_rate[t.cls] + 2.0 * sigma_w
        )

    def step(
        self,
        z: np.ndarray,
        R: np.ndarray,
        cls: np.ndarray,
        dt: float,
        other: np.ndarray | None = None,
        partial: np.ndarray | None = None,
        vague: np.ndarray | None = None,
    ) -> None:
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
        other_near = {
            i: bool(
                np.any(
                    np.hypot(other[:, 0] - self.slots[i].kf.x[0, 0], other[:, 1] - self.slots[i].kf.x[1, 0])
                    < self.birth_exclusion
                )
            )
            for i in live
        }
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
                if (
                    position_only
                ):  # a cut outline or a vague heading: the position only, the heading neither used nor rejected
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
            near = any(
                t is not None
                and t.cls == cls[j]
                and math.hypot(z[j, 0] - t.kf.x[0, 0], z[j, 1] - t.kf.x[1, 0]) < self.birth_exclusion
                for t in self.slots
            )
            if not near:
                may_start.append(j)
        # of detections closer than birth_exclusion, only the first may start a track
        born = [
            j
            for j in may_start
            if not any(
                i < j and cls[i] == cls[j] and math.hypot(*(z[j, :2] - z[i, :2])) < self.birth_exclusion
                for i in may_start
            )
        ]
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
            self.slots[i] = Track(kf, int(cls[j]), self.next_id + rank, self.n_confirm <= 1)
        self.next_id += min(len(free), len(born))
