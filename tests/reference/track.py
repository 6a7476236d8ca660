"""Stage g, tracking: one filterpy ``KalmanFilter`` per track with gtsjax's motion model and track life
cycle, and per track a mixture over heading side hypotheses, written out plainly from the module
docstring of ``gtsjax.core.g_track``."""

import dataclasses
import math

import numpy as np
import scipy.special
from filterpy.kalman import KalmanFilter

NX = 6
SIDES = 4  # heading hypotheses per track (gtsjax: ``e_refine.SIDES``)

# The heading mixture's constants (gtsjax: ``g_heading._OUTLIER_P``, ``g_types._REST_P``, ``g_heading._SAME_SIDE``, ``_NEW_P``,
# ``_MERGE``, ``_SWITCH_ODDS``): a detection's heading that none of its sides explains is at least this likely under a uniform heading
# (and the rest keeps this share of its weight after a read); a new track's rest has this weight;
# another hypothesis becomes the state's heading at these odds.
OUTLIER_P = 0.01
REST_P = 0.1
# A new hypothesis within SAME_SIDE (rad) of a predicted one also gets NEW_P of that one's weight.
SAME_SIDE = 0.5
NEW_P = 0.1
MERGE = 0.05  # hypotheses closer than this (rad) merge
SWITCH_ODDS = 3.0
MOTION_S = 1.0  # the direction of travel counts as one reading per this many seconds
MOTION_MIN_SPEED = 0.05  # m/s: slower, the direction of travel is not read
# A guess (gtsjax: ``g_track.GUESS_RADIUS``, ``GUESS_MISSES``) updates only a confirmed track that has
# missed at most this many scans in a row, within this distance (m) of its prediction.
GUESS_RADIUS = 0.03
GUESS_MISSES = 2


