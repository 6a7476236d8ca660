"""The live loops' skeleton, written once for one laser (:func:`~gtsjax.drivers.live.run_live`) and for
several (:func:`~gtsjax.drivers.live_several.run_live_several`): frames in order from the links, each
through its step, its rows written and sent, its latency taken; then, off the frame's path, its
recording, bag, view and counters and the caller's ``on_scan``; until ``stop``, ``duration`` or
``max_frames``; and what was opened closed in a ``finally``.

What differs between one laser and several is where the frames come from, a :class:`Frames`: how the
next frame is waited for (one link read as it delivers; several links' queues merged by stamp), when
a link that stays gone ends the run, and what each frame adds to the lasers' own counters.
:class:`KeepWarm` is ``keep_warm``'s schedule for both; :class:`LiveSession`, what a run writes, shows
and counts besides the frame's path.
"""

import time
from collections import deque
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.gtd import PACKED, STATUS_AT
from .live import LiveStats, Outputs, decoder_sample, rows_from_packed, warm_host, warm_up_lead
from .sink import Sink

# Where the packed table's status row (its last) holds what the loop reads.
DEGRADED, UNLIKE, OFF_ENVELOPE = (STATUS_AT[f] for f in ("degraded", "unlike", "off_envelope"))
N_PACKED = len(PACKED)  # the rows' columns; with ``run --smooth-lag`` the filtered states follow


class Frames:
    """Where the skeleton's frames come from. ``next(state)``: the next frame in order as
    ``(frame, k, step, args)`` (a :class:`~gtsjax.io.serial.LinkFrame`, its laser's index, the step
    that takes it and what that step takes after the intensities), or ``None`` when none is ready yet
    (``gone`` set: a link gone too long ends the run). ``count(k, frame, output, table, latency_ms,
    degraded)``: the frame's share of the lasers' own counters, after the run's. ``needs_output``:
    ``count`` reads the step's output, which is then unpacked on the host each frame."""

    needs_output = False
    gone: InputError | None = None

    def next(self, state):
        raise NotImplementedError

    def count(self, k, lf, o, table, lat: float, degraded: bool) -> None:
        raise NotImplementedError


class KeepWarm:
    """``keep_warm``'s schedule (see :func:`~gtsjax.drivers.live.run_live`): each laser's next frame is
    due at its last one's arrival plus its period, and a warm-up runs ``lead`` before it, ``lead`` from
    recent steps' times (:func:`~gtsjax.drivers.live.warm_up_lead`, for the shortest period); a warm-up
    reruns the laser's step on its last frame and the host's part of the path
    (:func:`~gtsjax.drivers.live.warm_host`), once per frame: a laser that stalls is not stepped for."""

    def __init__(self, links: list, stats: LiveStats, classes, robot_names: "tuple[str, ...]" = ()):
        self.periods = [link.model.period for link in links]
        self.min_period = min(self.periods)
        self.samples = [decoder_sample(link) for link in links]
        self.due: list = [None] * len(links)
        self.last: list = [None] * len(links)  # each laser's last frame and its packed rows as a list
        self.step_s: deque = deque(maxlen=50)
        self.lead = 0.0
        self.stats, self.classes, self.robot_names = stats, classes, robot_names

    def ran(self, k: int, lf, table: list, t_step: float, t_done: float) -> None:
        """Laser ``k``'s frame ``lf`` went through its step from ``t_step`` to ``t_done``."""
        self.last[k] = (lf, table)
        self.step_s.append(t_done - t_step)
        self.lead = warm_up_lead(self.step_s, self.min_period)
        self.due[k] = lf.recv_perf + self.periods[k]

    def warm(self, k: int, step, state) -> None:
        """The warm-up for laser ``k``'s next frame, thrown away."""
        self.due[k] = None
        step.warm(state)
        warm_host(step, self.last[k], self.classes, self.samples[k], self.robot_names)
        self.stats.warm_ups += 1


