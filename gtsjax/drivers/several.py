"""Batch replay of several lasers' logs on one field into one track table.

The logs (one per laser of the site's ``sensors`` list) are merged by stamp into one sequence
(:func:`merge_logs`; a stable sort, so equal stamps keep the lasers' order), which runs through the
batch engine (:mod:`gtsjax.drivers.batch`) chunk by chunk: perception ``vmap``ped over groups of
scans (whichever laser took them: perception needs no state), then the updates under ``lax.scan``,
each with its laser's index (:func:`~gtsjax.core.multi.update_several`). The outputs come out in the merged order, one per scan of any laser: a GTD
row per confirmed track per scan, stamped with that scan's stamp.

Lasers of different scanner models (one model each, :func:`models_for_lasers`) run in two passes
(:func:`perceive_lasers`): each laser's log perceived by its own model, then the merged sequence's
updates under one ``lax.scan`` that picks each scan's model (:func:`~gtsjax.core.multi.update_mixed`).
"""

import dataclasses
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.model import Model
from ..core.multi import SeveralState, identities, init_several, pad_perception, widest
from ..core.pipeline import Output, Perception
from ..core.scan import Scan
from ..errors import InputError
from ..io.logs import ScanLog, scan_dt, to_scans
from ..io.site import Site
from .batch import Lanes, chunk_for, concat, for_chunks, host_rows, on_host, pad_chunk, perceive_chunk, run_chunks
from .setup import check_models
from .sink import Sink


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
    if labelled and "truth_names" in first.extra:  # which robot each labelled object is: the same objects
        extra["truth_names"] = first.extra["truth_names"]
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


def widened(merged: Merged, names: "tuple[str, ...]") -> Merged:
    """``merged`` (scans of some of a site's lasers) as a merge of every laser of ``names``, the others
    without a scan: its laser indices into ``names``. One laser's scans, two lasers' and all run then
    through one compiled program (the state's shapes are the number of lasers), a laser without scans
    watching nothing (:func:`process_several`). One scanner model only (``sources`` holds only the
    lasers that have scans)."""
    at = np.asarray([names.index(n) for n in merged.names], np.int32)
    return dataclasses.replace(merged, laser=at[merged.laser], names=tuple(names))


def process_several(model: "Model | tuple[Model, ...]", merged: Merged, sensor_poses, *, kinds=None, chunk: int = 256,
                    state: SeveralState | None = None, callback=None, filtered: bool = False
                    ) -> tuple[SeveralState, Output]:
    """The merged scans through the several-laser pipeline ``chunk`` at a time (the batch engine,
    :func:`~gtsjax.drivers.batch.run_chunks`); outputs stacked on the host in the merged order.
    ``sensor_poses``: each laser's rough pose guess, in ``merged.names``' order. ``model``: every
    laser's, or one per scanner model with ``kinds`` (each laser's index into them,
    :func:`models_for_lasers`): then each laser's scans are perceived by its own model first
    (:func:`perceive_lasers`)."""
    models = model if isinstance(model, tuple) else (model,)
    kinds = tuple(int(i) for i in kinds) if kinds is not None else (0,) * len(merged.names)
    check_models(models)
    if state is None:
        state = init_several(models, jnp.asarray(sensor_poses, jnp.float32), kinds if len(models) > 1 else None)
        # A laser without a scan here (a merge widened to every laser of a site, :func:`widened`)
        # watches nothing: no track is taken as seen by it, as if it were not in the state at all.
        silent = ~np.isin(np.arange(len(merged.names)), merged.laser)
        if silent.any():
            state = eqx.tree_at(lambda st: st.reach, state, jnp.where(jnp.asarray(silent)[:, None], 0.0, state.reach))
    lanes = Lanes(jnp.asarray(merged.laser, jnp.int32), jnp.asarray(np.asarray(kinds, np.int32)[merged.laser]),
                  jnp.asarray(merged.span_dt, jnp.float32))
    if len(models) == 1:
        scans, percepts = to_scans(merged.log, models[0].n_beams), None
    else:
        scans, percepts = perceive_lasers(models, kinds, merged, chunk)
    return run_chunks(models, state, scans, lanes=lanes, percepts=percepts, chunk=chunk, callback=callback,
                      filtered=filtered)


