"""Test-wide JAX settings, as the command line sets them: 64-bit types available (GP fitting runs in
float64; the step is float32 by explicit dtypes), and strict dtype and rank promotion so that an
accidental float64 in the float32 core, or a silent broadcast, fails loudly."""

import os
import tempfile
from pathlib import Path

import pytest

# XLA told to compile fast rather than run at its fastest, in this process and every ``gtsjax`` child
# (they inherit the environment), set before JAX starts its backend: CI's time was more than half
# compiling, at some 50 ms per XLA kernel, and a test runs a program a few times where a user runs it
# for hours. XLA:CPU's older loop emitter instead of its MLIR fusion emitters, and LLVM at its first
# optimisation level, compile the live step twice as fast (10 → 5 s here) and run it at 1.5 ms instead
# of 0.9; what each program computes is the same. (LLVM's optimisation off compiles faster still, 3 s,
# but runs the step at 3 ms: the tests that train and check, or stream a laser in real time, lost more
# than the compiles gained.) Every user's command, and ``python -m benchmarks`` run by hand, compile
# with XLA's defaults (the benchmarks' smoke run in ``tests/test_benchmarks.py`` inherits these flags: it
# checks that the command runs, its figures are not measurements); ``benchmarks/kernels.py`` counts
# kernels under XLA's defaults whatever this says. ``GTSJAX_TEST_XLA_FLAGS=default`` runs the tests with XLA's defaults too.
TEST_XLA_FLAGS = "--xla_backend_optimization_level=1 --xla_cpu_use_fusion_emitters=false"
if os.environ.get("GTSJAX_TEST_XLA_FLAGS", "").strip().lower() != "default":
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()

# The stages' size buckets off (``gtsjax.core.buckets``), in this process and every child, for the same
# reason: each bucket is a copy of its stage in the program, and the step without them traces and
# compiles in half the time (the demo model's batch chunk 5 s against 10 here) and runs 1.5–2× slower,
# which a test's few hundred scans do not feel. What a step computes is the same to float32 round-off:
# ``tests/test_buckets.py`` runs the bucketed step, live and in batch, against this one, and
# ``benchmarks/kernels.py`` counts the kernels of the bucketed step users run.
os.environ.setdefault("GTSJAX_SIZE_BUCKETS", "off")

from tests._child import install_checks  # noqa: E402

# The core's and the GP library's annotations (shapes, dtypes) checked at run time in every test: when a
# function is traced, or called eagerly; installed before anything imports gtsjax. With JAX's settings
# above. The same in every ``gtsjax`` child the tests start (``tests._utils.run_cli`` and ``popen_cli``
# run ``python -m tests._child``).
install_checks()

# Compiled programs kept on disk, as the command line keeps them (``gtsjax.cli.use_compile_cache``), in a
# folder of the tests' own that every worker and every ``gtsjax`` subprocess shares: the step of the demo
# model compiles once per run, not once per command. ``GTSJAX_CACHE_DIR=off`` turns it off.
os.environ.setdefault("GTSJAX_CACHE_DIR", os.path.join(tempfile.gettempdir(), f"gtsjax-tests-xla-{os.getuid()}"))
import jax  # noqa: E402

from gtsjax.cli import release_compiled_if_crowded, use_compile_cache  # noqa: E402  (after the import hook)

use_compile_cache()


