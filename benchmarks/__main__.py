"""``python -m benchmarks``: run the benchmark sections, write results.json, results.md and scaling.png.

Thread counts are fixed before NumPy or JAX is imported, the same for both sides of every comparison:
``--threads`` sets the BLAS/OpenMP pools (``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``,
``MKL_NUM_THREADS``: NumPy, SciPy, scikit-learn, and jaxlib's LAPACK calls, which go through SciPy's
OpenBLAS) and XLA's CPU intra-op pool. The default, 1, is what a loaded machine makes reproducible:
on 2 busy cores a multi-threaded OpenBLAS spins against other processes (a 300 × 300 Cholesky went
from 0.8 ms to 67 ms here), on either side of a comparison.
"""

import argparse
import os
import sys
import time
import traceback
from pathlib import Path

SECTIONS = ("pipeline", "reference", "gp", "kalman", "smooth", "smooth_lag", "tags", "grade", "scaling", "scip", "live")
HERE = Path(__file__).resolve().parent


def _fix_threads(n: int) -> str:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)
    flags = os.environ.get("XLA_FLAGS", "")
    flags += f" --xla_cpu_multi_thread_eigen={'true' if n > 1 else 'false'} intra_op_parallelism_threads={n}"
    os.environ["XLA_FLAGS"] = flags.strip()
    return os.environ["XLA_FLAGS"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: small sizes, few repetitions (CI)")
    ap.add_argument("--out", type=Path, default=HERE / "results.json",
                    help="results file; results.md and scaling.png are written beside it")
    ap.add_argument("--threads", type=int, default=1, help="threads per library, both sides of each comparison")
    ap.add_argument("--only", nargs="+", choices=SECTIONS, help="run only these sections")
    ap.add_argument("--no-compile-cache", action="store_true",
                    help="do not keep XLA executables in benchmarks/.cache/xla between runs")
    ap.add_argument("--tune-malloc", action="store_true",
                    help="raise glibc's mmap threshold first (keeps XLA's buffers in the heap; process-wide)")
    args = ap.parse_args(argv)
    xla_flags = _fix_threads(args.threads)

    import jax

    jax.config.update("jax_enable_x64", True)  # GP fitting runs in float64; the step is float32 by explicit dtypes
    if not args.no_compile_cache:
        jax.config.update("jax_compilation_cache_dir", str(HERE / ".cache" / "xla"))
    import importlib

    from ._harness import Context, Results, jsonable, machine_info
    from ._report import evaluate_targets, markdown, print_tables

    malloc_tuned = False
    if args.tune_malloc:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        malloc_tuned = bool(libc.mallopt(-3, 64 << 20)) and bool(libc.mallopt(-1, 256 << 20))
    out = args.out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    res = Results(quick=args.quick)
    res.machine = machine_info()
    command = "python -m benchmarks" + (" --quick" if args.quick else "") + (
        f" --threads {args.threads}" if args.threads != 1 else "")
    sections = args.only or list(SECTIONS)
    res.settings = {"threads": args.threads, "command": command, "sections": sections,
                    "compile_cache": not args.no_compile_cache, "malloc_tuned": malloc_tuned, "xla_flags": xla_flags}

    def log(msg: str) -> None:
        print(f"[benchmarks] {msg}", file=sys.stderr, flush=True)

    ctx = Context(quick=args.quick, results=res, out_dir=out.parent, log=log)
    for name in ("sklearn", "filterpy", "tinygp", "dynamax"):
        ctx.peer(name)
    failed = []
    t_all = time.perf_counter()
    for name in sections:
        log(f"{name} ...")
        t0 = time.perf_counter()
        try:
            importlib.import_module(f".bench_{name}", __package__).run(ctx)
        except Exception:  # one failing section must not lose the others' figures
            failed.append(name)
            res.sections.setdefault(name, {})["error"] = traceback.format_exc()
            log(f"{name} FAILED:\n{traceback.format_exc()}")
        res.sections.setdefault(name, {})["seconds"] = round(time.perf_counter() - t0, 1)
        log(f"{name} done in {time.perf_counter() - t0:.0f} s")
        # every section compiles its own programs: drop them before the next (a program loaded from
        # the cache holds many memory mappings, gtsjax.cli.release_compiled_if_crowded)
        jax.clear_caches()
    res.machine["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    res.settings["total_seconds"] = round(time.perf_counter() - t_all, 1)
    evaluate_targets(res)

    import json

    tmp = out.with_name(out.name + ".part")
    tmp.write_text(json.dumps(jsonable(res.to_json()), indent=1, allow_nan=False) + "\n")
    os.replace(tmp, out)
    out.with_suffix(".md").write_text(markdown(res, command))
    print_tables(res)
    log(f"wrote {out}, {out.with_suffix('.md')}" + (", scaling.png" if "scaling" in sections else "")
        + f" in {res.settings['total_seconds']:.0f} s")
    if failed:
        log(f"failed sections: {', '.join(failed)}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
