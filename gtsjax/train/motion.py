"""What training learns for stage g, tracking: each tracked class's top speed and turn rate (the
tracker's plausible-motion test, :class:`~gtsjax.core.g_track.TrackerParams`) from its labelled motion
(:func:`motion_limits`), else the user's or the tracker's defaults (:func:`tracker_limits`), and the
scanner's rate, which sets the tracker's confirmation and deletion counts (:func:`scan_rate`).
"""

from collections.abc import Sequence

import numpy as np

from ..core.g_track import DEFAULT_MAX_SPEED, DEFAULT_MAX_TURN_RATE
from ..core.geometry import wrap
from ..io.logs import ScanLog
from .config import TrainConfig


def motion_limits(logs: Sequence[ScanLog], classes: tuple[str, ...], *, quantile: float = 0.995, margin: float = 1.25,
                  min_run: int = 5, min_steps: int = 50) -> dict[str, dict]:
    """Each labelled class's maximum speed (m/s) and turn rate (rad/s) from its labelled motion,
    where there is some: the ``quantile`` of its speeds and turn rates between consecutive scans, times
    ``margin``, over runs of at least ``min_run`` consecutive steps in which it moved. A training
    grid's robot is carried from pose to pose between scans: those jumps are single steps between
    scans where it stood still, never a run, so they do not count as motion; nor does a step of a run
    three times faster than the run's median (the jump to where a walk starts). A class with fewer than
    ``min_steps`` such steps gets no entry (the tracker's default applies)."""
    speeds: dict[str, list] = {}
    turns: dict[str, list] = {}
    for log in logs:
        if log.n_scans < 2:
            continue
        dt = np.diff(log.stamps)
        for m, name in enumerate(log.truth_classes):
            p = log.truth_poses[:, m]
            ok = ~np.isnan(p[:-1, 0]) & ~np.isnan(p[1:, 0]) & (dt > 0)
            step = np.hypot(*(p[1:, :2] - p[:-1, :2]).T)
            turn = np.abs(wrap(p[1:, 2] - p[:-1, 2]))
            moving = ok & ((step > 1e-4) | (turn > 1e-4))
            # Runs of consecutive moving steps, at least min_run long.
            edges = np.diff(np.concatenate([[0], moving.astype(int), [0]]))
            starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
            for a, b in zip(starts, ends, strict=True):
                if b - a >= min_run:
                    # A jump into or out of a run (put down, then walking) is not motion either: steps
                    # over three times the run's median speed are left out.
                    v = step[a:b] / dt[a:b]
                    smooth = v <= 3.0 * max(np.median(v), 1e-3)
                    speeds.setdefault(str(name), []).append(v[smooth])
                    turns.setdefault(str(name), []).append((turn[a:b] / dt[a:b])[smooth])
    out = {}
    for name in classes:
        if name not in speeds:
            continue
        v, w = np.concatenate(speeds[name]), np.concatenate(turns[name])
        if v.size >= min_steps:
            out[name] = {"max_speed": round(float(margin * np.quantile(v, quantile)), 3),
                         "max_turn_rate": round(float(margin * np.quantile(w, quantile)), 3), "steps": int(v.size)}
    return out


def tracker_limits(logs: Sequence[ScanLog], classes: tuple[str, ...], mobiles: tuple[str, ...],
                   cfg: TrainConfig) -> tuple[list[float], list[float], dict[str, dict]]:
    """Every class's top speed and turn rate for :meth:`~gtsjax.core.g_track.TrackerParams.default`: the
    user's (``cfg.max_speed``, ``cfg.max_turn_rate``), else from labelled motion
    (:func:`motion_limits`), else the tracker's defaults; and, for the report, each tracked or set
    class's limits and where they came from."""
    learnt = motion_limits(logs, classes)
    motion = {}
    speed, turn = [], []
    for c in classes:
        if c in cfg.max_speed or c in cfg.max_turn_rate or c in learnt or c in mobiles:
            src = learnt.get(c, {})
            v = cfg.max_speed.get(c, src.get("max_speed", DEFAULT_MAX_SPEED))
            w = cfg.max_turn_rate.get(c, src.get("max_turn_rate", DEFAULT_MAX_TURN_RATE))
            how = "set" if c in cfg.max_speed else "labelled motion" if "max_speed" in src else "default"
            how_w = "set" if c in cfg.max_turn_rate else "labelled motion" if "max_turn_rate" in src else "default"
            motion[c] = {"max_speed": v, "max_speed_from": how, "max_turn_rate": w, "max_turn_rate_from": how_w,
                         "labelled_steps": src.get("steps", 0)}
        speed.append(motion.get(c, {}).get("max_speed", DEFAULT_MAX_SPEED))
        turn.append(motion.get(c, {}).get("max_turn_rate", DEFAULT_MAX_TURN_RATE))
    return speed, turn, motion


def scan_rate(logs: Sequence[ScanLog]) -> float:
    """Scans per second of the logs (the median interval; 10 Hz when they have none)."""
    dts = np.concatenate([np.diff(log.stamps) for log in logs if log.n_scans > 1] or [np.array([0.1])])
    dts = dts[dts > 0]
    return float(1.0 / np.median(dts)) if dts.size else 10.0
