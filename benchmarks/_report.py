"""Targets, profiles of missed targets, and the Markdown and terminal tables of one run."""

import numpy as np

TARGET_STEP_P99_US = 1000.0
TARGET_BATCH = 3000.0
TARGET_VS_REFERENCE = 30.0
TARGET_GP_SPEEDUP = 5.0  # issue 16 (the benchmarks' first issue asked 3×)
TARGET_GRADE_S = 30.0  # issue 41: grade a 10-minute two-laser log of 10 robots in ≤ 30 s
# Issue 16's further targets, beside the first issue's above: the step's ratio to the reference at p99,
# batch replay against the reference's per-scan rate, live latency at 40 Hz, SCIP decode.
TARGET_VS_REFERENCE_P99 = 20.0
TARGET_BATCH_VS_REFERENCE = 70.0
TARGET_LIVE_P99_MS = 2.0
TARGET_SCIP_DECODE_US = 50.0
LML_TOLERANCE = 0.1  # nats: "equal" LML


def fmt(value: float, unit: str) -> str:
    """A number in its unit, latencies switched to ms above 1000 µs."""
    if not np.isfinite(value):
        return "n/a"
    if unit == "us":
        return f"{value:,.0f} µs".replace(",", " ") if value < 1000 else f"{value / 1e3:.2f} ms"
    if unit == "ms":
        return f"{value:.2f} ms"
    if unit == "s":
        return f"{value:.2f} s"
    if unit.endswith("/s"):
        return f"{value:,.0f} {unit}".replace(",", " ")
    return f"{value:.3g} {unit}"


def _stage_breakdown(res, key: str) -> dict:
    names = [m for m in res.measurements if m["name"].startswith(f"step.{key}.stage.") and
             not m["name"].endswith("frontend_a_to_c")]
    total = sum(m["median"] for m in names) or 1.0
    return {m["name"].rsplit(".", 1)[1]: {"median_us": round(m["median"], 1), "p99_us": round(m["p99"], 1),
                                          "share_of_stage_sum": round(m["median"] / total, 3)} for m in names}


