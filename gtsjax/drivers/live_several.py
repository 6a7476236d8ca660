"""The live loop for several lasers of one field: one reader thread per port (each a
:class:`~gtsjax.io.serial.Link`), frames merged by their host stamps into one track table
(:func:`~gtsjax.core.multi.step_several`), one GTD CSV, per-laser counters.

Merging: each laser's frames wait in its own queue; the loop takes the earliest stamped frame at the
queues' heads once no other laser can still send an earlier one: every laser has a frame waiting,
or the head is stamped before the earliest next frame of each laser without one (its last stamp
plus 0.9 of its period), or the head is ``hold_s`` old (a laser that stalled, or was unplugged,
holds the others back no longer than that). A frame whose stamp is earlier than
one already processed (its laser's link delivered it late) is still processed, with a prediction
step of zero, and counted (``out_of_order``): the tracker never steps back in time.
"""

import collections
import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..core.model import Model
from ..core.multi import init_several, miss_period, step_several
from ..errors import InputError
from ..sensors import SensorModel
from .live import LiveStep, Outputs, check_sensor
from .live_loop import LiveSession, run_loop
from .sink import Disagreement


@dataclasses.dataclass
class LaserStats:
    """One laser's share of a several-laser run."""

    frames: int = 0
    degraded: int = 0
    late: int = 0
    latencies_ms: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=2000))
    # The calibration check (:class:`~gtsjax.drivers.sink.Disagreement`) of this laser's scans that
    # shared a landmark with another laser's latest (metres), the largest, and how many times it stayed
    # above ``CALIBRATION_WARN_M`` for ``CALIBRATION_WARN_S`` (each such spell warned once).
    disagreement_m: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=2000))
    disagreement_max_m: float = 0.0
    moved_warnings: int = 0
    gone_warnings: int = 0  # times its link was gone longer than the reconnect timeout
    above_since: float | None = None  # stamp of the first scan of the present spell above the limit
    warned: bool = False  # this spell has been warned about

    def watch(self, stamp: float, d: float) -> bool:
        """Count one scan's calibration check ``d`` (metres; NaN: no landmark shared, not counted);
        True when this scan ends ``CALIBRATION_WARN_S`` of scans above ``CALIBRATION_WARN_M`` (once
        per spell: the next warning needs the check back within the limit first)."""
        if np.isnan(d):
            return False
        self.disagreement_m.append(d)
        self.disagreement_max_m = max(self.disagreement_max_m, d)
        if d <= CALIBRATION_WARN_M:
            self.above_since, self.warned = None, False
            return False
        if self.above_since is None:
            self.above_since = stamp
        if self.warned or stamp - self.above_since < CALIBRATION_WARN_S:
            return False
        self.warned = True
        self.moved_warnings += 1
        return True


# Two lasers' transforms that put a shared landmark further apart than this (metres) for this long
# (seconds) are out of calibration with each other: a tripod was bumped or a laser's transform went
# stale. With both lasers' transforms fresh the check stays within 1–3 cm on the simulated match.
CALIBRATION_WARN_M = 0.05
CALIBRATION_WARN_S = 1.0


def make_several_step(model: Model, sensor: SensorModel, state0, period: float | None = None,
                      filtered: bool = False) -> LiveStep:
    """``f(state, ranges_m, intensities, dt, k, span_dt) -> (state, output, packed)``: the live step
    (:class:`~gtsjax.drivers.live.LiveStep`: model closed over, frame, state and output as a few
    buffers) of :func:`~gtsjax.core.multi.step_several` from ``state0``'s layout; ``k`` is the
    laser. ``period``: the clock misses are counted on, with lasers of different rates
    (:func:`~gtsjax.core.multi.miss_period`). ``filtered``: see :class:`~gtsjax.drivers.live.LiveStep`."""
    def core(state, scan, extra):
        return step_several(model, state, scan, extra[0].astype(jnp.int32), extra[1], period)

    return LiveStep(model, sensor, state0=state0, core=core, extras=2, filtered=filtered)


def warm_up_several(model: "Model | tuple[Model, ...]", sensor: "SensorModel | tuple[SensorModel, ...]",
                    poses: np.ndarray, kinds: "tuple[int, ...] | None" = None, filtered: bool = False):
    """The steps, compiled before the lasers stream, and the initial state (each laser at its rough
    pose guess ``poses``, ``[lasers, 3]``; packed, one layout for every step): one step per model of
    ``model`` (every laser's, or one per scanner model, ``kinds`` each laser's index into them), for
    ``sensor``'s frames (one per model). ``filtered``: see :class:`~gtsjax.drivers.live.LiveStep`."""
    models = model if isinstance(model, tuple) else (model,)
    sensors = sensor if isinstance(sensor, tuple) else (sensor,)
    state0 = init_several(models, jnp.asarray(poses, jnp.float32), kinds)
    steps = []
    for m, sen in zip(models, sensors, strict=True):
        f = make_several_step(m, sen, state0, miss_period(models), filtered)
        jax.block_until_ready(f(f.initial_state(), np.zeros(sen.n_beams, np.float32), None, 0.0, 0, 0.0))
        steps.append(f)
    return tuple(steps), steps[0].initial_state()


