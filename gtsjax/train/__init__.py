"""Training from labelled logs (``gtsjax train``): the :class:`~gtsjax.core.model.Model` of one scanner
and the site's kinds of landmarks, and a report of how it was made and how it does on held-out data.

One module per step, in the order :func:`train` takes them (the paper's stages in brackets):

- :mod:`.labels`: stages a–c over the logs, each scan's map transformation (f), and the labelled
  examples, in two passes; background logs' examples; the held-out split by one-second blocks.
- :mod:`.fit`: each GP fitted in float64 and kept as the step's float32 bounded-cost predictor.
- :mod:`.classifier`: shape envelopes (c), the open-set test and the classifier's GPs (d, eq. 13–14).
- :mod:`.pose`: the landmark classes' position GPs and the mobile classes' pose GPs (e, eq. 15–17),
  with :mod:`.calibrate` scaling their variances on held-out examples.
- :mod:`.outline`: each mobile class's learnt outline, its side hypotheses and the calibration of the
  outline refinement (e′) on held-out examples.
- :mod:`.motion`: each tracked class's motion limits and the scanner's rate (g).
- :mod:`.report`: held-out classification as the step decides it, and pose errors.
- :mod:`.config`: :class:`TrainConfig`.

A caller follows the run through two callbacks of :func:`train`: ``stages`` as each stage begins, with
the GP fits still to come (:func:`planned_fits`: the first call, before any work, lists them all, so
that a display can say "fit k of N" and weigh what is left), and ``progress`` as each fit ends.
"""

import dataclasses
import warnings
from collections.abc import Callable, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.g_track import TrackerParams
from ..core.model import Model
from ..errors import InputError, InputWarning
from ..io.logs import ScanLog
from ..io.site import Site
from ..precision import exact_products
from ..sensors import MODELS, with_scanner
from .bounds import landmark_rows, outline_rows, shape_rows
from .calibrate import pose_bias, variance_floor
from .check import check_pipeline, coverage, held_mask, simulated_checks, verdict
from .classifier import fit_classifier, fit_support, landmark_lookalikes
from .classifier import fit_envelope as fit_envelope
from .config import TrainConfig as TrainConfig
from .fit import GPFits
from .labels import Examples as Examples
from .labels import (
    background_examples,
    check_logs,
    first_pass,
    front_end_logs,
    holdout_groups,
    per_log_sites,
    second_pass,
    step_beams,
)
from .labels import class_list as class_list
from .labels import estimate_transforms as estimate_transforms
from .labels import fit_background as fit_background
from .labels import label_log as label_log
from .labels import landmark_centres as landmark_centres
from .labels import run_front_end as run_front_end
from .motion import confirmation_entry, motion_heading, scan_rate_entry, tracker_limits, turn_rate_noise
from .motion import motion_limits as motion_limits
from .outline import fit_outlines, half_turn_symmetry
from .pose import POSE_GROUPS, fit_landmark_positions, fit_pose_regressors
from .report import evaluate_examples as evaluate_examples
from .tags import fit_tags

#: The stages of :func:`train`, in the order it takes them, as its ``stages`` callback names them.
STAGES = ("labelling", "landmark positions", "labelling, second pass", "classifier", "pose regressors",
          "outlines and motion limits", "held-out evaluation", "tracking check")

# The GP library's cap on a fit's rows when the caller sets none (``gp.fit``'s ``max_points``), and its
# screening of the starts on a subsample (``screen_points``): what a fit of n examples costs.
_GP_MAX_POINTS, _GP_SCREEN_POINTS = 3000, 500


def fit_cost(n: int, n_fit: int, restarts: int, outputs: int = 1) -> float:
    """A GP fit's cost relative to others, for an estimate of the time left (not a prediction in
    seconds): BFGS on ``n_fit`` rows, each step an O(n_fit³) factorisation per output, for every start
    (or, past the screening size, every start on the screening subsample and about two starts on all the
    rows); the conditioning on all ``n`` (its O(n³) factorisations, weighed as a fiftieth of a step's,
    so that the SPL match's pose GPs, 6 000 examples fitted on 2 000, weigh 2.8 times its classifier's
    on 1 500: they took 1.5 times as long on 2 otherwise idle cores, 4 times with other programs
    running); and a fixed part for what does not grow with n (a new shape's compilation, the host's
    work), as much as a fit of about 600 rows."""
    return fit_work(n, n_fit, restarts, outputs) + FIT_FIXED_COST


