"""Batch replay of several lasers' logs on one field into one track table.

The logs (one per laser of the site's ``sensors`` list) are merged by stamp into one sequence
(:func:`merge_logs`; a stable sort, so equal stamps keep the lasers' order), which runs through
:func:`~gtsjax.core.multi.step_several` chunk by chunk: perception ``vmap``ped over groups of scans
(whichever laser took them: perception needs no state), then the updates under ``lax.scan``, each
with its laser's index. The outputs come out in the merged order, one per scan of any laser: a GTD
row per confirmed track per scan, stamped with that scan's stamp.

Lasers of different scanner models (one model each, :func:`models_for_lasers`) run in two passes
(:func:`process_mixed`): each laser's log perceived by its own model, then the merged sequence's
updates under one ``lax.scan`` that picks each scan's model (:func:`~gtsjax.core.multi.update_mixed`).
"""

import csv
import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..core.geometry import wrap
from ..core.model import Model
from ..core.multi import SeveralState, init_several, pad_perception, update_mixed, update_several, widest
from ..core.pipeline import Output, Perception
from ..core.scan import Scan
from ..errors import InputError
from ..io.gtd import GTDWriter, rows_from_output
from ..io.logs import ScanLog, scan_dt, to_scans
from ..io.site import Site
from .compile import batch_jit
from .replay import SUB_CHUNK, _pad_chunk, chunk_for, perceive_batch
from .setup import check_models


@dataclasses.dataclass(frozen=True)
class Merged:
    """Several lasers' logs as one sequence in stamp order."""

    log: ScanLog  # every scan of every laser, by stamp (with the truth, where the logs are labelled)
    laser: np.ndarray  # int32 [T]: which laser (index into ``names``) took each scan
    index: np.ndarray  # int [T]: the scan's index in its own log
    span_dt: np.ndarray  # float32 [T]: time since the same laser's previous scan
    names: tuple[str, ...]
    # Each laser's own log, as merged (with lasers of different scanners, ``log``'s beams are the
    # first laser's geometry padded with NaN to the widest: read each laser's from here).
    sources: "dict[str, ScanLog]" = dataclasses.field(default_factory=dict)


def merge_logs(logs: "dict[str, ScanLog]", *, mixed: bool = False) -> Merged:
    """The logs laid end to end and sorted by stamp (stable). They must share one geometry (one
    scanner model; :func:`~gtsjax.io.logs.fit_to_model` each first), unless ``mixed`` (lasers of
    different scanners, each log fitted to its own model), and, where labelled, the same labelled
    objects (a match's robots, as each laser's log records them at its own times)."""
    names = tuple(logs)
    if not names:
        raise InputError("replay", "no logs to merge")
    first = logs[names[0]]
    if not mixed:
        for name, log in logs.items():
            if log.n_beams != first.n_beams or not math.isclose(log.angle_increment, first.angle_increment,
                                                                rel_tol=1e-6):
                raise InputError(name, f"{log.n_beams} beams of {math.degrees(log.angle_increment):.4f}°, the first "
                                       f"laser's log {first.n_beams} of {math.degrees(first.angle_increment):.4f}°: "
                                       "the lasers of one replay must be one scanner model")
    stamps = np.concatenate([logs[n].stamps for n in names])
    laser = np.concatenate([np.full(logs[n].n_scans, k, np.int32) for k, n in enumerate(names)])
    index = np.concatenate([np.arange(logs[n].n_scans) for n in names])
    order = np.argsort(stamps, kind="stable")
    labelled = all(logs[n].labelled for n in names)
    if labelled and len({tuple(map(str, logs[n].truth_classes)) for n in names}) != 1:
        raise InputError("replay", "the lasers' logs label different objects; a merged evaluation needs the same")
    extra = {}  # (each laser's true pose is in its own log: in merged order it would read as a bump)
    width = max(logs[n].n_beams for n in names)

    def cat(f):
        if any(getattr(logs[n], f) is None for n in names):
            return None
        parts = [np.asarray(getattr(logs[n], f), np.float32) for n in names]
        return np.concatenate([np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=np.nan)
                               for a in parts])[order]

    log = dataclasses.replace(first, ranges=cat("ranges"), stamps=stamps[order], intensities=cat("intensities"),
                              truth_poses=np.concatenate([logs[n].truth_poses for n in names])[order] if labelled
                              else None,
                              truth_classes=first.truth_classes if labelled else None, extra=extra)
    span = np.zeros(len(order), np.float32)
    for k in range(len(names)):
        mine = laser[order] == k
        span[mine] = scan_dt(stamps[order][mine])
    return Merged(log, laser[order], index[order], span, names, dict(logs))


