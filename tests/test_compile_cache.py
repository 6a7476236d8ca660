"""The persistent compilation cache in a long process: programs loaded from it are released by
``release_compiled_if_crowded`` (each holds memory mappings until JAX's caches are cleared; Linux
caps a process's mappings, and XLA crashes past the cap)."""

import subprocess
import sys
import textwrap

import pytest

from gtsjax.cli import memory_maps

pytestmark = pytest.mark.skipif(memory_maps() is None, reason="needs /proc/self/maps (Linux)")

CHILD = textwrap.dedent("""
    import sys
    import jax, jax.numpy as jnp
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    from gtsjax.cli import memory_maps, release_compiled_if_crowded

    def chain(x):
        for i in range(30):          # sorts do not fuse: one kernel each
            x = jnp.sort(x * 1.5 + i)[::-1]
        return x

    x = jnp.arange(64.0)
    base = memory_maps()
    fs = [jax.jit(lambda x: chain(x)) for _ in range(3)]   # three programs, one cache entry
    outs = [f(x).block_until_ready() for f in fs]
    held = memory_maps()
    kept = release_compiled_if_crowded(limit=held + 1_000)  # under the limit: nothing dropped
    released = release_compiled_if_crowded(limit=held - 1)
    print(base, held, memory_maps(), int(kept), int(released), float(outs[0][0]))
""")


def _run(cache):
    r = subprocess.run([sys.executable, "-c", CHILD, str(cache)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    base, held, after, kept, released, first = r.stdout.split()
    return int(base), int(held), int(after), bool(int(kept)), bool(int(released)), float(first)


def test_programs_loaded_from_the_cache_are_released(tmp_path):
    compiled = _run(tmp_path)   # compiles, writes the cache entry
    loaded = _run(tmp_path)     # the three programs come from the cache
    for base, held, after, kept, released, _ in (compiled, loaded):
        assert not kept and released
        assert held > base and after < held
        assert after - base < (held - base) / 2   # most of what the programs held is given back
    assert compiled[5] == loaded[5]               # the loaded program computes what the compiled one did
