"""The batch engine: stacks of scans through the pipeline in compiled chunks, for every batch driver
(one laser's log, several logs side by side, several lasers' logs merged by stamp, lasers of
different scanners).

Two jitted entry points, each compiled once per model shape, number of lasers or logs, and chunk
size (retuned thresholds, another log of the same scanner, the last padded chunk all reuse it):

* :func:`run_chunk`, a chunk of scans through the pipeline. Vectorised (the default): stages a–e′
  ``vmap``ped over groups of scans (:func:`perceive_batch`; or given, already done), then stages f–g
  under ``lax.scan``. Step by step: each scan's whole step in turn in a ``while_loop``, the live
  loop's computation. The state says which update a scan gets: a
  :class:`~gtsjax.core.pipeline.PipelineState` is one laser's
  (:func:`~gtsjax.core.pipeline.update`), a :class:`~gtsjax.core.multi.SeveralState` several lasers'
  (:func:`~gtsjax.core.multi.update_several`, or :func:`~gtsjax.core.multi.update_mixed` for
  lasers of different scanners), each scan with its :class:`Lanes` (its laser, its laser's model,
  the time since its laser's previous scan). A state with a leading axis of logs (and ``n_real``
  one count per log) runs several logs side by side, each with its own tracker.
* :func:`perceive_chunk`: stages a–e′ alone, for lasers of different scanners, each laser's scans
  perceived by its own model before the merged updates.

On the host one loop (:func:`for_chunks`) walks a stack of scans a chunk at a time, padding the last
chunk (its padding leaves the state as it was), so that device memory is bounded by the chunk
whatever the log's length; the outputs gather on the host (:func:`run_chunks`).
"""

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..core.model import Model
from ..core.multi import SeveralState, update_mixed, update_several
from ..core.pipeline import Output, Perception, PipelineState, init_state, perceive, update
from ..core.scan import Scan
from .compile import batch_jit

# Scans per ``vmap``ped group of perception in the vectorised batch form: each kernel's fixed cost is
# shared by the group, and the size buckets (``core.buckets``) still work, one per group (its largest
# count of robots and posts), where a whole chunk would pay for its busiest scan throughout.
SUB_CHUNK = 8


class Lanes(eqx.Module):
    """What each scan of a merged sequence of several lasers carries besides the scan (leading axis:
    the scans): the laser that took it, the index of that laser's model, and the time since the
    same laser's previous scan (``Scan.dt`` is the time since the previous scan of any laser)."""

    laser: Int[Array, " n"]
    kind: Int[Array, " n"]
    span_dt: Float[Array, " n"]


