"""Site files (JSON, ``shared/spec/formats.md``): the field's static landmarks, the user's rough
guess of the sensor pose, and optional bounds for mobile objects.

Several lasers on one field extend the format with an optional ``sensors`` list, each
``{"name": str, "sensor_pose": [x, y, θ], "model": "URG-04LX" | …}`` (``model`` optional: any
scanner). A site with ``sensors`` may leave out the top-level ``sensor_pose``; it is then written as
the first sensor's, so that a program that knows one sensor still reads the file. A site without
``sensors`` is one sensor, named ``laser``, at ``sensor_pose``, exactly as before.

Robots wearing reflective tags (``docs/tags.md``) add an optional ``tags`` entry: ``{"cells": N,
"perimeter_m": P, "range_m": R (optional: the range the cells were sized for), "robots": [{"name",
"code", "offset_cells"}]}``, each code a string of ``1`` (tape) and ``0`` (body), cell 0 first, as in
``gtsjax tags``'s ``tags.json``; ``offset_cells`` (optional, 0) how many cells the band is turned as
mounted. ``gtsjax simulate`` writes it for scenes whose robots wear tags.
"""

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_write


@dataclasses.dataclass(frozen=True)
class Landmark:
    cls: str
    x: float
    y: float


@dataclasses.dataclass(frozen=True)
class SiteSensor:
    """One laser of a site: its name (unique in the site), rough pose guess s′ in O, scanner model
    (``None``: any)."""

    name: str
    pose: tuple[float, float, float]
    model: str | None = None


@dataclasses.dataclass(frozen=True)
class TagWearer:
    """One robot's band: its name, its code (``1`` tape, ``0`` body, cell 0 first) and how many cells
    the band is turned as mounted (its cell 0 over the outline's cell ``offset_cells``)."""

    name: str
    code: str
    offset_cells: int = 0

    @property
    def bits(self) -> np.ndarray:
        return np.array([c == "1" for c in self.code], bool)


@dataclasses.dataclass(frozen=True)
class SiteTags:
    """The reflective tags a site's robots wear: bands of ``cells`` cells around an outline of
    ``perimeter_m``, sized for ``range_m`` (``None``: not said), one per robot."""

    cells: int
    perimeter_m: float
    robots: tuple[TagWearer, ...]
    range_m: float | None = None

    def to_json(self) -> dict:
        return {"cells": self.cells, "perimeter_m": self.perimeter_m,
                **({"range_m": self.range_m} if self.range_m is not None else {}),
                "robots": [{"name": w.name, "code": w.code, "offset_cells": w.offset_cells} for w in self.robots]}

    def code_of(self, name: str) -> np.ndarray | None:
        """The named robot's code as a bool array, ``None`` for a robot without one."""
        return next((w.bits for w in self.robots if w.name == name), None)


#: The name of a site's only sensor when the file has no ``sensors`` list.
DEFAULT_SENSOR = "laser"


@dataclasses.dataclass(frozen=True)
class Site:
    """A field: landmarks in O, the rough sensor pose s′ = (x, y, θ) in O, optional bounds, and the
    optional ``sensors`` list of a site with several lasers (``sensor_pose`` is then the first's)."""

    landmarks: tuple[Landmark, ...]
    sensor_pose: tuple[float, float, float]
    bounds: tuple[float, float, float, float] | None = None
    extra: dict = dataclasses.field(default_factory=dict, compare=False)
    sensors: tuple[SiteSensor, ...] = ()
    tags: SiteTags | None = None

    @property
    def sensor_list(self) -> tuple[SiteSensor, ...]:
        """Every laser of the site: the ``sensors`` list, or the one at ``sensor_pose``."""
        return self.sensors or (SiteSensor(DEFAULT_SENSOR, tuple(self.sensor_pose)),)

    def sensor(self, name: str) -> SiteSensor:
        for sen in self.sensor_list:
            if sen.name == name:
                return sen
        raise InputError("site", f"has no sensor named {name!r} (it has {', '.join(s.name for s in self.sensor_list)})")

    def for_sensor(self, name: str) -> "Site":
        """This site as seen by one of its lasers: ``sensor_pose`` that sensor's guess, no ``sensors``
        list (what a single-sensor model and the step take)."""
        sen = self.sensor(name)
        return dataclasses.replace(self, sensor_pose=tuple(sen.pose), sensors=())

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
        if self.sensors:
            out["sensors"] = [{"name": sen.name, "sensor_pose": list(sen.pose),
                               **({"model": sen.model} if sen.model is not None else {})} for sen in self.sensors]
        if self.tags is not None:
            out["tags"] = self.tags.to_json()
        return out

    def validate(self, where: object = "site") -> "Site":
        _check(self.to_json(), where)
        return self