def evaluate_targets(res) -> None:
    """Fill ``res.targets`` (met or missed, with the measured value) and, for every target, the
    profile that explains the figure (``res.profiles``); the Markdown shows the profile of a missed one."""
    targets = []
    load = res.machine.get("load_average_start") or [float("nan")]
    if res.has("step.urg-04lx.end_to_end"):
        m = res.get("step.urg-04lx.end_to_end")
        floor = res.get("step.dispatch_floor")["median"] if res.has("step.dispatch_floor") else float("nan")
        stages = _stage_breakdown(res, "urg-04lx")
        top = max(stages.items(), key=lambda kv: kv[1]["median_us"]) if stages else ("?", {"median_us": float("nan")})
        res.profiles["step_p99"] = {"stages": stages, "dispatch_floor_us": floor, "median_us": m["median"],
                                    "p99_us": m["p99"], "p99_over_median": m["p99"] / m["median"],
                                    "load_average_start": load,
                                    "xla_cost_per_stage": res.profiles.get("xla_cost.urg-04lx", {})}
        met = m["p99"] <= TARGET_STEP_P99_US
        if m["median"] <= TARGET_STEP_P99_US:
            why = (f"The median ({fmt(m['median'], 'us')}) is within the p99 budget; the tail is {m['p99'] / m['median']:.1f}× "
                   f"the median: host-side jitter (the scheduler, other processes: load average {load[0]:.1f} at the "
                   "start on this machine) more than computation. "
                   + ("What would widen the margin" if met else "What would close it")
                   + ": an idle core for the live loop (taskset/isolcpus), and a cheaper largest stage, "
                   f"{top[0]} ({fmt(top[1]['median_us'], 'us')} median on its own).")
        else:
            why = (f"The median itself ({fmt(m['median'], 'us')}) is over the budget; the largest stage is {top[0]} "
                   f"({fmt(top[1]['median_us'], 'us')} median); every jitted call also pays a dispatch floor of "
                   f"{fmt(floor, 'us')}. See the stage breakdown below.")
        n_step = res.sections.get("pipeline", {}).get("step_kernels")
        chain = res.get("step.kernel_chain.step") if res.has("step.kernel_chain.step") else None
        if n_step and chain:
            k = chain["params"]["kernels"]
            why += (f" The step runs {n_step} kernels (`python -m benchmarks.kernels`); on this machine a compiled "
                    f"chain of {k} kernels with no arithmetic to speak of takes {fmt(chain['median'], 'us')} "
                    f"({chain['median'] / k:.2f} µs a kernel), so the count alone prices the step at about "
                    f"{fmt(n_step * chain['median'] / k, 'us')}.")
        cost = res.profiles.get("xla_cost.urg-04lx", {})
        parts = {k: c.get("mflop", 0.0) for k, c in cost.items() if k != "frontend_a_to_c"}
        if sum(parts.values()) > 0 and stages:
            heavy = max(parts, key=parts.get)
            rest_mflop = sum(parts.values()) - parts[heavy]
            rest_us = sum(v["median_us"] for k, v in stages.items() if k != heavy)
            why += (f" XLA counts {sum(parts.values()):.1f} MFLOP per scan, {parts[heavy]:.1f} of them in {heavy} "
                    f"({parts[heavy] / stages[heavy]['median_us'] * 1e3:.0f} GFLOP/s on its own: bound by arithmetic, "
                    "the pose GPs' predictive means over their training points); the other stages do "
                    f"{rest_mflop:.1f} MFLOP in {fmt(rest_us, 'us')} ({rest_mflop / max(rest_us, 1e-9) * 1e3:.1f} "
                    "GFLOP/s): bound by the number of small operations and their per-op overhead, not by arithmetic.")
        targets.append({"name": "step_p99_urg04lx_8_tracks", "target": f"p99 ≤ {TARGET_STEP_P99_US:.0f} µs",
                        "measured": m["p99"], "unit": "us", "met": met,
                        "why": why, "profile": "step_p99"})
    # The best batch rate of the run: step by step or vectorised (both batch targets judge it).
    best_batch = max((res.get(k)["median"] for k in ("batch.urg-04lx.exact", "batch.urg-04lx.vmap") if res.has(k)),
                     default=None)
    if res.has("batch.urg-04lx.exact"):
        b = res.get("batch.urg-04lx.exact")
        v = res.get("batch.urg-04lx.vmap") if res.has("batch.urg-04lx.vmap") else None
        step = res.get("step.urg-04lx.end_to_end")["median"] if res.has("step.urg-04lx.end_to_end") else float("nan")
        per_scan = 1e6 / b["median"]
        res.profiles["batch"] = {"us_per_scan_in_batch": per_scan, "step_median_us": step,
                                 "vmap_scans_per_s": v["median"] if v else None,
                                 "frontend_batch_scans_per_s": res.get("batch.urg-04lx.frontend")["median"]
                                 if res.has("batch.urg-04lx.frontend") else None,
                                 "xla_cost_per_stage": res.profiles.get("xla_cost.urg-04lx", {})}
        cost = res.profiles.get("xla_cost.urg-04lx", {})
        stages = _stage_breakdown(res, "urg-04lx")
        heavy = max(cost.items(), key=lambda kv: kv[1].get("mflop", 0.0), default=("?", {}))
        total = sum(c.get("mflop", 0.0) for k, c in cost.items() if k != "frontend_a_to_c")
        per_vec = 1e6 / v["median"] if v else float("nan")
        why = (f"Step by step a scan costs {fmt(per_scan, 'us')} in batch against {fmt(step, 'us')} for a step called "
               "from the host: the compiled loop saves the per-call host overhead but not the per-scan computation. "
               f"The vectorised form (replay's default, {fmt(v['median'], 'scans/s') if v else 'n/a'}, "
               f"{fmt(per_vec, 'us')} a scan) runs perception vmapped over groups of 8 scans, one size bucket per "
               "group, so each kernel's fixed cost is shared by eight scans; the arithmetic stays. Both forms are "
               "compiled without XLA:CPU's library fusions of elementwise and reduce work "
               "(`gtsjax/drivers/compile.py`: with the model an argument, one of them recomputed the pose GPs' "
               "inducing norms for every candidate, half of batch replay's time). Of the "
               f"{total:.1f} MFLOP XLA counts per scan, {heavy[1].get('mflop', 0):.1f} are {heavy[0]} "
               f"({fmt(stages.get(heavy[0], {}).get('median_us', float('nan')), 'us')} median on its own). The pose "
               "GPs' exact means run over all their training examples (5 905 in the shipped model), four GPs "
               "with four kernel rows per robot candidate, from one product with their inputs (held once: "
               "`gp.sparse.CommonInputsGP`); `train --pose-kernels 2` halves the rows (the step "
               "1.57 against 1.78 ms) but cost tracked heading accuracy on the README's scenarios, so it is "
               "not the default (README, Speed).")
        targets.append({"name": "batch_replay_throughput", "target": f"≥ {TARGET_BATCH:.0f} scans/s",
                        "measured": best_batch, "unit": "scans/s", "met": best_batch >= TARGET_BATCH,
                        "why": why, "profile": "batch",
                        "note": "best of the step-by-step and the vectorised form"})
    try:
        r = res.get_ratio("reference_over_gtsjax.median")
    except KeyError:
        r = None
    if r is not None:
        prof = res.profiles.get("reference", {})
        share = prof.get("share", {})
        top = max(((k, v) for k, v in share.items() if not k.startswith("  ")), key=lambda kv: kv[1], default=("?", 0))
        ref_us = res.get(r["numerator"])["median"]
        g_us = res.get(r["denominator"])["median"]
        stages = _stage_breakdown(res, "urg-04lx")
        gp_share = sum(stages.get(k, {}).get("share_of_stage_sum", 0.0) for k in ("d_classifier", "e_pose_regression"))
        why = (f"The reference takes {fmt(ref_us, 'us')} per scan, {100 * top[1]:.0f} % of it in {top[0]}; gtsjax's "
               f"step takes {fmt(g_us, 'us')}, of which the GP stages d and e are {100 * gp_share:.0f} % (stage sums). "
               f"For {TARGET_VS_REFERENCE:.0f}× the step would have to take {fmt(ref_us / TARGET_VS_REFERENCE, 'us')}. "
               "The step's fixed shapes make it run the classifier's GPs on all K candidate slots and the pose GPs "
               "on a power-of-two bucket of robot slots and on the landmark-cap post slots, whether they hold "
               "candidates or not, where the reference evaluates only the candidates that survive each stage (a "
               "few per scan); the pose GPs of the shipped model are exact over 5 905 examples (scikit-learn's "
               "prediction over them is a single matrix product, as ours). What would close it: a "
               "cheaper step, above all stages d and e (see the batch profile).")
        fe_name = "step.urg-04lx.stage.frontend_a_to_c"
        fe_us = res.get(fe_name)["median"] if res.has(fe_name) else float("nan")
        if fe_us > ref_us / TARGET_VS_REFERENCE:
            why += (f" The front end alone takes {fmt(fe_us, 'us')} per call, more than the whole budget: "
                    f"{TARGET_VS_REFERENCE:.0f}× against this reference also needs a cheaper front end.")
        targets.append({"name": "speedup_vs_numpy_reference", "target": f"≥ {TARGET_VS_REFERENCE:.0f}× per scan",
                        "measured": r["value"], "unit": "×", "met": r["value"] >= TARGET_VS_REFERENCE,
                        "why": why, "profile": "reference"})
    try:
        r99 = res.get_ratio("reference_over_gtsjax.p99")
    except KeyError:
        r99 = None
    if r99 is not None:
        ref, g = res.get(r99["numerator"]), res.get(r99["denominator"])
        targets.append({"name": "speedup_vs_numpy_reference_p99", "target": f"≥ {TARGET_VS_REFERENCE_P99:.0f}× at p99",
                        "measured": r99["value"], "unit": "×", "met": r99["value"] >= TARGET_VS_REFERENCE_P99,
                        "why": f"p99 per scan: the reference {fmt(ref['p99'], 'us')}, gtsjax's step {fmt(g['p99'], 'us')}; "
                               "what moves the median moves it (see speedup_vs_numpy_reference).",
                        "profile": "reference"})
    if best_batch is not None and r is not None:
        ref_rate = 1e6 / res.get(r["numerator"])["median"]
        goal = TARGET_BATCH_VS_REFERENCE * ref_rate
        targets.append({"name": "batch_vs_reference", "target": f"≥ {TARGET_BATCH_VS_REFERENCE:.0f}× the reference's "
                        f"per-scan rate ({fmt(goal, 'scans/s')} in this run)", "measured": best_batch / ref_rate,
                        "unit": "×", "met": best_batch >= goal,
                        "why": f"The reference runs {fmt(ref_rate, 'scans/s')}, batch replay at best "
                               f"{fmt(best_batch, 'scans/s')}; see batch_replay_throughput for where a scan's time goes.",
                        "profile": "batch"})
    if res.has("live.utm-30lx_40hz"):
        lv = res.get("live.utm-30lx_40hz")
        p99_ms = lv["p99"] / 1e3 if lv["unit"] == "us" else lv["p99"]
        alone = (res.get("live.utm-30lx_40hz.step_every_period") if res.has("live.utm-30lx_40hz.step_every_period")
                 else None)
        targets.append({"name": "live_p99_40hz", "target": f"frame → GTD row p99 ≤ {TARGET_LIVE_P99_MS:.0f} ms at 40 Hz",
                        "measured": p99_ms, "unit": "ms", "met": p99_ms <= TARGET_LIVE_P99_MS,
                        "why": "Frame read to GTD row flushed, the emulator over a pty: "
                               f"median {fmt(lv['median'], lv['unit'])}, p99 {fmt(lv['p99'], lv['unit'])}"
                               + (f"; the step alone, called every 25 ms, {fmt(alone['median'], alone['unit'])} median "
                                  f"(its code and constants leave the caches between frames; the loop's warm-up step before each "
                                  f"frame, on here, takes part of that off: README, Speed)" if alone else "")
                               + ".", "profile": "live"})
    if res.has("grade.match_10_robots") and res.get("grade.match_10_robots")["params"].get("log_seconds", 0) >= 600:
        gr = res.get("grade.match_10_robots")
        targets.append({"name": "grade_10_minutes", "target": f"grade() of a 10-minute two-laser log, 10 robots, "
                        f"≤ {TARGET_GRADE_S:.0f} s", "measured": gr["median"], "unit": gr["unit"],
                        "met": gr["median"] <= TARGET_GRADE_S,
                        "why": f"median {fmt(gr['median'], gr['unit'])} over {gr['params'].get('rows')} rows "
                               f"of {gr['params'].get('log_seconds', 0) / 60:g} min.",
                        "profile": "grade"})
    if res.has("scip.decode_me_1081"):
        sd = res.get("scip.decode_me_1081")
        targets.append({"name": "scip_decode_me", "target": f"median ≤ {TARGET_SCIP_DECODE_US:.0f} µs (UTM-30LX ME frame)",
                        "measured": sd["median"], "unit": sd["unit"], "met": sd["median"] <= TARGET_SCIP_DECODE_US,
                        "why": f"median {fmt(sd['median'], sd['unit'])}, p99 {fmt(sd['p99'], sd['unit'])}.",
                        "profile": "scip"})
    for name in sorted(k for k in res.checks if k.startswith("gp_lml.")):
        tag = name.split(".", 1)[1]
        try:
            r = res.get_ratio(f"gp_fit.{tag}.sklearn_over_gtsjax")
        except KeyError:
            continue
        diff = res.checks[name]["gtsjax_minus_sklearn_common"]
        prof = res.profiles.get(f"gp_fit.{tag}", {})
        ev = prof.get("seconds_per_lml_and_gradient", {})
        n_ev = prof.get("fit_time_in_evaluations", {})
        ok_lml = diff >= -LML_TOLERANCE
        e_g, e_s = ev.get("gtsjax", float("nan")), ev.get("scikit-learn", float("nan"))
        n_g, n_s = n_ev.get("gtsjax", 0), n_ev.get("scikit-learn", 0)
        why = (f"One LML-and-gradient evaluation costs {fmt(1e3 * e_g, 'ms')} in gtsjax and {fmt(1e3 * e_s, 'ms')} in "
               f"scikit-learn ({e_s / e_g:.1f}× cheaper: closed-form gradient, no N×N×d tensor), but gtsjax's fit "
               f"lasts {n_g} such evaluations against scikit-learn's {n_s} ({n_g / max(n_s, 1):.1f}×): three BFGS "
               "starts, each to convergence (a first-order optimum, every gradient component of −LML/N at most "
               "1e-6, or the Cauchy test; vmapped together up to 200 rows, one after another above on a CPU; a "
               "second, clamped stage only where a length scale ran past its clamp)"
               + (f"; SciPy's L-BFGS-B on tinygp's objective made {prof['tinygp_lbfgsb_evaluations_counted']} "
                  "evaluations in all" if "tinygp_lbfgsb_evaluations_counted" in prof else "")
               + ". LML difference (gtsjax − scikit-learn, same function): "
               f"{diff:+.3f} nats. What would close it: fewer evaluations. Screening the starts on half the rows "
               "at every size was tried (1.6× faster at N = 300) and lost 4.7 nats on a 450-point set of the cold "
               "comparison, so screening stays above 500 rows; a looser tolerance on −LML/N ends short of the "
               "optimum (3.6 nats at N = 450); an initial scaling of BFGS's inverse Hessian (Shanno–Phua) "
               "helped some sets and slowed others.")
        targets.append({"name": f"gp_fit_speedup_{tag}", "target": f"≥ {TARGET_GP_SPEEDUP:.0f}× scikit-learn, LML ≥ "
                        f"scikit-learn's − {LML_TOLERANCE} nats", "measured": r["value"], "unit": "×",
                        "lml_difference": diff, "met": r["value"] >= TARGET_GP_SPEEDUP and ok_lml, "why": why,
                        "profile": f"gp_fit.{tag}"})
    cold = res.checks.get("gp_cold")
    if cold:
        sets = cold["sets"]
        wins = [c["sklearn_s"] / c["gtsjax_s"] for c in sets]
        worst = min(c["gtsjax_minus_sklearn_lml"] for c in sets)
        listing = ", ".join(f"N={c['n']}: {c['gtsjax_s']:.1f} s against {c['sklearn_s']:.1f} s" for c in sets)
        why = (f"Cold fit and prediction, every set a new shape, one fresh process per library ({listing}). "
               "A new shape costs gtsjax about 2.5 s before its first evaluation: tracing Optimistix's BFGS "
               "loop (0.6–0.8 s) and XLA's compilation of it (1.6–1.8 s), then conditioning and prediction; "
               "scikit-learn compiles nothing. Where that dominates (N ≤ 450 here) gtsjax is slower. What "
               "helps a user: `gtsjax train` keeps compiled programs in a persistent cache (GTSJAX_CACHE_DIR), "
               "and the GPs of a model share one padded shape. LML difference, worst set: "
               f"{worst:+.2f} nats.")
        targets.append({"name": "gp_fit_cold", "target": "cold fit faster than scikit-learn at every N ≥ 100",
                        "measured": min(wins), "unit": "× (worst set)", "met": min(wins) > 1.0, "why": why,
                        "profile": "gp_cold"})
    res.targets = targets


