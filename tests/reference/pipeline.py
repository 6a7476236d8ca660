"""Stages a–g (with e′) in order, one scan at a time (:class:`ReferencePipeline`), and how its tracks are
compared with gtsjax's (:func:`compare_tracks`)."""

import dataclasses
import math

import numpy as np

from .classify import Classifier
from .features import FrontEnd
from .gp import _f
from .maptransform import MapTransform
from .pose import PoseRegressors
from .refine import Outline, Sides, refine_candidates
from .segment import segments
from .track import Tracker, wrap


@dataclasses.dataclass
class Perceived:
    """Stages a–e′ of one scan, per candidate kept by the filters (stage c), in beam order."""

    cls: np.ndarray  # [n]
    ok: np.ndarray  # [n] an object of a known class, posed
    partial: np.ndarray  # [n]
    vague: np.ndarray  # [n]
    pose_s: np.ndarray  # [n, 3] after e′
    cov_s: np.ndarray  # [n, 3, 3] after e′
    sides: Sides  # e′: side hypotheses (in S) and which candidates were refined
    guess: np.ndarray  # [n] not ok, but posed and refined as the tracked class ``cls``


@dataclasses.dataclass
class RefOutput:
    """One scan's confirmed tracks (ids ascending by slot, as gtsjax's table) and the transform."""

    track_id: np.ndarray  # [n]
    track_class: np.ndarray  # [n]
    track_pose: np.ndarray  # [n, 3]
    track_var: np.ndarray  # [n, 3]
    track_cov_xy: np.ndarray  # [n]
    A: np.ndarray
    mu_s: np.ndarray
    mu_o: np.ndarray
    degraded: bool
    n_detections: int
    n_refined: int  # candidates whose pose came from the outline fit (stage e′)


