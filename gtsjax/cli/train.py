"""``gtsjax train LOG.npz ... --site SITE.json [--background LOG ...] --out MODEL``: learn the classifier,
its open-set test, the shape envelopes, the pose regressors and the motion limits from labelled logs
(and background logs: any log ``convert`` reads, recorded with no robot in view), with progress per
GP fit and summary tables.

Its GP fits take most of its minutes, one at a time, and one may take several: on a terminal a bar
(:class:`FitProgress`) says which fit of how many runs, for how long, and about how long the fits
left will take; a line per fit (above the bar) keeps each one's result, in a log too."""

import dataclasses
import json
import time
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from ..drivers.setup import MAX_TRACKS_LIMIT
from ..errors import InputError
from ..io import load_log, load_site
from ..io.modelfile import save_model
from ..io.site import one_sensor
from ..train import TrainConfig, fit_background, train
from ._app import app
from ._checks import check_class_names
from ._common import check_out_file, distinct_paths, interruptible, load_input


@app.command("train")
def train_cmd(
    logs: list[Path] = typer.Argument(None, help="Labelled scan logs (.npz) of one site."),
    laser_logs: list[str] = typer.Option([], "--log", metavar="NAME=LOG",
                                         help="A labelled log of one laser of a site with several (its name in the "
                                              "site's sensors list); repeatable, with or without positional logs."),
    site: Path = typer.Option(..., "--site", help="Site file (.json) the logs were recorded on."),
    sensor: str | None = typer.Option(None, "--laser", help="With a site of several lasers: the one the scans are "
                                                          "from (its name in the site's sensors list)."),
    out: Path = typer.Option(..., "--out", help="Model file to write."),
    max_per_class: int = typer.Option(TrainConfig.max_per_class, min=2, help="Classifier examples per class (balanced)."),
    max_pose: int = typer.Option(TrainConfig.max_pose_examples, min=2,
                                 help="Pose-GP examples per mobile class (the GPs' posterior; the step's cost grows "
                                      "with it)."),
    max_pose_fit: int = typer.Option(TrainConfig.max_pose_fit, min=2,
                                     help="Of those, how many the pose GPs' hyperparameters are fitted on (the "
                                          "fit's cost grows with its cube)."),
    max_landmark: int = typer.Option(TrainConfig.max_landmark_examples, min=2, help="Position-GP examples per landmark class."),
    inducing: int = typer.Option(TrainConfig.n_inducing, min=1,
                                 help="Inducing points of the mobile classes' pose GPs (exact mean up to this size)."),
    inducing_class: int = typer.Option(TrainConfig.n_inducing_class, min=1,
                                       help="Inducing points of the classifier's and landmark GPs."),
    pose_kernels: int = typer.Option(TrainConfig.pose_kernels, "--pose-kernels", min=1, max=4,
                                     help="Kernels of a tracked class's four pose GPs (x, y, sin θ, cos θ): 2 = one for "
                                          "the position, one for the heading (two kernel rows per candidate in the "
                                          "step), 1 = one for all, 4 = each its own. 3 is not a layout."),
    restarts: int = typer.Option(TrainConfig.restarts, min=1, help="Optimiser starts per GP fit."),
    max_tracks: int = typer.Option(TrainConfig.max_tracks, "--max-tracks", min=1, max=MAX_TRACKS_LIMIT,
                                   help="Track slots of the model (and robots given a pose per scan): at least as many "
                                        "as robots on the field, a few more for look-alikes; run, replay and evaluate "
                                        "can change it."),
    seed: int = typer.Option(TrainConfig.seed, help="Seed for sampling, the held-out split and restarts."),
    report: Path | None = typer.Option(None, "--report", help="Also write the training report as JSON."),
    background: list[Path] = typer.Option(
        [], "--background",
        help="Background log(s), any format convert reads, recorded with no robot in view (the empty field, people "
             "walking, chairs): every candidate in them is a background example. Same angular step as the labelled "
             "logs; a wider field of view is cropped. Several may follow one --background."),
    background_topic: str | None = typer.Option(None, "--background-topic",
                                                help="LaserScan topic of background ROS bags with several."),
    max_background: int | None = typer.Option(None, min=1, help="Classifier examples of the background class (default: "
                                                         "--max-per-class, or twelve times it with --background)."),
    max_mobile: int | None = typer.Option(None, min=1, help="Classifier examples of each tracked class (default: "
                                                     "--max-per-class, or four times it with --background)."),
    max_speed: list[str] = typer.Option([], "--max-speed", metavar="CLASS=M_PER_S",
                                        help="A class's maximum speed (default: from its labelled motion, else "
                                             "0.6 m/s)."),
    heading_turns: list[str] = typer.Option([], "--heading-turns", metavar="CLASS=1|2",
                                            help="A class's heading symmetry: 2 if it looks the same turned half a "
                                                 "turn (its heading then read modulo 180°), 1 if not (default: from "
                                                 "its outline)."),
    max_turn_rate: list[str] = typer.Option([], "--max-turn-rate", metavar="CLASS=RAD_PER_S",
                                            help="A class's maximum turn rate (default: from its labelled motion, "
                                                 "else 3 rad/s)."),
    scan_rate: float | None = typer.Option(None, "--scan-rate", metavar="HZ", min=0.5, max=200.0,
                                           help="The scanner's rate live (default: from the logs' stamps, or the "
                                                "named scanner's where the logs kept fewer scans)."),
    check: bool = typer.Option(True, "--check/--no-check",
                               help="After fitting, replay the labelled logs through the whole step (tracker "
                                    "included) and score tracking on their held-out seconds."),
    strict: bool = typer.Option(False, "--strict",
                                help="Exit 1 (the model still written) when that check finds a tracked class "
                                     "reported in fewer than 90 % of the held-out scans in which it was detected."),
    quiet: bool = typer.Option(False, "--quiet",
                               help="No progress on stderr: no bar, no line per GP fit (the tables on stdout list "
                                    "the fits)."),
):
    """Train a model from labelled logs (training and held-out evaluation)."""
    console = Console(stderr=True)
    full = load_site(site)
    logs = list(logs or [])
    if not logs and not laser_logs:
        raise InputError("train", "give labelled logs (or --log NAME=LOG per laser of a site with several)")
    sites = [one_sensor(full, sensor, site)] * len(logs) if logs else []
    for spec in laser_logs:
        name, eq, path = spec.partition("=")
        if not eq or not name or not path:
            raise InputError("--log", f"{spec!r} is not NAME=LOG")
        if not full.sensors:
            raise InputError(site, "has no sensors list; --log NAME=LOG is for a site with several lasers")
        sites.append(one_sensor(full, name, site))
        logs.append(Path(path))
    distinct_paths({"LOG": logs, "--site": site, "--background": list(background or [])},
                   {"--out": out, "--report": report})
    check_out_file(out)  # before the minutes of fitting
    if report is not None:
        check_out_file(report, "--report")
    cfg = dataclasses.replace(TrainConfig(), max_per_class=max_per_class, max_pose_examples=max_pose,
                              max_pose_fit=max_pose_fit, pose_kernels=pose_kernels,
                              max_landmark_examples=max_landmark, n_inducing=inducing, n_inducing_class=inducing_class,
                              restarts=restarts, seed=seed, max_tracks=max_tracks, max_background=max_background, max_mobile=max_mobile,
                              max_speed=_per_class(max_speed, "--max-speed"),
                              max_turn_rate=_per_class(max_turn_rate, "--max-turn-rate"), scan_rate_hz=scan_rate,
                              heading_turns=_turns(heading_turns),
                              check_pipeline=check)
    loaded = [load_log(p) for p in logs]
    if loaded and all(log.labelled for log in loaded):  # a class the labels do not have is a typo, said now
        from ..train.labels import class_list

        known = class_list(loaded, sites[0])[0][1:]
        for option, given in (("--max-speed", cfg.max_speed), ("--max-turn-rate", cfg.max_turn_rate),
                              ("--heading-turns", cfg.heading_turns)):
            check_class_names(option, given, known, "the labels and the site's landmarks")
    bg = [load_input(p, background_topic if _is_bag(p) else None, console) for p in background]
    if loaded and loaded[0].labelled:  # every input checked before the minutes of fitting
        bg = fit_background(loaded[0], bg, [str(p) for p in background])

    console.print(f"training on {sum(log.n_scans for log in loaded)} scans from {len(loaded)} log(s)"
                  + (f" and {sum(b.n_scans for b in bg)} background scans from {len(bg)} log(s)" if bg else ""))
    with FitProgress(console, bar=not quiet and console.is_terminal, lines=not quiet) as shown:
        model, rep = interruptible(lambda: train(loaded, sites, cfg, progress=shown.fitted, stages=shown.stage,
                                                 names=[str(p) for p in logs], background=bg,
                                                 background_names=[str(p) for p in background]))
        shown.finish()
    save_model(model, out, summary=rep)
    _summary(Console(), rep, out)
    if model.outline is not None:
        import matplotlib.pyplot as plt

        from ..viz import outline_figure

        figure = outline_path(out)
        fig = outline_figure(model, title=f"{out.name}: what the model learnt the robots look like")
        fig.savefig(figure, dpi=100)
        plt.close(fig)
        console.print(f"wrote {figure} (the learnt outline of each mobile class)")
    for w in rep.get("warnings", []):
        console.print(f"warning: {w}", soft_wrap=True)
    if report is not None:
        report.write_text(json.dumps(rep, indent=2) + "\n")
    for line in rep.get("pipeline_problems", []):
        console.print(f"warning: the model cannot track {line}", soft_wrap=True)
    if strict and rep.get("pipeline_problems"):
        console.print(f"train --strict: {out} was written, but fails the pipeline check (above)", soft_wrap=True)
        raise typer.Exit(1)


