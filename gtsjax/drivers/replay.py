"""Batch replay, the driver: a logged scan file through the pipeline in compiled chunks (the batch
engine, :mod:`gtsjax.drivers.batch`), into the GTD CSV, the sensor-pose CSV, a bag and the view
(:class:`~gtsjax.drivers.sink.Sink`).

``replay_log`` moves the log to the device a block of chunks at a time, so that memory stays bounded
whatever the log's length; ``replay_logs`` runs several logs of one scanner side by side, one
compiled program for all.
"""

from pathlib import Path

from ..core.pipeline import init_state
from ..io.logs import to_scans
from .batch import chunk_for, concat, for_chunks, process_log, process_logs
from .sink import Sink

__all__ = ["bag_for", "process_log", "process_logs", "replay_log", "replay_logs"]

# Chunks of scans moved to the device at a time.
BLOCK_CHUNKS = 16


def bag_for(log, path: Path | None):
    """A :class:`~gtsjax.io.bag_out.BagOut` at ``path`` for ``log``'s scans, one laser (``None``
    without a path); the scanner's timing as the log names it (:meth:`~gtsjax.io.bag_out.LaserGeometry.of_log`)."""
    if path is None:
        return None
    from ..io.bag_out import LASER, BagOut, LaserGeometry

    return BagOut(path, {LASER: LaserGeometry.of_log(log)})


def one_laser_frames(part):
    """``Sink.add``'s ``frame`` for a slice of one laser's log: each scan as it was taken."""
    valid = part.valid()
    return lambda i: (part.ranges[i], None if part.intensities is None else part.intensities[i], part.angle_min,
                      part.angle_increment, valid[i])


def totals(sink: Sink) -> dict:
    """What one log's replay reports: scans, rows, scans without a new map transformation, segments and
    candidates dropped, reported track ids per class, the run's ``diagnosis``
    (:mod:`gtsjax.drivers.diagnose`)."""
    return {"scans": int(sink.scans.sum()), "rows": sink.rows, "degraded": int(sink.degraded.sum()), **sink.dropped,
            "track_ids": sink.track_ids, "diagnosis": sink.tally.finish()}


def replay_log(log, model, out: Path, *, chunk: int = 256, sensor_out: Path | None = None, progress=None,
               vectorise: bool = True, out_bag: Path | None = None, view=None, csv_units: bool = False,
               smooth: bool = False) -> dict:
    """Run ``log`` through ``model`` (site attached) and write the GTD CSV; returns the run's
    :func:`totals`. ``vectorise``: see :func:`~gtsjax.drivers.batch.run_chunk` (off: each scan's whole
    step in turn, what the live loop computes, to float32 round-off: the live loop's program is
    compiled apart, with the model closed over). ``out_bag``: also a ROS 2 bag of the scans, laser
    poses and tracks (:mod:`gtsjax.io.bag_out`); ``view``: a :class:`~gtsjax.viewer.View` shown each
    scan (closed at the end); ``csv_units``: the CSV's optional header with units and the ``cov_xy``
    column (:mod:`gtsjax.io.gtd`); ``smooth``: the rows' poses smoothed over each track's whole life
    (:mod:`gtsjax.drivers.smoothing`), written once the forward pass is done: its outputs are opened
    only then, so that a replay stopped before leaves none (not a CSV of a header and no rows)."""
    def opened() -> Sink:
        return Sink(model, out, bag=bag_for(log, out_bag), view=view, sensor_out=sensor_out, csv_units=csv_units)

    sink = None if smooth else opened()

    def run(state, start, stop):
        part = log.slice(start, stop)
        scans = to_scans(part, model.n_beams, prev_stamp=log.stamps[start - 1] if start else None)
        cb = None if progress is None else (lambda n: progress(start + n))
        state, out = process_log(model, scans, chunk=chunk, state=state, callback=cb, vectorise=vectorise,
                                 filtered=smooth)
        if not smooth:
            sink.add(part.stamps, out, frame=one_laser_frames(part) if sink.wants_output else None)
        return state, out if smooth else None

    try:
        _, outs = for_chunks(run, init_state(model), log.n_scans, chunk * BLOCK_CHUNKS)
        if smooth:
            from .smoothing import smooth_output

            rows = smooth_output(*concat(outs), log.stamps, model.tracker) if log.n_scans else None
            sink = opened()
            if rows is not None:
                sink.add(log.stamps, rows, frame=one_laser_frames(log) if sink.wants_output else None)
    finally:
        if sink is not None:
            sink.close()
    return totals(sink)


def replay_logs(logs, model, outs: list[Path], *, chunk: int = 256, sensor_outs: list[Path | None] | None = None,
                progress=None, vectorise: bool = True, csv_units: bool = False) -> list[dict]:
    """Several logs of one scanner through ``model`` side by side (:func:`~gtsjax.drivers.batch.process_logs`:
    independent trackers, one compiled program for all), each into its own GTD CSV (and sensor-pose
    CSV); returns each log's :func:`totals`. ``progress(n)``: scans done, all logs together."""
    sensor_outs = sensor_outs or [None] * len(logs)
    longest = max(lg.n_scans for lg in logs)
    chunk = chunk_for(longest, chunk)
    sinks = [Sink(model, o, sensor_out=so, csv_units=csv_units) for o, so in zip(outs, sensor_outs, strict=True)]

    def run(states, start, stop):
        parts = [lg.slice(start, stop) if start < lg.n_scans else None for lg in logs]
        scans = [None if p is None else to_scans(p, model.n_beams, prev_stamp=lg.stamps[start - 1] if start else None)
                 for lg, p in zip(logs, parts, strict=True)]
        states, outs = process_logs(model, scans, chunk=chunk, states=states, vectorise=vectorise)
        for sink, p, o in zip(sinks, parts, outs, strict=True):
            if p is not None:
                sink.add(p.stamps, o)
        return states, None

    done = lambda stop: progress(sum(min(stop, lg.n_scans) for lg in logs))  # noqa: E731
    try:
        for_chunks(run, [init_state(model) for _ in logs], longest, chunk * BLOCK_CHUNKS,
                   None if progress is None else done)
    finally:
        for sink in sinks:
            sink.close()
    return [totals(sink) for sink in sinks]