#: :func:`fit_cost`'s fixed part: as much as a fit of about 600 rows.
FIT_FIXED_COST = 2e8


def fit_work(n: int, n_fit: int, restarts: int, outputs: int = 1) -> float:
    """The part of :func:`fit_cost` that grows with the fit's rows (its factorisations), without the
    fixed part: what ``train``'s estimate of the time left prices at the rate measured on the fits
    done, their compilation counted apart."""
    n_fit = min(n_fit, n)
    if restarts > 1 and n_fit > _GP_SCREEN_POINTS:
        steps = 2.0 * n_fit**3 + restarts * _GP_SCREEN_POINTS**3
    else:
        steps = restarts * float(n_fit) ** 3
    return outputs * (steps + 0.02 * float(n) ** 3)


def planned_fits(classes: Sequence[str], landmarks: Sequence[str], mobiles: Sequence[str], cfg: TrainConfig, *,
                 background_logs: bool = False, available: dict[str, int] | None = None) -> list[dict]:
    """The GP fits :func:`train` makes, in the order it makes them: one entry per line of its report's
    ``fits`` (``gp``, the ``stage`` that fits it, ``n`` examples, ``n_fit`` of them its hyperparameters
    are fitted on, ``weight``: :func:`fit_cost`, and ``work``: :func:`fit_work`, both carried by the
    first output of a fit of several with one shared kernel, the others 0). ``n`` is each fit's cap on its class's training examples
    (``available``, per class, where known: then as many as the fit will take; ``background_logs``: the
    classifier's caps with background logs)."""
    available = available or {}
    out = []

    def add(stage, labels, n, n_fit):
        n_fit = min(n, n_fit)
        work = fit_work(n, n_fit, cfg.restarts, len(labels))
        w = work + FIT_FIXED_COST  # fit_cost, its growing part computed once
        out.extend({"gp": g, "stage": stage, "n": int(n), "n_fit": int(n_fit), "weight": w if j == 0 else 0.0,
                    "work": work if j == 0 else 0.0} for j, g in enumerate(labels))

    def capped(name, cap):
        return min(available.get(name, cap), cap)

    for name in landmarks:
        n = min(capped(name, cfg.max_landmark_examples), _GP_MAX_POINTS)
        for comp in ("x", "y"):
            add("landmark positions", [f"{name}.{comp}"], n, n)
    # fit_classifier's caps: balanced classes, more background and mobile examples with background logs
    n_bg = cfg.max_per_class if not background_logs else (cfg.max_background or 12 * cfg.max_per_class)
    n_mobile = cfg.max_per_class if not background_logs else (cfg.max_mobile or 4 * cfg.max_per_class)
    n_cls = capped(classes[0], n_bg) + sum(capped(c, n_mobile if c in mobiles else cfg.max_per_class)
                                           for c in classes[1:])
    n_cls = n_cls if cfg.max_class_fit else min(n_cls, _GP_MAX_POINTS)
    for name in classes:
        add("classifier", [f"class.{name}"], n_cls, cfg.max_class_fit or n_cls)
    groups = POSE_GROUPS.get(cfg.pose_kernels, tuple((c,) for c in ("x", "y", "sin", "cos")))
    for name in mobiles:
        for group in groups:
            add("pose regressors", [f"{name}.{c}" for c in group], capped(name, cfg.max_pose_examples),
                cfg.max_pose_fit)
    return out


def _available(ex: Examples, is_held: np.ndarray, classes: Sequence[str]) -> dict[str, int]:
    """Training (not held-out) examples per class."""
    return {c: int(np.sum((ex.cls == k) & ~is_held)) for k, c in enumerate(classes)}


@exact_products
def _without_intensities_it_cannot_have(log: ScanLog, name: str) -> ScanLog:
    """``log`` without its intensities when it names a scanner that reports none (a URG-04LX log that
    a converter filled with intensities): a model trained on them would need, live, an input that
    scanner never gives. Said in an :class:`~gtsjax.errors.InputWarning`."""
    known = MODELS.get(log.sensor_model or "")
    if log.intensities is None or known is None or known.has_intensity:
        return log
    warnings.warn(InputWarning(name, f"carries intensities, but a {known.name} reports none: trained without them"),
                  stacklevel=3)
    return dataclasses.replace(log, intensities=None)


