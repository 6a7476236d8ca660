"""The batch drivers' compile options (``gtsjax.drivers.compile``): what they change in the compiled
program, and that they change nothing in what it computes."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.drivers.compile import batch_jit, batch_options


def kernel_row(z, w, x):
    """A GP's mean the way the pose GPs compute it: squared distances by one product, then exp."""
    d2 = jnp.sum(x * x, 1)[:, None] + jnp.sum(z * z, 1)[None, :] - 2.0 * x @ z.T
    return jnp.exp(-0.5 * jnp.maximum(d2, 0.0)) @ w


def library_fusion_roots(hlo: str) -> list[str]:
    """The root operation of each fusion the compiled program hands to the YNNPACK library."""
    roots = {}
    for m in re.finditer(r"^%?([\w.\-]+) \(.*?\) -> .*? \{\n(.*?)\n\}", hlo, re.S | re.M):
        root = re.search(r"ROOT %?[\w.\-]+ = \S+ ([a-z][\w\-]*)\(", m.group(2))
        roots[m.group(1)] = root.group(1) if root else "?"
    return [roots.get(re.search(r"calls=%?([\w.\-]+)", line).group(1), "?")
            for line in hlo.splitlines() if '"__ynn_fusion"' in line]


def problem():
    rng = np.random.default_rng(0)
    return (jnp.asarray(rng.normal(size=(600, 13)), jnp.float32), jnp.asarray(rng.normal(size=600), jnp.float32),
            jnp.asarray(rng.normal(size=(8, 13)), jnp.float32))


def test_batch_jit_leaves_only_products_to_the_library():
    if not batch_options():
        pytest.skip("this XLA has no YNNPACK fusion option (or the backend is not a CPU)")
    args = problem()
    roots = library_fusion_roots(batch_jit()(kernel_row).lower(*args).compile().as_text())
    assert all(r == "dot" for r in roots), roots


def test_batch_jit_computes_what_jit_computes():
    args = problem()
    f = batch_jit()(kernel_row)
    np.testing.assert_allclose(np.asarray(f(*args)), np.asarray(jax.jit(kernel_row)(*args)), rtol=1e-5, atol=1e-5)
    assert f.__doc__ == kernel_row.__doc__ and f._cache_size() == 1