def _row_value(m):
    return fmt(m["median"], m["unit"]), fmt(m["p99"], m["unit"])


SUMMARY = [
    ("step.urg-04lx.end_to_end", "whole step, URG-04LX scan (682 beams), 8 track slots (as the live loop calls it: `LiveStep`, the model closed over)"),
    ("step.utm-30lx.end_to_end", "whole step, UTM-30LX scan (1081 beams + intensity), 8 track slots"),
    ("step.urg-04lx.stage.frontend_a_to_c", "front end only (stages a–c), URG-04LX"),
    ("step.utm-30lx.stage.frontend_a_to_c", "front end only (stages a–c), UTM-30LX"),
    ("batch.urg-04lx.exact", "batch replay, step by step (`replay --step-by-step`: the live loop's computation, scan by scan)"),
    ("batch.urg-04lx.vmap", "batch replay, vectorised (`replay`'s default: perception vmapped over groups of 8 scans)"),
    ("batch.urg-04lx.logs4", "batch replay, four logs side by side (`replay A B C D`: one tracker each, one program)"),
    ("batch.urg-04lx.frontend", "front end in batch, URG-04LX"),
    ("step.several2.end_to_end", "whole step, one laser's scan of two (`step_several`), full-size field, 10 robots, 14 track slots"),
    ("step.several1.end_to_end", "whole step, the same match's north laser alone (one-laser step), 14 track slots"),
    ("batch.several2.vmap", "batch replay, two lasers' logs merged (`replay --log NAME=LOG ...`), per scan"),
    ("batch.several1.vmap", "batch replay, one laser's log of the same match, per scan"),
    ("reference.urg-04lx.numpy_sklearn_filterpy", "NumPy + scikit-learn + filterpy reference, per scan (spl-trajectory, one robot)"),
    ("reference.urg-04lx.gtsjax_step", "whole step on the reference's log, same run (the ratios below divide by this)"),
    ("gp_fit.n300.gtsjax", "GP fit, 300 points, d = 23, 3 starts: gtsjax"),
    ("gp_fit.n300.sklearn", "GP fit, same data: scikit-learn"),
    ("gp_fit.n100.gtsjax", "GP fit, 100 points, d = 23, 3 starts: gtsjax"),
    ("gp_fit.n100.sklearn", "GP fit, same data: scikit-learn"),
    ("kalman.one_step.gtsjax", "Kalman predict + update, one track: gtsjax (jitted call)"),
    ("kalman.one_step.filterpy", "Kalman predict + update, one track: filterpy"),
    ("scip.decode_me_1081", "SCIP decode, one UTM-30LX ME frame (1081 beams + intensity)"),
    ("live.urg-04lx_10hz", "live, frame read → GTD row flushed, URG-04LX at 10 Hz (emulator over a pty)"),
    ("live.utm-30lx_40hz", "live, frame read → GTD row flushed, UTM-30LX at 40 Hz (emulator over a pty)"),
    ("live.utm-30lx_40hz.step_back_to_back", "live step alone, UTM-30LX frames, called back to back"),
    ("live.utm-30lx_40hz.step_every_period", "live step alone, UTM-30LX frames, called every 25 ms (idle between)"),
]


