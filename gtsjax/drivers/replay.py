"""Batch replay, the driver: a logged scan file through the pipeline's ``step`` in compiled chunks,
into the GTD CSV (and the sensor-pose CSV).

``process_chunk`` is this driver's one jitted function: a chunk of scans through a ``while_loop``
whose body is one scan's whole step, or (``vectorise=True``, ``replay_log``'s default)
``scan(update) ∘ vmap(perceive)``, perception ``vmap``ped over groups of scans. It
compiles once per model shape and chunk size: retuned thresholds, another log of the same scanner,
the last (padded) chunk all reuse it. ``process_log`` feeds it a stack of scans a chunk at a time, so
device memory is bounded whatever the log's length; ``replay_log`` moves the log to the device a
block at a time and writes the rows.
"""

import csv
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from ..core.geometry import wrap
from ..core.model import Model
from ..core.pipeline import Output, PipelineState, init_state, perceive, step, update
from ..core.scan import Scan
from ..io.gtd import GTDWriter, rows_from_output
from ..io.logs import to_scans
from .compile import batch_jit
from .diagnose import Tally


def _run_scans(model: Model, state: PipelineState, scans: Scan, n_real: Int[Array, ""]):
    """``step`` over the first ``n_real`` scans of a stack, in a ``while_loop`` whose trip count is a
    runtime value (the padded last chunk runs the same program). Outputs past ``n_real`` are zeros."""
    one = jax.tree.map(lambda a: a[0], scans)
    out_shape = jax.eval_shape(lambda st, sc: step(model, st, sc)[1], state, one)
    size = scans.dt.shape[0]
    buf0 = jax.tree.map(lambda sd: jnp.zeros((size,) + sd.shape, sd.dtype), out_shape)

    def cond(c):
        return c[0] < n_real

    def body(c):
        i, st, buf = c
        sc = jax.tree.map(lambda a: jax.lax.dynamic_index_in_dim(a, i, keepdims=False), scans)
        st, o = step(model, st, sc)
        buf = jax.tree.map(lambda b, x: jax.lax.dynamic_update_index_in_dim(b, x, i, 0), buf, o)
        return i + 1, st, buf

    _, state, buf = jax.lax.while_loop(cond, body, (jnp.asarray(0, jnp.int32), state, buf0))
    return state, buf


def _pad_chunk(scans, start: int, stop: int, size: int):
    """Rows ``start:stop`` of every leaf (scans, or any pytree stacked along its first axis) padded to
    ``size`` by repeating the last row (so shapes never change)."""
    part = jax.tree.map(lambda a: a[start:stop], scans)
    pad = size - (stop - start)
    if pad == 0:
        return part
    return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), part)


def chunk_for(n: int, chunk: int) -> int:
    """The chunk size for ``n`` scans: ``chunk``, or for a log shorter than that the power of two that
    holds it (the chunk is padded, its padding leaves the state alone). The chunk's length is a shape
    of the compiled program: sized to each log, every log length would compile a program of its own
    (tens of seconds, and a miss of the persistent cache); so bucketed, a few serve all."""
    return max(1, min(chunk, 1 << max(0, n - 1).bit_length()))


# Scans per ``vmap``ped group of perception in the vectorised batch form: each kernel's fixed cost is
# shared by the group, and the size buckets (``core.buckets``) still work, one per group (its largest
# count of robots and posts), where a whole chunk would pay for its busiest scan throughout.
SUB_CHUNK = 8