class FitProgress:
    """``train``'s progress on stderr, fed by :func:`~gtsjax.train.train`'s ``stages`` and ``progress``
    callbacks: with ``bar``, a bar of the GP fits with the stage, "fit k of N" and the fit's name and
    size, the time elapsed and about how long the fits left will take; with ``lines``, a line per fit as
    it ends and a line per stage as it ends (printed above the bar), the tracking check announced as
    it begins (it runs the trained step, some minutes of a large training with nothing else to show).

    The estimate of the time left (:meth:`seconds_left`) prices each fit left at two measured rates:
    its rows' work (:func:`~gtsjax.train.fit_work`) at the seconds per unit of work the fits done took
    once their compilation is taken out (each fit's ``compile_seconds``), plus, for a fit of a size
    not fitted yet, the compilation a new size took on average (a size fitted already reuses its
    program). Pricing the first fits' whole time by their size instead, as this did, counted their
    compilation, most of a small fit, as work, and promised 12–49 minutes for a 12-minute training.
    Fits of one size still differ several-fold in their optimiser's steps, so it is "about".
    ``done`` and ``total`` are k and N."""

    def __init__(self, console: Console, *, bar: bool = True, lines: bool = True):
        self.console, self.lines = console, lines
        self.total: int | None = None
        self.done = 0
        self.plan: list[dict] = []
        self.stage_name = ""
        self.stage_began = time.monotonic()
        self.done_weight = 0.0
        self.history: list[tuple[float, float, float, tuple]] = []  # per fit done: work, seconds, compiling, size
        self.started: float | None = None  # when the running fit began; None between fits
        self.bar = Progress(TextColumn("{task.description}", markup=False), BarColumn(bar_width=20), TimeElapsedColumn(),
                            _Left(self), console=console, transient=True, disable=not bar)
        self.task = self.bar.add_task("training", total=None)

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def stage(self, name: str, fits: list[dict]) -> None:
        """Training entered stage ``name``; ``fits``: the GP fits still to come (the first call: all)."""
        if self.total is None:
            self.total = len(fits)
            self.bar.update(self.task, total=sum(f["weight"] for f in fits) or 1.0, completed=0.0)
        self.finish()
        self.stage_name, self.plan = name, list(fits)
        self.stage_began = time.monotonic()
        if self.lines and name == "tracking check":
            self._say("  tracking check: the trained step over the held-out seconds and simulated stays and walks "
                      "(the step compiles first)")
        self._next()

    def finish(self) -> None:
        """The running stage ended: its line (with ``lines``), once."""
        if self.lines and self.stage_name:
            self._say(f"  {self.stage_name}: done in {time.monotonic() - self.stage_began:.1f} s")
        self.stage_name = ""

    def fitted(self, info: dict) -> None:
        """A GP fit ended (its summary, a line of the report's ``fits``)."""
        self.done += 1
        entry = self.plan.pop(0) if self.plan else {"weight": 0.0}
        self.done_weight += entry["weight"]
        if entry["weight"] > 0:  # the second output of a shared kernel was fitted with the first
            self.history.append((float(entry.get("work", entry["weight"])), float(info["seconds"]),
                                 float(info.get("compile_seconds", 0.0)), _size(entry)))
        if self.lines:
            left = self.seconds_left(after_fit=True)
            self._say(f"  fitted GP {info['gp']:<22} n={info['n']:<5} LML={info['lml']:10.1f}  "
                      f"{info['seconds']:6.1f} s  (fit {self.done} of {self.total}"
                      + (f"; about {_clock(left)} of fitting left)" if left else ")"))
        self._next()

    def _say(self, line: str) -> None:
        self.console.print(line, markup=False, highlight=False, soft_wrap=True)

    def _next(self) -> None:
        fitting = bool(self.plan) and self.plan[0]["stage"] == self.stage_name
        self.started = time.monotonic() if fitting else None
        if fitting:
            f = self.plan[0]
            size = f"{f['n']} examples" + (f", fitted on {f['n_fit']}" if f["n_fit"] < f["n"] else "")
            what = f"fit {self.done + 1} of {self.total}: {f['gp']} ({size})"
        else:
            what = f"{self.stage_name} ({self.done} of {self.total} GP fits done)"
        self.bar.update(self.task, description=what, completed=self.done_weight)

    def fits_seconds(self, fits: list[dict]) -> list[float] | None:
        """About how long each of ``fits`` (entries of the plan, in order) will take, from the fits done
        (None before the first ends): its work at the measured rate, plus, for the first fit of a size
        not fitted yet, the compilation a new size took."""
        if not self.history:
            return None
        work = sum(h[0] for h in self.history)
        rate = sum(max(h[1] - h[2], 0.0) for h in self.history) / work if work > 0 else 0.0
        compiled = [h[2] for h in self.history if h[2] >= 0.5] or [max(h[2] for h in self.history)]
        compiling = sum(compiled) / len(compiled)
        seen = {h[3] for h in self.history}
        out = []
        for f in fits:
            new = _size(f) not in seen
            seen.add(_size(f))
            out.append(rate * float(f.get("work", f["weight"])) + (compiling if new else 0.0))
        return out

    def seconds_left(self, after_fit: bool = False) -> float | None:
        """About how long the fits left will take (None before the first ends, or with none left)."""
        ahead = [f for f in self.plan if f["weight"] > 0]
        each = self.fits_seconds(ahead) if ahead else None
        if not each:
            return None
        rest = sum(each)
        if self.started is None or after_fit:
            return rest
        running = time.monotonic() - self.started
        return max(rest - running, rest - each[0])