class MergedFrames:
    """Several lasers' frames for the live loop (:func:`~gtsjax.drivers.live_loop.run_loop`), merged by
    stamp as the module says, each with its laser's step and index and the time since its laser's
    last frame; ``keep_warm``'s warm-up (``warm``) runs while no frame waits. Each frame counts in its
    laser's :class:`LaserStats` and is checked against the other lasers' calibration (its output read:
    ``needs_output``). A laser gone over ``reconnect_timeout`` is said once through ``warn``; every
    laser gone ends the run (``gone``)."""

    needs_output = True

    def __init__(self, links: dict, steps: list, period_ms: list, warm, *, hold: float,
                 reconnect_timeout: float | None, warn):
        self.names, self.links, self.steps = list(links), list(links.values()), steps
        self.period_ms, self.warm, self.hold = period_ms, warm, hold
        self.reconnect_timeout, self.warn = reconnect_timeout, warn
        self.per = [LaserStats() for _ in self.names]
        self.heads = [collections.deque() for _ in self.names]
        self.last_stamp, self.last_own = None, [None] * len(self.names)
        self.out_of_order = 0
        self.check = Disagreement()
        self.lost_checked, self.said_gone = time.monotonic(), set()
        self.gone = None

    def next(self, state):
        if self.reconnect_timeout is not None and time.monotonic() - self.lost_checked > 0.25 and self.all_gone():
            return None
        heads, last_own, got = self.heads, self.last_own, False
        for link, queue in zip(self.links, heads, strict=True):
            while (lf := link.get(timeout=0)) is not None:
                queue.append(lf)
                got = True
        ready = [k for k, queue in enumerate(heads) if queue]
        if not ready:
            if not got:
                self.idle(state)
            return None
        k = min(ready, key=lambda x: heads[x][0].stamp)
        lf = heads[k][0]
        # A laser with no frame waiting cannot send one stamped before its last plus most of a
        # period: the head goes now if it is earlier than that for every such laser, else it
        # waits for them, at most ``hold`` (a stalled or unplugged laser holds the rest no longer).
        waiting = [m for m, queue in enumerate(heads) if not queue]
        if waiting and time.time() - lf.stamp < self.hold and not all(
                last_own[m] is not None and lf.stamp <= last_own[m] + 0.9 * self.period_ms[m] / 1000.0
                for m in waiting):
            time.sleep(0.0005)
            return None
        heads[k].popleft()
        dt = 0.0 if self.last_stamp is None else lf.stamp - self.last_stamp
        if dt < 0:
            self.out_of_order += 1
            dt = 0.0
        self.last_stamp = lf.stamp if self.last_stamp is None else max(self.last_stamp, lf.stamp)
        span = 0.0 if last_own[k] is None else max(lf.stamp - last_own[k], 0.0)
        last_own[k] = lf.stamp
        return lf, k, self.steps[k], (dt, k, span)

    def idle(self, state) -> None:
        """No frame waits: a laser's warm-up if its next frame is due soon, else a millisecond's sleep."""
        warm = self.warm
        if warm is not None:
            now = time.perf_counter()
            soon = [m for m, due in enumerate(warm.due) if due is not None and due - warm.lead <= now < due]
            if soon:
                warm.warm(soon[0], self.steps[soon[0]], state)
                return
        time.sleep(0.001)

    def all_gone(self) -> bool:
        """Each laser gone over the reconnect timeout said once (again once it has come back); True, and
        ``gone`` set, when every laser is."""
        self.lost_checked = time.monotonic()
        names, links, said_gone = self.names, self.links, self.said_gone
        lost = [link.lost_for() if hasattr(link, "lost_for") else 0.0 for link in links]
        said_gone &= {k for k in range(len(names)) if lost[k] > 0}  # back: it may be said again
        for k, n in enumerate(names):
            if lost[k] > self.reconnect_timeout and k not in said_gone:
                said_gone.add(k)
                self.per[k].gone_warnings += 1
                if self.warn is not None and len(said_gone) < len(names):
                    self.warn(f"laser {n} ({getattr(links[k], 'port', 'sensor')}): gone for {lost[k]:.0f} s "
                              f"({getattr(links[k], 'last_error', None) or 'no frames'}); the other lasers "
                              "go on, and it rejoins if it comes back")
        if len(said_gone) < len(names):
            return False
        self.gone = InputError(", ".join(str(getattr(links[k], "port", n)) for k, n in enumerate(names)),
                               f"every laser has been gone for over {self.reconnect_timeout:g} s and none came "
                               "back (--reconnect-timeout waits longer)")
        return True

    def count(self, k, lf, o, table, lat: float, degraded: bool) -> None:
        p = self.per[k]
        p.frames += 1
        p.degraded += int(degraded)
        p.late += int(lat > self.period_ms[k])
        p.latencies_ms.append(lat)
        d = self.check.update(k, o.landmark_residual, o.landmark_seen)
        if p.watch(lf.stamp, d) and self.warn is not None:
            self.warn(f"laser {self.names[k]}: its map transformation and another laser's put landmarks both see "
                      f"{d * 100:.0f} cm apart for {CALIBRATION_WARN_S:g} s: a tripod moved? (check the "
                      "site's sensor poses, or restart once it stands still)")