def perceive_batch(model: Model, scans: Scan, sub: int = SUB_CHUNK):
    """``perceive`` of a stack of scans: ``vmap``ped over groups of ``sub`` scans (one size bucket
    per group), the groups one after the other (``lax.map``). ``sub`` must divide the stack."""
    size = scans.dt.shape[0]
    group = jax.vmap(lambda sc: perceive(model, sc, axis_name="scans"), axis_name="scans")
    grouped = jax.tree.map(lambda a: a.reshape((size // sub, sub) + a.shape[1:]), scans)
    out = jax.lax.map(group, grouped)
    return jax.tree.map(lambda a: a.reshape((size,) + a.shape[2:]), out)


@batch_jit(static_argnames=("vectorise", "sub"))
def process_chunk(model: Model, state: PipelineState, scans: Scan, n_real: Int[Array, ""], vectorise: bool = False,
                  sub: int = SUB_CHUNK) -> tuple[PipelineState, Output]:
    """A chunk of scans (leading axis). Scans at index ``>= n_real`` (padding of the last chunk) leave
    the state as it was.

    ``vectorise=False``: the scans run one after the other through the whole step
    (:func:`_run_scans`), the same computation as the live loop's. ``vectorise=True``:
    ``perceive`` (stages a–e′) runs ``vmap``ped over groups of ``sub`` scans (:func:`perceive_batch`)
    and ``update`` (f–g) under ``lax.scan``; batched products may then round differently (float32
    round-off, which can tip a near-tie between heading hypotheses: on a real office log one row of
    80, a phantom track's, took its other side)."""
    if not vectorise:
        return _run_scans(model, state, scans, n_real)
    percepts = perceive_batch(model, scans, math.gcd(sub, scans.dt.shape[0]))

    def body(s, inp):
        p, sc, i = inp
        new, out = update(model, s, p, sc)
        keep = i < n_real
        return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, s), out

    idx = jnp.arange(scans.dt.shape[0], dtype=jnp.int32)
    return jax.lax.scan(body, state, (percepts, scans, idx))


@batch_jit(static_argnames=("vectorise", "sub"))
def process_chunks(model: Model, states: PipelineState, scans: Scan, n_real: Int[Array, " logs"],
                   vectorise: bool = True, sub: int = SUB_CHUNK) -> tuple[PipelineState, Output]:
    """Chunks of several logs side by side (leading axis: logs, then scans), each log with its own
    state (independent trackers); scans at index ``>= n_real[log]`` leave that log's state as it was.

    ``vectorise=True``: perception of every scan of every log at once (:func:`perceive_batch` over
    the logs' scans laid end to end, groups of ``sub`` within one log), then one ``lax.scan`` over
    time whose body is ``update`` ``vmap``ped over the logs: each kernel's fixed cost is shared by
    the logs as well as the scans. ``vectorise=False``: :func:`_run_scans` ``vmap``ped over the
    logs. Each log's outputs equal those of :func:`process_chunk` on it alone, to float32 round-off."""
    n_logs, size = scans.dt.shape[:2]
    if not vectorise:
        return jax.vmap(lambda st, sc, n: _run_scans(model, st, sc, n))(states, scans, n_real)
    flat = jax.tree.map(lambda a: a.reshape((n_logs * size,) + a.shape[2:]), scans)
    percepts = perceive_batch(model, flat, math.gcd(sub, size))
    by_time = jax.tree.map(lambda a: jnp.swapaxes(a.reshape((n_logs, size) + a.shape[1:]), 0, 1), percepts)
    scans_t = jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), scans)

    def body(s, inp):
        p, sc, i = inp
        new, out = jax.vmap(lambda s1, p1, sc1: update(model, s1, p1, sc1))(s, p, sc)
        keep = i < n_real
        return jax.tree.map(lambda a, b: jnp.where(keep.reshape(keep.shape + (1,) * (a.ndim - 1)), a, b), new, s), out

    idx = jnp.arange(size, dtype=jnp.int32)
    states, outs = jax.lax.scan(body, states, (by_time, scans_t, idx))
    return states, jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), outs)


def process_log(model: Model, scans: Scan, *, chunk: int = 256, state: PipelineState | None = None,
                callback=None, vectorise: bool = False, sub: int = SUB_CHUNK) -> tuple[PipelineState, Output]:
    """Run a stack of scans through the pipeline ``chunk`` at a time. Returns the final state and the
    stacked outputs as NumPy arrays on the host; ``callback(n_done)`` is called after each chunk.

    Device memory is bounded by the chunk size whatever the log's length (the last chunk is padded,
    and its padding does not touch the state); the outputs accumulate on the host.
    """
    state = init_state(model) if state is None else state
    n = scans.ranges.shape[0]
    chunk = chunk_for(n, chunk)
    outs = []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        part = _pad_chunk(scans, start, stop, chunk)
        state, out = process_chunk(model, state, part, jnp.asarray(stop - start, jnp.int32), vectorise=vectorise,
                                   sub=sub)
        real = stop - start
        outs.append(jax.tree.map(lambda a, real=real: np.asarray(a)[:real], out))
        if callback is not None:
            callback(stop)
    return state, jax.tree.map(lambda *a: np.concatenate(a), *outs)