# ------------------------------------------------------------------------------------------ device
def perceive_batch(model: Model, scans: Scan, sub: int = SUB_CHUNK) -> Perception:
    """``perceive`` of a stack of scans: ``vmap``ped over groups of ``sub`` scans (one size bucket
    per group), the groups one after the other (``lax.map``). ``sub`` must divide the stack."""
    size = scans.dt.shape[0]
    group = jax.vmap(lambda sc: perceive(model, sc, axis_name="scans"), axis_name="scans")
    grouped = jax.tree.map(lambda a: a.reshape((size // sub, sub) + a.shape[1:]), scans)
    out = jax.lax.map(group, grouped)
    return jax.tree.map(lambda a: a.reshape((size,) + a.shape[2:]), out)


def _updater(models: "tuple[Model, ...]", state):
    """``f(state, perception, scan, lane) -> (state, output)``, stages f–g of one scan as ``state``'s
    kind asks: one laser's, or one laser's among several (with its model, for several scanners)."""
    if isinstance(state, PipelineState):
        return lambda s, p, sc, lane: update(models[0], s, p, sc)
    if not isinstance(state, SeveralState):
        raise TypeError(f"a batch state is a PipelineState or a SeveralState, not {type(state).__name__}")
    if len(models) == 1:
        return lambda s, p, sc, lane: update_several(models[0], s, p, sc, lane.laser, lane.span_dt)
    return lambda s, p, sc, lane: update_mixed(models, s, p, sc, lane.laser, lane.kind, lane.span_dt)


def _keep(keep, new, old):
    """``new`` where ``keep`` (one flag, or one per log along the leading axis), else ``old``."""
    return jax.tree.map(lambda a, b: jnp.where(keep.reshape(keep.shape + (1,) * (a.ndim - keep.ndim)), a, b), new, old)


def _step_by_step(models, upd, state, scans: Scan, lanes, n_real: Int[Array, ""]):
    """Each of the first ``n_real`` scans' whole step in turn, in a ``while_loop`` whose trip count is
    a runtime value (the padded last chunk runs the same program). Outputs past ``n_real`` are zeros."""
    if len(models) != 1:
        raise ValueError("step by step runs one model; lasers of different scanners are vectorised only")
    model = models[0]
    at = lambda tree, i: jax.tree.map(lambda a: jax.lax.dynamic_index_in_dim(a, i, keepdims=False), tree)  # noqa: E731
    # Jitted so that the loop body's call finds the trace ``eval_shape`` made of it (JAX caches a jitted
    # function's trace by its arguments' shapes): the step is traced once, not twice (half the tracing).
    one = jax.jit(lambda st, sc, lane: upd(st, perceive(model, sc), sc, lane))
    out_shape = jax.eval_shape(one, state, at(scans, 0), None if lanes is None else at(lanes, 0))[1]
    size = scans.dt.shape[0]
    buf0 = jax.tree.map(lambda sd: jnp.zeros((size,) + sd.shape, sd.dtype), out_shape)

    def body(c):
        i, st, buf = c
        st, o = one(st, at(scans, i), None if lanes is None else at(lanes, i))
        buf = jax.tree.map(lambda b, x: jax.lax.dynamic_update_index_in_dim(b, x, i, 0), buf, o)
        return i + 1, st, buf

    _, state, buf = jax.lax.while_loop(lambda c: c[0] < n_real, body, (jnp.asarray(0, jnp.int32), state, buf0))
    return state, buf


def _vectorised(models, upd, state, scans: Scan, lanes, n_real, percepts, sub: int, by_log: bool):
    """Perception of the whole chunk at once (unless given), then the updates under ``lax.scan``;
    ``by_log``: a leading axis of logs, perceived together and updated side by side (``vmap``)."""
    if by_log:
        n_logs, size = scans.dt.shape[:2]
        flat = jax.tree.map(lambda a: a.reshape((n_logs * size,) + a.shape[2:]), scans)
        percepts = perceive_batch(models[0], flat, math.gcd(sub, size))
        by_time = jax.tree.map(lambda a: jnp.swapaxes(a.reshape((n_logs, size) + a.shape[1:]), 0, 1), percepts)
        xs = (by_time, jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), scans), None)
        upd = jax.vmap(upd)
    else:
        size = scans.dt.shape[0]
        if percepts is None:
            percepts = perceive_batch(models[0], scans, math.gcd(sub, size))
        xs = (percepts, scans, lanes)

    def body(s, inp):
        (p, sc, lane), i = inp
        new, out = upd(s, p, sc, lane)
        return _keep(i < n_real, new, s), out

    state, outs = jax.lax.scan(body, state, (xs, jnp.arange(size, dtype=jnp.int32)))
    return state, (jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), outs) if by_log else outs)


class Filtered(NamedTuple):
    """The track table's filtered state after a scan, for the smoother (:mod:`gtsjax.core.smooth`,
    :mod:`gtsjax.drivers.smoothing`): each slot's mean and covariance, which of its heading
    hypotheses the state's heading is, and the hypotheses themselves (headings, variances and
    log-weights, normalised with the rest's; -inf: unused), for re-deciding the side over a track's life."""

    mean: Float[Array, "tracks 6"]
    cov: Float[Array, "tracks 6 6"]
    main: Int[Array, " tracks"]
    side_heading: "Float[Array, 'tracks sides'] | None" = None
    side_var: "Float[Array, 'tracks sides'] | None" = None
    side_logw: "Float[Array, 'tracks sides'] | None" = None


def _with_filtered(upd):
    """``upd`` whose output also carries the track table's :class:`Filtered` state after the scan."""

    def f(s, p, sc, lane):
        new, out = upd(s, p, sc, lane)
        t = new.tracker
        return new, (out, Filtered(t.mean, t.cov, t.main, t.side_heading, t.side_var, t.side_logw))

    return f


