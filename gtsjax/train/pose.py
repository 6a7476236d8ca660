"""What training learns for stage e, pose regression (eq. 15–17): per landmark class, GPs of the
post's centre ``(x̃, ỹ)`` in the candidate's ORS (:func:`fit_landmark_positions`; they move the
landmark candidates to their centres for labelling's second pass and for stage f at run time); per
mobile class, GPs of ``x̃``, ``ỹ``, ``sin θ̃`` and ``cos θ̃`` (:func:`fit_pose_regressors`), their
variances calibrated on held-out examples (:func:`~gtsjax.train.calibrate.calibrate`).
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..core.e_pose import PoseRegressor
from ..errors import InputError
from .calibrate import calibrate
from .config import TrainConfig
from .fit import GPFits, sample
from .labels import Examples

# The pose GPs of a mobile class in groups of one kernel (``TrainConfig.pose_kernels``: 1 or 2 groups;
# 4 is each GP on its own).
POSE_GROUPS = {1: (("x", "y", "sin", "cos"),), 2: (("x", "y"), ("sin", "cos"))}


def fit_landmark_positions(ex: Examples, held: list, classes: tuple[str, ...], landmarks: tuple[str, ...],
                           cfg: TrainConfig, rng: np.random.Generator, gps: GPFits) -> dict[int, PoseRegressor]:
    """Position GPs of each landmark class (class index → regressor), on up to
    ``cfg.max_landmark_examples`` of its examples outside the ``held`` groups."""
    out = {}
    for name in landmarks:
        k = classes.index(name)
        idx = sample(rng, np.flatnonzero((ex.cls == k) & ~np.isin(ex.group, held)), cfg.max_landmark_examples)
        if idx.size < 3:
            raise InputError("training data", f"only {idx.size} examples of landmark class '{name}'; are the site's "
                                              "landmarks in view and sensor_pose roughly right?")
        x, y = (gps(ex.vectors[idx], ex.target[idx, j], f"{name}.{comp}", cfg.n_inducing_class)
                for j, comp in enumerate(("x", "y")))
        out[k] = PoseRegressor(x, y)
    return out


def fit_pose_regressors(ex: Examples, is_held: np.ndarray, classes: tuple[str, ...], mobiles: tuple[str, ...],
                        cfg: TrainConfig, rng: np.random.Generator,
                        gps: GPFits, turns: "dict[str, int] | None" = None) -> tuple[dict[int, PoseRegressor], dict[str, dict]]:
    """Pose GPs of each mobile class (class index → regressor): ``x̃``, ``ỹ``, ``sin θ̃``, ``cos θ̃``
    (eq. 15, 17), in groups of one kernel each (``cfg.pose_kernels``, :data:`POSE_GROUPS`), on up to
    ``cfg.max_pose_examples`` training examples, hyperparameters fitted on up
    to ``cfg.max_pose_fit``; variances calibrated on the class's held-out examples (on the training
    ones if fewer than 20 are held out). Also returns the calibration's summary per class.

    ``turns``: a class whose outline looks the same turned by ``2π/n`` (``n`` = 2, a half-turn:
    :func:`~gtsjax.train.outline.half_turn_symmetry`) has its heading GPs on ``(sin nθ̃, cos nθ̃)``:
    on ``θ̃`` itself their means average the two headings its views are alike from, and read neither."""
    turns = turns or {}
    out, report = {}, {}
    for name in mobiles:
        k = classes.index(name)
        idx = sample(rng, np.flatnonzero((ex.cls == k) & ~is_held), cfg.max_pose_examples)
        if idx.size < 3:
            raise InputError("training data", f"only {idx.size} examples of class '{name}'")
        tgt = ex.target[idx]
        n = turns.get(name, 1)
        comps = {"x": tgt[:, 0], "y": tgt[:, 1], "sin": np.sin(n * tgt[:, 2]), "cos": np.cos(n * tgt[:, 2])}
        if cfg.pose_kernels in POSE_GROUPS:
            reg = PoseRegressor(shared=tuple(
                gps.shared(ex.vectors[idx], {c: comps[c] for c in group}, name, cfg.n_inducing, cfg.max_pose_fit)
                for group in POSE_GROUPS[cfg.pose_kernels]))
        else:
            reg = PoseRegressor(**{comp: gps(ex.vectors[idx], y, f"{name}.{comp}", cfg.n_inducing, cfg.max_pose_fit)
                                   for comp, y in comps.items()})
        if n != 1:
            reg = dataclasses.replace(reg, turns=jnp.asarray(n, jnp.int32))
        cal = np.flatnonzero((ex.cls == k) & is_held)
        cal = cal if cal.size >= 20 else idx
        reg = calibrate(reg, ex.vectors[cal], ex.target[cal])
        out[k] = reg
        report[name] = {"examples": int(cal.size), "held_out": bool(cal is not idx),
                        "var_scale": [round(float(v), 4) for v in np.asarray(reg.var_scale)], "heading_turns": n}
        if reg.heading_var_max is not None:
            report[name]["vague_heading_sigma_deg"] = round(math.degrees(math.sqrt(float(reg.heading_var_max))), 2)
    return out, report
