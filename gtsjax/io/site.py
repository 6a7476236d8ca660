"""Site files (JSON, ``shared/spec/formats.md``): the field's static landmarks, the user's rough
guess of the sensor pose, and optional bounds for mobile objects."""

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from ..errors import InputError


@dataclasses.dataclass(frozen=True)
class Landmark:
    cls: str
    x: float
    y: float


@dataclasses.dataclass(frozen=True)
class Site:
    """A field: landmarks in O, the rough sensor pose s′ = (x, y, θ) in O, optional bounds."""

    landmarks: tuple[Landmark, ...]
    sensor_pose: tuple[float, float, float]
    bounds: tuple[float, float, float, float] | None = None
    extra: dict = dataclasses.field(default_factory=dict, compare=False)

    @property
    def landmark_xy(self) -> np.ndarray:
        """Landmark positions in O, float64 ``[n_landmarks, 2]``."""
        return np.array([[lm.x, lm.y] for lm in self.landmarks], dtype=np.float64)

    @property
    def landmark_classes(self) -> tuple[str, ...]:
        return tuple(lm.cls for lm in self.landmarks)

    def to_json(self) -> dict:
        out = dict(self.extra)
        out["landmarks"] = [{"class": lm.cls, "x": lm.x, "y": lm.y} for lm in self.landmarks]
        out["sensor_pose"] = list(self.sensor_pose)
        if self.bounds is not None:
            out["bounds"] = list(self.bounds)
        return out

    def validate(self, where: object = "site") -> "Site":
        _check(self.to_json(), where)
        return self


def save_site(site: Site, path: str | os.PathLike) -> None:
    path = Path(path)
    site.validate(path)
    path.write_text(json.dumps(site.to_json(), indent=2) + "\n")


def load_site(path: str | os.PathLike) -> Site:
    """Read and validate a site file; raise :class:`InputError` naming ``path`` on any broken rule."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(path, f"not a JSON site file ({type(err).__name__}: {err})") from None
    except IsADirectoryError:
        raise InputError(path, "is a directory, not a JSON site file") from None
    return parse_site(doc, path)


def parse_site(doc: object, where: object = "site") -> Site:
    _check(doc, where)
    assert isinstance(doc, dict)
    landmarks = tuple(Landmark(str(lm["class"]), float(lm["x"]), float(lm["y"])) for lm in doc["landmarks"])
    bounds = tuple(float(v) for v in doc["bounds"]) if doc.get("bounds") is not None else None
    extra = {k: v for k, v in doc.items() if k not in ("landmarks", "sensor_pose", "bounds")}
    return Site(landmarks, tuple(float(v) for v in doc["sensor_pose"]), bounds, extra)  # type: ignore[arg-type]


# Coordinates (and the heading) of a site beyond this are a mistake (a unit, an exponent), not a field:
# 10 km, where float32 still resolves 1 mm, and the step's float32 arithmetic neither overflows nor
# loses the landmarks' spread.
MAX_COORD = 1e4


def _is_num(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_size(bad, values, names, where: str) -> None:
    for v, name in zip(values, names, strict=True):
        if abs(v) > MAX_COORD:
            unit = "rad" if name == "theta" else "m"
            bad(f"{where} {name} is {v:g}, beyond ±{MAX_COORD:g} {unit}; site coordinates are metres in the field frame")


def _check(doc: object, where: object) -> None:
    def bad(problem: str):
        raise InputError(where, problem)

    if not isinstance(doc, dict):
        bad(f"top level must be a JSON object, got {type(doc).__name__}")
    for key in ("landmarks", "sensor_pose"):
        if key not in doc:
            bad(f"missing required key '{key}'")
    lms = doc["landmarks"]
    if not isinstance(lms, list):
        bad("'landmarks' must be a list")
    for i, lm in enumerate(lms):
        if not isinstance(lm, dict):
            bad(f"landmark {i} must be an object with 'class', 'x', 'y'")
        for k in ("class", "x", "y"):
            if k not in lm:
                bad(f"landmark {i} is missing '{k}'")
        if not isinstance(lm["class"], str) or not lm["class"]:
            bad(f"landmark {i}: 'class' must be a non-empty string")
        if not (_is_num(lm["x"]) and _is_num(lm["y"])):
            bad(f"landmark {i}: 'x' and 'y' must be finite numbers")
        _check_size(bad, (lm["x"], lm["y"]), ("'x'", "'y'"), f"landmark {i}:")
    if len(lms) < 3:
        bad(f"needs at least 3 landmarks, got {len(lms)}")
    xy = np.array([[lm["x"], lm["y"]] for lm in lms], dtype=np.float64)
    centred = xy - xy.mean(0)
    sv = np.linalg.svd(centred, compute_uv=False)
    # Not on one line: the smaller singular value of the centred positions must be a real spread
    # (1 mm RMS across the best-fit line), else the map transformation (eq. 2) is singular.
    if sv[1] / math.sqrt(len(lms)) < 1e-3:
        bad("all landmarks lie on one line; the map transformation needs them spread in 2-D")
    pose = doc["sensor_pose"]
    if not (isinstance(pose, list) and len(pose) == 3 and all(_is_num(v) for v in pose)):
        bad("'sensor_pose' must be [x, y, theta], three finite numbers")
    _check_size(bad, pose, ("x", "y", "theta"), "'sensor_pose'")
    if doc.get("bounds") is not None:
        b = doc["bounds"]
        if not (isinstance(b, list) and len(b) == 4 and all(_is_num(v) for v in b)):
            bad("'bounds' must be [xmin, ymin, xmax, ymax], four finite numbers")
        _check_size(bad, b, ("xmin", "ymin", "xmax", "ymax"), "'bounds'")
        if not (b[0] < b[2] and b[1] < b[3]):
            bad(f"'bounds' {b} must have xmin < xmax and ymin < ymax")
