"""Read the per-test compile profile ``tests/_compile_profile.py`` wrote and print where the time went:
JAX's compile events summed, the files by time, the programs compiled most, and the slowest tests
with their compile share. Issue 54's tool for choosing what to cut::

    GTSJAX_TEST_PROFILE=/tmp/prof pytest -p tests._compile_profile
    python scripts/test_profile.py /tmp/prof
"""

import argparse
import collections
import json
from pathlib import Path

COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="the folder GTSJAX_TEST_PROFILE named")
    ap.add_argument("--top", type=int, default=25, help="rows per table")
    args = ap.parse_args(argv)
    if args.top < 1:
        ap.error(f"--top {args.top}: rows per table, at least 1")
    if not args.folder.is_dir():
        ap.error(f"{args.folder}: not a folder (the one GTSJAX_TEST_PROFILE named)")
    tests: dict[str, dict] = {}
    files = sorted(args.folder.glob("*.json"))
    if not files:
        ap.error(f"{args.folder}: no profile files (*.json) there; run pytest -p tests._compile_profile first")
    for f in files:
        tests.update(json.loads(f.read_text()))
    events: collections.Counter = collections.Counter()
    per_file: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    program_s: collections.Counter = collections.Counter()
    program_n: collections.Counter = collections.Counter()
    for node, t in tests.items():
        c = per_file[node.split("::")[0]]
        c["wall"] += t["wall_s"]
        c["compile"] += t["events_s"].get(COMPILE, 0.0)
        c["trace"] += sum(t["events_s"].get(e, 0.0) for e in TRACE)
        events.update(t["events_s"])
        for name, s in t["compiled"]:
            program_s[name] += s
            program_n[name] += 1
    print(f"{len(tests)} tests, {sum(t['wall_s'] for t in tests.values()):.0f} s of test time (in-process)")
    for e, s in events.most_common():
        print(f"  {s:8.1f} s  {e}")
    print("\nfiles: wall, XLA compile, tracing+lowering [s]")
    for f, c in sorted(per_file.items(), key=lambda kv: -kv[1]["wall"])[: args.top]:
        print(f"  {c['wall']:7.1f} {c['compile']:7.1f} {c['trace']:6.1f}  {f}")
    print("\nprograms compiled: seconds, count")
    for name, s in program_s.most_common(args.top):
        print(f"  {s:7.1f} {program_n[name]:5d}  {name}")
    print("\nslowest tests: wall, XLA compile [s]")
    for node, t in sorted(tests.items(), key=lambda kv: -kv[1]["wall_s"])[: args.top]:
        print(f"  {t['wall_s']:7.1f} {t['events_s'].get(COMPILE, 0.0):7.1f}  {node}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
