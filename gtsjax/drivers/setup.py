"""A model ready to run: the host's one door to :class:`~gtsjax.core.model.Model`.

The core's model is a pure parameter tree; what turns a model file into one a run can use is here:
the file read once (:func:`~gtsjax.io.modelfile.load_model`, with its scanner's facts from the
sensor table), the site attached after checking that its landmark classes are the model's, the run's
options (``--confirm-scans``, ``--max-tracks``) checked and applied, and the model checked once
against what it will run on: a sensor (:func:`check_sensor`) or a log
(:func:`~gtsjax.io.logs.fit_to_model`). Several models that share one track table are checked
against one another (:func:`check_models`). Every message names the file or option the user gave.
The command line gets its models from here only.
"""

import os

from ..core.model import Model
from ..errors import InputError
from ..io.logs import check_intensities, fit_beams, fit_to_model
from ..io.modelfile import load_model
from ..io.site import Site, one_sensor
from ..sensors import SensorModel

__all__ = [
    "MAX_TRACKS_LIMIT",
    "attach_site",
    "check_models",
    "check_sensor",
    "fit_to_model",
    "load",
    "load_for_lasers",
    "with_options",
]

MAX_TRACKS_LIMIT = 64  # track slots a model may be given (--max-tracks)


def attach_site(model: Model, site: Site, where: object = "site") -> Model:
    """``model`` with ``site`` attached (:meth:`~gtsjax.core.model.Model.with_site`), after checking
    that every landmark class of the site is one the model knows as a landmark class (otherwise it
    could never be detected); a site that breaks this is one line naming ``where``."""
    known = model.landmark_classes
    unknown = sorted({c for c in site.landmark_classes if c not in known})
    if unknown:
        raise InputError(
            where,
            f"landmark class(es) {', '.join(unknown)} unknown to the model (it knows {', '.join(known) or 'none'})",
        )
    return model.with_site(site)


def with_options(model: Model, confirm_scans: int | None = None, max_tracks: int | None = None) -> Model:
    """``model`` with the run's ``--confirm-scans`` and ``--max-tracks`` (``None``: as trained),
    each checked first (:meth:`~gtsjax.core.model.Model.with_confirmation`,
    :meth:`~gtsjax.core.model.Model.with_capacity`)."""
    if confirm_scans is not None and confirm_scans < 1:
        raise InputError("--confirm-scans", f"must be at least 1, not {confirm_scans}")
    model = model.with_confirmation(confirm_scans)
    if max_tracks is not None and not 1 <= max_tracks <= MAX_TRACKS_LIMIT:
        raise InputError("--max-tracks", f"must be 1 to {MAX_TRACKS_LIMIT}, not {max_tracks}")
    return model.with_capacity(max_tracks)


def load(
    path: str | os.PathLike,
    site: Site | None = None,
    *,
    where: object = "site",
    confirm_scans: int | None = None,
    max_tracks: int | None = None,
    without_outline: bool = False,
) -> Model:
    """The model file at ``path``, read once, with ``site`` (one laser's: :func:`~gtsjax.io.site.one_sensor`)
    attached (:func:`attach_site`, naming ``where``), the run's options (:func:`with_options`), and
    without its outlines where asked (``evaluate --without-outline``). Without a site, a model to
    describe or to be given each log's or scenario's site later."""
    model = load_model(path)
    if site is not None:
        model = attach_site(model, site, where)
    model = with_options(model, confirm_scans, max_tracks)
    return model.without_outline() if without_outline else model


def load_for_lasers(
    paths: "list[os.PathLike]",
    site: Site,
    where: object = "site",
    *,
    confirm_scans: int | None = None,
    max_tracks: int | None = None,
) -> list[Model]:
    """Each of a site's several lasers' models (one per scanner model), with the site attached as
    its first laser sees it (each laser's own pose guess is in the several-laser state) and the
    run's options."""
    first = one_sensor(site, site.sensor_list[0].name)
    return [load(p, first, where=where, confirm_scans=confirm_scans, max_tracks=max_tracks) for p in paths]


def check_models(models: "tuple[Model, ...]", where: object = "--model") -> None:
    """Models of different scanners that are to share one track table must know the same classes
    (in the same order), have as many track slots and carry the same site's landmarks (and, where both
    read tags, the same robots' tags: a model that reads none may join one that does)."""
    first = models[0]
    for m in models[1:]:
        if m.classes != first.classes:
            raise InputError(
                where,
                f"the {m.sensor_model} model's classes ({', '.join(m.classes)}) differ from the "
                f"{first.sensor_model} model's ({', '.join(first.classes)}): one track table needs "
                "the same classes",
            )
        if m.max_tracks != first.max_tracks:
            raise InputError(
                where,
                f"the {m.sensor_model} model has {m.max_tracks} track slots, the "
                f"{first.sensor_model} model {first.max_tracks}: give --max-tracks",
            )
        if m.site is not None and first.site is not None and m.site.landmark_xy.shape != first.site.landmark_xy.shape:
            raise InputError(where, "the models carry different sites")
        if m.n_identities and first.n_identities and m.n_identities != first.n_identities:
            raise InputError(where, f"the {m.sensor_model} model reads the tags of {m.n_identities} robots, the "
                                    f"{first.sensor_model} model of {first.n_identities}: give both one site")


def check_sensor(model: Model, sensor: SensorModel, where: str, *, intensity: bool = True) -> None:
    """Refuse a live sensor that is not the scanner ``model`` was trained for, by the rules a log
    must meet (:func:`~gtsjax.io.logs.fit_beams` on the sensor's beams and the model's: the model's
    scanner name unless it is ``unknown``, the same angular step within 1 %, every beam inside the
    model's field of view, at most its beams). A live scan cannot be cropped, so a wider field of view
    is refused too. A model that reads intensities refuses a sensor that gives none, or a stream
    asked for without them (``intensity`` False)."""
    where = f"{where} ({sensor.name})"
    check_intensities(model, sensor.has_intensity and intensity, where)
    fit_beams(sensor.beams, model.beams, where, scanner=sensor.name, trained_for=model.sensor_model)
