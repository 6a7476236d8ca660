"""Heading and position error against range, beside the Cramér–Rao bound (issue 55, lever 7).

Where should a lab put its laser, and how far is the model from what the scanner allows? A robot is
put down alone on a site's field (``--layout``: its laser, landmarks and walls) at each range from the
laser (``--ranges``), ``--placements`` times at a random bearing inside the field of view and a random
heading, and scanned ``--scans`` times (the simulator's range noise and quantisation, dropouts and
grazing losses). Each scan goes through the step (stages a–f: segmentation to the outline fit, and
the map transformation from the site's landmarks, as a run places detections; the tracker's rows are
not scored, only the detections), and the detection's error against the truth is split per range into

- the bias of a view: the RMS over placements of each placement's mean error (what a robot standing
  still keeps, and no filter removes);
- the noise: the RMS about each placement's mean (what more scans average away);
- misreads: the share of detections more than 30° off (a side read wrong; left out of the RMS).

Beside them, the Cramér–Rao bound of one scan: the least error any unbiased estimator of the pose
from that scan's ranges can have, knowing the robot's true outline exactly. A beam ``i`` with
direction ``u`` hitting an edge of outward normal ``n`` at ``q`` has range ``r`` with
``n·(r u) = d(pose)``; moving the robot by ``(δx, δy, δθ)`` about its centre ``c`` moves that
edge's line by ``n·(δt + δθ J(q − c))``, so ``∂r/∂pose = (n_x, n_y, n·J(q − c)) / (n·u)`` and the
Fisher information is ``Σ gᵢgᵢᵀ / σ(rᵢ)²`` (σ the range noise with the quantisation's
``res²/12``). The bound's RMS over the placements (position radial, heading) is reported per range;
a view of one flat face leaves the position along it unbounded (the ranges do not change as the
robot slides along the face), so the position's is over the other views, with the share of
one-face views beside it.
A model's error well above the bound comes from the model (its outline, its regression), not the
scanner; an error near it can only drop with more beams on the robot (nearer, or a finer scanner).

    python scripts/range_curve.py [--model M.npz] [--outline nao] [--layout spl] [--ranges 0.75 1 ...]

Prints a Markdown table. Default: the shipped model (URG-04LX) on the SPL field it was trained for,
and the Nao outline. The errors are in the field frame: the shipped model's detections in the
sensor's own frame are 1 % of the range short (its landmarks' are too, and stage f's affine map,
singular values 1.010–1.015 on spl-eval, stretches both back: training's first pass leaves the
scale unanchored, docs/accuracy.md), so they are not scored there.
"""

import math
import sys
import warnings
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _args import parser  # noqa: E402  (scripts/_args.py, beside this script)

from gtsjax.cli.demo import demo_model_path  # noqa: E402
from gtsjax.drivers.batch import process_log  # noqa: E402
from gtsjax.drivers.evaluation import heading_turns  # noqa: E402
from gtsjax.errors import InputError  # noqa: E402
from gtsjax.io.logs import to_scans  # noqa: E402
from gtsjax.io.modelfile import load_model  # noqa: E402
from gtsjax.sensors import get_model  # noqa: E402
from gtsjax.sim.scenarios import Plan, hall_layout, lab_layout, render_plan, spl_layout  # noqa: E402
from gtsjax.sim.scene import Effects, Mover, Scene, render, robot_shape  # noqa: E402
from gtsjax.train.check import frame_error  # noqa: E402

RADIUS = 0.3  # m: a detection this near the robot is the robot's
WRONG_SIDE = math.radians(30.0)
LAYOUTS = {"spl": spl_layout, "hall": hall_layout, "lab": lab_layout}


def placements(layout, ranges, n: int, fov: float, rng: np.random.Generator, margin: float = 0.35) -> np.ndarray:
    """``[len(ranges), n, 3]`` poses in the field: at each range from the layout's laser, ``n`` random
    bearings inside ``fov`` (radians, centred on where it looks) that put the robot inside the field's
    bounds (``margin`` from them), and random headings. A range the field has no room for raises
    ``ValueError``."""
    sx, sy, sth = layout.sensor_pose
    x0, y0, x1, y1 = layout.bounds
    out = np.zeros((len(ranges), n, 3))
    for i, r in enumerate(ranges):
        b = sth + rng.uniform(-fov / 2, fov / 2, 200 * n)
        x, y = sx + r * np.cos(b), sy + r * np.sin(b)
        inside = np.flatnonzero((x >= x0 + margin) & (x <= x1 - margin) & (y >= y0 + margin) & (y <= y1 - margin))
        if len(inside) < n:
            raise ValueError(f"--ranges {r:g}: the field has no room for the robot that far from its laser")
        k = inside[:n]
        out[i] = np.column_stack([x[k], y[k], rng.uniform(-math.pi, math.pi, n)])
    return out


