"""How the batch drivers compile: ``jax.jit`` with XLA options chosen for programs that take the model
as an argument.

XLA:CPU (jaxlib 0.10) hands some fusions to the YNNPACK library by default. In a program that takes
the model as an argument (batch replay: one compiled chunk serves every model of a shape), the pose
GPs' kernel row became one such fusion that recomputes each inducing point's squared norm for every
candidate of every scan, ``[scans, GPs, inducing points]`` elements: nearly half of batch replay's
time in a ``jax.profiler`` trace of ``perceive_batch``. With those library fusions off, XLA's own
fusions compute the same in a fraction of it, and batch replay runs about twice as fast (figures in
``docs/speed.md``). The live step closes over the model, so XLA folds those norms into constants and
the option changes nothing there; it is left alone.

:func:`batch_jit` applies the option where the backend is a CPU and the installed XLA knows it
(checked once by compiling a trivial program with it); elsewhere it is plain ``jax.jit``.
"""

import functools

import jax

#: XLA options for the batch drivers' programs on a CPU (see the module docstring).
CPU_BATCH_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}


@functools.cache
def batch_options() -> dict[str, str]:
    """:data:`CPU_BATCH_OPTIONS` on a CPU backend whose XLA accepts them, else none."""
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=CPU_BATCH_OPTIONS).lower(1.0).compile()
    except Exception:  # an XLA without the option (older or newer jaxlib): compile as it would
        return {}
    return dict(CPU_BATCH_OPTIONS)


def batch_jit(**kwargs):
    """Decorator: ``jax.jit(fun, **kwargs)`` with :func:`batch_options`, made at the first call (the
    backend is known only then)."""
    return lambda fun: _BatchJit(fun, kwargs)


class _BatchJit:
    """A function jitted at its first call; attributes such as ``lower`` or ``_cache_size`` are the
    jitted function's."""

    def __init__(self, fun, kwargs: dict):
        self._fun, self._kwargs, self._jitted = fun, kwargs, None
        functools.update_wrapper(self, fun)

    def __call__(self, *args, **kwargs):
        return self.jitted(*args, **kwargs)

    @property
    def jitted(self):
        if self._jitted is None:
            self._jitted = jax.jit(self._fun, compiler_options=batch_options() or None, **self._kwargs)
        return self._jitted

    def __getattr__(self, name):  # only for names the instance lacks
        if name.startswith("_") and name != "_cache_size":
            raise AttributeError(name)
        return getattr(self.jitted, name)
