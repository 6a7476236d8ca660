"""Fixed shapes at a cost that follows the load: run a per-row computation on the first ``b`` rows of
a padded array, ``b`` the smallest of a few fixed sizes that holds the rows in use.

The step's arrays have fixed sizes (``K`` candidate slots, ``max_objects`` pose slots) so that it
compiles once, but a typical scan fills few of them: one robot in eight pose slots, a dozen kept
candidates in 32. Each size is a branch of one ``lax.switch``, compiled once with the rest; at run
time only the branch for the rows present runs. The rows must be packed first (the ones in use
before the others); the result's rows past ``b`` are zeros.

Each size is a copy of its stage's code in the compiled program: with the pose regression's four
sizes and the classifier's six, the step's program is about twice the size it is without them, and
takes twice as long to trace and compile (the demo model's batch chunk: 10 s against 5 on 2 cores),
for a step about 1.5× faster where a scan holds few objects. ``GTSJAX_SIZE_BUCKETS=off`` trades
back, for programs that run briefly (a short replay; the tests, ``tests/conftest.py``); ``on`` or
``auto`` (the default: on a CPU only, :func:`enabled`).
"""

import contextlib
import os

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

#: The environment variable that turns the size buckets on or off (:func:`enabled`).
ENV = "GTSJAX_SIZE_BUCKETS"
_forced: "list[bool]" = []


def enabled() -> bool:
    """Whether the stages bucket their rows by default (``perceive``'s ``bucket=None``), read when a
    step is traced: :data:`ENV` ``on`` or ``off``; unset or ``auto``, on a CPU only (on a GPU each
    branch choice waits for its index on the host). Inside :func:`forced`, what it says."""
    if _forced:
        return _forced[-1]
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("", "auto"):
        return jax.default_backend() == "cpu"
    if value in ("on", "off"):
        return value == "on"
    raise ValueError(f"{ENV}={os.environ[ENV]!r}: say on, off or auto")


@contextlib.contextmanager
def forced(on: bool):
    """Steps traced inside bucket (or not) whatever :data:`ENV` says: what a kernel count or a
    comparison of the two forms needs. Programs already traced keep the form they were traced in."""
    _forced.append(bool(on))
    try:
        yield
    finally:
        _forced.pop()


def sizes(cap: int) -> tuple[int, ...]:
    """Bucket sizes up to ``cap``: powers of two below it, then ``cap`` (8 -> 1, 2, 4, 8; 32 -> 1, 2,
    4, 8, 16, 32; 14 -> 1, 2, 4, 8, 14)."""
    out = [1]
    while out[-1] * 2 < cap:
        out.append(out[-1] * 2)
    return tuple(sorted(set(out + [cap])))


def _count(n: Int[Array, ""], axis_name) -> Int[Array, ""]:
    """``n``, or under ``vmap(..., axis_name=axis_name)`` its largest value over the mapped axis: one
    count for the whole batch, so the branch stays a branch (a count that differs per element would
    turn ``lax.switch`` into a select that runs every branch)."""
    n = jnp.asarray(n, jnp.int32)
    return n if axis_name is None else jax.lax.pmax(n, axis_name)


def _which(bs: tuple[int, ...], n: Int[Array, ""]) -> Int[Array, ""]:
    """The index of the smallest size at least ``n`` (the last if none is): how many sizes are below
    ``n``, one comparison and one sum (``searchsorted`` is a loop of a dozen kernels)."""
    return jnp.minimum(jnp.sum(jnp.asarray(bs, jnp.int32) < n, dtype=jnp.int32), len(bs) - 1)


def bucketed(fn, v: Float[Array, "rows features"], n: Int[Array, ""], width: int, axis_name=None):
    """``fn`` (``[b, features]`` -> a tuple of ``[b, width]`` arrays) on the first ``b`` rows of
    ``v``, ``b`` the smallest of :func:`sizes` at least ``n``; each result padded with zeros to
    ``v``'s row count. Under ``vmap`` with ``axis_name``, ``b`` holds the largest ``n`` of the batch."""
    n = _count(n, axis_name)
    cap = v.shape[0]
    bs = sizes(cap)

    def branch(b):
        def run(v):
            return tuple(jnp.zeros((cap, width), o.dtype).at[:b].set(o) for o in fn(v[:b]))
        return run

    which = _which(bs, n)
    return jax.lax.switch(which, [branch(b) for b in bs], v)


def bucketed_rows(fn, args, n: Int[Array, ""], axis_name=None):
    """:func:`bucketed` for a pytree: ``fn`` on the first ``b`` rows (leading axis) of every leaf of
    ``args``; every leaf of its result padded with zeros (False) to ``args``' row count."""
    n = _count(n, axis_name)
    cap = jax.tree.leaves(args)[0].shape[0]
    bs = sizes(cap)

    def branch(b):
        def run(a):
            out = fn(jax.tree.map(lambda x: x[:b], a))
            return jax.tree.map(lambda o: jnp.zeros((cap,) + o.shape[1:], o.dtype).at[:b].set(o), out)
        return run

    which = _which(bs, n)
    return jax.lax.switch(which, [branch(b) for b in bs], args)


def slots_of(idx: Int[Array, " k"], chosen, n: int):
    """Where rows gathered from ``n`` slots by distinct indices ``idx`` go back: per slot, whether a
    ``chosen`` row came from it and which row. A comparison with the slots and an argmax, so that
    results return by one gather of their rows side by side rather than by a scatter per array."""
    hit = (idx[None, :] == jnp.arange(n, dtype=jnp.int32)[:, None]) & chosen[None, :]  # [n, k]
    return jnp.any(hit, axis=1), jnp.argmax(hit, axis=1)