def in_sensor_frame(layout, poses: np.ndarray) -> np.ndarray:
    """Field poses ``[..., 3]`` in the layout's laser's frame."""
    sx, sy, sth = layout.sensor_pose
    c, s = math.cos(sth), math.sin(sth)
    dx, dy = poses[..., 0] - sx, poses[..., 1] - sy
    return np.stack([c * dx + s * dy, -s * dx + c * dy, poses[..., 2] - sth], axis=-1)


def fisher_information(shape, sensor, pose: np.ndarray, jacobian: "dict | None" = None) -> np.ndarray:
    """The Fisher information ``[3, 3]`` about the pose ``(x, y, θ)`` in one scan of the outline
    ``shape`` at ``pose`` seen from the origin (exact ranges: which beams hit, and where); NaN where
    fewer than three beams hit it. ``jacobian``: a dict given the beams that hit and their ``∂r/∂pose``."""
    exact, _ = render(Scene(movers=[Mover(shape, pose[None])]), sensor, np.zeros((1, 3)),
                      rng=np.random.default_rng(0), effects=Effects(noise=False))
    r = exact[0].astype(np.float64)
    hit = r > 0
    if hit.sum() < 3:
        return np.full((3, 3), np.nan)
    a = sensor.angle_min + sensor.angle_increment * np.flatnonzero(hit)
    u = np.stack([np.cos(a), np.sin(a)], 1)
    q = r[hit, None] * u
    c, s = math.cos(pose[2]), math.sin(pose[2])
    v = shape.vertices @ np.array([[c, s], [-s, c]]) + pose[:2]  # the outline in the field
    e0, e1 = v, np.roll(v, -1, axis=0)
    # Each hit's edge: the one it lies nearest to.
    t = np.clip(np.einsum("qed,ed->qe", q[:, None] - e0[None], e1 - e0) / np.sum((e1 - e0) ** 2, 1), 0, 1)
    d = np.linalg.norm(q[:, None] - (e0[None] + t[..., None] * (e1 - e0)[None]), axis=2)
    k = np.argmin(d, axis=1)
    edge = e1[k] - e0[k]
    n = np.stack([edge[:, 1], -edge[:, 0]], 1) / np.linalg.norm(edge, axis=1, keepdims=True)  # outward (CCW)
    rel = q - pose[:2]
    g = np.column_stack([n, n[:, 0] * -rel[:, 1] + n[:, 1] * rel[:, 0]]) / np.sum(n * u, 1, keepdims=True)
    var = sensor.noise.std(r[hit]) ** 2 + sensor.noise.resolution**2 / 12
    if jacobian is not None:
        jacobian.update(beams=np.flatnonzero(hit), g=g)
    return (g / var[:, None]).T @ g


def bounds(info: np.ndarray) -> tuple[float, float]:
    """The bound on the position (radial: the trace of its 2×2 block, m²) and the heading (rad²) from
    one scan's Fisher information ``info``. A view of one flat face says nothing of where along the
    face the robot is (the ranges do not change when it slides along it; only which beams hit it
    does, which no derivative sees): the position's bound is then unbounded (inf), the heading's
    still finite (the information about θ with x and y marginalised, from the pseudo-inverse)."""
    if not np.all(np.isfinite(info)):
        return math.inf, math.inf
    head = float(np.linalg.pinv(info, rcond=1e-10)[2, 2])
    if info[2, 2] <= 0:
        return math.inf, math.inf
    schur = info[:2, :2] - np.outer(info[:2, 2], info[2, :2]) / info[2, 2]  # x, y with θ marginalised
    ev = np.linalg.eigvalsh(schur)
    pos = float(np.trace(np.linalg.inv(schur))) if ev[0] > 1e-6 * ev[1] else math.inf
    return pos, head


def detections(model, layout, sensor, outline: str, poses: np.ndarray, scans: int, seed: int) -> np.ndarray:
    """``[P, scans, 3]`` errors in the robot's frame (ahead, left, heading) of the step's detection
    nearest each placement (``poses`` in the field) in each of its scans, in the field frame (the scan's
    own map transformation from the layout's landmarks, as the step places them); NaN where none is
    within :data:`RADIUS`."""
    truth = np.repeat(poses, scans, axis=0)
    T = truth.shape[0]
    plan = Plan(layout, np.repeat(np.asarray(layout.sensor_pose, np.float64)[None], T, 0), truth[:, None], outline=outline)
    log, site = render_plan(plan, seed=seed, model=sensor, tags=False)
    model = model.with_site(site)
    _, out = process_log(model, to_scans(log, model.n_beams))
    k = model.classes.index("robot")
    turns = heading_turns(model)[k]
    err = np.full((T, 3), np.nan)
    det_pose, mask = np.asarray(out.det_pose, np.float64), np.asarray(out.det_mask) & (np.asarray(out.det_class) == k)
    for t in range(T):
        dist = np.where(mask[t], np.linalg.norm(det_pose[t, :, :2] - truth[t, :2], axis=1), np.inf)
        j = int(np.argmin(dist))
        if dist[j] <= RADIUS:
            err[t] = frame_error(det_pose[t, j], truth[t], turns)
    return err.reshape(len(poses), scans, 3)


