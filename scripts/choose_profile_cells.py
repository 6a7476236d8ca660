"""Choose the profile-cell layout of the characteristic vector (eq. 11-12) by validation accuracy.

    python scripts/choose_profile_cells.py [--examples 800]

The paper leaves open whether the N_d / N_I profile cells tile the candidate's bounding box
(scale-free) or a fixed physical span centred on y' = 0 (keeps size), and how wide. For each layout
this trains the robot's pose GPs (x̃, sin θ̃, cos θ̃, exact, on ``--examples`` robot candidates of
the SPL training grid, seed 1) and scores them on the robot candidates of a held-out evaluation log
(spl-eval, seed 4242): position error along the beam and heading error per scan (median, RMSE and
the fraction misread by more than 30°). The default of :class:`gtsjax.FrontEndConfig` is the layout
this table favours.
"""

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from gtsjax import FrontEndConfig
from gtsjax.core.geometry import wrap
from gtsjax.gp import fit
from gtsjax.sim import simulate
from gtsjax.train import TrainConfig, class_list, label_log, landmark_centres, run_front_end

LAYOUTS = {
    "fixed span 0.6 m, 10 cells": dict(cells_on_bbox=False, cell_span=0.6),
    "fixed span 0.4 m, 10 cells": dict(cells_on_bbox=False, cell_span=0.4),
    "fixed span 0.4 m, 16 cells": dict(cells_on_bbox=False, cell_span=0.4, n_dist=16, n_intensity=16),
    "bounding box, 10 cells": dict(cells_on_bbox=True),
}


def robot_examples(log, site, fe: FrontEndConfig, cfg: TrainConfig):
    classes, _, _ = class_list([log], site)
    out = run_front_end(log, fe, log.n_beams)
    tf, _ = landmark_centres(log, out, site, cfg)
    ex, _ = label_log(log, out, tf, site, classes, cfg, 0)
    sel = ex.cls == classes.index("robot")
    return ex.vectors[sel], ex.target[sel]


def main():
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=800)
    args = ap.parse_args()
    cfg = TrainConfig()
    train_log, site = simulate("spl-train", seed=1)
    eval_log, eval_site = simulate("spl-eval", seed=4242)
    rng = np.random.default_rng(0)
    print(f"{'layout':<30} {'x̃ RMSE [cm]':>12} {'θ̃ median [°]':>14} {'θ̃ RMSE [°]':>11} {'misread':>8} {'fit [s]':>8}")
    for name, change in LAYOUTS.items():
        fe = dataclasses.replace(cfg.frontend, **change)
        x_tr, y_tr = robot_examples(train_log, site, fe, cfg)
        x_ev, y_ev = robot_examples(eval_log, eval_site, fe, cfg)
        idx = rng.choice(len(x_tr), min(args.examples, len(x_tr)), replace=False)
        t0 = time.perf_counter()
        pred = {}
        for comp, target in (("x", y_tr[:, 0]), ("sin", np.sin(y_tr[:, 2])), ("cos", np.cos(y_tr[:, 2]))):
            gp = fit(x_tr[idx], target[idx], key=jax.random.key(0), restarts=1, jitter=cfg.noise_floor)
            pred[comp] = np.asarray(gp.predict(jnp.asarray(x_ev))[0])
        err_x = pred["x"] - y_ev[:, 0]
        err_th = np.degrees(np.abs(wrap(np.arctan2(pred["sin"], pred["cos"]) - y_ev[:, 2])))
        print(f"{name:<30} {100 * np.sqrt(np.mean(err_x**2)):12.2f} {np.median(err_th):14.2f} "
              f"{np.sqrt(np.mean(err_th**2)):11.1f} {np.mean(err_th > 30):8.1%} {time.perf_counter() - t0:8.0f}",
              flush=True)


if __name__ == "__main__":
    main()
