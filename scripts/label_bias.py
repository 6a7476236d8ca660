"""The bias of the labels' map and of the learnt outline (issue 55, lever 4), against the simulator's truth.

Stage f maps S to O by an affine map (eq. 10), six degrees of freedom where a horizontal laser's
geometry has three: what a rigid motion cannot explain (a tilted scan plane's stretch, or landmark
centres biased towards the laser) becomes a scale. Training labels each view through that map, so a
scale in it moves every label along the laser's line of sight by a share of its range; the outline,
accumulated about the labels, then comes out smaller or larger than the robot, and every view's
heading carries the mismatch. Training fitted the first pass's map to the posts' visible surfaces,
which scaled it by 1.012 and left the outline 1.5 cm small; it now fits it to circles through the
posts' points (``gtsjax.train.labels.landmark_centres``). This script trains a model on one of the tests' recordings
(``tests/test_recordings.py``'s cases, the tests' small settings) and measures, on that recording
and on its held-out scenes, against the simulator's truth:

- the scale of the run-time map (``sqrt(det A)`` of every scan's transform: 1 for a rigid map);
- the detections' error along the line of sight (radial) and across it, by range (stage e′'s poses,
  before the tracker), and their heading's (those more than 30° off, the wrong side, counted apart);
  the same by the side of the robot that faces the laser (eight sectors of 45°);
- the learnt outline's radius against the true outline's, by bearing about the robot's centre (the
  zero crossing of the model's signed distance field along each bearing).

    python scripts/label_bias.py [--case SUBSTRING] [--model M.npz --site SITE.json --log LOG.npz]

Prints Markdown tables. With ``--model``, the model, site and simulated log given are measured instead
(a log with ``truth_poses`` and ``extra["truth_sensor_pose"]``, as ``gtsjax simulate`` writes them)."""

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from gtsjax.cli import use_compile_cache  # noqa: E402
from gtsjax.core.geometry import wrap  # noqa: E402
from gtsjax.drivers.batch import process_log  # noqa: E402
from gtsjax.io.logs import to_scans  # noqa: E402
from gtsjax.sim.scene import OUTLINES  # noqa: E402


def heading_error(d: float, period: float) -> float:
    """``d`` wrapped to ``[-period/2, period/2)``: a heading error, modulo a half-turn for a class read so."""
    return float((d + period / 2) % period - period / 2)


RANGES = ((0.0, 2.0), (2.0, 3.0), (3.0, 4.0), (4.0, 8.0))
# The side of the robot the laser sees: the laser's bearing in the robot's frame, in sectors of 45°.
SIDES = ("back (180°)", "back right (-135°)", "right (-90°)", "front right (-45°)", "front (0°)", "front left (45°)",
         "left (90°)", "back left (135°)")
BEARINGS = 72


