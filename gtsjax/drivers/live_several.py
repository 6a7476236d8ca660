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
from ..io.gtd import GTDWriter
from ..sensors import SensorModel
from .live import LiveStats, LiveStep, Outputs, check_sensor, decoder_sample, rows_from_packed, warm_host, warm_up_lead
from .several import Disagreement


@dataclasses.dataclass
class LaserStats:
    """One laser's share of a several-laser run."""

    frames: int = 0
    degraded: int = 0
    late: int = 0
    latencies_ms: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=2000))
    # The calibration check (:class:`~gtsjax.drivers.several.Disagreement`) of this laser's scans that
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


def make_several_step(model: Model, sensor: SensorModel, state0, period: float | None = None) -> LiveStep:
    """``f(state, ranges_m, intensities, dt, k, span_dt) -> (state, output, packed)``: the live step
    (:class:`~gtsjax.drivers.live.LiveStep`: model closed over, frame, state and output as a few
    buffers) of :func:`~gtsjax.core.multi.step_several` from ``state0``'s layout; ``k`` is the
    laser. ``period``: the clock misses are counted on, with lasers of different rates
    (:func:`~gtsjax.core.multi.miss_period`)."""
    def core(state, scan, extra):
        return step_several(model, state, scan, extra[0].astype(jnp.int32), extra[1], period)

    return LiveStep(model, sensor, state0=state0, core=core, extras=2)


def warm_up_several(model: "Model | tuple[Model, ...]", sensor: "SensorModel | tuple[SensorModel, ...]",
                    poses: np.ndarray, kinds: "tuple[int, ...] | None" = None):
    """The steps, compiled before the lasers stream, and the initial state (each laser at its rough
    pose guess ``poses``, ``[lasers, 3]``; packed, one layout for every step): one step per model of
    ``model`` (every laser's, or one per scanner model, ``kinds`` each laser's index into them), for
    ``sensor``'s frames (one per model)."""
    models = model if isinstance(model, tuple) else (model,)
    sensors = sensor if isinstance(sensor, tuple) else (sensor,)
    state0 = init_several(models, jnp.asarray(poses, jnp.float32), kinds)
    steps = []
    for m, sen in zip(models, sensors, strict=True):
        f = make_several_step(m, sen, state0, miss_period(models))
        jax.block_until_ready(f(f.initial_state(), np.zeros(sen.n_beams, np.float32), None, 0.0, 0, 0.0))
        steps.append(f)
    return tuple(steps), steps[0].initial_state()


