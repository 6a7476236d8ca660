"""``gtsjax train LOG.npz ... --site SITE.json --out MODEL``: learn the classifier and pose regressors
from labelled logs, with progress per GP fit and a summary table."""

import dataclasses
import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from ..io import load_log, load_site
from ..io.modelfile import save_model
from ..training import TrainConfig, train
from ._app import app


@app.command("train")
def train_cmd(
    logs: list[Path] = typer.Argument(..., help="Labelled scan logs (.npz) of one site."),
    site: Path = typer.Option(..., "--site", help="Site file (.json) the logs were recorded on."),
    out: Path = typer.Option(..., "--out", help="Model file to write."),
    max_per_class: int = typer.Option(TrainConfig.max_per_class, help="Classifier examples per class (balanced)."),
    max_pose: int = typer.Option(TrainConfig.max_pose_examples,
                                 help="Pose-GP examples per mobile class (the GPs' posterior; the step's cost grows "
                                      "with it)."),
    max_pose_fit: int = typer.Option(TrainConfig.max_pose_fit,
                                     help="Of those, how many the pose GPs' hyperparameters are fitted on (the "
                                          "fit's cost grows with its cube)."),
    max_landmark: int = typer.Option(TrainConfig.max_landmark_examples, help="Position-GP examples per landmark class."),
    inducing: int = typer.Option(TrainConfig.n_inducing,
                                 help="Inducing points of the mobile classes' pose GPs (exact mean up to this size)."),
    inducing_class: int = typer.Option(TrainConfig.n_inducing_class,
                                       help="Inducing points of the classifier's and landmark GPs."),
    restarts: int = typer.Option(TrainConfig.restarts, help="Optimiser starts per GP fit."),
    seed: int = typer.Option(0, help="Seed for sampling, the held-out split and restarts."),
    report: Path | None = typer.Option(None, "--report", help="Also write the training report as JSON."),
):
    """Train a model from labelled logs (training and held-out evaluation)."""
    console = Console(stderr=True)
    site_obj = load_site(site)
    loaded = [load_log(p) for p in logs]
    cfg = dataclasses.replace(TrainConfig(), max_per_class=max_per_class, max_pose_examples=max_pose,
                              max_pose_fit=max_pose_fit,
                              max_landmark_examples=max_landmark, n_inducing=inducing, n_inducing_class=inducing_class,
                              restarts=restarts, seed=seed)

    def progress(info):
        console.print(f"  fitted GP {info['gp']:<22} n={info['n']:<5} LML={info['lml']:10.1f}  {info['seconds']:6.1f} s")

    console.print(f"training on {sum(log.n_scans for log in loaded)} scans from {len(loaded)} log(s)")
    model, rep = train(loaded, site_obj, cfg, progress=progress, names=[str(p) for p in logs])
    save_model(model, out, summary=rep)
    _summary(Console(), rep, out)
    if report is not None:
        report.write_text(json.dumps(rep, indent=2) + "\n")


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
                      f"(x̃, ỹ, θ̃; calibrated on {c['examples']} {'held-out' if c['held_out'] else 'training'} examples)")
    console.print(f"{rep['degraded_scans']} of {rep['scans']} scans without a map transformation; model written to {out}")
