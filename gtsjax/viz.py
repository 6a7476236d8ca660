"""Figures (matplotlib, headless): the field with its landmarks and sensor, true and estimated
trajectories, and error over time."""

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def draw_site(ax, site, sensor_pose=None) -> None:
    """Bounds, landmarks and the sensor (the site's guess, or ``sensor_pose`` if given)."""
    if site.bounds is not None:
        x0, y0, x1, y1 = site.bounds
        ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=True, fc="#e8f4e8", ec="#3a7d3a", lw=1.5,
                                   zorder=0))
    xy = site.landmark_xy
    ax.scatter(xy[:, 0], xy[:, 1], marker="o", s=60, c="#222", zorder=3, label="landmarks")
    poses = [site.sensor_pose if sensor_pose is None else sensor_pose]
    names = [None]
    if sensor_pose is None and getattr(site, "sensors", ()):
        poses, names = [sen.pose for sen in site.sensors], [sen.name for sen in site.sensors]
    for k, ((sx, sy, sth), name) in enumerate(zip(poses, names, strict=True)):
        ax.scatter([sx], [sy], marker="s", s=80, c="#c33", zorder=4, label="laser" if k == 0 else None)
        ax.arrow(sx, sy, 0.35 * math.cos(sth), 0.35 * math.sin(sth), width=0.02, color="#c33", zorder=4)
        if name is not None:
            ax.annotate(name, (sx, sy), textcoords="offset points", xytext=(6, 6), fontsize=8, color="#c33", zorder=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def arrow_rows(pose: np.ndarray, spacing: float = 0.3, turn: float = math.radians(45), most: int = 25) -> np.ndarray:
    """Rows of a path ``[n, 3]`` (x, y, θ) to draw a heading arrow at, so that arrows stay sparse: the
    first row, then each row that lies ``spacing`` metres along the path or ``turn`` radians of heading
    from the last arrow; at most ``most``, evenly thinned, so that a jittery track does not become a
    solid block of arrows."""
    keep = [0] if len(pose) else []
    for i in range(1, len(pose)):
        j = keep[-1]
        moved = math.hypot(pose[i, 0] - pose[j, 0], pose[i, 1] - pose[j, 1])
        turned = abs(math.remainder(pose[i, 2] - pose[j, 2], 2 * math.pi))
        if moved >= spacing or turned >= turn:
            keep.append(i)
    idx = np.asarray(keep, dtype=int)
    if len(idx) > most:
        idx = idx[np.linspace(0, len(idx) - 1, most).round().astype(int)]
    return idx


def trajectory_figure(site, tracks: dict, truth=None, errors=None, title: str = "", sensor_pose=None, labels=None,
                      truth_labels=None, max_legend: int = 12):
    """``tracks``: track id -> array [n, 4] (stamp, x, y, θ); ``truth``: list of arrays [n, 3] (x, y, θ)
    per labelled object; ``errors``: (t [n], position error [n] m, heading error [n] rad), or a list of
    (label, t, position error, heading error) with one entry per labelled object, or None.

    ``labels``: track id -> legend text (default ``track <id>``); ``truth_labels``: legend text per
    labelled object (default: one entry, ``truth``), also written where each true path starts. Only the first ``max_legend`` tracks get a legend
    entry, so a log with many short tracks still leaves the field visible; the rest are counted.
    """
    rows = 2 if errors is not None else 1
    fig = plt.figure(figsize=(9, 7.5 if rows == 2 else 5.5), constrained_layout=True)
    gs = fig.add_gridspec(rows, 1, height_ratios=[3, 1.2][:rows])
    ax = fig.add_subplot(gs[0])
    draw_site(ax, site, sensor_pose)
    for k, tr in enumerate(truth or []):
        ok = ~np.isnan(tr[:, 0])
        label = truth_labels[k] if truth_labels is not None else ("truth" if k == 0 else None)
        ax.plot(tr[ok, 0], tr[ok, 1], "-", c="#999", lw=3, alpha=0.6, label=label)
        if truth_labels is not None and ok.any():  # name each true path where it starts
            x0, y0 = tr[ok][0, :2]
            ax.annotate(truth_labels[k], (x0, y0), textcoords="offset points", xytext=(0, -11), ha="center",
                        fontsize=7, color="#555")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (tid, tr) in enumerate(sorted(tracks.items())):
        c = colours[k % len(colours)]
        label = (labels or {}).get(tid, f"track {tid}") if k < max_legend else None
        ax.plot(tr[:, 1], tr[:, 2], "-", c=c, lw=1.2, label=label)
        a = tr[arrow_rows(tr[:, 1:])]
        ax.quiver(a[:, 1], a[:, 2], np.cos(a[:, 3]), np.sin(a[:, 3]), color=c, scale=30, width=0.003)
    if len(tracks) > max_legend:
        ax.plot([], [], " ", label=f"+ {len(tracks) - max_legend} more tracks")
    ax.legend(loc="upper right", fontsize=8, ncol=2)
    ax.set_title(title)
    if errors is not None:
        ax2 = fig.add_subplot(gs[1])
        ax2.set_xlabel("time [s]")
        ax2.grid(alpha=0.3)
        ax3 = ax2.twinx()
        if isinstance(errors, tuple):
            t, e_pos, e_th = errors
            ax2.plot(t, 100 * e_pos, c="#1f77b4", lw=1)
            ax2.set_ylabel("position error [cm]", color="#1f77b4")
            ax3.plot(t, np.degrees(np.abs(e_th)), c="#d62728", lw=1, alpha=0.7)
            ax3.set_ylabel("|heading error| [°]", color="#d62728")
        else:
            for k, (label, t, e_pos, e_th) in enumerate(errors):
                c = colours[k % len(colours)]
                ax2.plot(t, 100 * e_pos, "-", c=c, lw=1.2, label=f"{label} position")
                ax3.plot(t, np.degrees(np.abs(e_th)), ":", c=c, lw=1, alpha=0.8)
            ax2.set_ylabel("position error [cm] (solid)")
            ax3.set_ylabel("|heading error| [°] (dotted)")
            ax2.legend(loc="upper left", fontsize=8)
    return fig


def error_map_figure(site, points, pos_rmse, head_rmse, title: str = ""):
    """Fig. 6 of the paper: error by place on the field (position and heading RMSE per point)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), constrained_layout=True)
    for ax, vals, label, scale in ((axes[0], pos_rmse, "position RMSE [cm]", 100.0),
                                   (axes[1], head_rmse, "heading RMSE [°]", 1.0)):
        draw_site(ax, site)
        v = np.asarray(vals) * scale
        sc = ax.scatter(points[:, 0], points[:, 1], c=v, s=250, cmap="viridis", ec="k", zorder=5)
        for (x, y), val in zip(points, v, strict=True):
            ax.annotate(f"{val:.1f}", (x, y), textcoords="offset points", xytext=(0, 12), ha="center", fontsize=8)
        fig.colorbar(sc, ax=ax, label=label, shrink=0.8)
        ax.set_title(label)
    fig.suptitle(title)
    return fig


def outline_figure(model, title: str = ""):
    """What the model learnt each mobile class looks like at the laser's height (stage e′): the outline
    (zero level of its signed distance field) in the object's own frame, its heading (x) axis, and the
    outline turned to each of its side hypotheses (faint: the sides a partial view may be taken for)."""
    out = model.outline
    ks = [k for k in range(len(model.classes)) if out is not None and bool(out.has[k])]
    fig, axes = plt.subplots(1, max(len(ks), 1), figsize=(4.6 * max(len(ks), 1), 4.6), constrained_layout=True,
                             squeeze=False)
    if not ks:
        axes[0, 0].text(0.5, 0.5, "no learnt outline", ha="center", va="center")
        axes[0, 0].set_axis_off()
        return fig
    for ax, k in zip(axes[0], ks, strict=True):
        field = np.asarray(out.field[k, :, :, 0])
        lo, cell = np.asarray(out.lo[k], float), float(out.cell[k])
        g = field.shape[0]
        ax_x = lo[0] + cell * np.arange(g)
        ax_y = lo[1] + cell * np.arange(g)
        ax.contourf(ax_x, ax_y, field.T, levels=[-1.0, 0.0], colors=["#cfe0f5"])
        ax.contour(ax_x, ax_y, field.T, levels=[0.0], colors=["#1f5fa8"], linewidths=2)
        sides = np.asarray(out.sides[k])[np.asarray(out.side_mask[k])][1:]
        for a in sides:
            c, s = math.cos(a), math.sin(a)
            xx, yy = np.meshgrid(ax_x, ax_y, indexing="ij")
            ax.contour(c * xx - s * yy, s * xx + c * yy, field, levels=[0.0], colors=["#999"], linewidths=0.8,
                       linestyles="dashed")
        r = float(np.max(np.abs(lo)))
        ax.arrow(0, 0, 0.6 * r, 0, width=0.004 * r / 0.2, color="#c33", zorder=4, length_includes_head=True)
        ax.plot([0], [0], "k+", ms=10)
        ax.set_xlim(lo[0], -lo[0])
        ax.set_ylim(lo[1], -lo[1])
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (heading)")
        ax.set_ylabel("y [m]")
        turns = ", ".join(f"{math.degrees(a):+.0f}°" for a in sides) or "none"
        ax.set_title(f"{model.classes[k]}: learnt outline\nside hypotheses (dashed): {turns}", fontsize=10)
    if title:
        fig.suptitle(title, fontsize=9 if len(ks) == 1 else 11)
    return fig


def coverage_grid(site, models, step: float = 0.05, margin: float = 0.5):
    """How many of the site's lasers see each spot of the field: a grid over the bounds (or the
    landmarks' and sensors' extent, with ``margin``), and per sensor a boolean map of the spots within
    its scanner's range and field of view (``models``: one :class:`~gtsjax.sensors.SensorModel` per
    sensor of ``site.sensor_list``). Occlusion is not modelled: a robot between the laser and a spot
    hides it, which is why a crowded field wants more than one laser."""
    if site.bounds is not None:
        x0, y0, x1, y1 = site.bounds
    else:
        pts = np.vstack([site.landmark_xy, [sen.pose[:2] for sen in site.sensor_list]])
        (x0, y0), (x1, y1) = pts.min(0) - margin, pts.max(0) + margin
    xs = np.arange(x0 + step / 2, x1, step)
    ys = np.arange(y0 + step / 2, y1, step)
    gx, gy = np.meshgrid(xs, ys)
    spots = np.stack([gx, gy], axis=-1)
    seen = [m.beams.reach(np.asarray(sen.pose, float), spots) for sen, m in zip(site.sensor_list, models, strict=True)]
    return xs, ys, np.asarray(seen)


def coverage_figure(site, models, title: str = ""):
    """The field coloured by how many lasers see each spot (within range and field of view), each
    laser's reach outlined."""
    xs, ys, seen = coverage_grid(site, models)
    count = seen.sum(0)
    n = len(models)
    fig, ax = plt.subplots(figsize=(8, 6))
    cmap = plt.get_cmap("viridis", n + 1)
    im = ax.pcolormesh(xs, ys, count, cmap=cmap, vmin=-0.5, vmax=n + 0.5, shading="nearest", zorder=1, alpha=0.85)
    cb = fig.colorbar(im, ax=ax, ticks=range(n + 1), shrink=0.8)
    cb.set_label("lasers that see the spot")
    for sen, m in zip(site.sensor_list, models, strict=True):
        sx, sy, sth = sen.pose
        a = sth + np.linspace(m.angle_min, m.angle_max, 200)
        ax.plot(np.r_[sx, sx + m.range_max * np.cos(a), sx], np.r_[sy, sy + m.range_max * np.sin(a), sy],
                color="#c33", lw=0.8, ls="--", zorder=2)
    draw_site(ax, site)
    for patch in ax.patches:  # the bounds' fill would hide the map; keep their outline
        patch.set_fill(False)
        patch.set_zorder(3)
    if site.bounds is not None:
        x0, y0, x1, y1 = site.bounds
        ax.set_xlim(min(x0, *(s.pose[0] for s in site.sensor_list)) - 0.5, max(x1, *(s.pose[0] for s in site.sensor_list)) + 0.5)
        ax.set_ylim(min(y0, *(s.pose[1] for s in site.sensor_list)) - 0.5, max(y1, *(s.pose[1] for s in site.sensor_list)) + 0.5)
    ax.set_title(title)
    fig.tight_layout()
    return fig