def process_logs(model: Model, scans: "list[Scan | None]", *, chunk: int = 256,
                 states: list[PipelineState] | None = None, vectorise: bool = True,
                 sub: int = SUB_CHUNK) -> tuple[list[PipelineState], list[Output | None]]:
    """Several stacks of scans (logs of one scanner, any lengths) through the pipeline side by side,
    ``chunk`` scans of each at a time (:func:`process_chunks`): the final state and the stacked
    outputs (NumPy, on the host) of each, as :func:`process_log` gives them one log at a time.

    An entry ``None`` is a log with nothing to process in this call (one that ended before the
    others): its state passes through and its output is ``None``, and the number of logs, hence the
    compiled program, stays the same. The chunk size is used as given (not shrunk to the logs), so
    that one program serves every call of a replay."""
    n_logs = len(scans)
    states = [init_state(model) for _ in range(n_logs)] if states is None else states
    present = [sc for sc in scans if sc is not None]
    if not present:
        return states, [None] * n_logs
    filler = jax.tree.map(lambda a: a[:1], present[0])  # any scan: shapes only, n_real 0
    stacks = [filler if sc is None else sc for sc in scans]
    lengths = [0 if sc is None else int(sc.ranges.shape[0]) for sc in scans]
    state = jax.tree.map(lambda *a: jnp.stack(a), *states)
    outs: list[list] = [[] for _ in range(n_logs)]
    for start in range(0, max(lengths), chunk):
        real = [max(0, min(chunk, n - start)) for n in lengths]
        firsts = [min(start, int(sc.ranges.shape[0]) - 1) for sc in stacks]  # an ended log: its last scan
        parts = [_pad_chunk(sc, a, a + max(r, 1), chunk) for sc, a, r in zip(stacks, firsts, real, strict=True)]
        stacked = jax.tree.map(lambda *a: jnp.stack(a), *parts)
        state, out = process_chunks(model, state, stacked, jnp.asarray(real, jnp.int32), vectorise=vectorise, sub=sub)
        host = jax.tree.map(np.asarray, out)
        for k in range(n_logs):
            if real[k]:
                outs[k].append(jax.tree.map(lambda a, k=k, r=real[k]: a[k, :r], host))
    final = [jax.tree.map(lambda a, k=k: a[k], state) for k in range(n_logs)]
    return final, [jax.tree.map(lambda *a: np.concatenate(a), *o) if o else None for o in outs]


def bag_for(log, path: Path | None):
    """A :class:`~gtsjax.io.bag_out.BagOut` at ``path`` for ``log``'s scans, one laser (``None``
    without a path); the scanner's timing as the log names it (:meth:`~gtsjax.io.bag_out.LaserGeometry.of_log`)."""
    if path is None:
        return None
    from ..io.bag_out import LASER, BagOut, LaserGeometry

    return BagOut(path, {LASER: LaserGeometry.of_log(log)})


class _Sink:
    """One log's outputs as they come, block by block: its GTD CSV (rows flushed per scan), its
    sensor-pose rows, and the totals ``replay`` reports (with the run's ``diagnosis``:
    :mod:`gtsjax.drivers.diagnose`)."""

    def __init__(self, model: Model, out: Path, sensor_out: Path | None, bag=None, view=None, csv_units: bool = False):
        self.model, self.sensor_out, self.bag, self.view = model, sensor_out, bag, view
        self.writer = GTDWriter(out, units=csv_units)
        self.tally = Tally(model)
        self.totals = {"scans": 0, "rows": 0, "degraded": 0, "n_overflow": 0, "n_too_long": 0, "unlike": 0,
                       "off_envelope": 0, "track_ids": {}}
        self.sensor_rows = []

    def add(self, part, out_arrays) -> None:
        """The outputs of the scans ``part`` (a slice of the log) as stacked arrays."""
        totals = self.totals
        valid = part.valid() if self.view is not None else None
        for i in range(part.n_scans):
            rows = rows_from_output(part.stamps[i], out_arrays.track_id[i], out_arrays.track_class[i],
                                    out_arrays.track_pose[i], out_arrays.track_var[i], out_arrays.track_mask[i],
                                    self.model.classes, out_arrays.track_cov_xy[i])
            self.writer.write(rows)
            if self.bag is not None:
                self.bag.write(float(part.stamps[i]), part.ranges[i],
                               None if part.intensities is None else part.intensities[i], rows,
                               np.asarray(out_arrays.sensor_pose[i], np.float64))
            if self.view is not None:
                self.view.scan(float(part.stamps[i]), np.where(valid[i], part.ranges[i], 0.0), part.angle_min,
                               part.angle_increment, jax.tree.map(lambda a, i=i: a[i], out_arrays), rows)
            for row in rows:
                totals["track_ids"].setdefault(row.cls, set()).add(row.track_id)
        if self.sensor_out is not None:
            tf, sp = out_arrays.transform, out_arrays.sensor_pose.astype(np.float64)
            for i in range(part.n_scans):
                self.sensor_rows.append((repr(float(part.stamps[i])), f"{sp[i, 0]:.6f}", f"{sp[i, 1]:.6f}",
                                         f"{float(wrap(sp[i, 2])):.6f}", int(tf.degraded[i]), int(tf.n_landmarks[i])))
        self.tally.add(out_arrays)
        totals["scans"] += part.n_scans
        for k in ("degraded", "n_overflow", "n_too_long", "unlike", "off_envelope"):
            totals[k] += int(np.sum(getattr(out_arrays, k)))

    def close(self) -> dict:
        """Closes the CSV (and the bag), writes the sensor-pose CSV; returns the totals."""
        self.writer.close()
        if self.bag is not None:
            self.bag.close()
        if self.view is not None:
            self.view.close()
        self.totals["rows"] = self.writer.rows
        self.totals["diagnosis"] = self.tally.finish()
        if self.sensor_out is not None:
            with open(self.sensor_out, "w", newline="") as f:
                w = csv.writer(f, lineterminator="\n")
                w.writerow(("stamp", "x", "y", "theta", "degraded", "n_landmarks"))
                w.writerows(self.sensor_rows)
        return self.totals


