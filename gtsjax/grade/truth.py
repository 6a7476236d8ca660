"""The ground truth as grading reads it: a GTD CSV's rows as flat arrays (one entry per row), with
each row's track, its place among the track's rows, and the track's motion at that instant (speed
and turn rate over :data:`PROFILE_S`), so that matching a robot against every track at once is a few
array operations over the rows rather than a loop over tracks."""

from dataclasses import dataclass

import numpy as np

from ..core.geometry import wrap
from ..io.gtd import TrackRow
from .series import interpolate

#: The baseline of a motion profile (s): speed and turn rate are taken over this much time, centred
#: on the instant, so that a few centimetres of noise in a pose do not read as a fast step.
PROFILE_S = 1.0
#: Rows of one track further apart than this (s) are not interpolated across.
TRACK_GAP_S = 0.5


@dataclass(frozen=True)
class GroundTruth:
    """The rows of a GTD CSV (of the graded classes), sorted by stamp then track."""

    stamps: np.ndarray  # [N] laptop clock, s
    track: np.ndarray  # [N] index into ``ids``
    ids: np.ndarray  # [K] the CSV's track ids
    classes: list[str]  # [K] each track's class
    poses: np.ndarray  # [N, 3]
    var: np.ndarray  # [N, 3] the tracker's marginal variances (x, y, θ)
    spans: np.ndarray  # [K, 2] each track's first and last stamp

    @property
    def n(self) -> int:
        return int(self.stamps.size)

    def track_rows(self, k: int) -> np.ndarray:
        """The row indices of track ``k`` in stamp order."""
        return np.flatnonzero(self.track == k)


def from_rows(rows: list[TrackRow], classes: set[str] | None = None) -> GroundTruth:
    """:class:`GroundTruth` from :func:`~gtsjax.io.gtd.read_gtd`'s rows, keeping ``classes`` (all if
    None)."""
    rows = [r for r in rows if classes is None or r.cls in classes]
    ids = np.array(sorted({r.track_id for r in rows}), np.int64)
    where = {int(t): k for k, t in enumerate(ids)}
    cls_of = {r.track_id: r.cls for r in rows}
    a = np.array([[r.stamp, where[r.track_id], r.x, r.y, r.theta, r.var_x, r.var_y, r.var_theta] for r in rows],
                 np.float64).reshape(-1, 8)
    order = np.lexsort((a[:, 1], a[:, 0]))
    a = a[order]
    track = a[:, 1].astype(np.int64)
    spans = np.zeros((ids.size, 2))
    if a.size:
        spans[:, 0] = np.full(ids.size, np.inf)
        spans[:, 1] = np.full(ids.size, -np.inf)
        np.minimum.at(spans[:, 0], track, a[:, 0])
        np.maximum.at(spans[:, 1], track, a[:, 0])
    return GroundTruth(a[:, 0], track, ids, [cls_of[int(t)] for t in ids], a[:, 2:5], a[:, 5:8], spans)


def profiles(gt: GroundTruth) -> tuple[np.ndarray, np.ndarray]:
    """Each row's track speed (m/s) and turn rate (rad/s) over :data:`PROFILE_S` centred on the row
    (NaN where the track does not cover the whole baseline): :func:`belief_profiles` of each track."""
    speed = np.full(gt.n, np.nan)
    turn = np.full(gt.n, np.nan)
    for k in range(gt.ids.size):
        idx = gt.track_rows(k)
        t = gt.stamps[idx]
        speed[idx], turn[idx] = belief_profiles(t, t, gt.poses[idx], TRACK_GAP_S)
    return speed, turn


def belief_profiles(t: np.ndarray, stamps: np.ndarray, poses: np.ndarray, max_gap: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A series' speed and turn rate at times ``t`` (a belief's on its own clock, a track's at its rows)."""
    h = PROFILE_S / 2.0
    a, ok_a = interpolate(t - h, stamps, poses, max_gap)
    b, ok_b = interpolate(t + h, stamps, poses, max_gap)
    ok = ok_a & ok_b
    speed = np.where(ok, np.hypot(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]) / PROFILE_S, np.nan)
    turn = np.where(ok, wrap(b[:, 2] - a[:, 2]) / PROFILE_S, np.nan)
    return speed, turn
