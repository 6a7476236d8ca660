"""Count the kernels a compiled XLA program runs: the unit of a step's fixed cost, apart from its
arithmetic (on XLA:CPU each costs a microsecond or more, whatever its size; on a GPU, a launch).

A kernel is a top-level instruction of a computation that does work: a fusion, a dot, a copy, a
reduce, a scatter, a custom call (LAPACK), … Not kernels: parameters, constants, tuples and their
elements, bitcasts. Control flow is followed: a ``call`` counts its callee's kernels, a
``conditional`` the largest of its branches' (one runs), a ``while`` its condition's and body's
kernels per trip (times XLA's ``known_trip_count`` where it knows one; once, and flagged, where not).

    python -m benchmarks.kernels          # the step of the shipped model, by stage and kind
    python -m benchmarks.kernels --where  # … and by the gtsjax function each kernel was traced in
"""

import collections
import dataclasses
import json
import re
import sys
from pathlib import Path

# The most kernels the shipped model's step may run (``tests/test_kernels.py`` fails above it): where
# issue 16 has taken it so far (449), plus the 17 of stage f's rigid check of the associations
# (f_maptransform.rigid_inliers: a wrong landmark took a transform metres off), less the 4 that stage a's
# nearest-first choice of segments took off, plus the 4 of each candidate's position and verdict in
# the output (``Output.cand_*``, drawn by the view): 466; less the 51 that stage e′'s Gauss–Newton steps
# as a loop of a fixed trip count took off (one copy of a step's code instead of six, which XLA fuses
# into fewer kernels): 416; 415 at the next count, plus the 4 of each track slot's hold and estimated
# motion in the output (``Output.track_live``, ``track_hold``, ``track_speed``, ``track_turn_rate``:
# why a run reports nothing, issue 38): 419; plus the 2 of the guesses (``d_classify.classify``: a
# candidate the classifier takes for background, posed and refined as the tracked class it could be,
# so that a confirmed track follows its robot past a look-alike of its side, issue 38): 421; plus the 1
# of each track's x–y covariance (``Output.track_cov_xy``: the CSV's optional column and the bag's
# covariance, issue 39): 422. Those counts missed every instruction whose result is a tuple of six or
# more arrays (the ``/*index=5*/`` in its type ended the match), and with it stage e′'s bucketed branch
# once its result grew to six arrays: the same step counted again without that fault, as the test compiles it, is 494. The issue's
# target is 150; each reduction lowers this ratchet. Plus the 3 of stage e′'s sides merged and passed
# on best first (``e_refine.merge_sides``, one ``top_k``; issue 38, item 5): 497. A model trained since
# searches every side (``Outline.prior_search``): its step is 504 ("step, searching sides"). Plus the 4
# of the heading gate tested with a detection's sides together, each weighted by its probability
# (``g_heading.gate_statistic``; the state's gate is its main hypothesis's, and the vmapped χ² test of
# before is gone; issue 55): 501, and 508 searching sides. The model shipped since 2026-12-07 was
# trained with the search and with the direction of travel as heading evidence (``TrackerParams.
# motion_heading``, ``g_heading.motion_evidence``: 11 kernels, the von Mises of each hypothesis about
# each track's travel), which the model before lacked: 521, the step as users now run it (its pose
# offset, ``TrackerParams.off``, fuses into the rows' kernels and costs none).
STEP_KERNEL_BUDGET = 521

_FREE = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast", "after-all", "partition-id",
         "replica-id", "opt-barrier", "add-dependency"}
_COMP = re.compile(r"^(ENTRY )?%?([\w.\-]+) (\(.*\)) -> .* \{$")
_COMMENT = re.compile(r"/\*.*?\*/")
_INSTR = re.compile(r"^\s*(?:ROOT )?%?[\w.\-]+ = (?:\([^=]*?\)|[^ ]+) ([a-z][\w\-]*)\((.*)$")


@dataclasses.dataclass
class KernelCount:
    """Kernels run by one call of a compiled program."""

    total: int
    by_kind: dict[str, int]  # fusion, dot, copy, … (control flow resolved into its callees' kernels)
    unknown_trip_loops: int  # while loops whose trip count XLA does not know (counted once)

    def __str__(self) -> str:
        kinds = ", ".join(f"{k} {v}" for k, v in sorted(self.by_kind.items(), key=lambda kv: -kv[1]))
        extra = f"; {self.unknown_trip_loops} loop(s) of unknown trip count counted once" if self.unknown_trip_loops else ""
        return f"{self.total} kernels ({kinds}){extra}"


