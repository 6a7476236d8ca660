"""Sensor models as data: the Hokuyo scanners gtsjax knows, and how to build one from a SCIP ``PP`` reply.

A scanner is described by the seven numbers its ``PP`` command reports (SCIP 2.0):

========  ===========================================================
``AMIN``  first measurable step
``AMAX``  last measurable step
``ARES``  steps per full revolution (angular resolution)
``AFRT``  step that points along the sensor's forward axis (x of S)
``DMIN``  shortest valid range, mm
``DMAX``  longest valid range, mm
``SCAN``  motor speed, revolutions per minute (one scan per revolution)
========  ===========================================================

Beam ``i`` (``0 <= i < n_beams``) is step ``AMIN + i`` and points at
``(AMIN + i - AFRT) * 2π / ARES`` radians, counter-clockwise from the forward axis (the ROS
LaserScan convention of frame S).

The range noise is the random error from one scan to the next (repeatability), plus the 1 mm
quantisation of the SCIP encoding. It is *not* the data sheets' accuracy figure: that bounds the
systematic error too, which depends on the target's colour and material and drifts as the sensor
warms up (Kneip et al., ICRA 2009), and which a model trained on the real robot among the real
landmarks largely absorbs (the map transformation re-estimates scale and offset every scan). For the
URG-04LX the figure is measured on a real unit's log by ``scripts/measure_range_noise.py`` (2 mm
below 1 m, 3.5 mm at 1.5–2 m, 6–7 mm at 2.5–4 m) and taken 1.5 times larger, to stay on the safe
side: 3 mm up to 1 m, 0.3 % of the range beyond. The URG-04LX-UG01's data sheet quotes three times
the URG-04LX's accuracy, so its noise is taken three times larger. The UTM-30LX's and UST-10LX's data
sheets quote a repeatability of σ < 10 mm, taken as 10 mm.
"""

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from .core.scan import Beams
from .errors import InputError


@dataclasses.dataclass(frozen=True)
class RangeNoise:
    """Range noise of a scanner: ``σ(r) = sigma`` up to ``knee`` metres, beyond it
    ``max(sigma_far, frac_far * r)``; ranges are reported in steps of ``resolution`` metres."""

    sigma: float
    knee: float = math.inf
    sigma_far: float = 0.0
    frac_far: float = 0.0
    resolution: float = 0.001

    def std(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, dtype=np.float64)
        far = np.maximum(self.sigma_far, self.frac_far * r)
        return np.where(r <= self.knee, self.sigma, far)


@dataclasses.dataclass(frozen=True)
class SensorModel:
    """One scanner model: geometry, range window, rate, noise and whether it reports intensity."""

    name: str
    amin: int
    amax: int
    ares: int
    afrt: int
    dmin_mm: int
    dmax_mm: int
    scan_rpm: int
    has_intensity: bool
    noise: RangeNoise

    def __post_init__(self):
        if not (0 <= self.amin <= self.amax < self.ares + self.amin and self.ares > 0):
            raise InputError(self.name, f"inconsistent steps AMIN={self.amin} AMAX={self.amax} ARES={self.ares}")
        if not (0 < self.dmin_mm < self.dmax_mm):
            raise InputError(self.name, f"inconsistent range window DMIN={self.dmin_mm} DMAX={self.dmax_mm}")
        if self.scan_rpm <= 0:
            raise InputError(self.name, f"SCAN must be positive, got {self.scan_rpm}")

    @property
    def n_beams(self) -> int:
        return self.amax - self.amin + 1

    @property
    def beams(self) -> Beams:
        """The scanner's beams (first angle, step, count, range window) as logs, models and scans give theirs."""
        return Beams(self.angle_min, self.angle_increment, self.n_beams, self.range_min, self.range_max)

    @property
    def angle_increment(self) -> float:
        return 2.0 * math.pi / self.ares

    @property
    def angle_min(self) -> float:
        return (self.amin - self.afrt) * self.angle_increment

    @property
    def angle_max(self) -> float:
        return self.beams.angle_max

    @property
    def angles(self) -> np.ndarray:
        """Beam angles in S, radians, float64 ``[n_beams]``."""
        return self.beams.angles()

    @property
    def range_min(self) -> float:
        return self.dmin_mm / 1000.0

    @property
    def range_max(self) -> float:
        return self.dmax_mm / 1000.0

    @property
    def period(self) -> float:
        """Seconds per scan."""
        return 60.0 / self.scan_rpm

    @property
    def rate_hz(self) -> float:
        return self.scan_rpm / 60.0

    def pp_fields(self) -> dict[str, str]:
        """The fields of this model's ``PP`` reply, as a sensor would send them."""
        return {
            "MODL": self.name,
            "DMIN": str(self.dmin_mm),
            "DMAX": str(self.dmax_mm),
            "ARES": str(self.ares),
            "AMIN": str(self.amin),
            "AMAX": str(self.amax),
            "AFRT": str(self.afrt),
            "SCAN": str(self.scan_rpm),
        }

    @classmethod
    def from_pp(cls, fields: Mapping[str, str], *, where: str = "PP reply") -> "SensorModel":
        """Build a model from the fields of a ``PP`` reply (values as strings, as sent).

        All of AMIN, AMAX, ARES, AFRT, DMIN, DMAX and SCAN are required. ``MODL`` picks the noise
        model and intensity capability of a known scanner; an unknown one gets a generic 1 % noise
        model and no intensity. Geometry always comes from the reply, never from the table.
        """
        required = ("AMIN", "AMAX", "ARES", "AFRT", "DMIN", "DMAX", "SCAN")
        missing = [k for k in required if k not in fields]
        if missing:
            raise InputError(where, f"missing field(s) {', '.join(missing)}")
        try:
            num = {k: int(str(fields[k]).strip()) for k in required}
        except ValueError as err:
            raise InputError(where, f"non-integer field value ({err})") from None
        modl = str(fields.get("MODL", "unknown")).strip()
        known = _match_known(modl)
        name = known.name if known is not None else (modl.split("(")[0].strip() or "unknown")
        noise = known.noise if known is not None else RangeNoise(sigma=0.01, knee=1.0, frac_far=0.01)
        return cls(
            name=name,
            amin=num["AMIN"],
            amax=num["AMAX"],
            ares=num["ARES"],
            afrt=num["AFRT"],
            dmin_mm=num["DMIN"],
            dmax_mm=num["DMAX"],
            scan_rpm=num["SCAN"],
            has_intensity=known.has_intensity if known is not None else False,
            noise=noise,
        )