def one_sensor(site: Site, name: str | None, where: object = "site") -> Site:
    """``site`` for the scans of one of its lasers (:meth:`Site.for_sensor`): the one named, or the
    only one; a site with several and no name is one line asking for ``--laser NAME``."""
    if name is not None:
        try:
            return site.for_sensor(name)
        except InputError as err:
            raise InputError(where, err.problem) from None
    if len(site.sensor_list) > 1:
        names = ", ".join(sen.name for sen in site.sensor_list)
        raise InputError(where, f"has {len(site.sensor_list)} sensors ({names}): name the one the scans are from "
                                "with --laser NAME")
    return site.for_sensor(site.sensor_list[0].name)


def save_site(site: Site, path: str | os.PathLike) -> None:
    path = Path(path)
    site.validate(path)
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(json.dumps(site.to_json(), indent=2) + "\n")


def load_site(path: str | os.PathLike) -> Site:
    """Read and validate a site file; raise :class:`InputError` naming ``path`` on any broken rule."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    try:
        doc = json.loads(path.read_bytes().decode("utf-8-sig"))  # a byte-order mark, as Windows editors write, is no content
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(path, f"not a JSON site file ({type(err).__name__}: {err})") from None
    except RecursionError:
        raise InputError(path, "not a site file: JSON nested deeper than Python reads") from None
    except ValueError as err:  # an integer of thousands of digits
        raise InputError(path, f"not a site file: a number too long to read ({str(err).split(':')[0]})") from None
    except IsADirectoryError:
        raise InputError(path, "is a directory, not a JSON site file") from None
    except OSError as err:  # no permission to read it, a socket, a device that fails
        raise InputError(path, f"cannot be read ({err.strerror or err})") from None
    return parse_site(doc, path)


def parse_site(doc: object, where: object = "site") -> Site:
    _check(doc, where)
    assert isinstance(doc, dict)
    landmarks = tuple(Landmark(str(lm["class"]), float(lm["x"]), float(lm["y"])) for lm in doc["landmarks"])
    bounds = tuple(float(v) for v in doc["bounds"]) if doc.get("bounds") is not None else None
    extra = {k: v for k, v in doc.items() if k not in ("landmarks", "sensor_pose", "bounds", "sensors", "tags")}
    sensors = tuple(SiteSensor(str(sen["name"]), tuple(float(v) for v in sen["sensor_pose"]),  # type: ignore[arg-type]
                               None if sen.get("model") is None else str(sen["model"]))
                    for sen in doc.get("sensors") or ())
    pose = doc.get("sensor_pose")
    pose = tuple(float(v) for v in pose) if pose is not None else sensors[0].pose
    tags = None
    if (t := doc.get("tags")) is not None:
        tags = SiteTags(int(t["cells"]), float(t["perimeter_m"]),
                        tuple(TagWearer(str(w["name"]), str(w["code"]), int(w.get("offset_cells") or 0))
                              for w in t["robots"]),
                        None if t.get("range_m") is None else float(t["range_m"]))
    return Site(landmarks, pose, bounds, extra, sensors, tags)  # type: ignore[arg-type]


# Coordinates (and the heading) of a site beyond this are a mistake (a unit, an exponent), not a field:
# 10 km, where float32 still resolves 1 mm, and the step's float32 arithmetic neither overflows nor
# loses the landmarks' spread.
MAX_COORD = 1e4


def _is_num(v: object) -> bool:
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer beyond any float
        return False


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
    if "landmarks" not in doc:
        bad("missing required key 'landmarks'")
    if "sensor_pose" not in doc and not doc.get("sensors"):
        bad("missing required key 'sensor_pose' (or a 'sensors' list)")
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
    if "sensor_pose" in doc:
        _check_pose(bad, doc["sensor_pose"], "'sensor_pose'")
    if doc.get("sensors") is not None:
        _check_sensors(bad, doc["sensors"])
    if doc.get("tags") is not None:
        _check_tags(bad, doc["tags"])
    if doc.get("bounds") is not None:
        b = doc["bounds"]
        if not (isinstance(b, list) and len(b) == 4 and all(_is_num(v) for v in b)):
            bad("'bounds' must be [xmin, ymin, xmax, ymax], four finite numbers")
        _check_size(bad, b, ("xmin", "ymin", "xmax", "ymax"), "'bounds'")
        if not (b[0] < b[2] and b[1] < b[3]):
            bad(f"'bounds' {b} must have xmin < xmax and ymin < ymax")


def _check_pose(bad, pose, what: str) -> None:
    if not (isinstance(pose, list) and len(pose) == 3 and all(_is_num(v) for v in pose)):
        bad(f"{what} must be [x, y, theta], three finite numbers")
    _check_size(bad, pose, ("x", "y", "theta"), what)


def _check_sensors(bad, sensors) -> None:
    if not isinstance(sensors, list) or not sensors:
        bad("'sensors' must be a non-empty list of {\"name\", \"sensor_pose\", \"model\"} objects")
    names = set()
    for i, sen in enumerate(sensors):
        if not isinstance(sen, dict):
            bad(f"sensor {i} must be an object with 'name' and 'sensor_pose'")
        for k in ("name", "sensor_pose"):
            if k not in sen:
                bad(f"sensor {i} is missing '{k}'")
        name = sen["name"]
        if not isinstance(name, str) or not name or "=" in name or "," in name:
            bad(f"sensor {i}: 'name' must be a non-empty string without '=' or ','")
        if name in names:
            bad(f"sensor {i}: the name {name!r} is used twice")
        names.add(name)
        _check_pose(bad, sen["sensor_pose"], f"sensor {name!r}: 'sensor_pose'")
        model = sen.get("model")
        if model is not None:
            from ..sensors import MODELS

            if model not in MODELS:
                bad(f"sensor {name!r}: unknown scanner model {model!r} (known: {', '.join(sorted(MODELS))})")


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_tags(bad, tags) -> None:
    shape = '{"cells", "perimeter_m", "robots": [{"name", "code", "offset_cells"}]}'
    if not isinstance(tags, dict):
        bad(f"'tags' must be an object {shape}")
    for k in ("cells", "perimeter_m", "robots"):
        if k not in tags:
            bad(f"'tags' is missing '{k}' ({shape})")
    n = tags["cells"]
    if not _is_int(n) or not 2 <= n <= 64:
        bad(f"'tags': 'cells' must be a whole number from 2 to 64, got {n!r}")
    for k in ("perimeter_m", "range_m"):
        v = tags.get(k)
        if (k == "perimeter_m" or v is not None) and not (_is_num(v) and 0 < v <= MAX_COORD):
            bad(f"'tags': '{k}' must be a positive number of metres, got {v!r}")
    robots = tags["robots"]
    if not isinstance(robots, list) or not robots:
        bad("'tags': 'robots' must be a non-empty list of {\"name\", \"code\", \"offset_cells\"} objects")
    names = set()
    for i, w in enumerate(robots):
        if not isinstance(w, dict) or "name" not in w or "code" not in w:
            bad(f"'tags': robot {i} must be an object with 'name' and 'code'")
        name, code, off = w["name"], w["code"], w.get("offset_cells", 0)
        if not isinstance(name, str) or not name:
            bad(f"'tags': robot {i}: 'name' must be a non-empty string")
        if name in names:
            bad(f"'tags': robot {i}: the name {name!r} is used twice")
        names.add(name)
        if not (isinstance(code, str) and len(code) == n and set(code) <= {"0", "1"}):
            bad(f"'tags': robot {name!r}: 'code' must be a string of {n} '0' (body) and '1' (tape), cell 0 first, "
                f"got {code!r}")
        if off is not None and not (_is_int(off) and 0 <= off < n):
            bad(f"'tags': robot {name!r}: 'offset_cells' must be a whole number from 0 to {n - 1}, got {off!r}")
