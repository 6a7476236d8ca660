"""Command line: ``gtsjax COMMAND ...``. One module per command; parsing, progress, tables and exit
codes live here and nowhere else."""

import os
import signal
import sys
import threading
import warnings

from ..errors import InputError, InputWarning

# Each import registers its command(s) on ``app``.
from . import convert as _convert  # noqa: E402,F401
from . import demo as _demo  # noqa: E402,F401
from . import evaluate as _evaluate  # noqa: E402,F401
from . import export as _export  # noqa: E402,F401
from . import grade as _grade  # noqa: E402,F401
from . import info as _info  # noqa: E402,F401
from . import plot as _plot  # noqa: E402,F401
from . import replay as _replay  # noqa: E402,F401
from . import run as _run  # noqa: E402,F401
from . import simulate as _simulate  # noqa: E402,F401
from . import tags as _tags  # noqa: E402,F401
from . import train as _train  # noqa: E402,F401
from ._app import app as app  # the Typer application, for those who extend it
from ._app import command, set_quiet
from ._common import ABANDONED, forget_made_folders, remove_made_folders

# Options that take several values in a row (``--background A B C``), as argparse's ``nargs="+"``: Click's
# options take one value each, so the values after the first are given their own option.
_MULTI = ("--background",)
# ``--view`` alone opens the native viewer, ``--view web`` serves the web viewer: Click's options take
# a value or none, so a bare ``--view`` is given its value here.
VIEW_MODES = ("native", "web")


# One vocabulary: ``--scanner`` a scanner type, ``--model`` a model file, ``--laser`` a laser's name in a
# site, ``--seconds`` how long (``demo``, ``enrol``, ``run``), ``--tags`` a flag (simulate robots wearing tags)
# and ``--codes`` the file of designed codes (``enrol``). The old spellings still work for a release,
# with a warning: (command, old) -> new.
RENAMED = {("emulate", "--model"): "--scanner", ("simulate", "--sensor"): "--scanner", ("run", "--duration"): "--seconds",
           ("enrol", "--tags"): "--codes", ("simulate", "--beliefs"): "--out-beliefs",
           **{(c, "--sensor"): "--laser" for c in ("replay", "run", "evaluate", "train")}}
# The shipped model by name: ``--model demo``, ``gtsjax info demo`` (unless a file of that name is here).
SHIPPED = "demo"


def _vocabulary(argv: list[str]) -> list[str]:
    """``argv`` with the old spellings of renamed options (:data:`RENAMED`) in their new ones, each
    said once in a warning, and the shipped model's name (:data:`SHIPPED`) as its path."""
    from pathlib import Path

    from .demo import demo_model_path

    cmd = next((a for a in argv if not a.startswith("-")), None)
    out: list[str] = []
    said: set[str] = set()
    for i, a in enumerate(argv):
        name, eq, value = a.partition("=")
        new = RENAMED.get((cmd, name)) if name.startswith("--") else None
        if new is not None:
            if name not in said:
                warnings.warn(InputWarning(name, f"is now {new} (the old name goes in a later release)"), stacklevel=2)
                said.add(name)
            a = new + eq + value
        prev = out[-1] if out else ""
        if not Path(SHIPPED).exists():
            if a == SHIPPED and (prev == "--model" or (cmd == "info" and i > 0 and not prev.startswith("-"))):
                a = str(demo_model_path())
            elif a == f"--model={SHIPPED}":
                a = f"--model={demo_model_path()}"
        out.append(a)
    return out


def _spread(argv: list[str]) -> list[str]:
    out: list[str] = []
    i = 0
    while i < len(argv):
        out.append(argv[i])
        if argv[i] == "--view" and (i + 1 == len(argv) or argv[i + 1] not in VIEW_MODES):
            out.append("native")
        if argv[i] in _MULTI and i + 1 < len(argv):
            opt = argv[i]
            out.append(argv[i + 1])
            i += 2
            while i < len(argv) and not argv[i].startswith("-"):
                out += [opt, argv[i]]
                i += 1
            continue
        i += 1
    return out


