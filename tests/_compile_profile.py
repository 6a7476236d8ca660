"""Where the suite's time goes, test by test: a pytest plugin (``-p tests._compile_profile``) that adds
up JAX's own compile events (XLA's backend compilation, tracing, lowering, the persistent cache's
savings) and names each compiled program, per test, and writes them to
``$GTSJAX_TEST_PROFILE/<worker>.json``. ``python scripts/test_profile.py FOLDER`` reads them.

Issue 54 (CI in 15 minutes): compiling was a third of the in-process time, and one program, the
batch chunk (``run_chunk``), some 12 s a compilation on 2 cores, was compiled 50 times. Not on by
default: the names come from JAX's DEBUG log records, which every test then carries."""

import collections
import json
import logging
import os
import re
import time
from pathlib import Path

import pytest

_EVENTS: "collections.defaultdict[str, float]" = collections.defaultdict(float)
_COMPILED: list[tuple[str, float]] = []
_PER_TEST: dict[str, dict] = {}
_FINISHED = re.compile(r"Finished XLA compilation of (\S+) in ([0-9.]+) sec")
_LOGGERS = ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler")


class _Names(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        m = _FINISHED.search(record.getMessage())
        if m:
            _COMPILED.append((m.group(1), float(m.group(2))))


def _folder() -> Path:
    return Path(os.environ.get("GTSJAX_TEST_PROFILE", "test-profile"))


def pytest_configure(config) -> None:
    folder = _folder()
    if folder.exists() and not folder.is_dir():
        raise pytest.UsageError(f"GTSJAX_TEST_PROFILE={folder}: a file, not a folder for the profile")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise pytest.UsageError(f"GTSJAX_TEST_PROFILE={folder}: cannot make the folder ({err.strerror})") from None
    import jax.monitoring

    def listen(event: str, duration: float, **_kwargs) -> None:
        _EVENTS[event] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    for name in _LOGGERS:
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(_Names())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    before, n0 = dict(_EVENTS), len(_COMPILED)
    t0, c0 = time.perf_counter(), time.process_time()
    yield
    _PER_TEST[item.nodeid] = {
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,  # this process's: a test's child processes are not in it
        "events_s": {k: v - before.get(k, 0.0) for k, v in _EVENTS.items() if v - before.get(k, 0.0) > 1e-4},
        "compiled": _COMPILED[n0:],
    }


def pytest_sessionfinish(session) -> None:
    folder = _folder()
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (folder / f"{worker}.json").write_text(json.dumps(_PER_TEST))
