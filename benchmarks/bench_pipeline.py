"""Per-stage and end-to-end step latency for URG-04LX and UTM-30LX scans, and batch replay throughput.

* **End to end**: the step as the live loop calls it (``LiveCall``: ``drivers.live.LiveStep``, the
  model closed over and jitted once, the frame as the link delivers it, the state and output packed),
  one call per scan with the state carried over, scans cycled from a simulated log with robots in
  view (URG-04LX: ``spl-crossing``, three robots, M = 8 track slots; UTM-30LX: ``lab-trajectory``).
* **Per stage**: each stage of Fig. 1 jitted on its own with the model closed over, fed the inputs
  that stage really received on each scan of the same log (recorded by running the step first):
  a segmentation, b ORS and characteristic vectors, c binary filters, d classifier, e pose
  regression (into S), f map transformation (and detections into O), g tracking; plus the front
  end a–c as one jitted call, and the *dispatch floor*: a jitted call that does nothing, the fixed
  cost every jitted call pays on the host. The stages' sum exceeds the end-to-end step by about one
  dispatch floor per extra call.
* **Batch**: ``process_log`` over a simulated log (``spl-trajectory``) in chunks of 256, both the
  bit-exact loop and the ``vmap`` variant, and the front end alone in batch (``front_end_batch``).
* **Several lasers** (issue 18): a two-laser match (``spl-match-2``, ten robots): the several-laser
  step (``step_several``, jitted with the model closed over, the laser a traced index) per laser-scan,
  against the one-laser step on the same scans of one laser; batch replay of the merged log
  (``process_several``) against the one-laser batch replay of one laser's log, per scan.
"""

import jax
import jax.numpy as jnp

from gtsjax.core.a_segment import segment
from gtsjax.core.b_features import characterise_all
from gtsjax.core.c_filters import binary_filter, envelope_pass, shape_quantities
from gtsjax.core.d_classify import classify, gp_inputs
from gtsjax.core.e_pose import regress, to_sensor_frame
from gtsjax.core.e_refine import refine_candidates
from gtsjax.core.f_maptransform import poses_to_field, update_transform
from gtsjax.core.frontend import front_end, front_end_batch
from gtsjax.core.g_track import Detections, track_step
from gtsjax.core.geometry import wrap
from gtsjax.core.multi import init_several, step_several
from gtsjax.core.pipeline import init_state, landmark_cap, perceive, step
from gtsjax.drivers.batch import process_log, process_logs
from gtsjax.drivers.several import merge_logs, process_several, site_poses
from gtsjax.io import to_scans

from . import _data
from ._harness import LiveCall, closed_step
from .kernels import compiled_text, count_kernels

SECTION = "pipeline"


def take(tree, i):
    return jax.tree.map(lambda a: a[i], tree)