def summary_rows(res) -> list[tuple[str, str, str]]:
    rows = []
    for name, label in SUMMARY:
        if res.has(name):
            med, p99 = _row_value(res.get(name))
            rows.append((label, med, p99 if not res.get(name)["unit"].endswith("/s") else ""))
    return rows


def key_ratios(res) -> list[tuple[str, str]]:
    out = []
    for r in res.ratios:
        out.append((r["meaning"], f"{r['value']:.1f}×"))
    return out


def _md_table(header, rows) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def machine_line(res) -> str:
    m, s = res.machine, res.settings
    load = m.get("load_average_start") or [float("nan")]
    return (f"{m.get('cpu_model')}, {m.get('cores')} cores; JAX {m.get('jax')} / jaxlib {m.get('jaxlib')} on "
            f"{m.get('backend')}; {s.get('threads')} thread(s) per library (BLAS/OpenMP and XLA's intra-op pool); "
            f"{m.get('date')}; load average at start {load[0]:.2f}")


def summary_markdown(res) -> str:
    """The table for the README's Speed section."""
    lines = _md_table(("what", "median", "p99"), summary_rows(res))
    lines.append("")
    lines += _md_table(("side by side (same run, same thread count)", "ratio"), key_ratios(res))
    return "\n".join(lines)