def run_live_several(links: "dict[str, object]", model: "Model | tuple[Model, ...]", poses: np.ndarray, out: Path, *,
                     record: "dict[str, Path] | None" = None, outputs: Outputs | None = None,
                     duration: float | None = None, stop=None, on_scan=None, with_intensity: bool = False,
                     compiled=None, max_frames: int | None = None, hold_s: float | None = None, warn=None,
                     kinds: "tuple[int, ...] | None" = None, keep_warm: bool = True,
                     reconnect_timeout: float | None = None, out_bag: Path | None = None, view=None):
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
    laser's under its name (closed at the end); both written after the frame's latency is taken."""
    from ..io.bag_out import BagOut, LaserGeometry
    from ..io.record import Recorder

    names = list(links)
    sensors = [links[n].model for n in names]
    models = model if isinstance(model, tuple) else (model,)
    kinds = tuple(kinds) if kinds is not None else (0,) * len(names)
    for n, sen, i in zip(names, sensors, kinds, strict=True):
        check_sensor(models[i], sen, f"{n} ({getattr(links[n], 'port', 'sensor')})", intensity=with_intensity)
    first_of = [kinds.index(i) for i in range(len(models))]  # a laser of each model: its frames' geometry
    steps, state = compiled if compiled is not None else warm_up_several(
        models, tuple(sensors[k] for k in first_of), poses, kinds)
    model = models[0]
    from .diagnose import Tally

    stats, per = LiveStats(tally=Tally(model)), {n: LaserStats() for n in names}
    for n in names:  # frames that queued up while compiling are stale
        while links[n].get(timeout=0) is not None:
            stats.stale += 1
    hold = hold_s if hold_s is not None else 1.5 * max(s.period for s in sensors)
    period_ms = {n: s.period * 1000.0 for n, s in zip(names, sensors, strict=True)}
    outputs = outputs or Outputs()
    bag = BagOut(out_bag, {n: LaserGeometry.of_sensor(s) for n, s in zip(names, sensors, strict=True)}
                 ) if out_bag is not None else None
    recorders = ({n: Recorder(p, model=links[n].model, intensities=with_intensity and links[n].model.has_intensity)
                  for n, p in record.items()} if record else {})
    heads: dict[str, collections.deque] = {n: collections.deque() for n in names}
    last_stamp, last_own = None, dict.fromkeys(names)
    out_of_order = 0
    check = Disagreement()
    # keep_warm: each laser's next frame is due at its last one's arrival plus its period; a warm-up
    # runs ``lead`` before it (run_live's, for the shortest period).
    due, last, step_ms = dict.fromkeys(names), dict.fromkeys(names), collections.deque(maxlen=50)
    min_period = min(s.period for s in sensors)
    samples = {n: decoder_sample(links[n]) for n in names} if keep_warm else {}
    lead = 0.0
    t_end = None if duration is None else time.monotonic() + duration
    failed = gone = None
    lost_checked, said_gone = time.monotonic(), set()
    try:
        with GTDWriter(out, units=outputs.csv_units) as writer:
            while (not (stop is not None and stop.is_set()) and (t_end is None or time.monotonic() < t_end)
                   and (max_frames is None or stats.frames < max_frames)):
                if reconnect_timeout is not None and time.monotonic() - lost_checked > 0.25:
                    lost_checked = time.monotonic()
                    lost = {n: links[n].lost_for() if hasattr(links[n], "lost_for") else 0.0 for n in names}
                    said_gone &= {n for n in names if lost[n] > 0}  # back: it may be said again
                    for n in names:
                        if lost[n] > reconnect_timeout and n not in said_gone:
                            said_gone.add(n)
                            per[n].gone_warnings += 1
                            if warn is not None and len(said_gone) < len(names):
                                warn(f"laser {n} ({getattr(links[n], 'port', 'sensor')}): gone for {lost[n]:.0f} s "
                                     f"({getattr(links[n], 'last_error', None) or 'no frames'}); the other lasers "
                                     "go on, and it rejoins if it comes back")
                    if len(said_gone) == len(names):
                        gone = InputError(", ".join(str(getattr(links[n], "port", n)) for n in names),
                                          f"every laser has been gone for over {reconnect_timeout:g} s and none came "
                                          "back (--reconnect-timeout waits longer)")
                        break
                got = False
                for n in names:
                    while (lf := links[n].get(timeout=0)) is not None:
                        heads[n].append(lf)
                        got = True
                ready = [n for n in names if heads[n]]
                if not ready:
                    if not got:
                        now = time.perf_counter()
                        soon = [m for m in names if due[m] is not None and due[m] - lead <= now < due[m]]
                        if soon:
                            m = soon[0]
                            due[m] = None  # one warm-up per frame: a laser that stalls is not stepped for
                            step_m = steps[kinds[names.index(m)]]
                            step_m.warm(state)
                            warm_host(step_m, last[m], model.classes, samples[m])
                            stats.warm_ups += 1
                        else:
                            time.sleep(0.001)
                    continue
                n = min(ready, key=lambda x: heads[x][0].stamp)
                lf = heads[n][0]
                # A laser with no frame waiting cannot send one stamped before its last plus most of a
                # period: the head goes now if it is earlier than that for every such laser, else it
                # waits for them, at most ``hold`` (a stalled or unplugged laser holds the rest no longer).
                waiting = [m for m in names if not heads[m]]
                if waiting and time.time() - lf.stamp < hold and not all(
                        last_own[m] is not None and lf.stamp <= last_own[m] + 0.9 * period_ms[m] / 1000.0
                        for m in waiting):
                    time.sleep(0.0005)
                    continue
                heads[n].popleft()
                k = names.index(n)
                dt = 0.0 if last_stamp is None else lf.stamp - last_stamp
                if dt < 0:
                    out_of_order += 1
                    dt = 0.0
                last_stamp = lf.stamp if last_stamp is None else max(last_stamp, lf.stamp)
                span = 0.0 if last_own[n] is None else max(lf.stamp - last_own[n], 0.0)
                last_own[n] = lf.stamp
                t_step = time.perf_counter()
                state, o, packed = steps[kinds[k]](state, lf.ranges_m, lf.intensities, dt, k, span)
                table = np.asarray(packed).tolist()
                last[n] = (lf, table)
                rows = rows_from_packed(lf.stamp, table, model.classes)
                writer.write(rows)
                degraded = table[-1][0] > 0.5
                outputs.send(rows, lf.stamp, degraded=degraded, laser=n)
                t_done = time.perf_counter()
                lat = (t_done - lf.recv_perf) * 1000.0
                if keep_warm:
                    step_ms.append(t_done - t_step)
                    lead = warm_up_lead(step_ms, min_period)
                    due[n] = lf.recv_perf + period_ms[n] / 1000.0
                if n in recorders:
                    recorders[n].append_frame(lf)
                o = steps[kinds[k]].output(o)
                stats.count(rows, lat, degraded, period_ms[n])
                stats.tally.add_packed(table)
                late = lat > period_ms[n]
                p = per[n]
                p.frames += 1
                p.degraded += int(degraded)
                p.late += int(late)
                p.latencies_ms.append(lat)
                if bag is not None:
                    bag.write(lf.stamp, lf.ranges_m, lf.intensities, rows, np.asarray(o.sensor_pose, np.float64),
                              laser=n)
                if view is not None:
                    view.scan(lf.stamp, lf.ranges_m, sensors[k].angle_min, sensors[k].angle_increment, o, rows,
                              latency_ms=lat, dropped=getattr(getattr(links[n], "stats", None), "dropped", None),
                              laser=n)
                d = check.update(k, o.landmark_residual, o.landmark_seen)
                if p.watch(lf.stamp, d) and warn is not None:
                    warn(f"laser {n}: its map transformation and another laser's put landmarks both see "
                         f"{d * 100:.0f} cm apart for {CALIBRATION_WARN_S:g} s: a tripod moved? (check the "
                         "site's sensor poses, or restart once it stands still)")
                if on_scan is not None:
                    on_scan(stats, o, lf.stamp, n)
    except KeyboardInterrupt:
        pass
    except InputError as err:  # a write failed (a full disk): stop; what is written stays
        failed = err
    finally:
        outputs.close()
        for link in links.values():  # the lasers stop streaming with the loop (see ``run_live``)
            if hasattr(link, "stop"):
                link.stop()
        if bag is not None:
            bag.close()
        if view is not None:
            view.close()
        for rec in recorders.values():
            rec.close(write_log=failed is None)
    if failed is not None:
        raise InputError(failed.where, f"{failed.problem}; stopped after {stats.frames} frames")
    if gone is not None:
        raise InputError(gone.where, f"{gone.problem}; stopped after {stats.frames} frames, their rows kept in {out}")
    return stats, per, out_of_order