def stage_functions(model):
    """The stages of Fig. 1 as separately jitted functions of their real inputs (model closed over)."""
    fe = model.frontend

    def seg(scan):
        return segment(scan, max_candidates=fe.max_candidates, window=fe.window, break_distance=fe.break_distance,
                       break_growth=fe.break_growth)

    def char(cands):
        return characterise_all(cands, n_dist=fe.n_dist, n_intensity=fe.n_intensity, cells_on_bbox=fe.cells_on_bbox,
                                cell_span=fe.cell_span, sigma_cells=fe.sigma_cells, sigma_min=fe.sigma_min)

    def filt(cands, feats):
        return binary_filter(cands.live, cands.too_long, feats.n_points, feats.width, width_min=fe.width_min,
                             width_max=fe.width_max, min_points=fe.min_points)

    def cls(feats, keep):  # with the shape envelopes and the open-set test, as perceive() does
        rng = jnp.sqrt(jnp.sum(feats.origin**2, axis=-1))
        in_env = envelope_pass(model.envelope, shape_quantities(feats.width, feats.height, feats.n_points, rng), rng)
        return classify(model.classifier, gp_inputs(feats.vector, feats.origin, feats.height, model.gp_columns), keep,
                        in_env)

    def pose(feats, scores, c, ok):
        rel, var, _ = regress(model.pose, gp_inputs(feats.vector, feats.origin, feats.height, model.gp_columns), c, ok, scores,
                              model.max_objects, landmark_cap(model))
        return to_sensor_frame(feats.origin, feats.heading, rel, var)

    def refine(cands, scores, c, ok, pose_s, cov_s):  # stage e′ on stage e's output, as perceive() runs it
        return refine_candidates(model.outline, model.max_objects, c, ok & model.tracker.tracked[c], scores, cands.xy,
                                 cands.mask, pose_s, cov_s)

    def mapf(tf, p):
        site = model.site
        is_landmark = p.ok & model.landmark_mask[p.cls]
        tf, _, _ = update_transform(tf, p.pose_s[:, :2], p.cls, is_landmark, site.landmark_xy, site.landmark_class,
                                    model.map_gate, model.map_min_spread)
        pose_o, cov_o = poses_to_field(tf, p.pose_s, p.cov_s)
        b = site.bounds
        x, y = pose_o[:, 0], pose_o[:, 1]
        inside = ~site.has_bounds | ((x >= b[0]) & (y >= b[1]) & (x <= b[2]) & (y <= b[3]))
        mask = p.ok & model.tracker.tracked[p.cls] & inside
        side_o = jnp.concatenate([tf.apply(p.side_pose[..., :2]), wrap(p.side_pose[..., 2:] + tf.heading())], -1)
        return tf, Detections(pose_o, cov_o + jnp.diag(model.meas_var_floor)[None], p.cls, mask,
                              side_pose=side_o, side_logp=p.side_logp)

    def track(tracker, det, dt):
        return track_step(tracker, det, dt, model.tracker)

    return {
        "a_segmentation": CompiledOnce(seg),
        "b_characterisation": CompiledOnce(char),
        "c_filters": CompiledOnce(filt),
        "d_classifier": CompiledOnce(cls),
        "e_pose_regression": CompiledOnce(pose),
        "e2_outline_refinement": CompiledOnce(refine),
        "f_map_transformation": CompiledOnce(mapf),
        "g_tracking": CompiledOnce(track),
        "frontend_a_to_c": CompiledOnce(lambda scan: front_end(fe, scan)),
    }


class CompiledOnce:
    """``fn`` jitted, lowered and compiled on its first call's arguments, then called as that compiled
    program (JAX's C++ dispatch, as a jitted function's): the one compilation both runs the stage and
    gives XLA's cost analysis (:func:`xla_cost`), where ``jax.jit(fn)`` and then
    ``.lower(...).compile()`` compiled every stage twice."""

    def __init__(self, fn):
        self.jitted = jax.jit(fn)
        self.compiled = None

    def __call__(self, *args):
        if self.compiled is None:
            self.compiled = self.jitted.lower(*args).compile()
        return self.compiled(*args)


def record_inputs(model, scans, n: int):
    """Run the step over the first ``n`` scans and keep what each stage received on each scan."""
    st = stage_functions(model)
    step = closed_step(model)
    perc = jax.jit(lambda scan: perceive(model, scan))
    state = init_state(model)
    rec = []
    for i in range(n):
        scan = take(scans, i)
        cands = st["a_segmentation"](scan)
        feats = st["b_characterisation"](cands)
        keep = st["c_filters"](cands, feats)
        dec = st["d_classifier"](feats, keep)
        scores, c, ok = dec.scores, dec.cls, dec.ok
        pose_s, cov_s = st["e_pose_regression"](feats, scores, c, ok)
        p = perc(scan)
        _, det = st["f_map_transformation"](state.transform, p)
        rec.append({"scan": scan, "cands": cands, "feats": feats, "keep": keep, "cls": c, "scores": scores, "ok": ok,
                    "pose_s": pose_s, "cov_s": cov_s, "perception": p,
                    "transform": state.transform, "tracker": state.tracker, "det": det})
        state, _ = step(state, scan)
    return jax.block_until_ready(rec), st, step


