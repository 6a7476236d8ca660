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
from ..core.pipeline import Output, PipelineState, init_state, perceive, step, update
from ..core.scan import Scan
from ..io.gtd import GTDWriter, rows_from_output
from ..io.logs import to_scans
from ..model import Model


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


def _pad_chunk(scans: Scan, start: int, stop: int, size: int) -> Scan:
    """Scans ``start:stop`` padded to ``size`` by repeating the last one (so shapes never change)."""
    part = jax.tree.map(lambda a: a[start:stop], scans)
    pad = size - (stop - start)
    if pad == 0:
        return part
    return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), part)


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


@jax.jit(static_argnames=("vectorise", "sub"))
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


def process_log(model: Model, scans: Scan, *, chunk: int = 256, state: PipelineState | None = None,
                callback=None, vectorise: bool = False, sub: int = SUB_CHUNK) -> tuple[PipelineState, Output]:
    """Run a stack of scans through the pipeline ``chunk`` at a time. Returns the final state and the
    stacked outputs as NumPy arrays on the host; ``callback(n_done)`` is called after each chunk.

    Device memory is bounded by the chunk size whatever the log's length (the last chunk is padded,
    and its padding does not touch the state); the outputs accumulate on the host.
    """
    state = init_state(model) if state is None else state
    n = scans.ranges.shape[0]
    chunk = max(1, min(chunk, n))
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


def replay_log(log, model, out: Path, *, chunk: int = 256, sensor_out: Path | None = None, progress=None,
               vectorise: bool = True):
    """Run ``log`` through ``model`` (site attached) and write the GTD CSV; returns stacked outputs'
    summary counters. The log is moved to the device a block at a time, so memory stays bounded.
    ``vectorise``: see :func:`process_chunk` (off: bit for bit what the live loop computes)."""
    state = init_state(model)
    block = chunk * 16
    totals = {"scans": 0, "rows": 0, "degraded": 0, "n_overflow": 0, "n_too_long": 0, "unlike": 0, "off_envelope": 0,
              "track_ids": {}}
    sensor_rows = []
    with GTDWriter(out) as writer:
        for start in range(0, log.n_scans, block):
            part = log.slice(start, start + block)
            scans = to_scans(part, model.n_beams, prev_stamp=log.stamps[start - 1] if start else None)
            cb = None if progress is None else (lambda n, s=start: progress(s + n))
            state, out_arrays = process_log(model, scans, chunk=chunk, state=state, callback=cb, vectorise=vectorise)
            for i in range(part.n_scans):
                rows = rows_from_output(part.stamps[i], out_arrays.track_id[i], out_arrays.track_class[i],
                                        out_arrays.track_pose[i], out_arrays.track_var[i], out_arrays.track_mask[i],
                                        model.classes)
                writer.write(rows)
                for row in rows:
                    totals["track_ids"].setdefault(row.cls, set()).add(row.track_id)
            if sensor_out is not None:
                tf, sp = out_arrays.transform, out_arrays.sensor_pose.astype(np.float64)
                for i in range(part.n_scans):
                    sensor_rows.append((repr(float(part.stamps[i])), f"{sp[i, 0]:.6f}", f"{sp[i, 1]:.6f}",
                                        f"{float(wrap(sp[i, 2])):.6f}", int(tf.degraded[i]), int(tf.n_landmarks[i])))
            totals["scans"] += part.n_scans
            totals["degraded"] += int(np.sum(out_arrays.degraded))
            totals["n_overflow"] += int(np.sum(out_arrays.n_overflow))
            totals["n_too_long"] += int(np.sum(out_arrays.n_too_long))
            totals["unlike"] += int(np.sum(out_arrays.unlike))
            totals["off_envelope"] += int(np.sum(out_arrays.off_envelope))
        totals["rows"] = writer.rows
    if sensor_out is not None:
        with open(sensor_out, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(("stamp", "x", "y", "theta", "degraded", "n_landmarks"))
            w.writerows(sensor_rows)
    return totals