def perceive_lasers(models: "tuple[Model, ...]", kinds, merged: Merged, chunk: int) -> tuple[Scan, Perception]:
    """Lasers of different scanners (laser ``k``'s model ``models[kinds[k]]``): each laser's log
    perceived by its model (``chunk`` scans at a time, vmapped as in one laser's replay,
    :func:`~gtsjax.drivers.batch.perceive_chunk`), then laid out in the merged order on the device,
    scans and perception padded to the widest model's (:func:`~gtsjax.core.multi.widest`)."""
    n_cands, n_beams = widest(models)
    n_ids = identities(models)
    chunk = chunk_for(merged.log.n_scans, chunk)
    percepts, scans = [], []
    for k, name in enumerate(merged.names):
        m, log = models[kinds[k]], merged.sources[name]
        own = on_host(to_scans(log, m.n_beams))
        _, parts = for_chunks(lambda _, a, b, m=m, own=own: (None, host_rows(
            pad_perception(perceive_chunk(m, pad_chunk(own, a, b, chunk)), n_cands, n_ids), b - a)), None, log.n_scans,
                                   chunk)
        percepts.append(concat(parts))
        scans.append(to_scans(log, n_beams))
    # The merged order: laser k's i-th scan is row offset[k] + i of the lasers' scans laid end to end.
    offset = np.cumsum([0] + [merged.sources[nm].n_scans for nm in merged.names])[:-1]
    rows = offset[merged.laser] + merged.index
    percepts = jax.tree.map(lambda *a: jnp.asarray(np.concatenate(a)[rows]), *percepts)  # to the device once
    cat = lambda f: jnp.asarray(np.concatenate([np.asarray(getattr(sc, f)) for sc in scans])[rows])  # noqa: E731
    scans = Scan(cat("ranges"), cat("intensities"), cat("valid"), cat("angle_min"), cat("angle_increment"),
                 jnp.asarray(scan_dt(merged.log.stamps)))
    return scans, percepts


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
                   csv_units: bool = False, out_bag: Path | None = None, view=None, smooth: bool = False) -> dict:
    """Replay several lasers' logs (names of the site's ``sensors``) into one GTD CSV; returns totals
    (scans, rows, tracks per class, degraded scans per laser, the run's ``diagnosis``:
    :mod:`gtsjax.drivers.diagnose`). ``sensor_out``: each scan's laser pose
    in O as its own transform places it (``stamp,laser,x,y,theta,degraded,n_landmarks``): a tripod
    bumped shows as a step in its laser's rows. ``model``: every laser's, or one per scanner model
    with ``kinds`` (:func:`models_for_lasers`). ``out_bag``: also a ROS 2 bag, each laser's scans on
    its own topic and frame (:mod:`gtsjax.io.bag_out`); ``view``: a :class:`~gtsjax.viewer.View`
    shown each scan, each laser's under its name (closed at the end). ``smooth``: the rows' poses
    smoothed over each track's whole life, every laser's detections together
    (:mod:`gtsjax.drivers.smoothing`)."""
    from ..io.bag_out import BagOut, LaserGeometry

    mixed = isinstance(model, tuple) and len(model) > 1
    merged = merge_logs(logs, mixed=mixed)
    names = merged.names
    _, o = process_several(model, merged, site_poses(site, names), kinds=kinds, chunk=chunk, callback=progress,
                           filtered=smooth)
    if smooth:
        from .smoothing import smooth_output

        o, filtered = o
        first = model[0] if isinstance(model, tuple) else model
        o = smooth_output(o, filtered, merged.log.stamps, first.tracker)
    # Each scan as its own laser took it (the merged log's beams are padded to the widest scanner's).
    sources = [merged.sources[n] for n in names]
    bag = BagOut(out_bag, {n: LaserGeometry.of_log(src) for n, src in zip(names, sources, strict=True)}
                 ) if out_bag is not None else None
    sink = Sink(model[0] if isinstance(model, tuple) else model, out, names=names, bag=bag, view=view,
                sensor_out=sensor_out, csv_units=csv_units)
    try:
        valid = [src.valid() for src in sources] if sink.wants_output else None

        def frame(t):
            k, i = int(merged.laser[t]), int(merged.index[t])
            src = sources[k]
            return (src.ranges[i], None if src.intensities is None else src.intensities[i], src.angle_min,
                    src.angle_increment, valid[k][i])

        sink.add(merged.log.stamps, o, lasers=merged.laser, frame=frame)
    finally:
        sink.close()
    return {"scans": int(merged.log.n_scans), "rows": sink.rows,
            "tracks": {c: len(v) for c, v in sink.track_ids.items()},
            "degraded": {n: int(sink.degraded[k]) for k, n in enumerate(names)},
            "scans_per_laser": {n: int(sink.scans[k]) for k, n in enumerate(names)},
            "diagnosis": sink.tally.finish()}
