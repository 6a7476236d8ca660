"""Where a run's scans go, for batch replay and the live loops alike: the GTD CSV (rows flushed per
scan), the ROS 2 bag, the view, the sensor-pose CSV, and what the run's summary counts (track ids per
class, the run's :class:`~gtsjax.drivers.diagnose.Tally`, the candidates and segments dropped).

A live loop writes a frame's rows (:meth:`Sink.write`) on the frame's path and the rest
(:meth:`Sink.show`, :meth:`Sink.count`) after its latency is taken; batch replay hands over a stack
of outputs at a time (:meth:`Sink.add`). One laser or several: ``names``, the lasers' names, puts
each scan's bag topic, view entities and sensor-pose row under its laser's name and adds the
cross-laser calibration check (:class:`Disagreement`) to the sensor-pose CSV.

``identity`` (``run --beliefs``): the live association of robots to tracks
(:class:`~gtsjax.grade.online.OnlineIdentity`); the CSV then has the ``robot`` column, each scan's
rows are named by :meth:`Sink.label` before they are written and sent, and :meth:`Sink.count` hands
them to the association, after the latency is taken.
"""

import csv
import dataclasses
from pathlib import Path

import jax
import numpy as np

from ..core.geometry import wrap
from ..io.gtd import GTDWriter, TrackRow, rows_from_output
from .diagnose import Tally

# Per-scan counters of the pipeline's output that a run's summary sums.
DROPPED = ("n_overflow", "n_too_long", "unlike", "off_envelope")