def run_live_several(links: "dict[str, object]", model: "Model | tuple[Model, ...]", poses: np.ndarray, out: Path, *,
                     record: "dict[str, Path] | None" = None, outputs: Outputs | None = None,
                     duration: float | None = None, stop=None, on_scan=None, with_intensity: bool = False,
                     compiled=None, max_frames: int | None = None, hold_s: float | None = None, warn=None,
                     kinds: "tuple[int, ...] | None" = None, keep_warm: bool = True,
                     reconnect_timeout: float | None = None, out_bag: Path | None = None, view=None,
                     identity=None, smooth_lag: float | None = None, smoothed_out: Path | None = None):
    """Track from started links (one per laser, ``poses`` their rough pose guesses in the same order)
    until ``duration``, ``max_frames`` frames (all lasers together), ``stop`` or Ctrl-C. ``model``:
    every laser's, or one per scanner model with ``kinds`` (each laser's index into them; see
    :func:`~gtsjax.drivers.several.models_for_lasers`). Returns the
    run's :class:`~gtsjax.drivers.live.LiveStats`, the lasers' :class:`LaserStats` and the count of
    frames processed out of stamp order. ``warn(message)`` is called with a line when two lasers' map
    transformations disagree about the landmarks both see (:data:`CALIBRATION_WARN_M` for
    :data:`CALIBRATION_WARN_S`): a tripod bumped. ``keep_warm``: as :func:`~gtsjax.drivers.live.run_live`'s,
    per laser: shortly before a laser's next frame is due, while no frame waits, the step of its
    scanner runs once on its last frame and is thrown away, and so does the host's part
    (:func:`~gtsjax.drivers.live.warm_host`); once per frame of each laser. ``reconnect_timeout``: a
    laser whose link has been reconnecting this long is said once through ``warn`` (the others go on,
    and it rejoins if it comes back); when every laser has been gone this long the run ends with one
    line (:class:`InputError`) after what was written is closed, as :func:`~gtsjax.drivers.live.run_live`'s.
    ``out_bag``: also a ROS 2 bag, each laser's frames on its own topic and frame
    (:mod:`gtsjax.io.bag_out`); ``view``: a :class:`~gtsjax.viewer.View` shown each frame, each
    laser's under its name (closed at the end); both written after the frame's latency is taken.
    ``identity``: as :func:`~gtsjax.drivers.live.run_live`'s, the robots' names from their beliefs.
    ``smooth_lag``, ``smoothed_out``: as :func:`~gtsjax.drivers.live.run_live`'s, the lag in scans of
    the merged sequence (the lasers' rates summed: every laser's scan is one step of the one track table).

    The loop is :func:`~gtsjax.drivers.live_loop.run_loop`'s, with the lasers' merged frames
    (:class:`MergedFrames`)."""
    names = list(links)
    sensors = [links[n].model for n in names]
    models = model if isinstance(model, tuple) else (model,)
    kinds = tuple(kinds) if kinds is not None else (0,) * len(names)
    for n, sen, i in zip(names, sensors, kinds, strict=True):
        check_sensor(models[i], sen, f"{n} ({getattr(links[n], 'port', 'sensor')})", intensity=with_intensity)
    first_of = [kinds.index(i) for i in range(len(models))]  # a laser of each model: its frames' geometry
    steps, state = compiled if compiled is not None else warm_up_several(
        models, tuple(sensors[k] for k in first_of), poses, kinds, filtered=smooth_lag is not None)
    smooth = None
    if smooth_lag is not None:
        from .fixed_lag import lag_scans, smoothed_path

        if not all(f.filtered for f in steps):
            raise ValueError("run_live_several with smooth_lag needs warm_up_several(..., filtered=True)'s steps")
        smooth = (lag_scans(smooth_lag, sum(s.rate_hz for s in sensors)), smoothed_out or smoothed_path(out))
    session = LiveSession(links, models[0], out, named=True, record=record, outputs=outputs,
                          with_intensity=with_intensity, out_bag=out_bag, view=view, on_scan=on_scan,
                          keep_warm=keep_warm, duration=duration, stop=stop, max_frames=max_frames,
                          identity=identity, smooth=smooth)
    hold = hold_s if hold_s is not None else 1.5 * max(s.period for s in sensors)
    frames = MergedFrames(links, [steps[i] for i in kinds], session.period_ms, session.warm, hold=hold,
                          reconnect_timeout=reconnect_timeout, warn=warn)
    stats = session.stats
    failed = run_loop(session, frames, state)
    if failed is not None:
        raise InputError(failed.where, f"{failed.problem}; stopped after {stats.frames} frames")
    if frames.gone is not None:
        raise InputError(frames.gone.where, f"{frames.gone.problem}; stopped after {stats.frames} frames, their rows "
                                            f"kept in {out}")
    return stats, dict(zip(names, frames.per, strict=True)), frames.out_of_order
