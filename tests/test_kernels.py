"""The step's kernel budget (issue 16): a structural check on the compiled program, never a timing.

On XLA:CPU each kernel of a compiled step (a fusion, a dot, a copy, …) costs a few microseconds
whatever its size, and on a GPU a launch, so the step's kernel count is its cost floor. The counter
(``benchmarks.kernels.count_kernels``) reads the optimised HLO text; its own tests hold it to
programs whose structure is known: a loop's body counted per trip, a branch at its largest.
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

from benchmarks.kernels import STEP_KERNEL_BUDGET, compiled_text, count_kernels
from gtsjax.core.pipeline import init_state, step
from gtsjax.io.logs import to_scans
from gtsjax.io.modelfile import load_model
from gtsjax.sim import simulate

DEMO_MODEL = Path(__file__).resolve().parents[1] / "gtsjax" / "data" / "demo-model.npz"


def _body(x):
    return jnp.cumsum(jnp.sort(x)) * 0.5  # a sort and a scan: kernels that never fuse with each other


def test_a_loop_counts_its_body_once_per_trip():
    x = jnp.arange(64, dtype=jnp.float32)
    once = count_kernels(compiled_text(_body, x))
    n = {t: count_kernels(compiled_text(lambda x, t=t: jax.lax.fori_loop(0, t, lambda i, v: _body(v), x), x))
         for t in (3, 7)}
    assert once.total >= 2
    per_trip = (n[7].total - n[3].total) / 4
    assert per_trip >= once.total  # the body's kernels (plus the loop counter's) once per trip
    assert n[3].total == pytest.approx(3 * per_trip, abs=per_trip)
    assert n[3].unknown_trip_loops == n[7].unknown_trip_loops == 0


def test_a_branch_counts_its_largest_arm():
    x = jnp.arange(64, dtype=jnp.float32)

    def f(i, x):
        return jax.lax.switch(i, [lambda v: v + 1.0, lambda v: _body(_body(_body(v)))], x)

    big = count_kernels(compiled_text(lambda x: _body(_body(_body(x))), x)).total
    got = count_kernels(compiled_text(f, jnp.asarray(0, jnp.int32), x)).total
    assert big <= got <= big + 3  # the larger arm, plus the branch index's own


def test_a_branch_returning_many_arrays_is_counted():
    """A conditional whose result is a tuple of six or more arrays (its type then carries an
    ``/*index=5*/`` comment in the HLO text) is counted like one of fewer: its branches' kernels are
    not lost (the counter once read the comment's ``=`` as the end of the instruction's type)."""
    x = jnp.arange(64, dtype=jnp.float32)

    def arms(k):
        def f(i, x):
            return jax.lax.switch(i, [lambda v: tuple(v + j for j in range(k)),
                                      lambda v: tuple(_body(_body(v)) * (j + 1.0) for j in range(k))], x)
        return f

    two = count_kernels(compiled_text(lambda x: _body(_body(x)), x)).total
    for k in (2, 5, 6, 9):
        hlo = compiled_text(arms(k), jnp.asarray(0, jnp.int32), x)
        assert (k >= 6) == ("/*index=5*/" in hlo)
        assert count_kernels(hlo).total >= two, k


def test_the_compiled_step_stays_within_its_kernel_budget():
    """The demo model's whole step (a–g, the model closed over as the live driver compiles it): at most
    ``STEP_KERNEL_BUDGET`` kernels, every loop of a known trip count, no call back to the host."""
    log, site = simulate("spl-crossing", seed=3, n_scans=2)
    model = load_model(DEMO_MODEL).with_site(site)
    scan = jax.tree.map(lambda a: a[0], to_scans(log, model.n_beams))
    hlo = compiled_text(lambda s, x: step(model, s, x), init_state(model), scan)
    got = count_kernels(hlo)
    assert got.unknown_trip_loops == 0, "a loop of data-dependent length in the step"
    assert "callback" not in hlo, "the step calls back to the host"
    assert got.total <= STEP_KERNEL_BUDGET, (
        f"the step runs {got} against a budget of {STEP_KERNEL_BUDGET}: "
        "see benchmarks/kernels.py (python -m benchmarks.kernels) for where they come from")