def train(logs: Sequence[ScanLog], site: "Site | Sequence[Site]", cfg: TrainConfig = TrainConfig(), *,
          progress: Callable[[dict], None] | None = None, names: Sequence[str] | None = None,
          background: Sequence[ScanLog] = (), background_names: Sequence[str] | None = None,
          stages: Callable[[str, list[dict]], None] | None = None) -> tuple[Model, dict]:
    """Train a model from labelled logs of one site, and optional background logs (recorded anywhere,
    with no robot in view: every candidate in them is a background example; their beams are checked
    against the labelled logs' scanner and cropped to its field of view). Returns the model (float32
    predictors, bounded cost) and a report: examples per class, GP fits, shape envelopes, open-set
    thresholds, motion limits, held-out accuracy and pose errors, and warnings. ``progress`` is called
    with each GP fit's summary as it ends; ``stages(name, fits)`` as each of the :data:`STAGES` begins,
    with the GP fits still to come from there on (:func:`planned_fits`, their sizes as far as known
    then): its first call, before any work, lists every fit, one per summary ``progress`` will get.
    ``site``: the site of every log, or one per log (each the site as one laser of a field of several
    sees it, :meth:`~gtsjax.io.site.Site.for_sensor`)."""
    names = list(names) if names is not None else [f"log {i}" for i in range(len(logs))]
    bg_names = list(background_names) if background_names is not None else [
        f"background log {i}" for i in range(len(background))]
    check_logs(logs, names)
    logs = [_without_intensities_it_cannot_have(log, name) for log, name in zip(logs, names, strict=True)]
    background = [_without_intensities_it_cannot_have(log, name) for log, name in zip(background, bg_names, strict=True)]
    first = logs[0]
    n_beams = step_beams(first)
    background = fit_background(first, background, bg_names)
    run = _Run.begin(logs, site, cfg, names, bool(background), progress, stages)
    classes, landmarks, mobiles = run.classes, run.landmarks, run.mobiles

    run.stage("labelling")
    lab = _first_labels(run, logs, site, background, bg_names, n_beams)
    run.stage("landmark positions", _available(lab.ex1, np.isin(lab.ex1.group, lab.held), classes))
    pose = _landmark_positions(run, lab)
    run.stage("labelling, second pass")
    ex_lab, degraded, n_scans = second_pass(logs, lab.per_log, lab.cls_slots, pose, site, classes, landmarks, cfg)
    envelope, env_report = fit_envelope(ex_lab.take(np.flatnonzero(~np.isin(ex_lab.group, lab.held))),
                                        len(classes), first.angle_increment)
    support, sup_report = _open_set(run, ex_lab, lab)
    ex, source = _with_background_logs(run, ex_lab, lab, support)
    is_held = np.isin(ex.group, lab.held)

    run.stage("classifier", _available(ex, is_held, classes))
    classifier, train_idx, notes = fit_classifier(ex, is_held, source, len(lab.bg_info), support, classes, mobiles,
                                                  cfg, run.rng, run.gps)
    run.stage("pose regressors", _available(ex, is_held, classes))
    turns, half_turn_mm, half_turn_rows = half_turn_symmetry(logs, ex, is_held, classes, mobiles, cfg.frontend.window,
                                                             cfg.heading_turns)
    notes = notes + [f"{name}: its outline looks the same turned half a turn (within {half_turn_mm[name]:.1f} mm): "
                     "its heading is read only up to a half-turn, and each track keeps the side it started on "
                     f"(its heading may be the robot's back; --heading-turns {name}=1 if it is not)"
                     for name in turns if name not in cfg.heading_turns and name in half_turn_mm]
    mobile_pose, calibration = fit_pose_regressors(ex, is_held, classes, mobiles, cfg, run.rng, run.gps, turns)
    for k, reg in mobile_pose.items():
        pose[k] = reg
    run.stage("outlines and motion limits")
    outline, outline_report = fit_outlines(logs, ex, is_held, classes, mobiles, pose, cfg.frontend.window, run.rng,
                                           turns=turns)
    tracker, rate_hz, motion, learnt = _motion_limits(run, logs, env_report, sup_report)
    learnt = learnt + landmark_rows(lab.centres, names, run.landmarks) + half_turn_rows + outline_rows(outline_report)
    notes = notes + [row["warning"] for row in learnt if "warning" in row]
    model = _assemble(run, first, n_beams, lab.columns, classifier=classifier, envelope=envelope, pose=pose,
                      tracker=tracker, outline=outline)
    reader, tags_report = fit_tags(logs, ex, site, classes, mobiles, outline, cfg.frontend.window, run.rng)
    if reader is not None:
        first_tags = next(s.tags for s in per_log_sites(site, len(logs)) if getattr(s, "tags", None) is not None)
        model = dataclasses.replace(model, tags=reader).with_tags(first_tags)
    notes = notes + ([tags_report["warning"]] if "warning" in tags_report else [])

    run.stage("held-out evaluation")
    report = _report(run, model, ex, is_held, ex_lab, lab.bg_info, train_idx=train_idx, calibration=calibration,
                     env_report=env_report, sup_report=sup_report, motion=motion, learnt=learnt,
                     outline_report=outline_report, n_scans=n_scans, degraded=degraded, warnings=notes)
    report["half_turn_mm"] = half_turn_mm  # per mobile class: how far its outline is from its half-turn
    report["tags"] = tags_report
    report["coverage"], where = coverage(logs, per_log_sites(site, len(logs)), mobiles)
    report["warnings"] = report["warnings"] + where
    # Both row corrections as arrays from here on, zeros until learnt: the model the check runs and the
    # model saved are one tree structure, so the same compiled programs (TrackerParams.with_row_corrections).
    model = eqx.tree_at(lambda m: m.tracker, model, model.tracker.with_row_corrections())
    if cfg.check_pipeline:
        run.stage("tracking check")
        errors, row_errs = _tracking_check(report, model, logs, site, ex_lab, lab.held, mobiles, rate_hz, cfg.seed)
        # Each class's mean error in its own frame on the held-out detections, a bias no filter removes:
        # listed, and taken off the tracks' rows from now on (the check's figures are of the model before);
        # then the variance the rows need beside the filter's for their 95 % ellipses to hold 95 % of the
        # held-out rows' errors (with that offset off), added to every row's.
        offset, rows, warned = pose_bias(errors, classes)
        floor, floor_rows, floor_warned = variance_floor(row_errs, classes, offset, errors)
        report["learnt"] = report["learnt"] + rows + floor_rows
        report["warnings"] = report["warnings"] + warned + floor_warned
        model = eqx.tree_at(lambda m: m.tracker, model, model.tracker.with_row_corrections(offset, floor))
    if len(lab.bg_ex.cls):
        report["heldout_background_logs"] = evaluate_examples(
            model, lab.bg_ex.take(np.flatnonzero(np.isin(lab.bg_ex.group, lab.held))))
    return model, report


