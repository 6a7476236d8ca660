"""Settings of ``gtsjax train`` (:class:`TrainConfig`).

A setting the trained :class:`~gtsjax.core.model.Model` carries (front-end settings, the classifier's
threshold, stage f's gate and spread, the variance floor, the track slots) takes its default from the
core's own definition, so that a default lives in one place; the rest are training's alone (example
caps, inducing points, fits, the held-out split, the labelling radii).
"""

import dataclasses

from ..core.d_classify import DEFAULT_THRESHOLD
from ..core.frontend import FrontEndConfig
from ..core.model import DEFAULT_MAP_GATE, DEFAULT_MAP_MIN_SPREAD, DEFAULT_MAX_TRACKS, DEFAULT_MEAS_VAR_FLOOR
from ..errors import InputError


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Settings of ``gtsjax train``; the defaults are those the shipped results use."""

    frontend: FrontEndConfig = dataclasses.field(default_factory=FrontEndConfig)
    max_per_class: int = 500  # classifier examples per class (balanced and capped)
    # Pose GPs of a mobile class: conditioned on up to max_pose_examples examples, their
    # hyperparameters fitted on a subsample of max_pose_fit of them (``gp.fit``'s max_fit_points).
    # Heading accuracy grows with the examples the posterior sees (on the SPL field, from 2 000 to
    # 6 000: held-out median 2.6° -> 1.9°, misreads 7.1 % -> 5.0 %), while the fit's cost grows with
    # the cube of the examples it sees; the step's cost grows linearly with max_pose_examples.
    max_pose_examples: int = 6000
    max_pose_fit: int = 2000
    # Kernels of a mobile class's four pose GPs (x, y, sin, cos): 4 = each its own; 2 = the position pair
    # and the heading pair each share one (shared length scales, each GP its own signal and noise
    # variance, fitted jointly on the sum of their LMLs: gp.fit_shared), two kernel rows per robot
    # candidate in the step instead of four; 1 = all four share one. Sharing saves a part of the step
    # but, on the shipped model's data, cost tracked heading accuracy (the GP misreads in other
    # directions and the side hypotheses learnt from them differ; figures in docs/speed.md), so
    # each its own stays the default until that is understood.
    pose_kernels: int = 4
    max_landmark_examples: int = 500  # position-GP training examples per landmark class (simple shapes)
    # Inducing points of each GP's predictive mean: they bound the step's cost per candidate whatever
    # the training set, and a GP trained on this many examples or fewer predicts its exact mean. The
    # mobile classes' pose GPs run on a few candidates per scan (the model's max_objects) and get the
    # most, since heading accuracy depends on them; the classifier's GPs run on every candidate and
    # the landmark classes' position GPs learn a simple shape: they get fewer. The pose GPs' variance
    # (O(M^2) per candidate) uses the first n_inducing_var.
    n_inducing: int = 6144
    n_inducing_class: int = 2048
    n_inducing_var: int = 64
    restarts: int = 3  # optimiser starts per GP fit
    # Classifier: with background logs, the background class gets max_background examples (None: twelve
    # times max_per_class), as varied as real clutter is, and each mobile class max_mobile (None: four
    # times max_per_class): as many views of the robot as of clutter of its size keep a robot's score up
    # where clutter looks like it. Without background logs, both are max_per_class. With more than
    # max_class_fit examples in all, the hyperparameters are fitted on a subsample of that many and
    # the GPs conditioned on all of them.
    max_background: int | None = None
    max_mobile: int | None = None
    max_class_fit: int | None = 1500
    support_size: int = 512  # open-set test: training examples kept per class
    # Motion limits per class (m/s, rad/s) that override what labelled motion, or the tracker's default
    # (``g_track.DEFAULT_MAX_SPEED``, ``DEFAULT_MAX_TURN_RATE``), gives.
    max_speed: dict[str, float] = dataclasses.field(default_factory=dict)
    max_turn_rate: dict[str, float] = dataclasses.field(default_factory=dict)
    # A class's heading symmetry, overriding what its outline shows (``train.outline.half_turn_symmetry``):
    # 1, its front told from its back; 2, alike turned half a turn (its heading read modulo 180°).
    heading_turns: dict[str, int] = dataclasses.field(default_factory=dict)
    scan_rate_hz: float | None = None  # the scanner's rate (None: from the logs, ``train.motion.scan_rate_entry``)
    # After fitting, replay the labelled logs through the whole step and score tracking (``train.check``).
    check_pipeline: bool = True
    holdout: float = 0.2  # fraction of one-second blocks held out for evaluation
    label_radius: float = 0.3  # m: a candidate this close to a labelled object is that object
    landmark_radius: float = 0.25  # m: a candidate this close to a site landmark is that landmark
    bounds_margin: float | None = 0.5  # m: background examples only this far outside the site's bounds
    threshold: float = DEFAULT_THRESHOLD  # every class's score threshold (``Classifier.threshold``)
    map_gate: float = DEFAULT_MAP_GATE  # m: landmark association gate of stage f (``Model.map_gate``)
    map_min_spread: float = DEFAULT_MAP_MIN_SPREAD  # m: associated landmarks must spread this much in 2-D
    meas_var_floor: tuple[float, float, float] = DEFAULT_MEAS_VAR_FLOOR  # m², m², rad² (``Model.meas_var_floor``)
    # Noise floor of every GP, relative to its signal variance. Many scans of one static pose give
    # near-duplicate inputs with equal targets; without a floor the likelihood is maximised by
    # interpolating them (σn² → 0, tiny length scales), which generalises badly to new poses.
    noise_floor: float = 1e-2
    max_tracks: int = DEFAULT_MAX_TRACKS  # track slots (``Model.max_tracks``)
    seed: int = 0

    def __post_init__(self):
        if self.pose_kernels not in (1, 2, 4):
            raise InputError("--pose-kernels", f"must be 1, 2 or 4 (kernels of the four pose GPs), got {self.pose_kernels}")