def grade_figure(site, g, t0: float, title: str = ""):
    """One robot's grade (:class:`gtsjax.grade.RobotGrade`): the field with the ground truth's path of
    the robot (grey, thick) and its belief's (blue, at its clock offset, in the field's frame), then
    its position and heading error over time against the ground truth's own 2-σ band and the lost
    limits, with the belief's jumps marked."""
    from .grade.metrics import LOST_M, LOST_RAD

    e = g.errors
    fig = plt.figure(figsize=(9, 9), constrained_layout=True)
    gs = fig.add_gridspec(3, 1, height_ratios=[3, 1.1, 1.1])
    ax = fig.add_subplot(gs[0])
    if site is not None:
        draw_site(ax, site)
    else:
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    t = e.t - t0
    # Break the lines where the robot was unseen (rows further apart than a few of the ground truth's
    # usual intervals).
    from .grade import seen_gap

    usual = float(np.median(np.diff(e.t))) if e.t.size > 1 else 0.1
    cut = np.concatenate([[0], np.flatnonzero(np.diff(e.t) > seen_gap(usual)) + 1, [e.t.size]])
    for k, (a, b) in enumerate(zip(cut[:-1], cut[1:], strict=True)):
        ax.plot(e.truth[a:b, 0], e.truth[a:b, 1], "-", c="#888", lw=3.5, alpha=0.6,
                label="ground truth" if k == 0 else None)
        ax.plot(e.belief[a:b, 0], e.belief[a:b, 1], "-", c="#1f77b4", lw=1, label="belief" if k == 0 else None)
    lost = (e.pos > LOST_M) | (np.abs(e.head) > LOST_RAD)
    if lost.any():
        ax.scatter(e.belief[lost, 0], e.belief[lost, 1], s=4, c="#d62728", zorder=3, label="belief, lost")
    if e.t.size:  # the robot's part of the field, with room about it
        both = np.concatenate([e.truth[:, :2], e.belief[:, :2]])
        lo, hi = both.min(0) - 0.5, both.max(0) + 0.5
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_title(title or g.name)
    ax2 = fig.add_subplot(gs[1])
    ax2.fill_between(t, 0, 100 * e.band_pos, color="#aaa", alpha=0.5, lw=0, label="ground truth's 2σ")
    ax2.plot(t, 100 * e.pos, ".", ms=1.5, c="#1f77b4", label="position error")
    ax2.axhline(100 * LOST_M, c="#d62728", lw=0.8, ls="--", label=f"lost ({100 * LOST_M:.0f} cm)")
    ax2.set_ylabel("position error [cm]")
    ax2.set_yscale("symlog", linthresh=10.0)
    ax3 = fig.add_subplot(gs[2], sharex=ax2)
    ax3.fill_between(t, 0, np.degrees(e.band_head), color="#aaa", alpha=0.5, lw=0)
    ax3.plot(t, np.degrees(np.abs(e.head)), ".", ms=1.5, c="#9467bd")
    ax3.axhline(math.degrees(LOST_RAD), c="#d62728", lw=0.8, ls="--")
    ax3.set_ylabel("|heading error| [°]")
    ax3.set_xlabel("time from the ground truth's first row [s]")
    for j in g.jumps:
        for a in (ax2, ax3):
            a.axvline(j.stamp - t0, c="#ff7f0e", lw=0.8 if j.lost else 0.5, alpha=0.8 if j.lost else 0.4)
    if g.jumps:
        ax2.plot([], [], c="#ff7f0e", lw=0.8, label="jump of the belief")
    ax2.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), fontsize=7, ncol=4, frameon=False)
    for a in (ax2, ax3):
        a.grid(alpha=0.3)
    return fig