def markdown(res, command: str) -> str:
    m = res.machine
    out = ["# gtsjax benchmarks", "",
           f"`{command}`{' (smoke run: few repetitions, small sizes)' if res.quick else ''}", "",
           f"Machine: {machine_line(res)}. GPU: {m.get('gpu')}.", ""]
    load = m.get("load_average_start") or [0.0]
    if load[0] > 0.5 * (m.get("cores") or 1):
        out += [f"> Taken while other processes were running (load average {load[0]:.1f} on {m.get('cores')} cores at "
                "the start, " f"{(m.get('load_average_end') or [float('nan')])[0]:.1f} at the end): provisional; "
                "re-run on an idle machine for reference figures.", ""]
    out += ["## Summary", "", summary_markdown(res), "", "## Targets", ""]
    out += _md_table(("target", "goal", "measured", "met?"),
                     [(t["name"], t["target"], fmt(t["measured"], t["unit"]) if t["unit"] != "×" else
                       f"{t['measured']:.1f}×" + (f" (LML {t['lml_difference']:+.2f} nats)" if "lml_difference" in t else ""),
                       "met" if t["met"] else "**missed**") for t in res.targets])
    out.append("")
    for t in res.targets:
        out += [f"- **{t['name']}** ({'met' if t['met'] else 'missed'}): {t['why']}"]
    missed = [t for t in res.targets if not t["met"]]
    if missed:
        profiled = [t for t in missed if res.profiles.get(t["profile"])]
        if profiled:
            out += ["", "## Profiles of the missed targets", ""]
        for t in profiled:
            out += [f"### {t['name']}", "", "```", _profile_text(res.profiles[t["profile"]]), "```", ""]
    out += ["", "## All measurements", ""]
    sections = []
    for meas in res.measurements:
        if meas["section"] not in sections:
            sections.append(meas["section"])
    for sec in sections:
        out += [f"### {sec}", ""]
        out += _md_table(("measurement", "median", "p99", "n"),
                         [(x["label"].strip(), *_row_value(x), x["n"]) for x in res.measurements if x["section"] == sec])
        out.append("")
    out += ["## Ratios (same run)", ""]
    out += _md_table(("ratio", "value", "of"), [(r["meaning"], f"{r['value']:.2f}×", f"`{r['numerator']}` / "
                                                 f"`{r['denominator']}` ({r['stat']})") for r in res.ratios])
    out += ["", "## Peers", ""]
    out += _md_table(("peer", "version or status"), sorted(res.peers.items()))
    if res.scaling:
        out += ["", "## Scaling", "", "![scaling](scaling.png)", ""]
        for axis, s in res.scaling.items():
            cols = [k for k in s if k != "x"]
            out += _md_table((axis, *cols), [(x, *(_num(s[c][i]) for c in cols)) for i, x in enumerate(s["x"])])
            out.append("")
    out += ["## Checks", "", "```", _profile_text(res.checks), "```", ""]
    out += ["## Notes", "",
            "- Latencies are wall clock per call, each call ending in `block_until_ready`, after a warm-up; "
            "compilation is excluded (a GP fit's first call, which compiles, is given as `cold_s`).",
            "- Rates: the median is the rate at the median run time; p99 the rate at the 99th-percentile run time.",
            f"- Thread counts: {res.settings.get('threads')} for both sides of every comparison (BLAS/OpenMP pools of "
            "NumPy, SciPy and scikit-learn, and jaxlib's LAPACK calls, which use the same OpenBLAS; XLA's "
            "intra-op pool). Absolute times vary between machines; compare the ratios.",
            "- Schema of `results.json`: see `benchmarks/__init__.py`."]
    return "\n".join(out) + "\n"