URG_04LX = SensorModel(
    name="URG-04LX",
    amin=44, amax=725, ares=1024, afrt=384, dmin_mm=20, dmax_mm=5600, scan_rpm=600,
    has_intensity=False,
    noise=RangeNoise(sigma=0.003, knee=1.0, frac_far=0.003),
)
URG_04LX_UG01 = SensorModel(
    name="URG-04LX-UG01",
    amin=44, amax=725, ares=1024, afrt=384, dmin_mm=20, dmax_mm=5600, scan_rpm=600,
    has_intensity=False,
    noise=RangeNoise(sigma=0.009, knee=1.0, frac_far=0.009),
)
UTM_30LX = SensorModel(
    name="UTM-30LX",
    amin=0, amax=1080, ares=1440, afrt=540, dmin_mm=100, dmax_mm=30000, scan_rpm=2400,
    has_intensity=True,
    noise=RangeNoise(sigma=0.010, knee=10.0, sigma_far=0.015),
)
UST_10LX = SensorModel(
    name="UST-10LX",
    amin=0, amax=1080, ares=1440, afrt=540, dmin_mm=60, dmax_mm=10000, scan_rpm=2400,
    has_intensity=True,
    noise=RangeNoise(sigma=0.010),
)

MODELS: dict[str, SensorModel] = {m.name: m for m in (URG_04LX, URG_04LX_UG01, UTM_30LX, UST_10LX)}


def _match_known(modl: str) -> SensorModel | None:
    key = modl.upper()
    # Longest name first, so that "URG-04LX-UG01" is not taken for "URG-04LX", nor "UTM-30LX-EW" missed.
    for name in sorted(MODELS, key=len, reverse=True):
        if key.startswith(name):
            return MODELS[name]
    return None


def get_model(name: str) -> SensorModel:
    """The known model called ``name`` (case-insensitive; suffixes such as ``-EW`` accepted)."""
    model = _match_known(name.strip())
    if model is None:
        raise InputError(name, f"unknown sensor model; known: {', '.join(MODELS)}")
    return model


def with_scanner(model):
    """``model`` (a :class:`~gtsjax.core.model.Model`) with what this table says of the scanner its
    ``sensor_model`` names: its scan period (the tracker counts missed scans in it) and its beams (the
    reach of a model from before its own geometry was kept); ``None`` for a scanner the table does not
    know. Every loaded or trained model gets them (:func:`~gtsjax.io.modelfile.load_model`,
    :func:`~gtsjax.train.train`): the model file names its scanner and saves neither."""
    known = MODELS.get(model.sensor_model)
    if known is None:
        return dataclasses.replace(model, scan_period=None, sensor_beams=None)
    return dataclasses.replace(model, scan_period=1.0 / known.rate_hz, sensor_beams=known.beams)
