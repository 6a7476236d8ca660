"""Fixed-lag smoothing of a live run's ground truth (``run --smooth-lag S``, issue 42): beside the live
GTD CSV, a second one whose row of scan ``t`` is written once scan ``t + L`` has been processed
(``L = round(S × scan rate)``, at least 1) and carries the pose, variances and x–y covariance
smoothed over the scans up to ``t + L``.

**What is smoothed.** The live step hands the track table's filtered state after each scan (each slot's
mean, covariance and main heading hypothesis: :func:`pack_filtered`) to the host in the same transfer
as the scan's rows, as extra columns of its packed table. :class:`FixedLag` keeps the last ``L + 1``
scans' states in a window ``[L + 1, M]`` of fixed shape and, after each scan, runs the RTS smoother of
:mod:`gtsjax.core.smooth` backwards over it from the newest scan (:class:`WindowSmoother`, one jitted
call per scan): the smoothed state at the window's oldest scan is the fixed-interval smoother's over
the scans up to ``t + L`` evaluated at ``t``, since the backward pass from ``t + L`` reads nothing
older than ``t`` to reach it. Lives are cut and the prediction widened where the forward pass switched
side or reset part of a state, as :func:`~gtsjax.drivers.smoothing.cuts` and
:func:`~gtsjax.drivers.smoothing.resets` say for a replay (each scan's against the scan before, when it
enters the window). Unlike ``replay --smooth``, the sides are not re-decided
(:mod:`gtsjax.core.smooth_sides` weighs a ``heading_memory`` of evidence after each scan, which a
lag of a second or less does not hold).

**The rows.** Scan ``t``'s smoothed rows are its live rows (stamp, id, class, and the robot's name
with ``--beliefs``) with each track's pose, variances and ``cov_xy`` replaced by its slot's smoothed
values: the same rows as the live CSV, in the same format, each written (flushed) ``L`` scans later.
At the end of a run (:meth:`FixedLag.close`) the scans still in the window are smoothed with what
there is and written.
"""

import dataclasses
import time
import types
from collections import deque
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..core.g_types import NX, TrackerParams, TrackerState
from ..core.smooth import smooth_tracks
from ..io.gtd import COLUMN, PACKED, GTDWriter, TrackRow, wrap_angle
from .smoothing import cuts, resets

#: The filtered block's columns per slot after the packed table's (:data:`~gtsjax.io.gtd.PACKED`):
#: the mean, the covariance row by row, the main hypothesis.
MEAN, COV, MAIN = slice(0, NX), slice(NX, NX + NX * NX), NX + NX * NX
FILTERED_WIDTH = MAIN + 1
# The window's columns per slot: the filtered block, then live, cut and the widening of the prediction.
_LIVE, _CUT = FILTERED_WIDTH, FILTERED_WIDTH + 1
_EXTRA = slice(FILTERED_WIDTH + 2, FILTERED_WIDTH + 2 + NX)
_WIDTH = _EXTRA.stop
_ID, _REP, _LIVE_COL, _CLS_COL = COLUMN["track_id"], COLUMN["reported"], COLUMN["live"], COLUMN["class"]


def pack_filtered(tracker: TrackerState) -> Float[Array, "tracks filtered"]:
    """The track table's filtered state as one float32 block, a row per slot (:data:`MEAN`,
    :data:`COV`, :data:`MAIN`; the hypothesis index is exact in float32)."""
    m = tracker.mean.shape[0]
    f32 = jnp.float32
    return jnp.concatenate([tracker.mean.astype(f32), tracker.cov.reshape(m, NX * NX).astype(f32),
                            tracker.main[:, None].astype(f32)], axis=1)


def lag_scans(seconds: float, rate_hz: float) -> int:
    """``L``: the lag in scans, ``seconds`` at ``rate_hz`` scans a second, at least 1."""
    return max(1, int(round(seconds * rate_hz)))


def smoothed_path(out: Path) -> Path:
    """Where ``run --out GTD.csv --smooth-lag S`` writes its smoothed rows: ``<stem>-smoothed.csv``
    beside ``GTD.csv``."""
    out = Path(out)
    return out.with_name(f"{out.stem}-smoothed.csv")