def split(err: np.ndarray) -> dict:
    """Per range: detection rate, misreads, and the position (radial) and heading errors' RMS, bias of
    the view and noise about it, from ``[P, S, 3]`` errors (misreads left out of the RMS)."""
    warnings.simplefilter("ignore", RuntimeWarning)  # a range with no detection: its figures are NaN, said so
    found = np.isfinite(err[..., 0])
    wrong = found & (np.abs(err[..., 2]) > WRONG_SIDE)
    good = np.where((found & ~wrong)[..., None], err, np.nan)
    mean = np.nanmean(good, axis=1, keepdims=True)  # per placement: its view's bias
    pos = lambda e: float(np.sqrt(np.nanmean(e[..., 0] ** 2 + e[..., 1] ** 2)))  # noqa: E731
    head = lambda e: float(np.degrees(np.sqrt(np.nanmean(e[..., 2] ** 2))))  # noqa: E731
    return {"detected": float(found.mean()), "misread": float(wrong.sum() / max(found.sum(), 1)),
            "pos_rms": pos(good), "pos_bias": pos(mean), "pos_noise": pos(good - mean),
            "head_rms": head(good), "head_bias": head(mean), "head_noise": head(good - mean)}


def main(argv=None) -> None:
    ap = parser(__doc__)
    ap.add_argument("--model", default=None, help="model file (default: the shipped model)")
    ap.add_argument("--outline", default="nao", help="the simulated robot's outline (nao, box, cart)")
    ap.add_argument("--layout", default="spl", choices=sorted(LAYOUTS), help="the site: its laser, landmarks and field")
    ap.add_argument("--ranges", type=float, nargs="+", default=[0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5])
    ap.add_argument("--placements", type=int, default=40)
    ap.add_argument("--scans", type=int, default=5)
    ap.add_argument("--fov-deg", type=float, default=150.0, help="bearings drawn within this, centred ahead")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for bad, what in ((min(args.ranges) <= 0, f"--ranges must be positive metres, got {min(args.ranges):g}"),
                      (args.placements < 1, f"--placements must be at least 1, got {args.placements}"),
                      (args.scans < 1, f"--scans must be at least 1, got {args.scans}"),
                      (not 0 < args.fov_deg <= 360, f"--fov-deg must be in (0, 360], got {args.fov_deg:g}")):
        if bad:
            ap.error(what)
    try:
        model = load_model(args.model or demo_model_path())
        shape = robot_shape(args.outline)
    except InputError as e:
        ap.error(str(e))
    jax.config.update("jax_enable_x64", True)
    sensor = get_model(model.sensor_model)
    layout = LAYOUTS[args.layout]()
    rng = np.random.default_rng(args.seed)
    try:
        poses = placements(layout, args.ranges, args.placements, math.radians(args.fov_deg), rng)
    except ValueError as e:
        ap.error(str(e))
    print(f"{sensor.name} on the {args.layout} layout, model {args.model or 'demo'}, outline {args.outline}: "
          f"{args.placements} placements × {args.scans} scans per range; errors of single detections in the field "
          "(stages a–f, before the tracker), misreads (over 30°) apart\n")
    print("| range [m] | detected | misread | pos RMS [mm] | pos bias / noise [mm] | pos CRB [mm] | "
          "heading RMS [°] | heading bias / noise [°] | heading CRB [°] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(args.ranges):
        s = split(detections(model, layout, sensor, args.outline, poses[i], args.scans, args.seed + i))
        # The position bound's RMS over the views that bound it; in brackets the share of views of one face.
        b = np.array([bounds(fisher_information(shape, sensor, p)) for p in in_sensor_frame(layout, poses[i])])
        face = ~np.isfinite(b[:, 0])
        crb_pos = 1e3 * math.sqrt(np.mean(b[~face, 0])) if (~face).any() else math.inf
        fin = np.isfinite(b[:, 1])
        crb_head = math.degrees(math.sqrt(np.mean(b[fin, 1]))) if fin.any() else math.inf
        print(f"| {r:g} | {100 * s['detected']:.0f} % | {100 * s['misread']:.1f} % | {1e3 * s['pos_rms']:.1f} | "
              f"{1e3 * s['pos_bias']:.1f} / {1e3 * s['pos_noise']:.1f} | {crb_pos:.1f} ({100 * face.mean():.0f} %) | "
              f"{s['head_rms']:.2f} | {s['head_bias']:.2f} / {s['head_noise']:.2f} | {crb_head:.2f} |", flush=True)


if __name__ == "__main__":
    main()