def _computations(hlo: str, keep_lines: bool = False) -> tuple[dict[str, list[tuple[str, str]]], str]:
    comps: dict[str, list[tuple[str, str]]] = {}
    entry, name = None, None
    for line in hlo.splitlines():
        if name is None:
            m = _COMP.match(line)
            if m:
                name = m.group(2)
                comps[name] = []
                if m.group(1):
                    entry = name
            continue
        if line.startswith("}"):
            name = None
            continue
        # Comments out first: a tuple of six or more elements has ``/*index=5*/`` in its type, whose
        # ``=`` would otherwise end the type early and lose the instruction (a conditional returning
        # many arrays, and every kernel in its branches, went uncounted).
        m = _INSTR.match(_COMMENT.sub("", line))
        if m:
            comps[name].append((m.group(1), line if keep_lines else m.group(2)))
    if entry is None:
        raise ValueError("no ENTRY computation in the HLO text")
    return comps, entry


def _callees(attrs: str, *keys: str) -> list[str]:
    out = []
    for key in keys:
        m = re.search(key + r"=\{([^}]*)\}", attrs)
        if m:
            out += [c.strip().lstrip("%") for c in m.group(1).split(",") if c.strip()]
            continue
        m = re.search(key + r"=%?([\w.\-]+)", attrs)
        if m:
            out.append(m.group(1))
    return out


def _frames(hlo: str):
    """Stack frame id -> ``[(file, function, line), …]`` innermost first, from the HLO text's tables."""
    def table(name):
        m = re.search(r"\n" + name + r"\n(.*?)(?:\n\n|\Z)", hlo, re.S)
        return m.group(1) if m else ""
    files = dict(re.findall(r'^(\d+) "([^"]+)"', table("FileNames"), re.M))
    funcs = dict(re.findall(r'^(\d+) "([^"]+)"', table("FunctionNames"), re.M))
    locs = {a: (files.get(f, "?"), funcs.get(fn, "?"), int(line)) for a, f, fn, line in re.findall(
        r"^(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", table("FileLocations"), re.M)}
    stack = re.findall(r"^(\d+) \{file_location_id=(\d+) parent_frame_id=(\d+)", table("StackFrames"), re.M)
    frames = {f: loc for f, loc, _ in stack}
    parents = {f: parent for f, _, parent in stack}

    def chain(fid: str):
        out, seen = [], set()
        while fid in frames and fid not in seen:
            seen.add(fid)
            if frames[fid] in locs:
                out.append(locs[frames[fid]])
            fid = parents.get(fid, "")
        return out
    return chain


def count_kernels(hlo: str, *, where: bool = False) -> KernelCount:
    """Kernels run by one call of the program whose optimised HLO text is ``hlo``
    (``jax.jit(f).lower(...).compile().as_text()``). With ``where``, ``by_kind`` counts them by the
    innermost gtsjax function (and line) each was traced in instead."""
    comps, entry = _computations(hlo, keep_lines=where)
    chain = _frames(hlo) if where else None
    unknown = [0]
    memo: dict[str, collections.Counter] = {}

    def key(op: str, line: str) -> str:
        if chain is None:
            return op
        m = re.search(r"stack_frame_id=(\d+)", line)
        inner = [f for f in (chain(m.group(1)) if m else []) if "/gtsjax/" in f[0] and not f[0].endswith("precision.py")]
        return f"{Path(inner[0][0]).stem}.{inner[0][1]}:{inner[0][2]}" if inner else f"({op})"

    def count(name: str) -> collections.Counter:
        if name in memo:
            return memo[name]
        c: collections.Counter = collections.Counter()
        for op, rest in comps.get(name, []):
            if op in _FREE:
                continue
            if op == "call":
                c += count(_callees(rest, "to_apply")[0])
            elif op == "conditional":
                branches = _callees(rest, "branch_computations") or _callees(rest, "true_computation",
                                                                              "false_computation")
                c += max((count(b) for b in branches), key=lambda k: sum(k.values()), default=collections.Counter())
            elif op == "while":
                m = re.search(r'"known_trip_count":\{"n":"(\d+)"\}', rest)
                n = int(m.group(1)) if m else 1
                unknown[0] += m is None
                per_trip = count(_callees(rest, "body")[0]) + count(_callees(rest, "condition")[0])
                c += collections.Counter({k: v * n for k, v in per_trip.items()})
            else:
                c[key(op, rest)] += 1
        memo[name] = c
        return c

    total = count(entry)
    return KernelCount(sum(total.values()), dict(total), unknown[0])