def bench_sensor(ctx, key: str, model, scans, n_pool: int, repeats: int, stage_repeats: int, stages: bool = True
                 ) -> None:
    """End-to-end and (with ``stages``) per-stage latency of one sensor's scans."""
    res = ctx.results
    if stages:
        rec, st, _ = record_inputs(model, scans, n_pool)
    beams = int(scans.ranges.shape[-1])
    params = {"beams": beams, "K": model.frontend.max_candidates, "M": model.max_tracks, "sensor": model.sensor_model}
    run = LiveCall(model, jax.tree.map(lambda a: a[:n_pool], scans))
    res.add(f"step.{key}.end_to_end", "us", ctx.time_calls(run, repeats, warmup=20), section=SECTION,
            label=f"step, {model.sensor_model} ({beams} beams), whole pipeline a–g", **params)
    if not stages:
        return
    calls = {
        "a_segmentation": lambda r: st["a_segmentation"](r["scan"]),
        "b_characterisation": lambda r: st["b_characterisation"](r["cands"]),
        "c_filters": lambda r: st["c_filters"](r["cands"], r["feats"]),
        "d_classifier": lambda r: st["d_classifier"](r["feats"], r["keep"]),
        "e_pose_regression": lambda r: st["e_pose_regression"](r["feats"], r["scores"], r["cls"], r["ok"]),
        "e2_outline_refinement": lambda r: st["e2_outline_refinement"](*_stage_args("e2_outline_refinement", r)),
        "f_map_transformation": lambda r: st["f_map_transformation"](r["transform"], r["perception"]),
        "g_tracking": lambda r: st["g_tracking"](r["tracker"], r["det"], r["scan"].dt),
        "frontend_a_to_c": lambda r: st["frontend_a_to_c"](r["scan"]),
    }
    cost = {}
    for name, call in calls.items():
        samples = ctx.time_calls(lambda i, call=call: call(rec[i % n_pool]), stage_repeats, warmup=10)
        m = res.add(f"step.{key}.stage.{name}", "us", samples, section=SECTION,
                    label=f"  stage {name.replace('_', ' ', 1).replace('_', ' ')}", **params)
        cost[name] = xla_cost(st[name], _stage_args(name, rec[0]), m["median"])
    res.profiles[f"xla_cost.{key}"] = cost


def _stage_args(name: str, r: dict) -> tuple:
    return {
        "a_segmentation": (r["scan"],), "b_characterisation": (r["cands"],), "c_filters": (r["cands"], r["feats"]),
        "d_classifier": (r["feats"], r["keep"]), "e_pose_regression": (r["feats"], r["scores"], r["cls"], r["ok"]),
        "e2_outline_refinement": (r["cands"], r["scores"], r["cls"], r["ok"], r["pose_s"], r["cov_s"]),
        "f_map_transformation": (r["transform"], r["perception"]),
        "g_tracking": (r["tracker"], r["det"], r["scan"].dt), "frontend_a_to_c": (r["scan"],),
    }[name]


def xla_cost(fn: CompiledOnce, args: tuple, median_us: float) -> dict:
    """XLA's own count of a compiled stage's floating-point operations and bytes moved, and the rate
    the measured median implies: far below the core's peak means overhead-bound (many small ops,
    dispatch), not compute-bound."""
    try:
        if fn.compiled is None:
            fn(*args)
        ca = fn.compiled.cost_analysis()
        ca = ca[0] if isinstance(ca, list) else ca
        flops, nbytes = float(ca.get("flops", 0.0)), float(ca.get("bytes accessed", 0.0))
    except Exception as err:  # cost analysis is best effort (backend-dependent)
        return {"error": f"{type(err).__name__}: {err}"}
    return {"mflop": round(flops / 1e6, 3), "mbyte": round(nbytes / 1e6, 3),
            "gflop_per_s_at_median": round(flops / (median_us * 1e3), 3)}