# The test files that each hold a worker for a minute or more (``--durations=0`` of full runs on 2 cores),
# the longest first. xdist hands whole files (``--dist loadfile``) to the workers in collection order
# (``--no-loadscope-reorder``: its own order counts tests, not seconds); with these first, the long ones
# run while the other worker works through the rest, and the run does not end on one worker's long file
# with the other idle (in a run with three workers the 8-minute recordings file came last and ran alone).
LONGEST_FIRST = ("test_recordings.py", "test_docs_blocks.py", "test_benchmarks.py", "test_cli_commands.py",
                 "test_pipeline.py", "test_gp.py", "test_reference.py", "test_cli_paths.py", "test_enrol.py",
                 "test_several.py", "test_signals.py", "test_openset.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's tests in order


# Reading ``/proc/self/maps`` (some 30 000 lines in a busy worker) after every one of some 1 500 tests
# cost half a minute of CI, and what fills it is a program loaded from the compilation cache (~2 000
# mappings each) or compiled afresh (~90 for the step; a few for each of the many tiny programs of
# eager operations). So the mappings are counted after a test that loaded or compiled a program of a
# size that the cache keeps, and after every 25th test whatever it did. ``[big programs, tests]``
# since the last count.
_SINCE_COUNTED = [0, 0]


def _count_program(event: str, duration: float = 1.0, **_kwargs) -> None:
    if event.endswith("/cache_hits") or (event.endswith("/backend_compile_duration") and duration >= 0.2):
        _SINCE_COUNTED[0] += 1


jax.monitoring.register_event_listener(_count_program)
jax.monitoring.register_event_duration_secs_listener(_count_program)


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """A worker runs hundreds of tests in one process, and every step it loads from the compilation
    cache holds ~2 000 memory mappings until JAX's caches are cleared: past Linux's 65 530 the next
    load crashes the worker (``release_compiled_if_crowded``). Cleared after any test that leaves
    the process above half of that (counted as said above)."""
    yield
    _SINCE_COUNTED[1] += 1
    if _SINCE_COUNTED[0] or _SINCE_COUNTED[1] >= 25:
        _SINCE_COUNTED[:] = [0, 0]
        release_compiled_if_crowded()


SHARED = Path(os.environ.get("GTSJAX_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def need(what: bool, why: str) -> None:
    """Skip the test where ``what`` is false on a developer's machine; fail it in CI (``CI=true``),
    where every tool it needs is installed by ``.ci/run`` and a skip would be a test passing by not
    running."""
    if not what:
        if in_ci():
            pytest.fail(f"{why} (CI=true: this test must run)", pytrace=False)
        pytest.skip(why)


def shared_path(*parts: str) -> Path:
    """``SHARED/parts...`` (the real captures and logs beside the clone). Missing, the test is skipped on a
    developer's machine, and fails in CI (``CI=true``): there the real data must be present, or the
    tests on it would pass by not running."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        what = f"shared data not found at {p}"
        if in_ci():
            pytest.fail(f"{what} (CI=true: the tests on real captures and logs must run)", pytrace=False)
        pytest.skip(what)
    return p


@pytest.fixture(scope="session")
def shared_file():
    """:func:`shared_path` for the tests: ``shared_file("data", "logs", NAME)`` skips (fails in CI) when
    the file is not there."""
    return shared_path


def _once_per_run(tmp_path_factory, name: str, make) -> "tuple[Path, dict]":
    """``make(folder)``'s result, made once per run by the first worker that asks, in a folder every
    worker sees; a second worker waits for it and reads what the first left (``NAME.pkl``: the
    objects ``make`` returned, pickled, so that a model file's round trip is still tested against the
    trained model, not against itself)."""
    import fcntl
    import pickle

    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):  # each worker's base is a folder of the run's own
        shared = shared.parent
    d = shared / name
    d.mkdir(exist_ok=True)
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes (or its process ends)
        done = d / f"{name}.pkl"
        if not done.exists():
            part = d / f"{name}.pkl.part"
            part.write_bytes(pickle.dumps(make(d)))
            part.replace(done)
        return d, pickle.loads(done.read_bytes())


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """A small model trained on a subsample of the SPL training grid and a log with legs, shared by the
    test modules (:func:`_once_per_run`)."""
    d, made = _once_per_run(tmp_path_factory, "tiny", _train_tiny)
    return {"dir": d, "path": d / "model.npz", **made}


@pytest.fixture(scope="session")
def utm_small(tmp_path_factory) -> Path:
    """A small model for the UTM-30LX (a scanner with intensities), trained on its scans of the SPL
    training grid and a log with legs with the intensities taken out: a model that does not read them
    (``uses_intensity`` False), as ``run --no-intensity`` needs, and the same classes as the shipped
    URG-04LX model, as lasers of two scanners on one field need. Its file; made once per run
    (:func:`_once_per_run`)."""
    d, _ = _once_per_run(tmp_path_factory, "utm_small", _train_utm_small)
    return d / "utm.npz"


def _train_utm_small(d: Path) -> dict:
    import dataclasses

    from gtsjax.io.modelfile import save_model
    from gtsjax.sim import simulate
    from gtsjax.train import TrainConfig, train

    config = dataclasses.replace(TrainConfig(), max_per_class=60, max_pose_examples=80, n_inducing=32, restarts=1,
                                 check_pipeline=False)  # a model to run; training's tracking check is tested apart
    train_log, site = simulate("spl-train", seed=11, n_scans=500, sensor="UTM-30LX")
    legs, _ = simulate("spl-legs", seed=12, n_scans=150, sensor="UTM-30LX")
    assert train_log.intensities is not None and legs.intensities is not None
    logs = [dataclasses.replace(lg, intensities=None) for lg in (train_log, legs)]
    model, report = train(logs, site, config)
    assert model.sensor_model == "UTM-30LX" and not model.uses_intensity
    save_model(model, d / "utm.npz", summary=report)
    return {}


def _train_tiny(d: Path) -> dict:
    import dataclasses

    from gtsjax.io import save_site
    from gtsjax.io.modelfile import save_model
    from gtsjax.sim import simulate
    from gtsjax.train import TrainConfig, train

    config = dataclasses.replace(TrainConfig(), max_per_class=60, max_pose_examples=80, n_inducing=32, restarts=1,
                                 check_pipeline=False)  # a model to run; training's tracking check is tested apart
    train_log, site = simulate("spl-train", seed=11, n_scans=500)
    legs, _ = simulate("spl-legs", seed=12, n_scans=150)
    model, report = train([train_log, legs], site, config)
    save_model(model, d / "model.npz", summary=report)
    save_site(site, d / "site.json")
    return {"model": model, "site": site, "report": report, "train_log": train_log, "config": config}