@dataclasses.dataclass
class _Run:
    """What every phase of :func:`train` shares: the configuration, the classes, the one random
    generator (drawn from in a fixed order, so that a seed repeats a run), the GP fits so far and the
    caller's ``stages`` callback."""

    cfg: TrainConfig
    classes: tuple[str, ...]
    landmarks: tuple[str, ...]
    mobiles: tuple[str, ...]
    background_logs: bool
    rng: np.random.Generator
    gps: GPFits
    stages: Callable[[str, list[dict]], None] | None

    @classmethod
    def begin(cls, logs: Sequence[ScanLog], site: "Site | Sequence[Site]", cfg: TrainConfig, names: Sequence[str],
              background_logs: bool, progress: Callable[[dict], None] | None,
              stages: Callable[[str, list[dict]], None] | None) -> "_Run":
        """The classes to learn (background, the site's landmarks, the logs' labelled objects; logs
        without the last leave nothing to learn), the random generator and the GP fits' record."""
        classes, landmarks, mobiles = class_list(logs, site if isinstance(site, Site) else site[0])
        if not mobiles:
            raise InputError(names[0], "no labelled object classes in the logs")
        rng = np.random.default_rng(cfg.seed)  # examples, the held-out split, the open-set supports
        return cls(cfg, classes, landmarks, mobiles, background_logs, rng, GPFits(cfg, progress), stages)

    def stage(self, name: str, available: dict[str, int] | None = None) -> None:
        """Tell ``stages`` that stage ``name`` begins, with the GP fits still to come (sized by ``available``)."""
        if self.stages is not None:
            plan = planned_fits(self.classes, self.landmarks, self.mobiles, self.cfg,
                                background_logs=self.background_logs, available=available)
            self.stages(name, plan[len(self.gps.fits):])