def replay_log(log, model, out: Path, *, chunk: int = 256, sensor_out: Path | None = None, progress=None,
               vectorise: bool = True, out_bag: Path | None = None, view=None, csv_units: bool = False):
    """Run ``log`` through ``model`` (site attached) and write the GTD CSV; returns stacked outputs'
    summary counters. The log is moved to the device a block at a time, so memory stays bounded.
    ``vectorise``: see :func:`process_chunk` (off: each scan's whole step in turn, what the live loop computes, to float32 round-off: the live loop's program is compiled apart, with the model closed over).
    ``out_bag``: also a ROS 2 bag of the scans, laser poses and tracks (:mod:`gtsjax.io.bag_out`);
    ``view``: a :class:`~gtsjax.viewer.View` shown each scan (closed at the end); ``csv_units``: the
    CSV's optional header with units and the ``cov_xy`` column (:mod:`gtsjax.io.gtd`)."""
    state = init_state(model)
    block = chunk * 16
    sink = _Sink(model, out, sensor_out, bag_for(log, out_bag), view, csv_units)
    try:
        for start in range(0, log.n_scans, block):
            part = log.slice(start, start + block)
            scans = to_scans(part, model.n_beams, prev_stamp=log.stamps[start - 1] if start else None)
            cb = None if progress is None else (lambda n, s=start: progress(s + n))
            state, out_arrays = process_log(model, scans, chunk=chunk, state=state, callback=cb, vectorise=vectorise)
            sink.add(part, out_arrays)
    finally:
        totals = sink.close()
    return totals


def replay_logs(logs, model, outs: list[Path], *, chunk: int = 256, sensor_outs: list[Path | None] | None = None,
                progress=None, vectorise: bool = True, csv_units: bool = False) -> list[dict]:
    """Several logs of one scanner through ``model`` side by side (:func:`process_logs`: independent
    trackers, one compiled program for all), each into its own GTD CSV (and sensor-pose CSV); returns
    each log's totals as :func:`replay_log` does. ``progress(n)``: scans done, all logs together."""
    sensor_outs = sensor_outs or [None] * len(logs)
    states = [init_state(model) for _ in logs]
    longest = max(lg.n_scans for lg in logs)
    chunk = chunk_for(longest, chunk)
    block = chunk * 16
    sinks = [_Sink(model, o, so, csv_units=csv_units) for o, so in zip(outs, sensor_outs, strict=True)]
    done = 0
    try:
        for start in range(0, longest, block):
            parts = [lg.slice(start, start + block) if start < lg.n_scans else None for lg in logs]
            scans = [None if p is None else to_scans(p, model.n_beams, prev_stamp=lg.stamps[start - 1] if start else None)
                     for lg, p in zip(logs, parts, strict=True)]
            states, out_arrays = process_logs(model, scans, chunk=chunk, states=states, vectorise=vectorise)
            for sink, p, o in zip(sinks, parts, out_arrays, strict=True):
                if p is not None:
                    sink.add(p, o)
                    done += p.n_scans
            if progress is not None:
                progress(done)
    finally:
        totals = [s.close() for s in sinks]
    return totals