#: XLA options a program is counted under, whatever ``XLA_FLAGS`` the process runs with: the kernels
#: XLA:CPU's fusion emitters (its default) make, as every user's command compiles them. The tests compile
#: with the older loop emitter, which compiles faster and splits a few fusions differently
#: (``tests/conftest.py``); LLVM's optimisation level, which they lower too, leaves the HLO as it is.
COUNTED_UNDER = {"xla_cpu_use_fusion_emitters": True}


def compiled_text(fn, *args) -> str:
    """The optimised HLO text of ``jax.jit(fn)`` for ``args``, compiled under :data:`COUNTED_UNDER`
    where the backend is a CPU, and traced with the size buckets a user's step has
    (:func:`gtsjax.core.buckets.enabled` without ``GTSJAX_SIZE_BUCKETS``, which the tests turn off)."""
    import jax

    from gtsjax.core import buckets

    options = COUNTED_UNDER if jax.default_backend() == "cpu" else None
    with buckets.forced(jax.default_backend() == "cpu"):
        return jax.jit(fn, compiler_options=options).lower(*args).compile().as_text()


def main() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    from gtsjax.core import pipeline as P
    from gtsjax.io.logs import to_scans

    from . import _data

    log, site = _data.scenario("spl-crossing", 3, 5)
    model = _data.demo_model(site)
    scan = jax.tree.map(lambda a: a[0], to_scans(log, model.n_beams))
    state = P.init_state(model)
    step_hlo = compiled_text(lambda s, x: P.step(model, s, x), state, scan)
    report = {"step": count_kernels(step_hlo), "step without outline": count_kernels(
        compiled_text(lambda s, x, m=model.without_outline(): P.step(m, s, x), state, scan))}
    # A model calibrated before stage e′'s search over every side has no ``prior_search`` and fits the
    # learnt sides only; the shipped model (since 2026-12-07) searches, so both lines count the same.
    import equinox as eqx
    import jax.numpy as jnp

    searching = eqx.tree_at(lambda m: m.outline.prior_search, model,
                            jnp.full(len(model.classes), 0.05, jnp.float32), is_leaf=lambda x: x is None)
    report["step, searching sides"] = count_kernels(
        compiled_text(lambda s, x: P.step(searching, s, x), state, scan))
    percept = jax.jit(P.perceive, static_argnames="bucket")(model, scan)
    report["perceive (a–e′)"] = count_kernels(compiled_text(lambda x: P.perceive(model, x), scan))
    report["update (f–g)"] = count_kernels(compiled_text(lambda s, p, x: P.update(model, s, p, x), state, percept, scan))
    # Several lasers (issue 18): one laser's scan, two lasers' transforms and one track table.
    from gtsjax.core import multi as M

    several = M.init_several(model, jnp.asarray([site.sensor_pose, site.sensor_pose], jnp.float32))
    report["step, 2 lasers"] = count_kernels(compiled_text(
        lambda s, x, k, d: M.step_several(model, s, x, k, d), several, scan, jnp.asarray(0, jnp.int32),
        jnp.asarray(0.1, jnp.float32)))
    for k, v in report.items():
        print(f"{k:24s} {v}")
    if "--where" in sys.argv[1:]:
        by = count_kernels(step_hlo, where=True).by_kind
        funcs = collections.Counter()
        for k, v in by.items():
            funcs[k.rsplit(":", 1)[0]] += v
        print("\nthe step's kernels by the function they were traced in (kernels: function):")
        for k, v in funcs.most_common():
            print(f"{v:5d}  {k}")
        print("\n… and by line:")
        for k, v in sorted(by.items(), key=lambda kv: -kv[1])[:40]:
            print(f"{v:5d}  {k}")
    print(json.dumps({k: dataclasses.asdict(v) for k, v in report.items()}))


if __name__ == "__main__":
    main()