@batch_jit()
def process_several_chunk(model: Model, state: SeveralState, scans: Scan, laser: Int[Array, " n"],
                          span_dt: Float[Array, " n"], n_real: Int[Array, ""]) -> tuple[SeveralState, Output]:
    """A chunk of merged scans: perception ``vmap``ped over groups of scans, then the updates under
    ``lax.scan`` with each scan's laser; scans at index ``>= n_real`` (padding) leave the state as it was."""
    size = scans.dt.shape[0]
    percepts = perceive_batch(model, scans, math.gcd(SUB_CHUNK, size))

    def body(s, inp):
        p, sc, k, span, i = inp
        new, out = update_several(model, s, p, sc, k, span)
        keep = i < n_real
        return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, s), out

    idx = jnp.arange(size, dtype=jnp.int32)
    return jax.lax.scan(body, state, (percepts, scans, laser, span_dt, idx))


def process_several(model: "Model | tuple[Model, ...]", merged: Merged, sensor_poses, *, kinds=None, chunk: int = 256,
                    state: SeveralState | None = None, callback=None) -> tuple[SeveralState, Output]:
    """The merged scans through the several-laser pipeline ``chunk`` at a time; outputs stacked on the
    host in the merged order. ``sensor_poses``: each laser's rough pose guess, in ``merged.names``' order.
    ``model``: every laser's, or one per scanner model with ``kinds`` (each laser's index into them,
    :func:`models_for_lasers`): then :func:`process_mixed`."""
    if isinstance(model, tuple) and len(model) > 1:
        return process_mixed(model, kinds, merged, sensor_poses, chunk=chunk, state=state, callback=callback)
    model = model[0] if isinstance(model, tuple) else model
    state = init_several(model, jnp.asarray(sensor_poses, jnp.float32)) if state is None else state
    scans = to_scans(merged.log, model.n_beams)
    n = merged.log.n_scans
    chunk = chunk_for(n, chunk)
    laser = jnp.asarray(merged.laser, jnp.int32)
    span = jnp.asarray(merged.span_dt, jnp.float32)
    outs = []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        part, k, sp = _pad_chunk((scans, laser, span), start, stop, chunk)
        state, out = process_several_chunk(model, state, part, k, sp, jnp.asarray(stop - start, jnp.int32))
        outs.append(_host_rows(out, stop - start))
        if callback is not None:
            callback(stop)
    return state, jax.tree.map(lambda *a: np.concatenate(a), *outs)


def _host_rows(tree, n: int):
    return jax.tree.map(lambda a: np.asarray(a)[:n], tree)


@batch_jit()
def _perceive_chunk(model: Model, scans: Scan) -> Perception:
    return perceive_batch(model, scans, math.gcd(SUB_CHUNK, scans.dt.shape[0]))


@batch_jit()
def process_mixed_chunk(models: "tuple[Model, ...]", state: SeveralState, percepts: Perception, scans: Scan,
                        laser: Int[Array, " n"], kind: Int[Array, " n"], span_dt: Float[Array, " n"],
                        n_real: Int[Array, ""]) -> tuple[SeveralState, Output]:
    """:func:`process_several_chunk` for lasers of different scanners, their perception done:
    the updates under ``lax.scan``, each by its scan's model (``kind``)."""
    def body(s, inp):
        p, sc, k, c, span, i = inp
        new, out = update_mixed(models, s, p, sc, k, c, span)
        keep = i < n_real
        return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, s), out

    idx = jnp.arange(scans.dt.shape[0], dtype=jnp.int32)
    return jax.lax.scan(body, state, (percepts, scans, laser, kind, span_dt, idx))