def dispatch_floor(ctx, repeats: int, step_links: int = 140) -> None:
    """The host cost of calling any jitted function: a jitted no-op on a scalar. ``step_links``: the
    longer chain's length (the smoke run's is shorter: XLA compiles such a chain at some 50 ms a
    kernel, 14 s for the full one's 280 on a busy 2-core machine)."""
    f = jax.jit(lambda x: x)
    x = jnp.asarray(1.0, jnp.float32)
    ctx.results.add("step.dispatch_floor", "us", ctx.time_calls(lambda i: f(x), repeats, warmup=20), section=SECTION,
                    label="jitted no-op call (dispatch floor)")
    # What kernels cost with next to no arithmetic: a compiled chain of tiny reductions and elementwise
    # kernels (64 floats each) of the budget (150) and of about the step's count; the report
    # prices the step's count at the larger chain's cost per kernel.
    v = jnp.ones((64,), jnp.float32)
    for tag, links in (("budget", 50), ("step", step_links)):
        def chain(a, links=links):
            for i in range(links):
                a = a * 0.5 + jnp.max(a) * 0.001 + i  # a reduction, then an elementwise kernel using it
            return a
        g = jax.jit(chain).lower(v).compile()  # one compilation, counted and timed
        n = count_kernels(g.as_text()).total
        ctx.results.add(f"step.kernel_chain.{tag}", "us", ctx.time_calls(lambda i, g=g: g(v), repeats // 3, warmup=20),
                        section=SECTION, label=f"a compiled chain of {n} tiny kernels (no arithmetic to speak of)",
                        kernels=n)


def bench_batch(ctx, model, n_scans: int, runs: int, chunk: int = 256, vmap_chunk: int | None = None) -> None:
    """``process_log`` throughput (step by step, and vectorised: perception vmapped over groups of
    scans), and the front end alone in batch. ``vmap_chunk``: the vectorised forms' chunk (``chunk``
    where not given); the smoke run's is its short log's length, since a chunk longer than the log
    computes its padding (four logs side by side, four times over)."""
    res = ctx.results
    log, _ = _data.scenario("spl-trajectory", 4, n_scans)
    scans = to_scans(log, model.n_beams)
    vchunk = vmap_chunk or chunk
    for vec, key, c in ((False, "exact", chunk), (True, "vmap", vchunk)):
        samples = ctx.time_calls(lambda i, vec=vec, c=c: process_log(model, scans, chunk=c, vectorise=vec), runs,
                                 warmup=1)
        res.add_rate(f"batch.urg-04lx.{key}", log.n_scans, samples, section=SECTION,
                     label=f"batch replay, URG-04LX, chunk {c}, {'step by step' if not vec else 'vectorised (default)'}",
                     chunk=c, vectorise=vec)
    # Four logs side by side (replay A B C D): the same log four times, one tracker each.
    n_logs = 4
    part = jax.tree.map(lambda a: a[: max(vchunk, n_scans // n_logs)], scans)
    samples = ctx.time_calls(lambda i: process_logs(model, [part] * n_logs, chunk=vchunk), runs, warmup=1)
    res.add_rate("batch.urg-04lx.logs4", n_logs * int(part.ranges.shape[0]), samples, section=SECTION,
                 label=f"batch replay, URG-04LX, {n_logs} logs side by side (replay A B C D), chunk {vchunk}, vectorised",
                 chunk=vchunk, logs=n_logs)
    batch = jax.jit(front_end_batch)
    samples = ctx.time_calls(lambda i: batch(model.frontend, scans), runs, warmup=1)
    res.add_rate("batch.urg-04lx.frontend", log.n_scans, samples, section=SECTION,
                 label="front end a–c in batch, URG-04LX (front_end_batch)")


def bench_several(ctx, n_pool: int, repeats: int, runs: int, seconds: float, compare: bool = True) -> None:
    """Two lasers on the full-size field: the step per laser-scan and batch replay per scan, each beside
    the one-laser form on one laser's scans of the same match (same model, the shipped one: the cost
    of a step depends on the scans' shapes and what is in view, not on what the model was trained on).
    ``compare=False`` (the smoke run) leaves out the one-laser forms: two programs more to compile, of
    code the other sections run."""
    from gtsjax.io.site import one_sensor
    from gtsjax.sim.match import simulate_match

    res = ctx.results
    logs, site = simulate_match("spl-match-2", seed=3, n_robots=10, seconds=seconds)
    names = list(logs)
    model = _data.demo_model(one_sensor(site, names[0])).with_capacity(14)
    merged = merge_logs(logs)
    poses = jnp.asarray(site_poses(site, merged.names), jnp.float32)
    scans = to_scans(merged.log, model.n_beams)
    n = min(n_pool, merged.log.n_scans)
    pool = jax.block_until_ready([take(scans, i) for i in range(n)])
    lasers = [jnp.asarray(int(k), jnp.int32) for k in merged.laser[:n]]
    spans = [jnp.asarray(float(d), jnp.float32) for d in merged.span_dt[:n]]
    step2 = jax.jit(lambda st, scan, k, span: step_several(model, st, scan, k, span))
    state = {"s": init_several(model, poses)}

    def run2(i):
        state["s"], out = step2(state["s"], pool[i % n], lasers[i % n], spans[i % n])
        return out

    params = {"lasers": 2, "M": model.max_tracks, "robots": 10, "sensor": model.sensor_model}
    res.add("step.several2.end_to_end", "us", ctx.time_calls(run2, repeats, warmup=20), section=SECTION,
            label="step, one laser's scan of two (step_several), spl-match-2, 10 robots, 14 track slots", **params)
    samples = ctx.time_calls(lambda i: process_several(model, merged, poses), runs, warmup=1)
    res.add_rate("batch.several2.vmap", merged.log.n_scans, samples, section=SECTION,
                 label="batch replay, two lasers merged (replay --log NAME=LOG ...), per scan of either", **params)
    if not compare:
        return
    one_log = logs[names[0]]
    one_scans = to_scans(one_log, model.n_beams)
    one_pool = jax.block_until_ready([take(one_scans, i) for i in range(min(n_pool, one_log.n_scans))])
    step1 = closed_step(model)
    state1 = {"s": init_state(model)}

    def run1(i):
        state1["s"], out = step1(state1["s"], one_pool[i % len(one_pool)])
        return out

    res.add("step.several1.end_to_end", "us", ctx.time_calls(run1, repeats, warmup=20), section=SECTION,
            label="step, the same match's north laser alone (one-laser step), 14 track slots", **params)
    samples = ctx.time_calls(lambda i: process_log(model, one_scans, chunk=256, vectorise=True), runs, warmup=1)
    res.add_rate("batch.several1.vmap", one_log.n_scans, samples, section=SECTION,
                 label="batch replay, the north laser's log alone (replay LOG)", **params)
    res.ratio("several.step_per_laser_scan_over_one", "step.several2.end_to_end", "step.several1.end_to_end",
              meaning="step per laser-scan, two lasers / one laser (issue 18: at most 1.3)")
    res.ratio("several.batch_one_over_two", "batch.several1.vmap", "batch.several2.vmap",
              meaning="batch replay per scan, one laser's rate / two lasers' rate (issue 18: at most 1)")


def run(ctx) -> None:
    q = ctx.quick
    n_pool = 60 if q else 200
    repeats = 300 if q else 3000
    stage_repeats = 150 if q else 1000
    dispatch_floor(ctx, repeats, 70 if q else 140)
    log, site = _data.scenario("spl-crossing", 3, n_pool)
    model = _data.demo_model(site)
    bench_sensor(ctx, "urg-04lx", model, to_scans(log, model.n_beams), n_pool, repeats, stage_repeats)
    # The same step without stage e′ (the model's outlines left out): what the refinement costs. Not in
    # the smoke run: a whole step more to compile, timed by the same code as the UTM-30LX's step below.
    if not q:
        bench_sensor(ctx, "urg-04lx-no-outline", model.without_outline(), to_scans(log, model.n_beams), n_pool,
                     repeats, stage_repeats, stages=False)
    ulog, usite = _data.scenario("lab-trajectory", 5, n_pool)
    umodel = _data.utm_model(usite, ctx.log, ctx.quick)
    # The smoke run times the UTM-30LX stages only end to end (the stage code is the URG-04LX's).
    bench_sensor(ctx, "utm-30lx", umodel, to_scans(ulog, umodel.n_beams), n_pool, repeats, stage_repeats,
                 stages=not q)
    # The smoke run replays a short log once (a compile and a run: a check that it runs, not a rate),
    # step by step in the chunk the scaling section's replay compiles too, vectorised in its length.
    bench_batch(ctx, model, 64 if q else 3000, 1 if q else 5, 256, 64 if q else None)
    bench_several(ctx, n_pool, 100 if q else repeats, 1 if q else 5, 3.0 if q else 30.0, compare=not q)
    # The step's kernels as a user's step has them (XLA's defaults, size buckets on): a compilation of
    # its own, left out of the smoke run (``benchmarks.kernels`` counts them on its own too).
    kernels = None
    if not q:
        scan0 = jax.tree.map(lambda a: a[0], to_scans(log, model.n_beams))
        kernels = count_kernels(compiled_text(lambda s, x: step(model, s, x), init_state(model), scan0)).total
    ctx.results.sections[SECTION] = {"urg_log": "spl-crossing seed 3", "utm_log": "lab-trajectory seed 5",
                                     "pool": n_pool, "batch_log": "spl-trajectory seed 4", "step_kernels": kernels}