class WindowSmoother:
    """The RTS smoother over a window of ``L + 1`` scans and ``M`` slots, jitted once with the tracker's
    parameters closed over (constants of the program, as :class:`~gtsjax.drivers.live.LiveStep` closes
    over the model): ``f(window, dt) -> [L + 1, M, 7]``, each scan's and slot's smoothed ``x, y, θ``,
    variances of ``x, y, θ`` and x–y covariance. ``window[i, m]``: the filtered block, live, cut and
    the prediction's widening (columns as :class:`FixedLag` lays them out); ``dt[i]``: the time from
    scan ``i − 1`` to ``i`` (``dt[0]`` unused). ``parallel``: the associative form (the sequential one,
    ``L + 1`` steps one after another, is the quicker for a short window on a CPU)."""

    def __init__(self, params: TrackerParams, scans: int, tracks: int, parallel: bool = False):
        self.shape = (scans, tracks, _WIDTH)

        @jax.jit
        def smooth(window, dt):
            mean = window[..., MEAN]
            cov = window[..., COV].reshape(scans, tracks, NX, NX)
            live, cut = window[..., _LIVE] > 0.5, window[..., _CUT] > 0.5
            ms, ps = smooth_tracks(mean, cov, dt, live, params, parallel=parallel, cut=cut, extra=window[..., _EXTRA])
            var = jnp.diagonal(ps, axis1=-2, axis2=-1)[..., :3]
            return jnp.concatenate([ms[..., :3], var, ps[..., 0, 1][..., None]], axis=-1)

        self.jitted = smooth

    def __call__(self, window: np.ndarray, dt: np.ndarray) -> np.ndarray:
        return np.asarray(self.jitted(window, dt))


@dataclasses.dataclass
class LagStats:
    """What the smoothing added per scan, on the host after the scan's live rows were written: the
    window's update, the smoother's call and the smoothed rows written (ms, recent 2 000 scans)."""

    lag: int
    path: "Path | None"
    rows: int = 0
    scans: int = 0
    ms: deque = dataclasses.field(default_factory=lambda: deque(maxlen=2000))

    def quantiles(self) -> tuple[float, float]:
        """Median and p99 of the recent per-scan times, ms."""
        if not self.ms:
            return float("nan"), float("nan")
        a = np.asarray(self.ms)
        return float(np.median(a)), float(np.percentile(a, 99))

    def as_dict(self) -> dict:
        med, p99 = self.quantiles()
        return {"lag_scans": self.lag, "out": str(self.path), "rows": self.rows, "ms_median": med, "ms_p99": p99}