class ReferencePipeline:
    """Stages a–g of one scan at a time (e′, the outline refinement, after e), from a trained
    :class:`gtsjax.Model` with its site attached."""

    def __init__(self, model):
        if model.site is None:
            raise ValueError("attach a site first (Model.with_site)")
        s = model.site
        self.frontend = FrontEnd(model.frontend, model.gp_columns)
        self.classifier = Classifier(model)
        # the site's posts and as many look-alikes as objects
        self.pose = PoseRegressors(model, int(s.landmark_xy.shape[0]) + model.max_objects)
        self.landmark_mask = np.asarray(model.landmark_mask, bool)
        self.meas_var_floor = _f(model.meas_var_floor)
        self.transform = MapTransform(
            s.landmark_xy, s.landmark_class, float(model.map_gate), float(model.map_min_spread)
        )
        self.sensor_pose = _f(s.sensor_pose)
        self.bounds = _f(s.bounds) if bool(s.has_bounds) else None
        self.tracker = Tracker(model.tracker, model.max_tracks, period=model.scan_period)
        self.outline = None if model.outline is None else Outline.of(model.outline)
        offset = model.tracker.pose_offset
        self.pose_offset = None if offset is None else _f(offset)
        floor = model.tracker.var_floor
        self.var_floor = None if floor is None else _f(floor)
        self.max_objects = model.max_objects
        self.reset()

    def reported_pose(self, cls: int, pose) -> np.ndarray:
        """A track's pose as reported: its class's mean error in its own frame (``pose_offset``)
        taken off, moved back along the track's axes after its heading is turned back."""
        x, y, th = (float(v) for v in pose)
        if self.pose_offset is None:
            return np.array([x, y, th])
        ahead, left, turn = self.pose_offset[cls]
        th -= turn
        return np.array([x - (math.cos(th) * ahead - math.sin(th) * left),
                         y - (math.sin(th) * ahead + math.cos(th) * left), wrap(th)])

    def reported_var(self, cls: int, var) -> np.ndarray:
        """A track's (var_x, var_y, var_theta) as reported: its class's floor (``var_floor``: position,
        heading) added."""
        var = np.array([float(v) for v in var])
        if self.var_floor is not None:
            var += self.var_floor[cls][[0, 0, 1]]
        return var

    def reset(self) -> None:
        """Before the first scan: the site's rough sensor pose as the transform, no tracks."""
        self.transform.reset(self.sensor_pose)
        self.tracker.reset()

    def candidates(self, ranges, intensities, valid, angles):
        """Stages a–c (see :meth:`FrontEnd.candidates`)."""
        return self.frontend.candidates(ranges, intensities, valid, angles)

    def windows(self, ranges, valid, angles, headings):
        """The points in S ``[n, window, 2]`` and their mask of the candidates with ORS headings
        ``headings`` (from :meth:`candidates`): each candidate is the segment whose angular middle is its
        heading (segments are disjoint, so their middles differ)."""
        fe = self.frontend
        segs, _, px, py = segments(ranges, valid, angles, fe.fe["break_distance"], fe.fe["break_growth"], fe.K)
        by_middle = {float(0.5 * (angles[s] + angles[e])): (s, e) for s, e in segs}
        pts = np.zeros((len(headings), fe.L, 2))
        mask = np.zeros((len(headings), fe.L), bool)
        for i, th in enumerate(headings):
            s, e = by_middle[float(th)]
            n = e - s + 1
            pts[i, :n, 0], pts[i, :n, 1] = px[s : e + 1], py[s : e + 1]
            mask[i, :n] = True
        return pts, mask

    def update_transform(self, det_s, det_cls) -> bool:
        """Stage f (see :meth:`MapTransform.update`)."""
        return self.transform.update(det_s, det_cls)

    def perceive(self, ranges, intensities, valid, angle_min, angle_increment) -> Perceived:
        """Stages a–e′ for one scan (NumPy arrays of the padded scan, as gtsjax's ``Scan``)."""
        ranges, intensities = _f(ranges), _f(intensities)
        valid = np.asarray(valid, bool)
        angles = float(angle_min) + np.arange(ranges.shape[0]) * float(angle_increment)
        x, origin, heading, shape, occluded = self.candidates(ranges, intensities, valid, angles)
        clf = self.classifier
        envelope = clf.in_envelope(shape, np.hypot(origin[:, 0], origin[:, 1]))
        cls, ok, scores = clf.classify(x, envelope)
        # Guesses: candidates that are not ok but could be a tracked class are posed as it, after the
        # candidates classified as it (the cap takes the highest scores first).
        guess, guess_cls = (clf.guesses(x, envelope, ok, scores, self.tracker.tracked) if len(x)
                            else (np.zeros(0, bool), np.zeros(0, int)))
        cls = np.where(guess, guess_cls, cls)
        partial = occluded & clf.whole[cls]  # occluded views of a class seen whole
        rel, var, posed = self.pose.regress(x, cls, ok | guess, scores)
        ok, guess = ok & posed, guess & posed
        vague = self.pose.vague(var, cls)
        # ORS -> S (eq. 16 with the ORS in place of O)
        c, s = np.cos(heading), np.sin(heading)
        pose_s = np.stack(
            [
                origin[:, 0] + c * rel[:, 0] - s * rel[:, 1],
                origin[:, 1] + s * rel[:, 0] + c * rel[:, 1],
                heading + rel[:, 2],
            ],
            1,
        )
        cov_s = np.zeros((len(x), 3, 3))
        cov_s[:, 0, 0] = c**2 * var[:, 0] + s**2 * var[:, 1]
        cov_s[:, 1, 1] = s**2 * var[:, 0] + c**2 * var[:, 1]
        cov_s[:, 0, 1] = cov_s[:, 1, 0] = c * s * (var[:, 0] - var[:, 1])
        cov_s[:, 2, 2] = var[:, 2]
        # e′: the outline refinement of the tracked classes' posed candidates, and every candidate's sides
        pts, mask = self.windows(ranges, valid, angles, heading)
        sides = refine_candidates(self.outline, self.max_objects, cls, (ok | guess) & self.tracker.tracked[cls],
                                  scores, pts, mask, pose_s, cov_s)
        # a guess is kept only where its outline fit succeeded
        return Perceived(cls, ok, partial, vague & ~sides.refined, sides.pose, sides.cov, sides, guess & sides.refined)

    def step(self, ranges, intensities, valid, angle_min, angle_increment, dt) -> RefOutput:
        """The whole pipeline for one scan (NumPy arrays of the padded scan, as gtsjax's ``Scan``)."""
        p = self.perceive(ranges, intensities, valid, angle_min, angle_increment)
        ranges, valid = _f(ranges), np.asarray(valid, bool)
        cls, ok, partial, vague, pose_s, cov_s, sides = p.cls, p.ok, p.partial, p.vague, p.pose_s, p.cov_s, p.sides
        guess = p.guess
        lm = ok & self.landmark_mask[cls]
        tf = self.transform
        degraded = not self.update_transform(pose_s[lm, :2], cls[lm])
        tf.supported = not degraded
        # S -> O (eq. 10) and tracking of the mobile classes inside the bounds.
        trk = (ok | guess) & self.tracker.tracked[cls]
        ps, cs, kc = pose_s[trk], cov_s[trk], cls[trk]
        xy = tf.to_o(ps[:, :2])
        theta = wrap(ps[:, 2] + tf.rotation)
        side_heading = wrap(sides.side_pose[trk, :, 2] + tf.rotation)
        side_logp = sides.side_logp[trk]
        A3 = np.eye(3)
        A3[:2, :2] = tf.A
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
        # (a guess is one of them: it counts against a tentative track as it did when it was background)
        det_idx = np.flatnonzero(trk)[inside & ~guess[trk]]
        is_other = np.ones(len(cls), bool)
        is_other[det_idx] = False
        other_xy = tf.to_o(pose_s[is_other, :2])
        self.tracker.step(z, cov_o[inside], kc[inside], float(dt), other_xy, partial[trk][inside], vague[trk][inside],
                          side_heading[inside], side_logp[inside], guess=guess[trk][inside])
        b = self.bounds
        tracks = [
            t
            for t in self.tracker.slots
            if t is not None
            and t.confirmed
            and t.misses < self.tracker.m_report
            and (b is None or b[0] <= t.kf.x[0, 0] <= b[2] and b[1] <= t.kf.x[1, 0] <= b[3])
            and (t.misses == 0 or not self.seen_through(t.kf.x[:2, 0], ranges, valid, angle_min, angle_increment))
        ]
        return RefOutput(
            track_id=np.array([t.track_id for t in tracks], int),
            track_class=np.array([t.cls for t in tracks], int),
            track_pose=np.array([self.reported_pose(t.cls, t.kf.x[:3, 0]) for t in tracks]).reshape(-1, 3),
            track_var=np.array([self.reported_var(t.cls, np.diag(t.kf.P)[:3]) for t in tracks]).reshape(-1, 3),
            track_cov_xy=np.array([t.kf.P[0, 1] for t in tracks]).reshape(-1),
            A=tf.A.copy(),
            mu_s=tf.mu_s.copy(),
            mu_o=tf.mu_o.copy(),
            degraded=degraded,
            n_detections=int(np.sum(~guess[trk][inside])),
            n_refined=int(np.sum(sides.refined)),
        )

    def seen_through(self, xy_o, ranges, valid, angle_min, angle_increment, margin=0.3) -> bool:
        """Whether the three beams nearest the bearing of field point ``xy_o`` show it empty: none
        returns before ``margin`` past it (no return counts as empty)."""
        x, y = self.transform.to_s(xy_o)
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
    return tuple(
        np.asarray(getattr(scans, f)) for f in ("ranges", "intensities", "valid", "angle_min", "angle_increment", "dt")
    )