@batch_jit(static_argnames=("vectorise", "sub", "filtered"))
def run_chunk(models: "tuple[Model, ...]", state, scans: Scan, lanes: "Lanes | None", n_real: Int[Array, "*logs"],
              percepts: "Perception | None" = None, vectorise: bool = True, sub: int = SUB_CHUNK,
              filtered: bool = False):
    """A chunk of scans (leading axis) through the pipeline from ``state``: returns the state after
    them and their stacked outputs. Scans at index ``>= n_real`` (the padding of a last chunk) leave
    the state as it was.

    ``models``: one model, or one per scanner with a several-laser state (``lanes.kind`` each scan's
    index into them; ``percepts`` then given, each scan perceived by its laser's model, padded to the
    widest: :func:`~gtsjax.core.multi.widest`). ``lanes``: each scan's laser (several-laser states),
    else ``None``. A state and scans with a leading axis of logs, ``n_real`` one count per log:
    several logs side by side (one laser each), each log's outputs those it would get alone to
    float32 round-off.

    ``vectorise=True``: perception ``vmap``ped over groups of ``sub`` scans (:func:`perceive_batch`),
    the updates under ``lax.scan``; batched products may round differently from one scan's (float32
    round-off, which can tip a near-tie between heading hypotheses: on a real office log one row of
    80, a phantom track's, took its other side). ``vectorise=False``: each scan's whole step in turn,
    the live loop's computation (one model). ``filtered``: each output is ``(Output, Filtered)``, the
    track table's filtered state after the scan beside it (a program of its own, for the smoother)."""
    by_log = n_real.ndim == 1
    upd = _updater(models, state)
    if filtered:
        upd = _with_filtered(upd)
    if not vectorise:
        if by_log:
            return jax.vmap(lambda st, sc, n: _step_by_step(models, upd, st, sc, None, n))(state, scans, n_real)
        return _step_by_step(models, upd, state, scans, lanes, n_real)
    return _vectorised(models, upd, state, scans, lanes, n_real, percepts, sub, by_log)


@batch_jit()
def perceive_chunk(model: Model, scans: Scan) -> Perception:
    """Stages a–e′ of a chunk of scans (:func:`perceive_batch`), for :func:`run_chunk`'s ``percepts``."""
    return perceive_batch(model, scans, math.gcd(SUB_CHUNK, scans.dt.shape[0]))


# -------------------------------------------------------------------------------------------- host
def chunk_for(n: int, chunk: int) -> int:
    """The chunk size for ``n`` scans: ``chunk`` itself, whatever ``n``; a shorter log (or a long log's
    last block) is padded, and its padding leaves the state alone. The chunk's length is a shape of the
    compiled program: one length means one program per model and form, compiled once and then found
    in the persistent cache by every later replay of that model, where a length per log (or per power
    of two, as before) compiled a program of its own for each (some 20 s each on 2 cores). Padding
    costs only the vectorised form, which perceives the padded scans: a fraction of a second for a
    short log. ``n`` is kept for the callers, which size by the log."""
    del n
    return max(1, chunk)


def pad_chunk(tree, start: int, stop: int, size: int):
    """Rows ``start:stop`` of every leaf (scans, or any pytree stacked along its first axis; ``None``
    leaves none) padded to ``size`` by repeating the last row (so shapes never change). NumPy leaves
    are cut on the host (:func:`on_host`), device arrays on the device."""
    part = jax.tree.map(lambda a: a[start:stop], tree)
    pad = size - (stop - start)
    if pad == 0:
        return part

    def padded(a):
        xp = np if isinstance(a, np.ndarray) else jnp
        return xp.concatenate([a, xp.repeat(a[-1:], pad, axis=0)])

    return jax.tree.map(padded, part)


def on_host(tree):
    """Every leaf of ``tree`` (scans read from a log: host data) as a NumPy array, for the chunk loop:
    a device array's every slice and pad is a small program compiled for its shape and bounds (some
    tens of them at each replay's start, each a few milliseconds), NumPy's none. The chunk goes to the
    device as the compiled chunk's argument, as it would anyway."""
    return jax.tree.map(np.asarray, tree)


def host_rows(tree, n: int):
    """The first ``n`` rows of every leaf, as NumPy arrays on the host."""
    return jax.tree.map(lambda a: np.asarray(a)[:n], tree)


def concat(parts: list):
    """Stacked outputs of consecutive chunks as one stack (NumPy)."""
    return jax.tree.map(lambda *a: np.concatenate(a), *parts)