def true_radii(vertices: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """The distance from the centre to the polygon ``vertices`` along each bearing ``phi`` (a NumPy loop
    over bearings and edges)."""
    out = np.full(phi.shape, np.nan)
    for i, p in enumerate(phi):
        d = np.array([math.cos(p), math.sin(p)])
        for s, e in zip(vertices, np.roll(vertices, -1, 0), strict=True):
            u = e - s
            den = d[0] * u[1] - d[1] * u[0]
            if abs(den) < 1e-12:
                continue
            t = (s[0] * u[1] - s[1] * u[0]) / den
            q = (s[0] * d[1] - s[1] * d[0]) / den
            if t > 0 and 0 <= q <= 1:
                out[i] = t if np.isnan(out[i]) else min(out[i], t)
    return out


def learnt_radii(model, c: int, phi: np.ndarray, step: float = 5e-4) -> np.ndarray:
    """Where the model's signed distance field of class ``c`` first turns positive along each bearing
    from the centre (nearest-cell lookup, ``step`` m apart)."""
    o = model.outline
    field, lo, cell = np.asarray(o.field[c, ..., 0]), np.asarray(o.lo[c]), float(o.cell[c])
    g = field.shape[0]
    r = np.arange(0.0, 0.5, step)
    out = np.full(phi.shape, np.nan)
    for i, p in enumerate(phi):
        xy = np.stack([r * math.cos(p), r * math.sin(p)], -1)
        ij = np.rint((xy - lo) / cell).astype(int)
        ok = np.all((ij >= 0) & (ij < g), -1)
        d = np.where(ok, field[np.clip(ij[:, 0], 0, g - 1), np.clip(ij[:, 1], 0, g - 1)], np.inf)
        k = np.flatnonzero(d > 0)
        out[i] = r[k[0]] if k.size else np.nan
    return out


def measure(model, log, name: str) -> str:
    """The scale of the map and the detections' errors along and across the line of sight, by range."""
    _, out = process_log(model, to_scans(log, model.n_beams))
    A = np.asarray(out.transform.A, np.float64)
    ok = ~np.asarray(out.transform.degraded)
    scale = np.sqrt(np.abs(np.linalg.det(A[ok])))
    c = list(model.classes).index("robot")
    turns = model.pose[c].turns
    period = 2 * math.pi / (1 if turns is None else int(turns))  # a class alike turned half a turn: modulo π
    sp = np.asarray(log.extra["truth_sensor_pose"], np.float64)
    rows = []
    for t in range(log.n_scans):
        for m in range(log.truth_poses.shape[1]):
            truth = log.truth_poses[t, m]
            if np.isnan(truth[0]):
                continue
            det = np.asarray(out.det_mask[t]) & (np.asarray(out.det_class[t]) == c)
            pose = np.asarray(out.det_pose[t], np.float64)
            gap = np.where(det, np.hypot(pose[:, 0] - truth[0], pose[:, 1] - truth[1]), np.inf)
            j = int(np.argmin(gap))
            if gap[j] > 0.3:
                continue
            los = truth[:2] - sp[t, :2]
            rng = float(np.hypot(*los))
            u = los / rng
            e = pose[j, :2] - truth[:2]
            side = float(wrap(math.atan2(-los[1], -los[0]) - truth[2]))  # the laser's bearing in the robot's frame
            rows.append((rng, float(e @ u), float(e[1] * u[0] - e[0] * u[1]), heading_error(pose[j, 2] - truth[2], period), side))
    r = np.asarray(rows).reshape(-1, 5)
    lines = [f"**{name}**: map scale √det A median {np.median(scale):.4f} (5–95 %: {np.percentile(scale, 5):.4f}–"
             f"{np.percentile(scale, 95):.4f}) over {ok.sum()} scans; {len(r)} detections", "",
             "| range [m] | detections | radial bias [mm] | across bias [mm] | heading bias [°] | heading sd [°] "
             "| misread (> 30° off) |", "|---|---|---|---|---|---|---|"]
    right = np.abs(r[:, 3]) <= math.radians(30.0)
    for lo, hi in RANGES:
        s = (r[:, 0] >= lo) & (r[:, 0] < hi)
        h = s & right
        if h.sum() >= 5:
            lines.append(f"| {lo:.0f}–{hi:.0f} | {s.sum()} | {1e3 * r[s, 1].mean():+.1f} | {1e3 * r[s, 2].mean():+.1f} | "
                         f"{np.degrees(r[h, 3].mean()):+.2f} | {np.degrees(r[h, 3].std()):.2f} | {(s & ~right).sum()} |")
    # By the side the laser sees: a view's own bias, which a wrong outline gives each side its own of.
    lines += ["", "| side facing the laser | detections | radial bias [mm] | across bias [mm] | heading bias [°] "
              "| heading sd [°] |", "|---|---|---|---|---|---|"]
    sector = np.floor((np.degrees(r[:, 4]) + 202.5) / 45.0).astype(int) % 8
    for i, name in enumerate(SIDES):
        s = (sector == i) & right
        if s.sum() >= 5:
            lines.append(f"| {name} | {s.sum()} | {1e3 * r[s, 1].mean():+.1f} | {1e3 * r[s, 2].mean():+.1f} | "
                         f"{np.degrees(r[s, 3].mean()):+.2f} | {np.degrees(r[s, 3].std()):.2f} |")
    per = [np.degrees(r[(sector == i) & right, 3].mean()) for i in range(8) if ((sector == i) & right).sum() >= 5]
    if per:
        lines += ["", f"Heading bias of the sides: RMS {math.sqrt(np.mean(np.square(per))):.2f}°, "
                      f"largest {max(np.abs(per)):.2f}°."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="turned on the spot, SPL field", help="the first recording case whose name holds this")
    ap.add_argument("--model", type=Path, help="measure this model instead of training one")
    ap.add_argument("--site", type=Path, help="with --model: the site of --log")
    ap.add_argument("--log", type=Path, help="with --model: a simulated log to measure it on")
    ap.add_argument("--outline", default="nao", help="with --model: the simulated robot's outline (gtsjax.sim.scene.OUTLINES)")
    args = ap.parse_args()
    use_compile_cache()
    if args.model:
        from gtsjax.io import load_log, load_site
        from gtsjax.io.modelfile import load_model

        model, outline = load_model(args.model), args.outline
        scenes = {"given log": (load_log(args.log), load_site(args.site))}
    else:
        from gtsjax.sim import check_scene, recording
        from gtsjax.train import train
        from tests.test_recordings import CASES, SMALL

        name = next(n for n in CASES if args.case in n)
        case = CASES[name]
        seed, check_seed = case.get("seeds", (1, 2))
        log, site = recording(case["site"], case["style"], seed=seed, rate_hz=case["rate_hz"], clutter=case["clutter"],
                              outline=case["outline"], seconds=case["seconds"])
        model, _ = train([log], site, case.get("config", SMALL))
        outline = case["outline"]
        scenes = {"the training recording": (log, site)}
        for kind in ("static", "walking"):
            scenes[f"held-out {kind} scene"] = check_scene(case["site"], kind, seed=check_seed, rate_hz=case["rate_hz"],
                                                          outline=outline, clutter=case["clutter"])
        print(f"# {name}\n")
    for what, (log, site) in scenes.items():
        print(measure(model.with_site(site), log, what) + "\n")
    c = list(model.classes).index("robot")
    if model.outline is not None and bool(model.outline.has[c]):
        phi = 2 * math.pi * (np.arange(BEARINGS) + 0.5) / BEARINGS - math.pi
        got, want = learnt_radii(model, c, phi), true_radii(OUTLINES[outline][0], phi)
        err = got - want
        print(f"**Learnt outline against the true one** ({BEARINGS} bearings): radius {1e3 * np.nanmean(err):+.1f} mm "
              f"on average (RMS {1e3 * np.sqrt(np.nanmean(err**2)):.1f} mm, from {1e3 * np.nanmin(err):+.1f} to "
              f"{1e3 * np.nanmax(err):+.1f} mm)")


if __name__ == "__main__":
    main()