def process_mixed(models: "tuple[Model, ...]", kinds, merged: Merged, sensor_poses, *, chunk: int = 256,
                  state: SeveralState | None = None, callback=None) -> tuple[SeveralState, Output]:
    """Lasers of different scanners (laser ``k``'s model ``models[kinds[k]]``) in two passes: each
    laser's log perceived by its model (``chunk`` scans at a time, vmapped as in one laser's replay),
    then the merged sequence's updates (:func:`process_mixed_chunk`), perception and scans padded to
    the widest model's (:func:`~gtsjax.core.multi.widest`)."""
    kinds = tuple(int(i) for i in kinds)
    check_models(models)
    state = init_several(models, jnp.asarray(sensor_poses, jnp.float32), kinds) if state is None else state
    n_cands, n_beams = widest(models)
    n = merged.log.n_scans
    chunk = chunk_for(n, chunk)
    # Pass 1: each laser's scans, perceived by its own model, on the host in the laser's order.
    percepts, scans = [], []
    for k, name in enumerate(merged.names):
        m, log = models[kinds[k]], merged.sources[name]
        own = to_scans(log, m.n_beams)
        parts = []
        for start in range(0, log.n_scans, chunk):
            stop = min(start + chunk, log.n_scans)
            parts.append(_host_rows(pad_perception(_perceive_chunk(m, _pad_chunk(own, start, stop, chunk)), n_cands),
                                    stop - start))
        percepts.append(jax.tree.map(lambda *a: np.concatenate(a), *parts))
        scans.append(to_scans(log, n_beams))
    # The merged order: laser k's i-th scan is row offset[k] + i of the lasers' scans laid end to end.
    offset = np.cumsum([0] + [merged.sources[nm].n_scans for nm in merged.names])[:-1]
    rows = offset[merged.laser] + merged.index
    percepts = jax.tree.map(lambda *a: jnp.asarray(np.concatenate(a)[rows]), *percepts)  # to the device once
    cat = lambda f: jnp.asarray(np.concatenate([np.asarray(getattr(sc, f)) for sc in scans])[rows])  # noqa: E731
    scans = Scan(cat("ranges"), cat("intensities"), cat("valid"), cat("angle_min"), cat("angle_increment"),
                 jnp.asarray(scan_dt(merged.log.stamps)))
    laser = jnp.asarray(merged.laser, jnp.int32)
    kind = jnp.asarray(np.asarray(kinds, np.int32)[merged.laser])
    span = jnp.asarray(merged.span_dt, jnp.float32)
    # Pass 2: the updates in the merged order.
    outs = []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        p, sc, k, c, sp = _pad_chunk((percepts, scans, laser, kind, span), start, stop, chunk)
        state, out = process_mixed_chunk(models, state, p, sc, k, c, sp, jnp.asarray(stop - start, jnp.int32))
        outs.append(_host_rows(out, stop - start))
        if callback is not None:
            callback(stop)
    return state, jax.tree.map(lambda *a: np.concatenate(a), *outs)


def models_for_lasers(models: "list[Model]", site: Site, names, where: object = "--model"
                      ) -> "tuple[tuple[Model, ...], tuple[int, ...]]":
    """Which of ``models`` (one per scanner model) serves each laser named: the one trained for the
    scanner the site's ``sensors`` entry names (``model``). One model serves every laser, whatever
    they name. Returns the models in use and each laser's index into them."""
    if len(models) == 1:
        return (models[0],), (0,) * len(names)
    by_scanner: dict[str, int] = {}
    for i, m in enumerate(models):
        if m.sensor_model in by_scanner:
            raise InputError(where, f"two models for the {m.sensor_model}: give one model per scanner model")
        by_scanner[m.sensor_model] = i
    kinds = []
    for name in names:
        scanner = site.sensor(name).model
        if scanner is None:
            raise InputError(where, f"laser {name!r} names no scanner model in the site (its sensors entry's "
                                    "\"model\"): with several models each laser's scanner must be named")
        if scanner not in by_scanner:
            raise InputError(where, f"laser {name!r} is a {scanner}; no model given for it (models for "
                                    f"{', '.join(by_scanner)})")
        kinds.append(by_scanner[scanner])
    used = sorted(set(kinds))
    chosen = tuple(models[i] for i in used)
    check_models(chosen, where)
    return chosen, tuple(used.index(i) for i in kinds)


def site_poses(site: Site, names) -> np.ndarray:
    """The site's rough pose guess of each laser named, in that order."""
    return np.asarray([site.sensor(n).pose for n in names], np.float32)