def compare_tracks(outputs, ref: list[RefOutput]) -> dict:
    """Agreement of gtsjax's stacked outputs (``process_log`` or stacked ``step`` outputs, NumPy) with
    the reference's, scan by scan: confirmed track ids, counts, and pose differences of equal ids."""
    mask = np.asarray(outputs.track_mask)
    ids = np.asarray(outputs.track_id)
    pose = np.asarray(outputs.track_pose, np.float64)
    var, cov_xy = np.asarray(outputs.track_var, np.float64), np.asarray(outputs.track_cov_xy, np.float64)
    n = len(ref)
    same_ids = 0
    dpos, dth, dcorr, dvar = [], [], [], []
    all_g, all_r = set(), set()
    for t in range(n):
        g = {int(i): pose[t, m] for m, i in enumerate(ids[t]) if mask[t, m]}
        r = {int(i): p for i, p in zip(ref[t].track_id, ref[t].track_pose, strict=True)}
        # The x–y correlation coefficient (the covariance over the deviations' product: scale-free).
        g_corr = {int(i): cov_xy[t, m] / np.sqrt(var[t, m, 0] * var[t, m, 1]) for m, i in enumerate(ids[t]) if mask[t, m]}
        r_corr = {int(i): c / np.sqrt(v[0] * v[1])
                  for i, c, v in zip(ref[t].track_id, ref[t].track_cov_xy, ref[t].track_var, strict=True)}
        g_var = {int(i): var[t, m] for m, i in enumerate(ids[t]) if mask[t, m]}
        r_var = {int(i): np.asarray(v, np.float64) for i, v in zip(ref[t].track_id, ref[t].track_var, strict=True)}
        all_g |= g.keys()
        all_r |= r.keys()
        same_ids += g.keys() == r.keys()
        for i in g.keys() & r.keys():
            dpos.append(float(np.hypot(*(g[i][:2] - r[i][:2]))))
            dth.append(abs(float(wrap(g[i][2] - r[i][2]))))
            dcorr.append(abs(float(g_corr[i] - r_corr[i])))
            dvar.append(float(np.max(np.abs(g_var[i] - r_var[i]) / r_var[i])))
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
        "max_xy_correlation_diff": max(dcorr, default=0.0),
        "max_variance_rel_diff": max(dvar, default=0.0),
        # The share of compared rows whose headings agree within 0.2° and variances within 5 %: a
        # near-flat outline fit (stage e′) of an odd view can settle elsewhere in float32 than in
        # float64, and the track follows that read for a few scans (``tests/test_reference.py``).
        "share_heading_within_0.2deg": float(np.mean(np.degrees(dth) < 0.2)) if dth.size else 1.0,
        "share_variance_within_5pc": float(np.mean(np.asarray(dvar) < 0.05)) if dvar else 1.0,
        "degraded_scans_reference": int(sum(o.degraded for o in ref)),
    }