def for_chunks(run, state, n: int, chunk: int, callback=None):
    """The batch drivers' one chunk loop: ``run(state, start, stop) -> (state, out)`` for consecutive
    chunks of ``n`` rows, ``callback(stop)`` after each. Returns the last state and the outs, in order."""
    outs = []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        state, out = run(state, start, stop)
        outs.append(out)
        if callback is not None:
            callback(stop)
    return state, outs


def run_chunks(models: "tuple[Model, ...]", state, scans: Scan, *, lanes: "Lanes | None" = None,
               percepts: "Perception | None" = None, chunk: int = 256, vectorise: bool = True,
               sub: int = SUB_CHUNK, callback=None, filtered: bool = False):
    """A stack of scans (one log, or several lasers' merged, with their ``lanes`` and, for several
    scanners, ``percepts``) through :func:`run_chunk` ``chunk`` at a time from ``state``: the final
    state and the stacked outputs, NumPy on the host; ``callback(n_done)`` after each chunk."""
    n = scans.dt.shape[0]
    chunk = chunk_for(n, chunk)
    scans, lanes = on_host((scans, lanes))

    def run(state, start, stop):
        sc, ln, pc = pad_chunk((scans, lanes, percepts), start, stop, chunk)
        state, out = run_chunk(models, state, sc, ln, jnp.asarray(stop - start, jnp.int32), pc,
                               vectorise=vectorise, sub=sub, filtered=filtered)
        return state, host_rows(out, stop - start)

    state, outs = for_chunks(run, state, n, chunk, callback)
    return state, concat(outs)


def process_log(model: Model, scans: Scan, *, chunk: int = 256, state: PipelineState | None = None,
                callback=None, vectorise: bool = False, sub: int = SUB_CHUNK, filtered: bool = False
                ) -> tuple[PipelineState, Output]:
    """Run one laser's stack of scans through the pipeline ``chunk`` at a time (:func:`run_chunks`).
    Returns the final state and the stacked outputs as NumPy arrays on the host; ``callback(n_done)``
    is called after each chunk. ``vectorise``: see :func:`run_chunk` (off by default here: each
    scan's step in turn, what the live loop computes)."""
    state = init_state(model) if state is None else state
    return run_chunks((model,), state, scans, chunk=chunk, vectorise=vectorise, sub=sub, callback=callback,
                      filtered=filtered)


def process_logs(model: Model, scans: "list[Scan | None]", *, chunk: int = 256,
                 states: list[PipelineState] | None = None, vectorise: bool = True,
                 sub: int = SUB_CHUNK) -> tuple[list[PipelineState], list[Output | None]]:
    """Several stacks of scans (logs of one scanner, any lengths) through the pipeline side by side,
    ``chunk`` scans of each at a time (:func:`run_chunk` with a leading axis of logs): the final
    state and the stacked outputs (NumPy, on the host) of each, as :func:`process_log` gives them
    one log at a time.

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
    stacks = on_host([filler if sc is None else sc for sc in scans])
    lengths = [0 if sc is None else int(sc.ranges.shape[0]) for sc in scans]

    def run(state, start, stop):
        real = [max(0, min(chunk, n - start)) for n in lengths]
        firsts = [min(start, int(sc.ranges.shape[0]) - 1) for sc in stacks]  # an ended log: its last scan
        parts = [pad_chunk(sc, a, a + max(r, 1), chunk) for sc, a, r in zip(stacks, firsts, real, strict=True)]
        stacked = jax.tree.map(lambda *a: np.stack(a), *parts)
        state, out = run_chunk((model,), state, stacked, None, jnp.asarray(real, jnp.int32), vectorise=vectorise,
                               sub=sub)
        host = jax.tree.map(np.asarray, out)
        return state, [jax.tree.map(lambda a, k=k, r=r: a[k, :r], host) if r else None for k, r in enumerate(real)]

    state, outs = for_chunks(run, jax.tree.map(lambda *a: jnp.stack(a), *states), max(lengths), chunk)
    final = [jax.tree.map(lambda a, k=k: a[k], state) for k in range(n_logs)]
    per_log = [[o[k] for o in outs if o[k] is not None] for k in range(n_logs)]
    return final, [concat(o) if o else None for o in per_log]