def use_compile_cache() -> None:
    """Keep compiled steps on disk between runs, so that a command's second run on a model of the same
    shapes skips XLA's compilation: in ``$GTSJAX_CACHE_DIR``, else ``$XDG_CACHE_HOME/gtsjax/xla``
    (``~/.cache/gtsjax/xla``); ``GTSJAX_CACHE_DIR=off`` (or empty) keeps nothing. Only compilations
    over 0.2 s are kept (JAX's ``jax_persistent_cache_min_compile_time_secs``)."""
    import os
    from pathlib import Path

    import jax

    env = os.environ.get("GTSJAX_CACHE_DIR")
    if env is not None and env.strip().lower() in ("", "off", "0", "no", "false"):
        return
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    jax.config.update("jax_compilation_cache_dir", env or str(Path(base) / "gtsjax" / "xla"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def memory_maps() -> int | None:
    """How many memory mappings this process holds (lines of ``/proc/self/maps``); None where the
    system does not say (not Linux)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return f.read().count(b"\n")
    except OSError:
        return None


def release_compiled_if_crowded(limit: int = 30_000) -> bool:
    """Drop JAX's in-memory compiled programs (``jax.clear_caches()``) when this process holds more
    than ``limit`` memory mappings; True if it did.

    An executable loaded from the persistent cache (:func:`use_compile_cache`) keeps each of its XLA
    kernels' code in mappings of its own: the step, some 470 kernels, takes about 2 000 mappings so
    loaded, against about 90 compiled afresh. Linux refuses a process more than
    ``vm.max_map_count`` (65 530 by default), and XLA's loader then aborts or crashes
    ("LLVM ERROR: Unable to allocate section memory!"): the 33rd step loaded in one process. A
    command loads a few; a long process that loads many (the test suite, the benchmarks) calls
    this between its parts, and a program dropped here is loaded again from the cache when next
    called."""
    n = memory_maps()
    if n is None or n <= limit:
        return False
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    return True


# Signals that stop a command as Ctrl-C does: service managers and containers stop a program with
# SIGTERM, a closed terminal or SSH session sends SIGHUP.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


def _stop_on_signals() -> list[int]:
    """Make SIGTERM and SIGHUP raise KeyboardInterrupt in the main thread, as SIGINT does, so that every
    command stops the way Ctrl-C stops it: ``run`` sends QT, flushes its CSV and finalises its
    recording and reports, ``emulate`` removes its link, ``replay`` keeps the rows written, ``train``
    writes nothing half-done. Returns the list the handler appends each signal number to (the exit
    status then says which signal, 128 + its number, where the command did not end by itself).
    Only in the main thread (a signal handler cannot be set elsewhere)."""
    seen: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        return seen

    def stop(signum, frame):
        seen.append(signum)
        raise KeyboardInterrupt

    for sig in STOP_SIGNALS:
        _restore.append((sig, signal.signal(sig, stop)))
    return seen


_restore: list = []  # (signal, handler before main) pairs, put back when main returns

# Typer turns a KeyboardInterrupt raised inside a command into exit status 130, silently.
_TYPER_INTERRUPTED = 130


def _interrupted(stopped: list[int]) -> int:
    """One line and the exit status of a command stopped before its end: 128 + the signal's number
    for SIGTERM/SIGHUP, 130 for Ctrl-C."""
    if stopped:
        print(f"gtsjax: stopped by {signal.Signals(stopped[-1]).name}", file=sys.stderr)
        return 128 + stopped[-1]
    print("gtsjax: interrupted", file=sys.stderr)
    return 130


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gtsjax`` console script. A user's mistake (:class:`InputError`) is one
    line on stderr and exit status 2, never a traceback; usage errors are Click's, also status 2."""
    import jax

    # Stamps and GP fitting need float64; the real-time core is float32 by explicit dtypes.
    jax.config.update("jax_enable_x64", True)
    use_compile_cache()
    stopped = _stop_on_signals()
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, InputWarning):  # one line, as an error is, without the source line
            print(f"gtsjax: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    set_quiet(False)
    try:
        code = _dispatch(stopped, argv)
    finally:
        while _restore:
            signal.signal(*_restore.pop())
        warnings.showwarning = shown
        if sys.exc_info()[0] is not None or code != 0:
            remove_made_folders()  # a failed command leaves no empty output folder of its own behind
        forget_made_folders()
    if ABANDONED:
        # A command stopped while a thread of its own computed (``interruptible``): that thread cannot
        # be stopped, and the interpreter's ordinary exit after it aborts in XLA's C++ code (SIGABRT and
        # "terminate called" instead of the stop's own status). Nothing is left to write.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def usage_line(err: Exception) -> str:
    """A usage error (an unknown option, a value of the wrong type or out of its range, a missing
    argument) as one line, as every other mistake of a user is: the command, Click's message, where the
    options are listed. Click's own form is a box of five or six lines."""
    ctx = getattr(err, "ctx", None)
    where = ctx.command_path if ctx is not None else "gtsjax"
    message = " ".join((err.format_message() if hasattr(err, "format_message") else str(err)).split())
    command = where.partition(" ")[2]
    return f"{command + ': ' if command else ''}{message} (see {where} --help)"


def _dispatch(stopped: list[int], argv: list[str] | None) -> int:
    """The command's exit status (see :func:`main`)."""
    import typer

    try:
        rv = command().main(args=_spread(_vocabulary(sys.argv[1:] if argv is None else list(argv))),
                            prog_name="gtsjax", standalone_mode=False)
    except InputError as err:
        print(f"gtsjax: {err}", file=sys.stderr)
        return 2
    except typer.Abort:  # Ctrl-C or end of input at a prompt
        return _interrupted(stopped)
    except typer.TyperException as err:  # Click's usage errors (its exceptions derive from it)
        print(f"gtsjax: {usage_line(err)}", file=sys.stderr)
        return getattr(err, "exit_code", 2)
    except KeyboardInterrupt:
        return _interrupted(stopped)
    except SystemExit as exc:
        rv = exc.code
    # Typer returns the status a command exits with (``typer.Exit``), or the command's own return value
    # (None): Ctrl-C inside a command is its status 130.
    code = rv if isinstance(rv, int) and not isinstance(rv, bool) else (0 if rv is None else 2)
    if code == _TYPER_INTERRUPTED or (stopped and code == 0):
        return _interrupted(stopped)
    if code != 0:
        return code
    # A command that stops itself cleanly on SIGTERM or SIGHUP (``run`` closes its files and returns)
    # still says so, with the status a stopped command has (128 + the signal), as it would have had the
    # signal come a moment earlier, while it compiled.
    return _interrupted(stopped) if stopped else 0