class Sink:
    """One run's outputs (see the module). ``bag``: a :class:`~gtsjax.io.bag_out.BagOut` or ``None``;
    ``view``: a :class:`~gtsjax.viewer.View` or ``None``; ``sensor_out``: the sensor-pose CSV's path
    (batch), written at :meth:`close`; ``identity``: see the module. Everything given is closed by :meth:`close`."""

    def __init__(self, model, out: Path, *, names: "tuple[str, ...] | None" = None, bag=None, view=None,
                 sensor_out: Path | None = None, csv_units: bool = False, identity=None):
        from ..io.bag_out import LASER

        self.classes = model.classes
        # The identities a model reads from tags (``Output.track_robot``), named in the ``robot`` column.
        self.tag_names = tuple(getattr(model, "tag_names", ()))
        self.writer = GTDWriter(out, units=csv_units, robot=identity is not None or bool(self.tag_names))
        self.identity = identity
        # The rows' names, on the frame's path; ``None`` without beliefs, so that path is as it was.
        self.label = identity.label if identity is not None else None
        self.bag, self.view, self.sensor_out = bag, view, sensor_out
        self.names = names
        self.bag_names = names or (LASER,)
        self.view_names = names or (None,)
        self.tally = Tally(model)
        self.track_ids: dict[str, set] = {}  # class name -> ids of reported tracks
        self.scans = np.zeros(len(self.bag_names), np.int64)  # per laser
        self.degraded = np.zeros(len(self.bag_names), np.int64)  # per laser: scans without a new transform
        self.dropped = dict.fromkeys(DROPPED, 0)
        self.sensor_rows: list[tuple] = []
        self._check = None
        if names is not None and sensor_out is not None:
            self._check = Disagreement()

    @property
    def wants_output(self) -> bool:
        """Whether :meth:`show` reads the step's output (a bag or a view to write)."""
        return self.bag is not None or self.view is not None

    @property
    def rows(self) -> int:
        return self.writer.rows

    # ---------------------------------------------------------------------------------- one scan
    def write(self, rows: "list[TrackRow]") -> None:
        """One scan's GTD rows, flushed (on a live frame's path)."""
        self.writer.write(rows)

    def show(self, k: int, stamp: float, rows, ranges, intensities, angle_min: float, angle_increment: float, out, *,
             valid=None, latency_ms: float | None = None, dropped: int | None = None) -> None:
        """Laser ``k``'s scan in the bag and the view: its ranges as it took them (metres; NaN, 0 or out
        of range: no return; ``valid``, where given, the beams that hold one), the step's output
        ``out`` for that scan (host arrays), its GTD rows."""
        if self.bag is not None:
            self.bag.write(stamp, ranges, intensities, rows, np.asarray(out.sensor_pose, np.float64),
                           laser=self.bag_names[k])
        if self.view is not None:
            shown = ranges if valid is None else np.where(valid, ranges, 0.0)
            self.view.scan(stamp, shown, angle_min, angle_increment, out, rows, latency_ms=latency_ms,
                           dropped=dropped, laser=self.view_names[k])

    def count(self, rows: "list[TrackRow]", k: int = 0, degraded: bool = False, stamp: float | None = None) -> None:
        """One scan of laser ``k``, stamped ``stamp``, in the run's counts: its reported track ids,
        whether its transform was degraded; and in the live association, where there is one."""
        if self.identity is not None and stamp is not None:
            self.identity.observe(stamp, rows)
        for row in rows:
            self.track_ids.setdefault(row.cls, set()).add(row.track_id)
        self.scans[k] += 1
        self.degraded[k] += int(degraded)

    def name_rows(self, rows: "list[TrackRow]", track_id, track_robot) -> "list[TrackRow]":
        """``rows`` with the identity each track reports from its tag (``robot``), where it reports one."""
        robot = {int(t): int(r) for t, r in zip(np.asarray(track_id), np.asarray(track_robot), strict=True)}
        return [dataclasses.replace(r, robot=self.tag_names[robot[r.track_id]]) if robot.get(r.track_id, -1) >= 0
                else r for r in rows]

    # ------------------------------------------------------------------------------------ a stack
    def add(self, stamps, out, *, lasers=None, frame=None) -> None:
        """Stacked outputs (NumPy, leading axis: scans) of scans stamped ``stamps``, in order.
        ``lasers``: each scan's laser index (several lasers); ``frame(i)``: scan ``i``'s ranges, intensities, first beam's
        angle and increment as its laser took it, and which beams hold a return, read only for the
        bag and the view."""
        n = len(stamps)
        lasers = np.zeros(n, np.int64) if lasers is None else np.asarray(lasers)
        degraded = np.asarray(out.degraded, bool)
        for i in range(n):
            stamp = float(stamps[i])
            rows = rows_from_output(stamp, out.track_id[i], out.track_class[i], out.track_pose[i], out.track_var[i],
                                    out.track_mask[i], self.classes, out.track_cov_xy[i])
            if self.tag_names and getattr(out, "track_robot", None) is not None:
                rows = self.name_rows(rows, out.track_id[i], out.track_robot[i])
            self.write(rows)
            k = int(lasers[i])
            if self.wants_output:
                ranges, intensities, angle_min, increment, valid = frame(i)
                self.show(k, stamp, rows, ranges, intensities, angle_min, increment,
                          jax.tree.map(lambda a, i=i: a[i], out), valid=valid)
            self.count(rows, k, bool(degraded[i]), stamp)
        if self.sensor_out is not None:
            self._sensor_rows(stamps, out, lasers)
        self.tally.add(out)
        for key in DROPPED:
            self.dropped[key] += int(np.sum(getattr(out, key)))

    def _sensor_rows(self, stamps, out, lasers) -> None:
        """Each scan's laser pose in O as its transform places it; with several lasers its laser's
        name and the calibration check (blank where no landmark was shared)."""
        tf, sp = out.transform, np.asarray(out.sensor_pose, np.float64)
        res, seen = np.asarray(out.landmark_residual, np.float64), np.asarray(out.landmark_seen, bool)
        for i in range(len(stamps)):
            pose = (f"{sp[i, 0]:.6f}", f"{sp[i, 1]:.6f}", f"{float(wrap(sp[i, 2])):.6f}", int(tf.degraded[i]),
                    int(tf.n_landmarks[i]))
            if self._check is None:
                self.sensor_rows.append((repr(float(stamps[i])), *pose))
                continue
            d = self._check.update(int(lasers[i]), res[i], seen[i])
            self.sensor_rows.append((repr(float(stamps[i])), self.names[lasers[i]], *pose,
                                     "" if np.isnan(d) else f"{d:.4f}"))

    # -------------------------------------------------------------------------------------- end
    def close(self) -> None:
        """Closes the CSV, the bag and the view; writes the sensor-pose CSV. Safe to call twice."""
        self.writer.close()
        for part in (self.bag, self.view):
            if part is not None:
                part.close()
        self.bag = self.view = None
        if self.sensor_out is not None:
            head = ("stamp", "x", "y", "theta", "degraded", "n_landmarks")
            if self.names is not None:
                head = ("stamp", "laser") + head[1:] + ("disagreement",)
            with open(self.sensor_out, "w", newline="") as f:
                w = csv.writer(f, lineterminator="\n")
                w.writerow(head)
                w.writerows(self.sensor_rows)
            self.sensor_out = None


class Disagreement:
    """The cross-laser calibration check, one scan at a time: each laser's map
    transformation places its detection of a landmark at the landmark's map position plus that
    laser's residual, so two lasers put the same landmark ``|r_k − r_j|`` apart. :meth:`update` gives
    the largest such distance over the landmarks a scan saw and another laser saw in its latest scan
    (NaN where none is shared). A tripod bumped, a laser whose transform went stale (degraded) after
    it moved, shows as a step. Used by batch replay (:class:`Sink`, the sensor-pose CSV) and the live
    loop alike (host arrays, a few landmarks: microseconds)."""

    def __init__(self):
        self.latest: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def update(self, k: int, residual, seen) -> float:
        residual, seen = np.asarray(residual, np.float64), np.asarray(seen, bool)
        worst = np.nan
        for j, (res_j, seen_j) in self.latest.items():
            if j == k:
                continue
            both = seen & seen_j
            if both.any():
                d = float(np.linalg.norm(residual[both] - res_j[both], axis=1).max())
                worst = d if np.isnan(worst) else max(worst, d)
        self.latest[k] = (residual, seen)
        return worst