class FixedLag:
    """The smoothed CSV of a live run (module docstring). :meth:`push` after each scan, with its packed
    table as the live step returned it (the filtered block after the :data:`PACKED` columns; its last
    row the status), its live rows and the ``dt`` the step was given; :meth:`close` at the end. The
    window's smoother is compiled here, before the first scan. ``writer``: where the rows go in place
    of a :class:`~gtsjax.io.gtd.GTDWriter` of ``out`` (anything with ``write(rows)`` and ``close()``)."""

    def __init__(self, params: TrackerParams, lag: int, tracks: int, out: "Path | None", *, units: bool = False,
                 robot: bool = False, parallel: bool = False, writer: GTDWriter | None = None):
        if lag < 1:
            raise ValueError(f"a lag of {lag} scans: at least 1")
        self.params, self.lag, self.tracks = params, lag, tracks
        # what ``resets`` reads of the parameters, read once: a per-scan call reads no device array
        self._reset_params = types.SimpleNamespace(omega_var0=float(np.asarray(params.omega_var0)))
        self.smoother = WindowSmoother(params, lag + 1, tracks, parallel)
        self.window = np.zeros(self.smoother.shape, np.float32)
        self.dt = np.zeros(lag + 1, np.float32)
        self.classes = np.zeros((lag + 1, tracks), np.int32)  # each slot's class per scan of the window
        self.pending: deque = deque()  # the scans not yet written: (scan, rows, slot of each row's track id)
        self.newest = -1  # the window's newest scan, counted from the first
        self.prev = None  # the last scan's (live, ids, heading, cov, main), for its successor's cut and widening
        self.stats = LagStats(lag, None if out is None else Path(out))
        self.writer = writer if writer is not None else GTDWriter(out, units=units, robot=robot)
        self.smoother(self.window, self.dt)  # compiled now, not on the first scan's path

    def push(self, packed: np.ndarray, rows: "list[TrackRow]", dt: float) -> None:
        """One scan in; the row of the scan ``L`` before, smoothed, written."""
        t0 = time.perf_counter()
        n = len(PACKED)
        table = packed[:-1]
        filt = table[:, n:n + FILTERED_WIDTH]
        live, ids = table[:, _LIVE_COL] > 0.5, table[:, _ID].astype(np.int64)
        mean, cov = filt[:, MEAN], filt[:, COV].reshape(-1, NX, NX)
        main = filt[:, MAIN].astype(np.int64)
        cut, extra = np.zeros(self.tracks, bool), np.zeros((self.tracks, NX), np.float32)
        if self.prev is not None:
            p_live, p_ids, p_heading, p_cov, p_main = self.prev
            two = lambda a, b: np.stack([a, b])  # noqa: E731
            cut = cuts(two(p_live, live), two(p_ids, ids), two(p_heading, mean[:, 2]))[1]
            extra = resets(two(p_live, live), two(p_ids, ids), two(p_cov, cov), two(p_main, main),
                           self._reset_params)[1]
        self.prev = (live, ids, mean[:, 2], cov, main)
        w = self.window
        w[:-1] = w[1:]
        self.dt[:-1] = self.dt[1:]
        self.classes[:-1] = self.classes[1:]
        self.classes[-1] = table[:, _CLS_COL].astype(np.int32)
        w[-1, :, :FILTERED_WIDTH] = filt
        w[-1, :, _LIVE], w[-1, :, _CUT], w[-1, :, _EXTRA] = live, cut, extra
        self.dt[-1] = dt
        self.newest = self.stats.scans  # the window's newest scan, counted from the first
        self.stats.scans += 1
        reported = table[:, _REP] > 0.5
        self.pending.append((self.newest, rows,
                             dict(zip(ids[reported].tolist(), np.flatnonzero(reported).tolist(), strict=True))))
        if len(self.pending) > self.lag:
            smoothed = self.smoother(w, self.dt)
            self._write(smoothed, *self.pending.popleft())
        self.stats.ms.append((time.perf_counter() - t0) * 1e3)

    def flush(self) -> None:
        """The scans still in the window smoothed with what there is (the newest's state as filtered)
        and written, in order."""
        if not self.pending:
            return
        smoothed = self.smoother(self.window, self.dt)
        while self.pending:
            self._write(smoothed, *self.pending.popleft())

    def close(self) -> None:
        """The window flushed and the CSV closed (safe to call twice; closed even if the flush fails)."""
        try:
            self.flush()
        finally:
            self.writer.close()

    def _write(self, smoothed: np.ndarray, scan: int, rows: "list[TrackRow]", slot_of: dict) -> None:
        """Scan ``scan``'s rows (counted from the first) with its slots' smoothed values in the window,
        written and flushed."""
        i = self.lag - (self.newest - scan)  # its place in the window, the newest scan last
        if not rows or not 0 <= i <= self.lag:
            return
        s = smoothed[i]
        if self.params.pose_offset is not None or self.params.var_floor is not None:  # as the live row's
            s = s.copy()
            s[:, :3] = np.asarray(self.params.off(jnp.asarray(self.classes[i]), jnp.asarray(s[:, :3])))
            s[:, 3:6] = np.asarray(self.params.widened(jnp.asarray(self.classes[i]), jnp.asarray(s[:, 3:6])))
        s = s.tolist()
        out = []
        for r in rows:
            x, y, th, vx, vy, vth, cxy = s[slot_of[r.track_id]]
            out.append(dataclasses.replace(r, x=x, y=y, theta=wrap_angle(th), var_x=vx, var_y=vy, var_theta=vth,
                                           cov_xy=cxy))
        self.writer.write(out)
        self.stats.rows += len(out)