def _size(fit: dict) -> tuple:
    """What makes a GP fit's compiled programs: its stage (the pose regressors' fits share kernels
    across outputs), its rows and the rows its hyperparameters are fitted on."""
    return fit["stage"], int(fit["n"]), int(fit["n_fit"])


class _Left(ProgressColumn):
    """The bar's estimate of the fitting time left (:meth:`FitProgress.seconds_left`; none once the
    fits are done: the stages after them, the tracking check, are not estimated)."""

    def __init__(self, shown: FitProgress):
        super().__init__()
        self.shown = shown

    def render(self, task) -> Text:
        left = self.shown.seconds_left()
        return Text(f"about {_clock(left)} left" if left else "", style="progress.remaining")


def _clock(seconds: float) -> str:
    """``m:ss`` (``h:mm:ss`` past an hour)."""
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def outline_path(model_path: Path) -> Path:
    """Where ``train`` draws a model's learnt outlines: beside it, ``NAME-outline.png``."""
    return model_path.with_name(model_path.stem + "-outline.png")


def _is_bag(p: Path) -> bool:
    from ..io.importers import detect_format

    return detect_format(p) in ("ros1", "ros2")


def _per_class(items: list[str], option: str) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            v = float(value)
        except ValueError:
            v = float("nan")
        if not sep or not name or not (v > 0) or v == float("inf"):
            raise InputError(option, f"expected CLASS=VALUE with a positive value, got {item!r}")
        out[name] = v
    return out