class LiveSession:
    """What a live run writes, shows and counts besides the frame's path: the run's
    :class:`~gtsjax.drivers.live.LiveStats` (frames that queued up while compiling counted stale and
    let go), the :class:`~gtsjax.drivers.live.Outputs`, a recording per laser of ``record``, the bag,
    the view, ``on_scan`` and :class:`KeepWarm`. ``links``: the lasers' by name; ``named``: each
    frame's JSON line, bag topic, view entities and ``on_scan`` carry its laser's name (several
    lasers), else a one-laser run's, ``links`` then keyed by :data:`~gtsjax.io.bag_out.LASER`.
    ``identity``: the robots' names from their beliefs (:class:`~gtsjax.grade.online.OnlineIdentity`,
    ``run --beliefs``), the sink's."""

    def __init__(
        self,
        links: dict,
        model,
        out: Path,
        *,
        named: bool,
        record: "dict[str, Path] | None",
        outputs: Outputs | None,
        with_intensity: bool,
        out_bag: Path | None,
        view,
        on_scan,
        keep_warm: bool,
        identity=None,
        duration: float | None,
        stop,
        max_frames: int | None,
        smooth: "tuple[int, Path] | None" = None,
    ):
        from ..io.bag_out import BagOut, LaserGeometry
        from ..io.record import Recorder

        names = list(links)
        self.links = [links[n] for n in names]
        self.outputs = outputs or Outputs()
        self.lag = None
        if smooth is not None:  # its smoother compiled before the stale frames are let go
            from .fixed_lag import FixedLag

            self.lag = FixedLag(model.tracker, smooth[0], model.max_tracks, smooth[1],
                                units=self.outputs.csv_units, robot=identity is not None or bool(model.tag_names))
        bag = BagOut(out_bag, {n: LaserGeometry.of_sensor(links[n].model) for n in names}) if out_bag is not None else None
        self.sink = Sink(model, out, names=tuple(names) if named else None, bag=bag, view=view,
                         csv_units=self.outputs.csv_units, identity=identity)
        self.stats = LiveStats(tally=self.sink.tally, track_ids=self.sink.track_ids,
                               smoothing=None if self.lag is None else self.lag.stats)
        for link in self.links:  # frames that queued up while compiling are stale
            while link.get(timeout=0) is not None:
                self.stats.stale += 1
        self.classes = model.classes
        self.period_ms = [link.model.period * 1000.0 for link in self.links]
        recorders = {
            n: Recorder(p, model=links[n].model, intensities=with_intensity and links[n].model.has_intensity)
            for n, p in (record or {}).items()
        }
        self.recorders = [recorders.get(n) for n in names]
        self.all_recorders = list(recorders.values())
        self.on_scan = on_scan
        self.tags = [{"laser": n} if named else {} for n in names]  # what each frame's JSON line adds
        self.scan_args = [(n,) if named else () for n in names]  # what ``on_scan`` gets after the stamp
        self.warm = KeepWarm(self.links, self.stats, model.classes, self.sink.tag_names) if keep_warm else None
        self.t_end = None if duration is None else time.monotonic() + duration
        self.stop, self.max_frames = stop, max_frames

    def emit(self, k: int, lf, step, o, rows, lat: float, unpack: bool):
        """Laser ``k``'s frame after its latency is taken: recorded, its output unpacked on the host when
        something reads it (``unpack``), in the bag and the view (the sink's). Returns the output."""
        if self.recorders[k] is not None:
            self.recorders[k].append_frame(lf)
        if unpack:
            o = step.output(o)
        if self.sink.wants_output:
            sensor = self.links[k].model
            self.sink.show(k, lf.stamp, rows, lf.ranges_m, lf.intensities, sensor.angle_min, sensor.angle_increment, o,
                           latency_ms=lat, dropped=getattr(getattr(self.links[k], "stats", None), "dropped", None))
        return o

    def close(self, failed: InputError | None) -> None:
        """Everything opened closed. The sensors are stopped (QT) as soon as the loop ends, before the
        recordings are finalised (an hour's journal takes a while to become a log): they stream no
        longer than they are read, and the links' counters end with the loop. After a failed write
        (``failed``) the scan logs would not fit either: the journals keep the scans."""
        self.outputs.close()
        for link in self.links:
            if hasattr(link, "stop"):
                link.stop()
        try:
            if self.lag is not None:  # the scans still in the smoother's window written
                self.lag.close()
        finally:
            self.sink.close()
            for rec in self.all_recorders:
                rec.close(write_log=failed is None)


def run_loop(session: LiveSession, frames: Frames, state) -> InputError | None:
    """The live loop: ``frames`` through their steps from ``state`` into the session's GTD CSV (flushed
    per scan) and outputs until ``stop``, ``duration``, ``max_frames``, Ctrl-C, a link gone too long
    (``frames.gone``) or a failed write (a full disk: returned; what is written stays). The latency is
    the frame's last byte read (``LinkFrame.recv_perf``) to its rows written and sent; the rest of a
    frame's work comes after it. The session is closed however the loop ends."""
    stats, classes, tags, period_ms = session.stats, session.classes, session.tags, session.period_ms
    send, warm, on_scan = session.outputs.send, session.warm, session.on_scan
    stop, t_end, max_frames = session.stop, session.t_end, session.max_frames
    sink, lag = session.sink, session.lag
    label = sink.label  # None without --beliefs: the frame's path is then as it was
    robot_names = sink.tag_names  # () for a model that reads no tags
    unpack = frames.needs_output or sink.wants_output or on_scan is not None
    failed = None
    try:
        while (
            not (stop is not None and stop.is_set())
            and (t_end is None or time.monotonic() < t_end)
            and (max_frames is None or stats.frames < max_frames)
        ):
            got = frames.next(state)
            if got is None:
                if frames.gone is not None:
                    break
                continue
            lf, k, step, args = got
            t_step = time.perf_counter()
            state, o, packed = step(state, lf.ranges_m, lf.intensities, *args)
            if lag is None:
                table = np.asarray(packed).tolist()  # the rest of the frame's path is plain Python
            else:  # the filtered states came in the same transfer, columns after the rows'
                packed = np.asarray(packed)
                table = packed[:, :N_PACKED].tolist()
            rows = rows_from_packed(lf.stamp, table, classes, robot_names)
            if label is not None:
                rows = label(rows)
            sink.write(rows)
            degraded = table[-1][DEGRADED] > 0.5
            send(rows, lf.stamp, degraded=degraded, **tags[k])
            t_done = time.perf_counter()
            lat = (t_done - lf.recv_perf) * 1000.0
            if warm is not None:
                warm.ran(k, lf, table, t_step, t_done)
            if lag is not None:  # the scan L before, smoothed: after the latency is taken
                lag.push(packed, rows, args[0])
            # Bookkeeping after the latency is taken: the recording, the bag and the view are not on the path.
            o = session.emit(k, lf, step, o, rows, lat, unpack)
            stats.count(rows, lat, degraded, period_ms[k])
            sink.count(rows, k, degraded, lf.stamp)
            sink.tally.add_packed(table)
            stats.unlike += int(table[-1][UNLIKE])  # the packed status row: one laser or several alike
            stats.off_envelope += int(table[-1][OFF_ENVELOPE])
            frames.count(k, lf, o, table, lat, degraded)
            if on_scan is not None:
                on_scan(stats, o, lf.stamp, *session.scan_args[k])
    except KeyboardInterrupt:
        pass
    except InputError as err:
        failed = err
    finally:
        session.close(failed)
    return failed
