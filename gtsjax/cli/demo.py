"""``gtsjax demo``: live ground truth of a simulated robot, end to end, with nothing but the package.

An emulated URG-04LX on a pseudo-terminal serves the paper's SPL field with a robot walking a path;
``gtsjax run``'s loop reads it over pyserial with the model shipped in the package, shows the live
view for about 20 s, then writes ``demo-out/`` (the GTD CSV, the site file, and a PNG of the field,
true and estimated trajectories and the error over time) and says where they are. No confirmed track
at all is a failure: one line on stderr and exit status 1.
"""

import sys
import time
from importlib import resources
from pathlib import Path

import numpy as np
import typer
from rich.console import Console

from ..core.geometry import wrap
from ._app import QUIET_HELP, app
from ._common import VIEW_HELP, VIEW_SAVE_HELP

DEMO_SCENARIO = "spl-trajectory"
DEMO_SEED = 7


def demo_model_path() -> Path:
    return Path(str(resources.files("gtsjax") / "data" / "demo-model.npz"))


def match_truth(stamps_gtd: np.ndarray, served_times: np.ndarray, served_index: np.ndarray, truth: np.ndarray):
    """For each GTD stamp, the truth pose of the frame served nearest in time (the emulator records
    when it produced each frame; the link maps the sensor's clock onto the same host clock)."""
    order = np.argsort(served_times)
    st, si = served_times[order], served_index[order]
    j = np.clip(np.searchsorted(st, stamps_gtd), 1, len(st) - 1)
    j = np.where(np.abs(st[j - 1] - stamps_gtd) < np.abs(st[j] - stamps_gtd), j - 1, j)
    return truth[si[j] % len(truth)], np.abs(st[j] - stamps_gtd)


@app.command("demo")
def demo_cmd(
    seconds: float = typer.Option(20.0, help="How long to track."),
    out_dir: Path = typer.Option(Path("demo-out"), "--out-dir", help="Where to write the results."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
    view: str | None = typer.Option(None, "--view", metavar="[web]", help=VIEW_HELP),
    view_save: Path | None = typer.Option(None, "--view-save", help=VIEW_SAVE_HELP),
):
    """Track a simulated robot live for ~20 s over an emulated sensor; write demo-out/ (CSV + PNG)."""
    import os

    from ..io.gtd import read_gtd, tracks_of
    from ..io.site import save_site
    from ..sim import simulate
    from ..sim.emulator import SensorEmulator, log_source
    from ..viewer import VIEWER_EXTRA, rerun_available
    from ..viz import trajectory_figure
    from ._live import track_live

    console = Console(stderr=True)
    t0 = time.perf_counter()
    if not rerun_available():
        console.print(f"(to watch it in Rerun's viewer: {VIEWER_EXTRA}, then gtsjax demo --view, or --view web "
                      "without a display)", soft_wrap=True, markup=False)  # the extra's [brackets] are not markup
    elif view is None and not quiet and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        view = "native"  # the extra is there and so is a screen
    out_dir.mkdir(parents=True, exist_ok=True)
    log, site = simulate(DEMO_SCENARIO, seed=DEMO_SEED)
    site_path = out_dir / "site.json"
    save_site(site, site_path)
    base = log_source(log)
    served_t, served_i = [], []

    def source(i):
        # The emulator numbers frames by the time since it started, and the walk is 60 s long: a slow
        # first start-up (compiling for over a minute) once began the tracking past its end, the walk
        # looping back within 20 s (two tracks, a teleport). The walk starts at the first frame asked for.
        if not served_i:
            start.append(i)
        j = i - start[0]
        served_t.append(time.time())
        served_i.append(j)
        return base(j)

    start: list[int] = []

    gtd = out_dir / "gtd.csv"
    from ..sensors import get_model

    with SensorEmulator(get_model(log.sensor_model), source) as emu:
        console.print(f"emulated {log.sensor_model} on {emu.path}: the SPL field, a robot walking ({DEMO_SCENARIO})")
        stats, link_stats, _ = track_live(emu.path, demo_model_path(), site_path, gtd, duration=seconds,
                                          view=not quiet, console=console, rerun_view=view, view_save=view_save)
    rows = read_gtd(gtd)
    tracks = {tid: arr for tid, _, arr in tracks_of(rows)}
    truth = log.truth_poses[:, 0]
    errors = None
    summary = "no track was confirmed"
    if rows:
        st = np.array([r.stamp for r in rows])
        est = np.array([[r.x, r.y, r.theta] for r in rows])
        tru, _ = match_truth(st, np.asarray(served_t), np.asarray(served_i), truth)
        e_pos = np.linalg.norm(est[:, :2] - tru[:, :2], axis=1)
        e_th = wrap(est[:, 2] - tru[:, 2])
        errors = (st - st[0], e_pos, e_th)
        summary = (f"position RMSE {100 * np.sqrt(np.mean(e_pos**2)):.1f} cm, heading RMSE "
                   f"{np.degrees(np.sqrt(np.mean(e_th**2))):.1f}° over {len(rows)} rows")
    served_idx = np.asarray(served_i) % len(truth)
    shown_truth = truth[served_idx.min(): served_idx.max() + 1] if served_i else truth
    med, p99 = stats.latency()
    fig = trajectory_figure(site, tracks, truth=[shown_truth], errors=errors,
                            title=f"gtsjax demo: {summary}\nframe-to-GTD latency median {med:.2f} ms, p99 {p99:.2f} ms")
    png = out_dir / "demo.png"
    fig.savefig(png, dpi=110)
    console.print(f"tracked {stats.frames} frames in {seconds:.0f} s: {summary}; latency median {med:.2f} ms, "
                  f"p99 {p99:.2f} ms; {link_stats.bad_frames} bad frames")
    console.print(f"wrote {gtd}, {site_path} and {png} ({time.perf_counter() - t0:.0f} s in all)")
    if not rows:  # the demo's one promise is a tracked robot: without one it failed, whatever it wrote
        print(f"gtsjax: demo: no track was confirmed in {stats.frames} frames over {seconds:g} s "
              f"({link_stats.bad_frames} bad frames)", file=sys.stderr)
        raise typer.Exit(1)
