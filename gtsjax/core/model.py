"""The trained model and the site, as the arrays the step needs: a pure parameter tree.

A :class:`Model` is what ``gtsjax train`` produces (front-end settings, per-class shape envelopes,
one score GP per class with its open-set examples, pose GPs per class, tracker tuning) plus the site it runs on (landmarks, the rough sensor pose, bounds),
attached with :meth:`Model.with_site` at load time: the same trained model serves any field with the
same kinds of landmarks. Shapes that must be static (class count, maximum tracks) are static fields;
everything a user may tune is an array, so tuning does not recompile the step.

Nothing here knows files, sensors' tables or command-line options: the replacers (``with_site``,
``with_confirmation``, ``with_capacity``) take values the host has checked. Reading a model from a
file and checking it against a site, the options and a sensor or log is the host's one door,
:mod:`gtsjax.drivers.setup`.
"""

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .c_filters import Envelope
from .d_classify import Classifier
from .e_pose import PoseRegressor
from .e_refine import Outline
from .e_tags import TagReader, patterns
from .frontend import FrontEndConfig
from .g_track import TrackerParams
from .scan import Beams

_F32 = jnp.float32

# Defaults of the model's tunable settings, the one home of these values (``gtsjax train`` starts from
# them): stage f's landmark association gate and the 2-D spread its landmarks need (m), the floor added
# to the pose GPs' variances ((5 mm)², (5 mm)², (1°)²), and the number of track slots.
DEFAULT_MAP_GATE = 0.4
DEFAULT_MAP_MIN_SPREAD = 0.3
DEFAULT_MEAS_VAR_FLOOR = (2.5e-5, 2.5e-5, 3e-4)
DEFAULT_MAX_TRACKS = 8


class SiteArrays(eqx.Module):
    """A site file as arrays: landmark positions in O and their class indices in the model."""

    landmark_xy: Float[Array, "landmarks 2"]
    landmark_class: Int[Array, " landmarks"]
    sensor_pose: Float[Array, "3"]
    bounds: Float[Array, "4"]
    has_bounds: Bool[Array, ""]