@dataclasses.dataclass
class _FirstPass:
    """The labelling's first pass: the front end's output per log, the GP input columns, the labelled
    examples and each log's class per candidate slot, the background logs' examples, the held-out groups."""

    per_log: list[dict]
    columns: tuple[int, ...]
    ex1: Examples
    cls_slots: list[np.ndarray]
    bg_ex: Examples
    bg_info: list[dict]
    held: list
    centres: list[dict]  # per labelled log: the landmarks' radius and the map's scale (labels.landmark_centres)


def _first_labels(run: _Run, logs: Sequence[ScanLog], site: "Site | Sequence[Site]", background: Sequence[ScanLog],
                  bg_names: Sequence[str], n_beams: int) -> _FirstPass:
    """Labels, pass 1 (transforms from raw ORS origins), the background logs' examples and the held-out
    split by one-second blocks: what the landmark classes' position GPs are learnt from."""
    per_log, columns = front_end_logs(logs, run.cfg.frontend, n_beams)
    ex1, cls_slots, offset, centres = first_pass(logs, per_log, site, run.classes, run.cfg)
    bg_ex, bg_info = background_examples(background, bg_names, run.cfg, n_beams, columns, offset)
    held = holdout_groups(run.rng, np.concatenate([ex1.group, bg_ex.group]), run.cfg.holdout)
    return _FirstPass(per_log, columns, ex1, cls_slots, bg_ex, bg_info, held, centres)


def _landmark_positions(run: _Run, lab: _FirstPass) -> list:
    """Each class's pose regressor so far: the landmark classes' position GPs, by which the second pass
    places landmark candidates at their predicted centres (the mobile classes' come later)."""
    pose = [None] * len(run.classes)
    for k, reg in fit_landmark_positions(lab.ex1, lab.held, run.classes, run.landmarks, run.cfg, run.rng,
                                         run.gps).items():
        pose[k] = reg
    return pose


def _open_set(run: _Run, ex_lab: Examples, lab: _FirstPass) -> tuple:
    """The open-set test's supports and thresholds, from the labelled classes and the background logs'
    examples alike (before the look-alikes of landmarks are taken out of the latter)."""
    return fit_support(Examples.concat([ex_lab, lab.bg_ex]),
                       np.isin(np.concatenate([ex_lab.group, lab.bg_ex.group]), lab.held), len(run.classes), run.rng,
                       size=run.cfg.support_size)


def _with_background_logs(run: _Run, ex_lab: Examples, lab: _FirstPass, support) -> tuple[Examples, np.ndarray]:
    """The examples the classifier and the pose GPs learn from: the labelled logs', then the background
    logs' as the background class, landmark look-alikes left out; and each one's source (-1: the
    labelled logs, else the background log's index)."""
    lookalike = landmark_lookalikes(support, lab.bg_ex, lab.bg_info, run.classes, run.landmarks)
    ex = Examples.concat([ex_lab, lab.bg_ex.take(np.flatnonzero(~lookalike))])
    source = np.concatenate([np.full(len(ex_lab.cls), -1),  # the labelled logs, then each background log
                             np.repeat(np.arange(len(lab.bg_info)), [i["candidates"] for i in lab.bg_info])[~lookalike]])
    return ex, source


def _motion_limits(run: _Run, logs: Sequence[ScanLog], env_report: dict,
                   sup_report: dict) -> tuple[TrackerParams, float, dict, list[dict]]:
    """The scanner's rate, each tracked class's speed and turn-rate limits and the tracker they make;
    with the rows of the learnt-parameter table (the shapes' rows too: the report's one table)."""
    cfg, classes, mobiles = run.cfg, run.classes, run.mobiles
    rate_hz, rate_row = scan_rate_entry(logs, cfg.scan_rate_hz)
    speed, turn, motion, motion_rows = tracker_limits(logs, classes, mobiles, cfg, period=1.0 / rate_hz)
    # How fast the robots' turn rate changes while they move: the tracker's turn-rate process noise.
    q_theta, q_row = turn_rate_noise(logs, mobiles, period=1.0 / rate_hz, max_speed=dict(zip(classes, speed, strict=True)),
                                     max_turn_rate=dict(zip(classes, turn, strict=True)))
    tracker = TrackerParams.default([c in mobiles for c in classes], rate_hz=rate_hz, max_speed=speed,
                                    max_turn_rate=turn, q_theta=q_theta)
    # The heading against the direction of travel, the tracker's evidence from a track's motion.
    heading_table, heading_rows = motion_heading(logs, classes, mobiles, period=1.0 / rate_hz)
    if heading_table is not None:
        tracker = eqx.tree_at(lambda t: t.motion_heading, tracker, jnp.asarray(heading_table, jnp.float32),
                              is_leaf=lambda x: x is None)
    learnt = [rate_row, confirmation_entry(int(tracker.n_confirm), rate_hz), *motion_rows, q_row, *heading_rows,
              *shape_rows(env_report, sup_report, classes, mobiles)]
    return tracker, rate_hz, motion, learnt


