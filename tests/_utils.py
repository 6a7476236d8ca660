"""Helpers shared by the test modules (``from tests._utils import ...``): dtype-aware tolerances, the emulator's test frame source, and the command line run as a
user runs it, importing this tree."""

import dataclasses
import os
import select
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

# Default tolerances by dtype, as tinygp's ``test_utils.assert_allclose``: what the arithmetic of the
# compared values keeps over the few dozen operations that separate two ways of computing them (float32:
# eps 1.2e-7, held to 1e-5 relative and 1e-6 absolute; float64: eps 2.2e-16, held to 1e-10 and 1e-12).
TOLERANCES = {
    np.dtype(np.float16): (1e-3, 1e-3),
    np.dtype(np.float32): (1e-5, 1e-6),
    np.dtype(np.float64): (1e-10, 1e-12),
}


def tolerance(*arrays) -> tuple[float, float]:
    """``(rtol, atol)`` for the least precise floating dtype among ``arrays`` (float64 when none is
    floating)."""
    dtypes = [np.asarray(a).dtype for a in arrays]
    floats = [d for d in dtypes if np.issubdtype(d, np.floating)]
    worst = min(floats, key=lambda d: np.finfo(d).bits) if floats else np.dtype(np.float64)
    return TOLERANCES.get(np.dtype(worst), TOLERANCES[np.dtype(np.float32)])


def assert_allclose(actual, desired, *, rtol: float | None = None, atol: float | None = None, err_msg: str = ""):
    """``np.testing.assert_allclose`` with default tolerances from the dtypes compared: the least precise
    of the two decides (a float32 result against a float64 reference is held to float32's)."""
    r, a = tolerance(actual, desired)
    np.testing.assert_allclose(
        np.asarray(actual),
        np.asarray(desired),
        rtol=r if rtol is None else rtol,
        atol=a if atol is None else atol,
        err_msg=err_msg,
    )


def frame_source(model):
    """An emulator frame source whose frames can be checked one by one: scan i has beam b at
    500 + (7 b + 13 i) % 3000 mm, every 50th beam no return, and beam 0 holds 1000 + i % 1000."""
    b = np.arange(model.n_beams)

    def source(i):
        r = 500 + (7 * b + 13 * i) % 3000
        r = np.where(b % 50 == 49, 0, r)
        r[0] = 1000 + i % 1000
        inten = (b * 3 + i) % 4000 if model.has_intensity else None
        return r, inten

    return source


def cli_env() -> dict:
    """The environment for ``python -m gtsjax``: this tree first on the path, whatever is installed."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


# ``gtsjax ARGS`` as a child process runs it here: ``python -m tests._child ARGS``, the command line under
# the checks the in-process tests run with (the beartype import hook, strict dtype and rank promotion).
CHILD = (sys.executable, "-m", "tests._child")


def run_cli(*args, timeout: float = 600, **kwargs) -> subprocess.CompletedProcess:
    """``gtsjax ARGS`` in a child process, as a user runs it (under the tests' checks: ``CHILD``); stdout
    and stderr captured."""
    return subprocess.run(
        [*CHILD, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=cli_env(),
        **kwargs,
    )


def cli(capsys, *args) -> subprocess.CompletedProcess:
    """``gtsjax ARGS`` in this process, its stdout and stderr as pytest's ``capsys`` captured them, as
    :func:`run_cli` gives them: for a command whose test needs no child (no signal, terminal or fresh
    interpreter), so that it shares the worker's compiled programs instead of compiling its own."""
    from gtsjax.cli import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    got = capsys.readouterr()
    return subprocess.CompletedProcess([str(a) for a in args], code, got.out, got.err)


def popen_cli(*args, **kwargs) -> subprocess.Popen:
    """``gtsjax ARGS`` started in the background (stdout a pipe of text lines), under the tests' checks
    and with Ctrl-C as a user's terminal delivers it (``tests._child`` restores SIGINT's handler)."""
    kwargs.setdefault("stdout", subprocess.PIPE)
    kwargs.setdefault("stderr", subprocess.PIPE)
    return subprocess.Popen([*CHILD, *map(str, args)], text=True, bufsize=1, env=cli_env(), **kwargs)


def read_lines(proc, n, timeout):
    """Up to ``n`` lines of a child's stdout, until it ends or ``timeout`` passes."""
    lines, deadline = [], time.monotonic() + timeout
    while len(lines) < n and time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
    return lines


class _Msg:
    def __init__(self, schema, channel, message, ros_msg):
        self.schema, self.channel, self.log_time_ns, self.ros_msg = schema, channel, message.log_time, ros_msg


def read_mcap(path) -> list:
    """Every message of an MCAP file, decoded by the ``mcap`` library's ROS 2 decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        return [_Msg(*m) for m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]


def first_scans(log, n: int):
    """The first ``n`` scans of a simulated log, its per-scan extras (the truth's ids and classes) cut
    with them: :meth:`ScanLog.slice` leaves extras alone, as it cannot know a key is per scan."""
    return dataclasses.replace(log.slice(0, n), extra={k: v[:n] for k, v in log.extra.items()})


def stop_with_ctrl_c(proc: subprocess.Popen, timeout: float = 30) -> None:
    """End a child started by :func:`popen_cli` as a user does, Ctrl-C (SIGINT), and wait for it; one
    that does not end within ``timeout`` is killed (no emulator outlives a failed test) and the wait's
    error raised. Its pipes are closed either way."""
    import signal

    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    finally:
        proc.stdout.close()
        proc.stderr.close()


def without_offset_and_floor(model):
    """``model`` with no class's mean error taken off its rows and no variance floor added (the
    shipped model learnt a pose bias): the rows as the filter gives them, for the tests that set
    their own (:func:`offset_and_floor`) or compare the rows with a smoother's raw states."""
    import equinox as eqx

    # Zeros, not None: the same tree as a model with both (``offset_and_floor``, a trained model's), so
    # the same compiled programs (``TrackerParams.with_row_corrections``).
    return eqx.tree_at(lambda m: m.tracker, model, model.tracker.with_row_corrections())


def offset_and_floor(model):
    """The tracker of ``model`` with a robot's mean error to take off (``pose_offset``: 2 cm ahead, 1 cm
    to the right, 3°) and a variance floor to add (``var_floor``: (1 cm)² to each position variance,
    (2°)² to the heading's), every other class without: ``(offset [classes, 3], floor [classes, 2],
    params)``, for the tests of the rows that carry them."""
    k = model.class_index("robot")
    offset = np.zeros((len(model.classes), 3), np.float32)
    offset[k] = (0.02, -0.01, np.radians(3.0))
    floor = np.zeros((len(model.classes), 2), np.float32)
    floor[k] = (1e-4, np.radians(2.0) ** 2)
    return offset, floor, model.tracker.with_row_corrections(offset, floor)