def _num(v):
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _profile_text(d, indent: int = 0) -> str:
    lines = []
    pad = "  " * indent
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"{pad}{k}:")
            lines.append(_profile_text(v, indent + 1))
        elif isinstance(v, float):
            lines.append(f"{pad}{k}: {v:.4g}")
        else:
            lines.append(f"{pad}{k}: {v}")
    return "\n".join(line for line in lines if line)


def print_tables(res, console=None) -> None:
    """The summary, ratios and targets on the terminal (rich)."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title=f"gtsjax benchmarks{' (quick)' if res.quick else ''}", caption=machine_line(res))
    t.add_column("what")
    t.add_column("median", justify="right")
    t.add_column("p99", justify="right")
    for row in summary_rows(res):
        t.add_row(*row)
    console.print(t)
    r = Table(title="side by side (same run)")
    r.add_column("comparison")
    r.add_column("ratio", justify="right")
    for row in key_ratios(res):
        r.add_row(*row)
    console.print(r)
    g = Table(title="targets")
    for c in ("target", "goal", "measured", "met?"):
        g.add_column(c)
    for x in res.targets:
        val = fmt(x["measured"], x["unit"]) if x["unit"] != "×" else f"{x['measured']:.1f}×"
        g.add_row(x["name"], x["target"], val, "met" if x["met"] else "[bold red]missed[/]")
    console.print(g)