def _turns(items: list[str]) -> dict[str, int]:
    """``--heading-turns CLASS=1|2`` as a dict."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or value.strip() not in ("1", "2"):
            raise InputError("--heading-turns", f"expected CLASS=1 or CLASS=2, got {item!r}")
        out[name] = int(value)
    return out


def _summary(console: Console, rep: dict, out: Path) -> None:
    t = Table(title="examples per class")
    t.add_column("class")
    t.add_column("found", justify="right")
    t.add_column("used", justify="right")
    t.add_column("held-out recall", justify="right")
    held = rep["heldout"]
    for c in rep["classes"]:
        rec = held.get("per_class", {}).get(c)
        t.add_row(c, str(rep["examples"][c]), str(rep["examples_used"][c]),
                  f"{100 * rec['recall']:.1f} % of {rec['n']}" if rec else "–")
    console.print(t)
    f = Table(title="GP fits")
    for col in ("GP", "n", "LML", "σf²", "σn²", "median ℓ", "s"):
        f.add_column(col, justify="right")
    for info in rep["fits"]:
        f.add_row(info["gp"], str(info["n"]), f"{info['lml']:.1f}", f"{info['signal_var']:.3g}",
                  f"{info['noise_var']:.3g}", f"{info['lengthscale_median']:.3g}", f"{info['seconds']:.1f}")
    console.print(f)
    if held.get("n"):
        console.print(f"held-out classification accuracy: {100 * held['accuracy']:.2f} % on {held['n']} candidates")
        for name, p in held.get("pose", {}).items():
            console.print(f"held-out pose error per scan ({name}, in the ORS): position RMSE {100 * p['rmse_xy_m']:.1f} cm, "
                          f"heading median {p['median_theta_deg']:.1f}°, RMSE {p['rmse_theta_deg']:.1f}°, "
                          f"{100 * p['misread_fraction']:.1f} % misread (> 30°), on {p['n']} candidates")
    for name, c in rep.get("variance_calibration", {}).items():
        console.print(f"pose variances of {name} scaled by {', '.join(f'{v:.3g}' for v in c['var_scale'])} "
                      f"(x̃, ỹ, θ̃; calibrated on {c['examples']} {'held-out' if c['held_out'] else 'training'} examples)"
                      + (f"; a heading read with σ above {c['vague_heading_sigma_deg']:.1f}° updates a track's "
                         "position only" if "vague_heading_sigma_deg" in c else ""))
    for name, o in rep.get("outlines", {}).items():
        if not o.get("outline"):
            console.print(f"no outline of {name}: {o.get('why', '')}; its headings are the GP's")
            continue
        line = (f"outline of {name}: {o['size_m'][0]:.2f} × {o['size_m'][1]:.2f} m from {o['views']} views; side "
                f"hypotheses {', '.join(f'{d:+.0f}°' for d in o['sides_deg']) or 'none'} (from {o['sides_from']})")
        if (c := o.get("calibration")) is not None:
            g, r = c["gp"], c["refined"]
            line += (f"; held-out heading per scan, GP → outline: median {g['heading_median_deg']:.1f}° → "
                     f"{r['heading_median_deg']:.1f}°, misread (> 30°) {100 * g['misread_fraction']:.1f} % → "
                     f"{100 * r['misread_fraction']:.1f} %, on {c['examples']} views")
        if o.get("used") is False:
            line += f"; not used: {o['why']}"
        console.print(line)
    _openset_tables(console, rep)
    _learnt_table(console, rep)
    _pipeline_table(console, rep)
    console.print(f"{rep['degraded_scans']} of {rep['scans']} scans without a map transformation; model written to {out}")


def _openset_tables(console: Console, rep: dict) -> None:
    """What the model rejects: shape envelopes, open-set thresholds and motion limits per class, and
    what the held-out background (of the labelled and of the background logs) was taken for."""
    t = Table(title="what each class may look like (shape envelopes, open-set test) and do (motion limits)")
    for col in ("class", "width [m]", "depth [m]", "points at 1 m", "open set: d² ≤", "its held-out rejected",
                "held-out background rejected", "max speed [m/s]", "max turn [rad/s]"):
        t.add_column(escape(col), justify="right")  # units in [] are not Rich markup
    for c in rep["classes"][1:]:
        env = rep.get("envelopes", {}).get(c, {})
        op = rep.get("open_set", {}).get(c, {})
        mo = rep.get("motion_limits", {}).get(c)

        def rng(v):
            return "–" if v is None else f"{v[0]:g}–{v[1]:g}"

        bg_rej = op.get("background_rejected")
        t.add_row(c, rng(env.get("width_m")), rng(env.get("depth_m")), rng(env.get("points_at_1m")),
                  f"{op['threshold_d2']:.3g}" if op else "–",
                  f"{100 * op['class_rejected']:.1f} %" if op else "–",
                  "–" if bg_rej is None else f"{100 * bg_rej:.1f} %",
                  "–" if mo is None else f"{mo['max_speed']:.2f} ({mo['max_speed_from']})",
                  "–" if mo is None else f"{mo['max_turn_rate']:.2f} ({mo['max_turn_rate_from']})")
    console.print(t)
    for item in rep.get("background_logs", []):
        console.print(f"background log {item['log']}: {item['scans']} scans, {item['candidates']} candidates"
                      + (f" ({item['landmark_lookalikes_left_out']} left out as look-alikes of a landmark class)"
                         if item.get("landmark_lookalikes_left_out") else ""), soft_wrap=True)
    for key, what in (("heldout", "held-out background of the labelled logs"),
                      ("heldout_background_logs", "held-out background logs")):
        bg = rep.get(key, {}).get("per_class", {}).get("background")
        if bg:
            taken = ", ".join(f"{c} {100 * v:.2f} %" for c, v in bg["taken_for"].items() if c != "background")
            console.print(f"{what}: {bg['n']} candidates, taken for {taken or 'nothing else'}")


def _learnt_table(console: Console, rep: dict) -> None:
    """Every value learnt from the logs that the tracker relies on, with where it came from."""
    rows = rep.get("learnt", [])
    if not rows:
        return
    t = Table(title="learnt from your logs (value, where it came from, sanity range)")
    for col in ("class", "parameter", "value", "from", "evidence", "plausible"):
        t.add_column(col, justify="right" if col == "value" else "left")
    for r in rows:
        lo_hi = r.get("plausible")
        t.add_row(r["class"] or "–", r["parameter"], f"{r['value']:.3g} {r['unit']}".strip(),
                  r["source"] + (" ⚠" if "warning" in r else ""), r["evidence"],
                  "–" if not lo_hi else f"{lo_hi[0]:g}–{lo_hi[1]:.3g}")
    console.print(t)


def _pipeline_table(console: Console, rep: dict) -> None:
    """The whole step on the labelled logs' held-out seconds (``train.check``), per tracked class."""
    if not rep.get("pipeline") and not rep.get("pipeline_simulated"):
        return
    t = Table(title="tracking check: the whole step on the labelled logs' held-out seconds, and the tracker on a "
                    "simulated stay and walk with the held-out errors")
    for col in ("class", "check", "scans in view", "detected", "rows (of detected)", "position RMSE", "heading RMSE",
                "scans without a row lost at"):
        t.add_column(col, justify="left" if col in ("class", "check", "scans without a row lost at") else "right")

    def pct(v):
        return "–" if v is None else f"{100 * v:.1f} %"

    checks = [(n, "held-out", s) for n, s in rep.get("pipeline", {}).items()]
    checks += [(n, "simulated", s) for n, s in rep.get("pipeline_simulated", {}).items()]
    for name, which, s in checks:
        lost = ", ".join(f"{k} {100 * v:.0f} %" for k, v in sorted(s["lost_share"].items(), key=lambda kv: -kv[1]))
        t.add_row(name, which, f"{s['scans_in_view']} ({s['scans_scored']} scored)", pct(s["detection_rate"]),
                  pct(s["rows_per_detected_scan"]),
                  "–" if s["position_rmse_m"] is None else f"{100 * s['position_rmse_m']:.1f} cm",
                  "–" if s["heading_rmse_deg"] is None else f"{s['heading_rmse_deg']:.1f}°", lost or "–")
    console.print(t)
