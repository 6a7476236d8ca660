"""``python -m tests._child ARGS``: ``gtsjax ARGS`` (or ``--module NAME ARGS``) in a child process under the checks the in-process
tests run with (:func:`install_checks`, which ``tests/conftest.py`` calls too): the core's and the GP
library's annotations checked at run time by beartype, strict dtype promotion and rank promotion that
raises. Without them a command run as a subprocess would pass a float64 leaking into the float32 step,
or a silent broadcast, that the same code fails on in-process.

SIGINT is restored to Python's default handler first: a shell that starts the tests in the background
(a CI script's ``&``, ``nohup``) leaves SIGINT ignored, and a child that inherits that never sees a
Ctrl-C (a ``preexec_fn`` would fork a process that runs JAX's threads). Needs this tree's root on
``sys.path`` (``tests._utils.cli_env`` puts it first on ``PYTHONPATH``)."""

import runpy
import signal
import sys

CHECKED_PACKAGES = ("gtsjax.core", "gtsjax.gp")


def install_checks() -> None:
    """The import hook (before anything imports gtsjax) and JAX's settings of the tests: 64-bit types
    available (GP fitting runs in float64), strict dtype promotion, rank promotion an error."""
    if any(name == "gtsjax" or name.startswith("gtsjax.") for name in sys.modules):
        raise RuntimeError("install_checks() must run before gtsjax is imported")
    from jaxtyping import install_import_hook

    install_import_hook(list(CHECKED_PACKAGES), "beartype.beartype")
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_dtype_promotion", "strict")
    jax.config.update("jax_numpy_rank_promotion", "raise")


def main() -> None:
    """``gtsjax ARGS``; or ``--module NAME ARGS``: another module's command line (``python -m NAME``)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    install_checks()
    module = "gtsjax"
    if sys.argv[1:2] == ["--module"]:
        module = sys.argv[2]
        del sys.argv[1:3]
    sys.argv[0] = module
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