class Model(eqx.Module):
    """Everything the step needs, as a pytree of arrays."""

    frontend: FrontEndConfig
    classifier: Classifier
    envelope: Envelope  # per-class shape envelopes (stage c), applied before the classifier's argmax
    pose: tuple[PoseRegressor | None, ...]
    tracker: TrackerParams
    landmark_mask: Bool[Array, " classes"]  # which classes are static landmarks
    map_gate: Float[Array, ""]  # metres: landmark association gate of stage f
    map_min_spread: Float[Array, ""]  # metres: landmarks must spread at least this much in 2-D
    meas_var_floor: Float[Array, "3"]  # added to the GP variances: m², m², rad²
    site: SiteArrays | None
    classes: tuple[str, ...] = eqx.field(static=True)
    max_tracks: int = eqx.field(static=True)
    sensor_model: str = eqx.field(static=True)
    n_beams: int = eqx.field(static=True)
    # Candidates of each mobile class that get a pose per scan (the best by class score): the pose GPs'
    # variance is the step's costliest part, so it is computed for these only.
    max_objects: int = eqx.field(static=True, default=8)
    # The GP inputs (``d_classify.gp_inputs``) that varied over the training set; the others (the
    # intensity profile of a scanner without intensity) carry nothing and are left out of every kernel.
    gp_columns: tuple[int, ...] = eqx.field(static=True, default=())
    # The scanner geometry the model was trained on (beam ``i`` at ``angle_min + i * angle_increment``
    # in S, ``n_beams`` beams, returns inside ``[range_min, range_max]``): every input is checked
    # against it on the host (:func:`gtsjax.io.logs.fit_to_model`), never in the step.
    angle_min: float = eqx.field(static=True, default=float("nan"))
    angle_increment: float = eqx.field(static=True, default=float("nan"))
    range_min: float = eqx.field(static=True, default=0.0)
    range_max: float = eqx.field(static=True, default=float("inf"))
    # The mobile classes' learnt outlines and side hypotheses (stage e′); None: a model trained before
    # them, whose poses are the GP's.
    outline: Outline | None = None
    # The scan period (s) of the scanner ``sensor_model`` names, ``None`` for one of unknown rate; the
    # tracker counts missed scans in these periods (:func:`~gtsjax.core.g_track.track_step`). Never
    # saved (the file names its scanner): the host fills it in from its sensor table wherever a model
    # is loaded or trained (:func:`gtsjax.io.modelfile.with_scanner`).
    scan_period: float | None = eqx.field(static=True, default=None)
    # The same table's beams of that scanner, filled in likewise: the reach of a model from before its
    # own geometry was kept (:func:`~gtsjax.core.multi.laser_reach`).
    sensor_beams: Beams | None = eqx.field(static=True, default=None)
    # Reading reflective tags (stage e″, :mod:`~gtsjax.core.e_tags`): the reader, its identities' bands
    # from the site's tags; None: the model reads no tags. ``tag_names``: the identities' names, in
    # the order of the reader's patterns.
    tags: TagReader | None = None
    tag_names: tuple[str, ...] = eqx.field(static=True, default=())

    @property
    def n_identities(self) -> int:
        """How many robot identities the model's tags tell apart (0: it reads no tags)."""
        return 0 if self.tags is None else int(self.tags.pattern.shape[0])

    @property
    def beams(self) -> Beams:
        """The scanner geometry the model was trained on (its first angle and step NaN in a model
        from before that was kept), as sensors and logs give theirs."""
        return Beams(self.angle_min, self.angle_increment, self.n_beams, self.range_min, self.range_max)

    @property
    def n_classes(self) -> int:
        return len(self.classes)

    @property
    def uses_intensity(self) -> bool:
        """Whether the GPs read the intensity profile (eq. 12): the model was trained on scans that
        carried intensities, and every input it tracks must carry them too. Read from ``gp_columns``
        (the profile's columns are left out when it never varied, as on a scanner without intensity);
        a model from before ``gp_columns`` (empty) is not known to need them."""
        first = 1 + self.frontend.n_dist
        return any(first <= c < first + self.frontend.n_intensity for c in self.gp_columns)

    def class_index(self, name: str) -> int:
        return self.classes.index(name)

    def with_confirmation(self, n_scans: int | None) -> "Model":
        """The model with tracks confirmed (reported) only after ``n_scans`` scans of detections, more
        of them of the track's class than of anything else at its spot (``None``: as trained, half a
        second of scans). Longer confirmation keeps short-lived look-alikes of a robot (a chair seen
        for a moment) out of the ground truth and delays every real robot's first row as much.
        ``n_scans`` is at least 1 (the host checks a user's)."""
        if n_scans is None:
            return self
        return eqx.tree_at(lambda m: m.tracker.n_confirm, self, jnp.asarray(n_scans, jnp.int32))

    def with_capacity(self, max_tracks: int | None) -> "Model":
        """The model with ``max_tracks`` track slots, and as many candidates of each tracked class
        given a pose per scan (``max_objects``); ``None``: as trained. Nothing learnt depends on them:
        they are the step's array sizes, and a field with more robots than slots cannot track them all
        (a match of 10 robots on a model of 8). Each slot costs step time (the tracker's matrices grow
        with their square). ``max_tracks`` is at least 1 (the host checks a user's against its limit)."""
        if max_tracks is None:
            return self
        return dataclasses.replace(self, max_tracks=int(max_tracks), max_objects=int(max_tracks))

    def without_outline(self) -> "Model":
        """The model without its learnt outlines: no outline refinement (stage e′), every candidate's
        pose the GP's, its side hypotheses the GP's heading turned by quarter turns
        (``e_refine.DEFAULT_SIDES``). For comparison (``gtsjax evaluate --without-outline``)."""
        return eqx.tree_at(lambda m: m.outline, self, None, is_leaf=lambda x: x is None)

    def with_common_pose_inputs(self) -> "Model":
        """This model with each class's separate pose GPs also held as one
        :class:`~gtsjax.gp.sparse.CommonInputsGP` where they share their inputs
        (:meth:`~gtsjax.core.e_pose.PoseRegressor.with_common_inputs`): how a model file loads and
        training hands a model over. Host-side, outside any jit."""
        pose = tuple(None if r is None else r.with_common_inputs() for r in self.pose)
        return eqx.tree_at(lambda m: m.pose, self, pose, is_leaf=lambda x: x is None)

    @property
    def landmark_classes(self) -> tuple[str, ...]:
        """The classes that are static landmarks (host-side: reads ``landmark_mask``)."""
        return tuple(c for c, is_lm in zip(self.classes, np.asarray(self.landmark_mask), strict=True) if is_lm)

    def with_site(self, site) -> "Model":
        """Attach a site (anything with ``landmark_xy``, ``landmark_classes``, ``sensor_pose`` and
        ``bounds``: :class:`~gtsjax.io.site.Site`). Every landmark class must be one the model knows as
        a landmark class, or it could never be detected: a site that breaks this is a ``ValueError``
        here; the host refuses a user's first, naming the file (:func:`gtsjax.drivers.setup.attach_site`)."""
        unknown = sorted(set(site.landmark_classes) - set(self.landmark_classes))
        if unknown:
            raise ValueError(f"landmark class(es) {', '.join(unknown)} unknown to the model")
        arrays = SiteArrays(
            landmark_xy=jnp.asarray(site.landmark_xy, _F32),
            landmark_class=jnp.asarray([self.classes.index(c) for c in site.landmark_classes], jnp.int32),
            sensor_pose=jnp.asarray(site.sensor_pose, _F32),
            bounds=jnp.asarray(site.bounds if site.bounds is not None else (0.0, 0.0, 0.0, 0.0), _F32),
            has_bounds=jnp.asarray(site.bounds is not None),
        )
        model = eqx.tree_at(lambda m: m.site, self, arrays, is_leaf=lambda x: x is None)
        return model.with_tags(getattr(site, "tags", None))

    def with_tags(self, tags) -> "Model":
        """The model reading the bands of ``tags`` (a site's :class:`~gtsjax.io.site.SiteTags`: its robots'
        names, codes and offsets, ``offset_cells`` cells counter-clockwise from the outline's origin);
        ``None``: reading none. A model trained without tags reads none whatever the site says."""
        if self.tags is None:
            return self
        if tags is None:
            return dataclasses.replace(self, tags=None, tag_names=())
        codes = np.stack([np.asarray(w.bits, bool) for w in tags.robots])
        offsets = np.asarray([w.offset_cells / tags.cells for w in tags.robots], np.float32)
        reader = dataclasses.replace(self.tags, pattern=patterns(codes, offsets), cells=jnp.asarray(tags.cells, jnp.int32))
        return dataclasses.replace(self, tags=reader, tag_names=tuple(w.name for w in tags.robots))