def _assemble(run: _Run, first: ScanLog, n_beams: int, columns: tuple[int, ...], *, classifier, envelope,
              pose: list, tracker: TrackerParams, outline) -> Model:
    """The model of the fitted parts and the labelled logs' scanner geometry, as a model file loads."""
    cfg, classes = run.cfg, run.classes
    model = Model(
        frontend=cfg.frontend,
        classifier=classifier,
        envelope=envelope,
        pose=tuple(pose),
        tracker=tracker,
        landmark_mask=jnp.asarray([c in run.landmarks for c in classes]),
        map_gate=jnp.asarray(cfg.map_gate, jnp.float32),
        map_min_spread=jnp.asarray(cfg.map_min_spread, jnp.float32),
        meas_var_floor=jnp.asarray(cfg.meas_var_floor, jnp.float32),
        site=None,
        classes=classes,
        max_tracks=cfg.max_tracks,
        max_objects=cfg.max_tracks,
        sensor_model=first.sensor_model or "unknown",
        n_beams=n_beams,
        gp_columns=columns,
        angle_min=float(first.angle_min),
        angle_increment=float(first.angle_increment),
        range_min=float(first.range_min),
        range_max=float(first.range_max),
        outline=outline,
    ).with_common_pose_inputs()
    return with_scanner(model)  # as a model file loads


def _report(run: _Run, model: Model, ex: Examples, is_held: np.ndarray, ex_lab: Examples, bg_info: list[dict], *,
            train_idx: np.ndarray, calibration: dict, env_report: dict, sup_report: dict, motion: dict,
            learnt: list[dict], outline_report: dict, n_scans: int, degraded: int, warnings: list[str]) -> dict:
    """The report of how the model was made, with its held-out classification and pose errors."""
    classes = run.classes
    return {
        "classes": list(classes),
        "examples": {c: int(np.sum(ex.cls == k)) for k, c in enumerate(classes)},
        "examples_labelled_logs": {c: int(np.sum(ex_lab.cls == k)) for k, c in enumerate(classes)},
        "examples_used": {c: int(np.sum(ex.cls[train_idx] == k)) for k, c in enumerate(classes)},
        "background_logs": bg_info,
        "fits": run.gps.fits,
        "variance_calibration": calibration,
        "envelopes": {classes[k]: v for k, v in env_report.items()},
        "open_set": {classes[k]: v for k, v in sup_report.items()},
        "motion_limits": motion,
        "learnt": learnt,
        "outlines": outline_report,
        "scans": n_scans,
        "degraded_scans": degraded,
        "warnings": warnings,
        "heldout": evaluate_examples(model, ex.take(np.flatnonzero(is_held))),
    }


def _tracking_check(report: dict, model: Model, logs: Sequence[ScanLog], site: "Site | Sequence[Site]",
                    ex_lab: Examples, held: list, mobiles: tuple[str, ...], rate_hz: float,
                    seed: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The trained step run over the labelled logs' held-out seconds and on simulated stays and walks
    with the held-out errors: whether it can track each class, a verdict no single figure gives.
    Returns the held-out detections' errors in each class's own frame (for :func:`pose_bias`) and the
    held-out rows' errors with their variances (for :func:`variance_floor`)."""
    held_scans = [held_mask(log, i, ex_lab.where, ex_lab.group, held) for i, log in enumerate(logs)]
    report["pipeline"], errors, rows = check_pipeline(model, logs, per_log_sites(site, len(logs)), held_scans, mobiles)
    report["pipeline_simulated"] = simulated_checks(model, report["heldout"], mobiles, rate_hz, seed)
    report["pipeline_problems"] = verdict(report["pipeline"], report["pipeline_simulated"])
    return errors, rows