def wrap(a):
    """Angle to (−π, π]."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def logsumexp(values) -> float:
    """``log Σ exp`` of a list of floats, some of them maybe ``-inf``."""
    top = max(values)
    if top == -math.inf:
        return -math.inf
    return top + math.log(sum(math.exp(v - top) for v in values))


@dataclasses.dataclass
class Track:
    kf: KalmanFilter
    cls: int
    track_id: int
    confirmed: bool
    heading: np.ndarray  # [SIDES] heading hypotheses
    var: np.ndarray  # [SIDES] their variances
    logw: np.ndarray  # [SIDES] their log-weights, normalised with the rest; -inf: unused
    rest: float  # the log-weight of a heading none of them is (uniform)
    main: int  # the hypothesis the filter's heading is
    hits: int = 1
    misses: int = 0
    contrary: int = 0


class Tracker:
    """Stage g with one filterpy ``KalmanFilter`` per track (same model and life cycle as gtsjax).

    Gating follows the model's tracker: on position (2 dof), with an assigned detection's heading used
    only if its own innovation passes ``heading_gate`` (otherwise a position-only update, and the
    turn rate is forgotten); ``|ω| ≤ max_turn_rate`` of the track's class; the heading a mixture over
    side hypotheses (below); leftover detections within ``birth_exclusion`` of a leftover track
    recaptured by it; confirmation after ``n_confirm`` hits, if more than the tentative scans with no
    detection but an "other" candidate within ``birth_exclusion`` of the prediction (``contrary``), and
    if the motion is plausible: speed at most ``max_speed + 2 σ_v`` (``σ_v²`` the largest eigenvalue of
    the velocity covariance, from ``eigvalsh``), turn rate before clipping at most ``max_turn_rate +
    2 σ_ω``; an implausible scan takes the confirmation away and restarts ``hits`` and ``contrary`` at
    0; tracks reported while confirmed and missed fewer than ``m_report`` scans.

    The heading mixture, per track and hypothesis ``j`` (heading ``φ_j``, variance ``σ_j²``, log-weight
    ``w_j``) and its rest (log-weight ``w_u``, a uniform heading): the prediction turns ``φ_j`` by the
    filter's heading change and adds to ``σ_j²`` what the filter's heading variance gained. An assigned
    detection (neither partial nor vague) with sides ``h`` (headings ``z_h``, log-probabilities ``log
    p_h``; one side, its heading, by default) and heading variance ``r`` has the evidence ``e_j =
    log(Σ_h p_h N(z_h; φ_j, σ_j² + r) + OUTLIER_P / 2π)``; every scan ``w_j ← exp(−dt /
    heading_memory) w_j + e_j`` (no ``e_j`` without such a detection), and ``w_u`` fades the same way.
    Each hypothesis but ``main`` whose nearest side (the side ``h`` of the largest ``log p_h − (z_h −
    φ_j)² / 2(σ_j² + r)``, the likeliest to explain it) passes ``heading_gate`` takes it as a scalar Kalman
    update. Then the rest reads the detection's most probable side ``z``: ``log(1 − OUTLIER_P) / 2π``
    plus ``w_u`` goes to the hypothesis that (updated) has ``z`` within the gate with the smallest
    normalised distance, or where none has, to a new hypothesis ``z`` (variance ``r``) in place of the
    weakest one other than the filter's (``main``), whose weight is added to the rest's, and which also
    gets ``NEW_P`` times the weight of the heaviest other hypothesis whose predicted heading is within
    ``SAME_SIDE`` of ``z``; ``w_u`` itself adds ``log OUTLIER_P / 2π``. Hypotheses closer than
    ``MERGE`` merge: each one outranked by such a near one (``main`` first, then by weight, then by
    index) adds its weight to the top one of those and is dropped. The weights are normalised with the
    rest's. Where the most probable hypothesis has more than ``SWITCH_ODDS`` times the weight of
    ``main``, it becomes ``main``: the filter's heading is set to that hypothesis's predicted heading
    and variance, uncorrelated with the rest of the state. The filter's update then uses the side
    nearest ``main``'s predicted heading (in that sense); after it, ``main`` is the filter's heading and variance. A
    new track's hypotheses are its detection's sides (variance ``r``, log-weights ``log p_h + log(1 −
    REST_P)``), ``main`` the most probable, its rest ``log REST_P``."""

    def __init__(self, params, max_tracks: int, sides: int = SIDES, period: float | None = None):
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
        mh = getattr(params, "motion_heading", None)  # per class: offset of the heading from the travel, κ, other share
        self.motion_heading = None if mh is None else np.asarray(mh, np.float64)
        self.max_tracks = max_tracks
        self.sides = sides
        self.period = period  # a scan without a detection counts as the scan periods its dt spans
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

    def travel_evidence(self, t: Track, phi: float, dt: float) -> float:
        """The direction of travel's evidence for heading ``phi`` of the (predicted) track: the class's
        von Mises about the travel plus its learnt offset, its concentration lowered by the travel
        direction's own variance, mixed with a uniform share, against a uniform heading; weighted by
        ``dt`` over ``MOTION_S``; zero when slow, untaught or not constant-velocity. Written from its
        definition with SciPy's Bessel function."""
        if self.motion_heading is None or not self.constant_velocity:
            return 0.0
        mu, kappa, other = self.motion_heading[t.cls]
        kappa, other = max(kappa, 0.0), min(max(other, 1e-3), 1.0)
        vx, vy = float(t.kf.x[3, 0]), float(t.kf.x[4, 0])
        speed2 = max(vx * vx + vy * vy, 1e-12)
        if speed2 < MOTION_MIN_SPEED**2 or kappa <= 0.0:
            return 0.0
        across = np.array([-vy, vx])
        var_dir = float(across @ t.kf.P[3:5, 3:5] @ across) / speed2**2
        k = kappa / (1.0 + kappa * var_dir)
        delta = wrap(phi - math.atan2(vy, vx) - mu)
        vm = math.exp(k * (math.cos(delta) - 1.0)) / scipy.special.i0e(k)  # 2π times the von Mises density
        return min(dt / MOTION_S, 1.0) * math.log((1.0 - other) * vm + other)

    def mixture(self, t: Track, zh, zlp, r: float, seen: bool, dt: float) -> tuple[int, int | None]:
        """This scan's weights and updates of the track's (predicted) heading hypotheses, for a
        detection with side headings ``zh`` and log-probabilities ``zlp`` (``None``: no detection) and
        heading variance ``r``, whose heading is used where ``seen``. Returns the hypothesis the filter's
        heading is to be and the index of the detection's side nearest that hypothesis's prediction."""
        n = len(t.logw)
        phi, var = t.heading.copy(), t.var.copy()  # the predicted hypotheses
        used = [j for j in range(n) if np.isfinite(t.logw[j])]
        sides = [] if zh is None else [h for h in range(len(zh)) if np.isfinite(zlp[h])]

        def nearest(j):  # the detection's side most likely to explain hypothesis j's prediction
            return max(sides, key=lambda h: zlp[h] - 0.5 * wrap(zh[h] - phi[j]) ** 2 / (var[j] + r))

        def within(j):  # the heading gate of hypothesis j's prediction: its nearest side, and all sides together
            s = var[j] + r
            d2 = [wrap(zh[h] - phi[j]) ** 2 / s for h in sides]
            together = -2.0 * logsumexp([zlp[h] - 0.5 * d for h, d in zip(sides, d2, strict=True)])
            return d2[sides.index(nearest(j))] <= self.heading_gate and together <= self.heading_gate

        fade = math.exp(-dt / self.heading_memory)
        logw = np.full(n, -np.inf)
        for j in used:
            logw[j] = fade * t.logw[j]
            if seen:
                s = var[j] + r
                terms = [zlp[h] - 0.5 * wrap(zh[h] - phi[j]) ** 2 / s - 0.5 * math.log(2 * math.pi * s) for h in sides]
                logw[j] += logsumexp([logsumexp(terms), math.log(OUTLIER_P / (2 * math.pi))])
                logw[j] += self.travel_evidence(t, phi[j], dt)
        rest = fade * t.rest
        if seen:
            for j in used:  # each hypothesis takes its nearest side where that passes the heading gate
                if j == t.main:  # the filter's heading: updated with the filter, below
                    continue
                h = nearest(j)
                nu = wrap(zh[h] - phi[j])
                s = var[j] + r
                if within(j):
                    t.heading[j] = wrap(phi[j] + var[j] / s * nu)
                    t.var[j] = (1.0 - var[j] / s) * var[j]
            # the rest reads the detection's most probable side
            z = zh[max(sides, key=lambda h: zlp[h])]
            d2 = {j: wrap(z - t.heading[j]) ** 2 / (t.var[j] + r) for j in used}
            explains = [j for j in used if d2[j] <= self.heading_gate]
            spawn = rest + math.log((1.0 - OUTLIER_P) / (2 * math.pi))
            rest += math.log(OUTLIER_P / (2 * math.pi))
            if explains:
                target = min(explains, key=lambda j: d2[j])
            else:  # a new hypothesis in place of the weakest one
                target = min((j for j in range(n) if j != t.main), key=lambda j: logw[j])
                rest = logsumexp([rest, logw[target]])
                t.heading[target], t.var[target], logw[target] = z, r, -math.inf
            logw[target] = logsumexp([logw[target], spawn])
            if not explains:  # near a hypothesis it was (predicted): that side again, turned further
                near = [j for j in used if j != target and abs(wrap(z - phi[j])) < SAME_SIDE]
                if near:
                    logw[target] = logsumexp([logw[target], max(logw[j] for j in near) + math.log(NEW_P)])
        # near-duplicates merge into the top-ranked one near them; a dropped one keeps nothing
        rank = [math.inf if j == t.main else logw[j] for j in range(n)]
        live = [j for j in range(n) if np.isfinite(logw[j])]
        over = {k: [j for j in live if j != k and (rank[j] > rank[k] or (rank[j] == rank[k] and j < k))
                    and abs(wrap(t.heading[j] - t.heading[k])) < MERGE] for k in live}
        merged = logw.copy()
        for k, js in over.items():
            if js:
                into = max(js, key=lambda j: rank[j])
                merged[into] = logsumexp([merged[into], logw[k]])
        for k, js in over.items():
            if js:
                merged[k] = -math.inf
        total = logsumexp(list(merged) + [rest])
        logw, t.rest = merged - total, rest - total
        t.logw = logw
        best = max(range(n), key=lambda j: logw[j])
        main = best if logw[best] - logw[t.main] > math.log(SWITCH_ODDS) else t.main
        if main != t.main:  # the filter's heading becomes that hypothesis (as predicted)
            t.kf.x[2] = phi[main]
            t.kf.P[2, :] = 0.0
            t.kf.P[:, 2] = 0.0
            t.kf.P[2, 2] = var[main]
            t.main = main
        return main, (nearest(main) if sides else None), (within(main) if sides else True)

    def step(
        self,
        z: np.ndarray,
        R: np.ndarray,
        cls: np.ndarray,
        dt: float,
        other: np.ndarray | None = None,
        partial: np.ndarray | None = None,
        vague: np.ndarray | None = None,
        side_heading: np.ndarray | None = None,
        side_logp: np.ndarray | None = None,
        guess: np.ndarray | None = None,
    ) -> None:
        """Predict, gate, assign, update, and start, confirm and end tracks, for detections ``z`` [n, 3]
        with covariances ``R`` [n, 3, 3] and classes ``cls`` [n] (all of tracked classes); ``other``
        [n_o, 2]: positions of the scan's other candidates (not detections of a tracked class);
        ``partial`` [n]: occluded views of a class seen whole, which only a confirmed track may take;
        ``vague`` [n]: headings read with a variance above the class's ``heading_var_max``. Neither
        kind's heading is used or rejected: the track takes its position only. ``side_heading``,
        ``side_logp`` [n, sides]: each detection's side headings and their log-probabilities (-inf:
        unused; the most probable side's heading is ``z[:, 2]``); ``None``: one side, ``z[:, 2]``.
        ``guess`` [n]: candidates classified as something else but posed as this class, which only a
        confirmed track with at most ``GUESS_MISSES`` misses may take, within ``GUESS_RADIUS`` of its
        prediction and its gate; never recaptured, never starting a track."""
        other = np.zeros((0, 2)) if other is None else np.asarray(other, np.float64).reshape(-1, 2)
        partial = np.zeros(len(z), bool) if partial is None else np.asarray(partial, bool)
        vague = np.zeros(len(z), bool) if vague is None else np.asarray(vague, bool)
        guess = np.zeros(len(z), bool) if guess is None else np.asarray(guess, bool)
        if side_heading is None or side_logp is None:
            side_heading = np.repeat(np.asarray(z, np.float64)[:, 2:3], self.sides, axis=1)
            side_logp = np.full((len(z), self.sides), -np.inf)
            side_logp[:, 0] = 0.0
        side_heading = np.asarray(side_heading, np.float64)
        side_logp = np.asarray(side_logp, np.float64)
        F, Q = self.motion_model(dt)
        live = [i for i, t in enumerate(self.slots) if t is not None]
        for i in live:
            t = self.slots[i]
            kf = t.kf
            theta, var = kf.x[2, 0], kf.P[2, 2]
            kf.predict(F=F, Q=Q)
            kf.x[2] = wrap(kf.x[2])
            # the hypotheses turn with the filter's heading and grow as uncertain as it does
            turn = wrap(kf.x[2, 0] - theta)
            for j in range(len(t.heading)):
                t.heading[j] = wrap(t.heading[j] + turn)
                t.var[j] += kf.P[2, 2] - var
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
                if guess[j] and not (t.confirmed and t.misses <= GUESS_MISSES
                                     and math.hypot(z[j, 0] - x[0], z[j, 1] - x[1]) < GUESS_RADIUS):
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
                if (j not in det_of.values() and d < self.birth_exclusion and (t.confirmed or not partial[j])
                        and not guess[j]):
                    near[j, i] = d
        while n and np.isfinite(near).any():
            j, i = np.unravel_index(np.argmin(near), near.shape)
            det_of[i] = j
            near[j, :] = np.inf
            near[:, i] = np.inf
        for i in live:
            t = self.slots[i]
            j = det_of.get(i)
            position_only = j is not None and bool(partial[j] or vague[j])
            if j is None:
                self.mixture(t, None, None, 0.0, False, dt)
            else:
                _, h, sides_ok = self.mixture(t, side_heading[j], side_logp[j], R[j][2, 2], not position_only, dt)
            omega = t.kf.x[5, 0]  # a coasting track's turn rate: clipped at its last update
            if j is not None:
                zj = z[j].copy()
                zj[2] = side_heading[j, h]  # the side nearest the filter's heading
                zj[2] = t.kf.x[2, 0] + wrap(zj[2] - t.kf.x[2, 0])  # innovation wrapped
                r_theta = R[j][2, 2]
                head_ok = (zj[2] - t.kf.x[2, 0]) ** 2 <= self.heading_gate * (t.kf.P[2, 2] + r_theta) and sides_ok
                w_max = self.max_turn_rate[t.cls]
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
                t.kf.x[2] = wrap(t.kf.x[2])
                t.kf.P = 0.5 * (t.kf.P + t.kf.P.T)
                t.hits += 1
                t.misses = 0
            else:
                t.misses += 1 if self.period is None else max(1, round(dt / self.period))
                if not t.confirmed and other_near[i]:
                    t.contrary += 1
            # the filter's heading is its main hypothesis
            t.heading[t.main], t.var[t.main] = t.kf.x[2, 0], t.kf.P[2, 2]
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
            if j in used or partial[j] or guess[j]:
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
            self.slots[i] = Track(
                kf, int(cls[j]), self.next_id + rank, self.n_confirm <= 1,
                heading=side_heading[j].copy(), var=np.full(len(side_heading[j]), R[j][2, 2]),
                logw=side_logp[j] + math.log1p(-REST_P), rest=math.log(REST_P), main=int(np.argmax(side_logp[j])),
            )
        self.next_id += min(len(free), len(born))