def replay_several(logs: "dict[str, ScanLog]", model: "Model | tuple[Model, ...]", site: Site, out: Path, *,
                   kinds=None, chunk: int = 256, progress=None, sensor_out: Path | None = None,
                   csv_units: bool = False, out_bag: Path | None = None, view=None) -> dict:
    """Replay several lasers' logs (names of the site's ``sensors``) into one GTD CSV; returns totals
    (scans, rows, tracks per class, degraded scans per laser, the run's ``diagnosis``:
    :mod:`gtsjax.drivers.diagnose`). ``sensor_out``: each scan's laser pose
    in O as its own transform places it (``stamp,laser,x,y,theta,degraded,n_landmarks``): a tripod
    bumped shows as a step in its laser's rows. ``model``: every laser's, or one per scanner model
    with ``kinds`` (:func:`models_for_lasers`). ``out_bag``: also a ROS 2 bag, each laser's scans on
    its own topic and frame (:mod:`gtsjax.io.bag_out`); ``view``: a :class:`~gtsjax.viewer.View`
    shown each scan, each laser's under its name (closed at the end)."""
    from ..io.bag_out import BagOut, LaserGeometry

    mixed = isinstance(model, tuple) and len(model) > 1
    merged = merge_logs(logs, mixed=mixed)
    _, o = process_several(model, merged, site_poses(site, merged.names), kinds=kinds, chunk=chunk, callback=progress)
    model = model[0] if isinstance(model, tuple) else model
    rows_total, ids = 0, {}
    # Each scan as its own laser took it (the merged log's beams are padded to the widest scanner's).
    sources = [merged.sources[n] for n in merged.names]
    valid = [src.valid() for src in sources] if view is not None else None
    bag = BagOut(out_bag, {n: LaserGeometry.of_log(src) for n, src in zip(merged.names, sources, strict=True)}
                 ) if out_bag is not None else None
    try:
        with GTDWriter(out, units=csv_units) as w:
            for t in range(merged.log.n_scans):
                stamp = float(merged.log.stamps[t])
                rows = rows_from_output(stamp, o.track_id[t], o.track_class[t], o.track_pose[t], o.track_var[t],
                                        o.track_mask[t], model.classes, o.track_cov_xy[t])
                w.write(rows)
                rows_total += len(rows)
                for r in rows:
                    ids.setdefault(r.cls, set()).add(r.track_id)
                k, i = int(merged.laser[t]), int(merged.index[t])
                src = sources[k]
                if bag is not None:
                    bag.write(stamp, src.ranges[i], None if src.intensities is None else src.intensities[i], rows,
                              np.asarray(o.sensor_pose[t], np.float64), laser=merged.names[k])
                if view is not None:
                    view.scan(stamp, np.where(valid[k][i], src.ranges[i], 0.0), src.angle_min, src.angle_increment,
                              jax.tree.map(lambda a, t=t: a[t], o), rows, laser=merged.names[k])
    finally:
        if bag is not None:
            bag.close()
        if view is not None:
            view.close()
    if sensor_out is not None:
        sp = np.asarray(o.sensor_pose, np.float64)
        disagreement = cross_laser_disagreement(merged, o)
        with open(sensor_out, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(("stamp", "laser", "x", "y", "theta", "degraded", "n_landmarks", "disagreement"))
            for t in range(merged.log.n_scans):
                d = disagreement[t]
                w.writerow((repr(float(merged.log.stamps[t])), merged.names[merged.laser[t]], f"{sp[t, 0]:.6f}",
                            f"{sp[t, 1]:.6f}", f"{float(wrap(sp[t, 2])):.6f}", int(o.transform.degraded[t]),
                            int(o.transform.n_landmarks[t]), "" if np.isnan(d) else f"{d:.4f}"))
    degraded = {n: int(np.sum(o.degraded[merged.laser == k])) for k, n in enumerate(merged.names)}
    from .diagnose import tally_outputs

    return {"scans": int(merged.log.n_scans), "rows": rows_total, "tracks": {c: len(v) for c, v in ids.items()},
            "degraded": degraded, "scans_per_laser": {n: int(np.sum(merged.laser == k))
                                                       for k, n in enumerate(merged.names)},
            "diagnosis": tally_outputs(model, o)}


class Disagreement:
    """The cross-laser calibration check, one scan at a time: each laser's map
    transformation places its detection of a landmark at the landmark's map position plus that
    laser's residual, so two lasers put the same landmark ``|r_k − r_j|`` apart. :meth:`update` gives
    the largest such distance over the landmarks a scan saw and another laser saw in its latest scan
    (NaN where none is shared). A tripod bumped, a laser whose transform went stale (degraded) after
    it moved, shows as a step. Used by batch replay (:func:`cross_laser_disagreement`) and the live
    loop alike (host arrays, a few landmarks: microseconds)."""

    def __init__(self):
        self.latest: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def update(self, k: int, residual, seen) -> float:
        residual, seen = np.asarray(residual, np.float64), np.asarray(seen, bool)
        worst = np.nan
        for j, (res_j, seen_j) in self.latest.items():
            if j == k:
                continue
            both = seen & seen_j
            if both.any():
                d = float(np.linalg.norm(residual[both] - res_j[both], axis=1).max())
                worst = d if np.isnan(worst) else max(worst, d)
        self.latest[k] = (residual, seen)
        return worst


def cross_laser_disagreement(merged: Merged, o: Output) -> np.ndarray:
    """Per scan of a merged replay, :class:`Disagreement` (NaN where no landmark is shared)."""
    check = Disagreement()
    res = np.asarray(o.landmark_residual, np.float64)  # [T, L, 2]
    seen = np.asarray(o.landmark_seen, bool)  # [T, L]
    return np.array([check.update(int(merged.laser[t]), res[t], seen[t]) for t in range(merged.log.n_scans)])
