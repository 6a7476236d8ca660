"""Scan logs in the ``.npz`` format of ``shared/spec/formats.md``: load, validate, save, and convert
to the padded :class:`~gtsjax.Scan` arrays the numeric core takes.

Every rule of the format is checked on load; a file that breaks one raises :class:`InputError` with a
single line naming the file and the rule. Keys the format does not know are kept (``ScanLog.extra``)
and written back on save, so other programs' additions survive a round trip.
"""

import dataclasses
import math
import os
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import numpy as np

from ..core.scan import Beams
from ..errors import InputError, InputWarning
from .atomic import atomic_write
from .kinds import not_expected
from .npz import check_npz

REQUIRED = ("ranges", "stamps", "angle_min", "angle_increment")
OPTIONAL = ("intensities", "range_min", "range_max", "sensor_model", "truth_classes", "truth_poses")
DEFAULT_RANGE_MIN = 0.02
DEFAULT_RANGE_MAX = 30.0


#: Optional keys of a scan log (``ScanLog.extra``) that hold one row per scan: the simulator's truth of
#: the sensor's pose. A slice of the log cuts them with the scans; other keys are kept whole.
PER_SCAN_EXTRAS = ("truth_sensor_pose",)


@dataclasses.dataclass
class ScanLog:
    """A scan log in memory (NumPy arrays, host side). Shapes: ``T`` scans, ``N`` beams, ``M`` labelled objects."""

    ranges: np.ndarray  # float32 [T, N]
    stamps: np.ndarray  # float64 [T]
    angle_min: float
    angle_increment: float
    intensities: np.ndarray | None = None  # float32 [T, N]
    range_min: float = DEFAULT_RANGE_MIN
    range_max: float = DEFAULT_RANGE_MAX
    sensor_model: str | None = None
    truth_classes: np.ndarray | None = None  # str [M]
    truth_poses: np.ndarray | None = None  # float64 [T, M, 3]
    extra: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def n_scans(self) -> int:
        return self.ranges.shape[0]

    @property
    def n_beams(self) -> int:
        return self.ranges.shape[1]

    @property
    def labelled(self) -> bool:
        return self.truth_poses is not None

    @property
    def beams(self) -> Beams:
        """The log's scanner geometry: first angle, step, beams per scan, range window."""
        return Beams(self.angle_min, self.angle_increment, self.n_beams, self.range_min, self.range_max)

    def angles(self) -> np.ndarray:
        return self.beams.angles()

    def valid(self) -> np.ndarray:
        """Beams with a return (:meth:`~gtsjax.core.scan.Beams.valid`)."""
        return self.beams.valid(self.ranges)

    def slice(self, start: int, stop: int) -> "ScanLog":
        """Scans ``start:stop`` as a log of their own (with the optional keys that hold a row per scan,
        :data:`PER_SCAN_EXTRAS`, cut alike)."""
        s = np.s_[start:stop]
        return dataclasses.replace(
            self,
            ranges=self.ranges[s],
            stamps=self.stamps[s],
            intensities=None if self.intensities is None else self.intensities[s],
            truth_poses=None if self.truth_poses is None else self.truth_poses[s],
            extra={k: v[s] if k in PER_SCAN_EXTRAS else v for k, v in self.extra.items()},
        )

    def to_dict(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = dict(self.extra)
        out["ranges"] = np.asarray(self.ranges, dtype=np.float32)
        out["stamps"] = np.asarray(self.stamps, dtype=np.float64)
        out["angle_min"] = np.asarray(self.angle_min, dtype=np.float64)
        out["angle_increment"] = np.asarray(self.angle_increment, dtype=np.float64)
        out["range_min"] = np.asarray(self.range_min, dtype=np.float64)
        out["range_max"] = np.asarray(self.range_max, dtype=np.float64)
        if self.intensities is not None:
            out["intensities"] = np.asarray(self.intensities, dtype=np.float32)
        if self.sensor_model is not None:
            out["sensor_model"] = np.asarray(self.sensor_model, dtype=np.str_)
        if self.truth_poses is not None:
            out["truth_classes"] = np.asarray(self.truth_classes, dtype=np.str_)
            out["truth_poses"] = np.asarray(self.truth_poses, dtype=np.float64)
        return out

    def validate(self, where: object = "scan log") -> "ScanLog":
        """Check every rule of the format; raise :class:`InputError` naming ``where`` on the first broken one."""
        _validate(self.to_dict(), where)
        return self


def save_log(log: ScanLog, path: str | os.PathLike) -> None:
    """Write ``log`` as an ``.npz`` per the spec. The file appears whole or not at all (written to a
    temporary name, then renamed), so a crash never leaves a half-written log under ``path``."""
    path = Path(path)
    log.validate(path)
    with atomic_write(path) as f:  # a full disk (or Ctrl-C) leaves the previous file, and no .part
        np.savez(f, **log.to_dict())


def load_log(path: str | os.PathLike) -> ScanLog:
    """Read and validate a scan log; raise :class:`InputError` (one line, naming ``path``) if it breaks the format."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, "is a directory, not a .npz scan log")
    check_npz(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {}
            for key in npz.files:
                try:
                    data[key] = npz[key]
                except ValueError:
                    raise InputError(
                        path, f"key '{key}' holds pickled Python objects, which the format forbids"
                    ) from None
    except InputError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as err:
        if isinstance(err, OSError) and err.errno is not None:  # no permission, a socket: the file, not its format
            raise InputError(path, f"cannot be read ({err.strerror})") from None
        if (other := not_expected(path, "a .npz scan log")) is not None:  # a PNG, a CSV, a bag: named as info names it
            raise InputError(path, other) from None
        what = type(err).__name__
        if isinstance(err, zipfile.BadZipFile):  # what zipfile found: "Bad CRC-32 for file 'ranges.npy'", ...
            what += ": " + " ".join(str(err).split())[:120]
        raise InputError(path, f"not a NumPy .npz archive ({what})") from None
    if not isinstance(data, dict) or not data:
        raise InputError(path, "empty archive, not a scan log")
    _validate(data, path)
    if data["stamps"].dtype != np.float64:
        warnings.warn(InputWarning(path, f"'stamps' are {data['stamps'].dtype}, not float64 as the format says; read "
                                         "as float64 (each stamp is still later than the one before)"), stacklevel=2)
    extra = {k: v for k, v in data.items() if k not in REQUIRED + OPTIONAL}
    has_truth = "truth_poses" in data
    return ScanLog(
        ranges=data["ranges"].astype(np.float32, copy=False),
        stamps=data["stamps"].astype(np.float64, copy=False),
        angle_min=float(data["angle_min"]),
        angle_increment=float(data["angle_increment"]),
        intensities=data["intensities"].astype(np.float32, copy=False) if "intensities" in data else None,
        range_min=float(data["range_min"]) if "range_min" in data else DEFAULT_RANGE_MIN,
        range_max=float(data["range_max"]) if "range_max" in data else DEFAULT_RANGE_MAX,
        sensor_model=str(data["sensor_model"]) if "sensor_model" in data else None,
        truth_classes=data["truth_classes"].astype(np.str_) if has_truth else None,
        truth_poses=data["truth_poses"].astype(np.float64, copy=False) if has_truth else None,
        extra=extra,
    )


def _validate(d: dict[str, np.ndarray], where: object) -> None:
    """Every rule of the format, raising :class:`InputError` naming ``where`` on the first broken one, in
    a fixed order (a file that breaks several always gets the same line): ``ranges`` before the keys
    whose shapes are checked against it."""
    def bad(problem: str):
        raise InputError(where, problem)

    if "gtsjax_model" in d:
        bad("a gtsjax model file, not a scan log")
    missing = [k for k in REQUIRED if k not in d]
    if missing:
        bad(f"missing required key(s) {', '.join(repr(k) for k in missing)}")
    ranges = _check_ranges(d, bad)
    t = ranges.shape[0]
    _check_stamps(d, t, bad)
    _check_geometry(d, bad)
    if "intensities" in d:
        _check_intensities(d, ranges, bad)
    if "sensor_model" in d:
        sm = np.asarray(d["sensor_model"])
        if sm.shape != () or sm.dtype.kind != "U":
            bad(f"'sensor_model' must be a string scalar, got {sm.dtype} of shape {list(sm.shape)}")
    _check_truth(d, t, bad)


def _check_ranges(d: dict[str, np.ndarray], bad: Callable[[str], NoReturn]) -> np.ndarray:
    """``ranges``: float, ``[T, N]``, not empty; returned, since every other key's shape follows from it."""
    ranges = np.asarray(d["ranges"])
    if ranges.dtype.kind != "f":
        bad(f"'ranges' must be float32, got {ranges.dtype}")
    if ranges.ndim != 2:
        bad(f"'ranges' must have shape [T, N], got shape {list(ranges.shape)}")
    t, n = ranges.shape
    if t == 0 or n == 0:
        bad(f"'ranges' is empty (shape {list(ranges.shape)})")
    return ranges


def _check_stamps(d: dict[str, np.ndarray], t: int, bad: Callable[[str], NoReturn]) -> None:
    """``stamps``: float, one per scan, finite and never decreasing; a rule of its own since stamps
    rounded to float32 get their own message (the rounding, not the recorder, lost the time)."""
    stamps = np.asarray(d["stamps"])
    if stamps.dtype.kind != "f":
        bad(f"'stamps' must be float64, got {stamps.dtype}")
    if stamps.dtype != np.float64 and t > 1 and stamps.shape == (t,) and np.any(np.diff(stamps) <= 0):
        # Seconds since 1970 in float32 step by 128 s: every scan of a minute gets one stamp.
        i = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 1
        bad(f"'stamps' are {stamps.dtype} (the format says float64) and scan {i} has no later stamp than the one "
            f"before ({float(stamps[i - 1])!r}): the rounding lost the time; write the stamps as float64")
    if stamps.shape != (t,):
        bad(f"'stamps' must have shape [{t}] to match 'ranges', got {list(stamps.shape)}")
    if not np.all(np.isfinite(stamps)):
        i = int(np.flatnonzero(~np.isfinite(stamps))[0])
        bad(f"'stamps' has a non-finite value at scan {i}")
    if t > 1 and np.any(np.diff(stamps) < 0):
        i = int(np.flatnonzero(np.diff(stamps) < 0)[0]) + 1
        bad(f"'stamps' decrease at scan {i} ({stamps[i - 1]!r} -> {stamps[i]!r})")


def _check_geometry(d: dict[str, np.ndarray], bad: Callable[[str], NoReturn]) -> None:
    """The scanner's scalars: finite numbers, a positive angular step and a non-empty range window
    (the defaults standing in for a missing one), the geometry every scan shares."""
    for key in ("angle_min", "angle_increment", "range_min", "range_max"):
        if key not in d:
            continue
        v = np.asarray(d[key])
        if v.shape != () or v.dtype.kind not in "fiu":
            bad(f"'{key}' must be a float64 scalar, got {v.dtype} of shape {list(v.shape)}")
        if not np.isfinite(v):
            bad(f"'{key}' is not finite")
    if not float(d["angle_increment"]) > 0:
        bad(f"'angle_increment' must be > 0, got {float(d['angle_increment'])}")
    rmin = float(d.get("range_min", DEFAULT_RANGE_MIN))
    rmax = float(d.get("range_max", DEFAULT_RANGE_MAX))
    if not 0 <= rmin < rmax:
        bad(f"range window [{rmin}, {rmax}] is empty or negative")


def _check_intensities(d: dict[str, np.ndarray], ranges: np.ndarray, bad: Callable[[str], NoReturn]) -> None:
    """``intensities`` (optional): float, one per range, finite and not negative."""
    inten = np.asarray(d["intensities"])
    if inten.dtype.kind != "f":
        bad(f"'intensities' must be float32, got {inten.dtype}")
    if inten.shape != ranges.shape:
        bad(f"'intensities' must have the shape of 'ranges' {list(ranges.shape)}, got {list(inten.shape)}")
    if not np.all(np.isfinite(inten)) or np.any(inten < 0):
        bad("'intensities' must be finite and >= 0")


def _check_truth(d: dict[str, np.ndarray], t: int, bad: Callable[[str], NoReturn]) -> None:
    """The labels (optional, together or not at all): classes a 1-D string array, poses ``[T, M, 3]``
    float with an object's row either whole or all NaN (absent); the optional ``truth_names`` (the
    simulator's, for robots wearing tags) one string per object."""
    has_cls, has_poses = "truth_classes" in d, "truth_poses" in d
    if has_cls != has_poses:
        bad("'truth_classes' and 'truth_poses' must come together")
    if not has_poses:
        if "truth_names" in d:
            bad("'truth_names' names labelled objects: it needs 'truth_classes' and 'truth_poses'")
        return
    cls = np.asarray(d["truth_classes"])
    if cls.ndim != 1 or cls.dtype.kind != "U":
        bad(f"'truth_classes' must be a 1-D string array, got {cls.dtype} of shape {list(cls.shape)}")
    m = cls.shape[0]
    poses = np.asarray(d["truth_poses"])
    if poses.dtype.kind != "f":
        bad(f"'truth_poses' must be float64, got {poses.dtype}")
    if poses.shape != (t, m, 3):
        bad(f"'truth_poses' must have shape [{t}, {m}, 3], got {list(poses.shape)}")
    nan = np.isnan(poses)
    partial = nan.any(-1) & ~nan.all(-1)
    if partial.any():
        i, j = (int(v) for v in np.argwhere(partial)[0])
        bad(f"'truth_poses' row for object {j} at scan {i} is partly NaN (absent objects need an all-NaN row)")
    if np.isinf(poses).any():
        bad("'truth_poses' has an infinite value")
    if "truth_names" in d:  # optional (kept in ``ScanLog.extra``): which robot each labelled object is
        names = np.asarray(d["truth_names"])
        if names.shape != (m,) or names.dtype.kind != "U":
            bad(f"'truth_names' must be a string array of shape [{m}] (one name per labelled object), got "
                f"{names.dtype} of shape {list(names.shape)}")


# ------------------------------------------------------------------ a log against a model's scanner geometry

STEP_TOLERANCE = 0.01  # relative difference of angular steps that still counts as the same scanner
MIN_BEAM_FRACTION = 0.1  # a cropped log must keep at least this share of the model's beams


def fit_geometry(
    log: ScanLog,
    *,
    angle_min: float,
    angle_increment: float,
    n_beams: int,
    range_min: float,
    range_max: float,
    where: object,
    crop: bool,
    hint: str = "",
    sensor_model: str | None = None,
) -> ScanLog:
    """``log`` checked against (and with ``crop``, cut to) the scanner geometry a model was trained on:
    beam ``i`` at ``angle_min + i * angle_increment``, ``n_beams`` beams, returns in ``[range_min, range_max]``.

    The model's features (the characteristic vector, the shape envelopes) are measured in beams, so a
    scan at another angular step gives other numbers for the same object: the steps must agree within
    :data:`STEP_TOLERANCE`, and no cropping can fix that. The beams must lie inside the model's field
    of view ``[angle_min, angle_min + (n_beams - 1) * angle_increment]``, half a beam of tolerance
    either side (beams are never resampled, so a log whose beams fall between the model's is taken as
    it is), and there must be at most ``n_beams`` of them: the step pads every scan to that width.

    With ``crop`` a wider log is cut to the beams inside (its ``angle_min`` moves to the first kept
    beam; at most ``n_beams`` are kept, the first ones; fewer than :data:`MIN_BEAM_FRACTION` of the
    model's beams is refused), and every return outside the model's range window becomes 0 (no return),
    since the model never saw anything there; the log's range window narrows to the overlap. Without
    ``crop`` such a log is refused and ``hint`` (e.g. ``"; crop it with --crop-fov"``) ends the message.

    A log that names its scanner must name the model's (unless the model's is ``unknown``): this is
    the one check that a model fits the scans, for logs, background logs and live sensors alike.

    A model from before its geometry was stored (``angle_increment`` NaN) takes any log of at most
    ``n_beams`` beams, as it did then. Every refusal is :class:`InputError` naming ``where``; without
    ``crop`` a log that fits is returned as it is (the same object).
    """
    return _fit_log(log, Beams(angle_min, angle_increment, n_beams, range_min, range_max), where, crop, hint,
                    sensor_model)


def fit_to_model(log: ScanLog, model, where: object, *, crop: bool = False, hint: str = "") -> ScanLog:
    """:func:`fit_geometry` with the geometry ``model`` (a :class:`~gtsjax.core.model.Model`, read only for
    its scanner attributes) was trained on; and, where the model's GPs read intensities, that the log
    carries them (a model trained with them would see an all-zero profile, find nothing, and say
    nothing)."""
    check_intensities(model, log.intensities is not None, where)
    want = Beams(model.angle_min, model.angle_increment, model.n_beams, model.range_min, model.range_max)
    return _fit_log(log, want, where, crop, hint, model.sensor_model)


def check_intensities(model, given: bool, where: object) -> None:
    """A model whose GPs read the intensity profile refuses scans without intensities (``given``
    False): it would see an all-zero profile, find nothing, and say nothing."""
    if getattr(model, "uses_intensity", False) and not given:
        raise InputError(where, "has no intensities, but the model was trained on scans with them (its GPs read the "
                                "intensity profile): give it scans with intensities, or train a model on scans without")


def fit_beams(have: Beams, want: Beams, where: object, *, crop: bool = False, hint: str = "",
              scanner: str | None = None, trained_for: str | None = None) -> slice | None:
    """The scanner geometry ``have`` (a log's or a live sensor's, of the scanner named ``scanner``)
    against ``want`` (a model's, trained for ``trained_for``), by the rules of :func:`fit_geometry`:
    the beams of ``have`` to keep (all of them, unless ``crop``), ``None`` for a model from before
    its geometry was stored (it takes any scan of at most its beams), or :class:`InputError` naming
    ``where``."""
    name = trained_for or "unknown scanner"
    if trained_for not in (None, "unknown") and scanner is not None and scanner != trained_for:
        raise InputError(where, f"scans from a {scanner}, but the model was trained for sensor {trained_for}")
    if not math.isfinite(want.increment):
        if have.count > want.count:
            raise InputError(where, f"has {have.count} beams per scan; the model ({name}) takes at most {want.count}")
        return None
    return _beams_inside(have, want, where, crop, hint, name)


def _fit_log(log: ScanLog, want: Beams, where: object, crop: bool, hint: str, sensor_model: str | None) -> ScanLog:
    """:func:`fit_geometry` against the beams ``want``."""
    name = sensor_model or "unknown scanner"
    keep = fit_beams(log.beams, want, where, crop=crop, hint=hint, scanner=log.sensor_model, trained_for=sensor_model)
    if keep is None or not crop:
        return log
    range_min, range_max = want.range_min, want.range_max
    lo, hi = max(log.range_min, range_min), min(log.range_max, range_max)
    if not lo < hi:
        raise InputError(where, f"range window [{log.range_min:g}, {log.range_max:g}] m does not overlap the "
                                f"model's [{range_min:g}, {range_max:g}] m ({name})")
    ranges = log.ranges[:, keep]
    with np.errstate(invalid="ignore"):
        outside = np.isfinite(ranges) & (ranges > 0) & ((ranges < range_min) | (ranges > range_max))
    ranges = np.where(outside, np.float32(0.0), ranges).astype(np.float32)
    inten = None if log.intensities is None else np.where(outside, np.float32(0.0), log.intensities[:, keep])
    return dataclasses.replace(log, ranges=ranges, intensities=inten,
                               angle_min=float(log.angle_min + keep.start * log.angle_increment),
                               range_min=float(lo), range_max=float(hi))


def _beams_inside(have: Beams, want: Beams, where, crop, hint, name) -> slice:
    """The beams of ``have`` to keep (all of them, unless ``crop``), or :class:`InputError`; see
    :func:`fit_geometry` for the rules."""
    deg = math.degrees
    if abs(have.increment - want.increment) > STEP_TOLERANCE * want.increment:
        raise InputError(where, f"angular step {deg(have.increment):.3f}° differs from the model's "
                                f"{deg(want.increment):.3f}° ({name}) by more than {100 * STEP_TOLERANCE:g} %")
    half = 0.5 * want.increment
    angles = have.angles()
    inside = (angles >= want.angle_min - half) & (angles <= want.angle_max + half)
    first, count = int(np.argmax(inside)), int(inside.sum())  # beam angles increase: the inside is one run
    if count < have.count:
        fov = (f"field of view {deg(have.angle_min):.1f}° … {deg(have.angle_max):.1f}° is not inside the model's "
               f"{deg(want.angle_min):.1f}° … {deg(want.angle_max):.1f}° ({name})")
        if not crop:
            raise InputError(where, fov + hint)
        need = math.ceil(MIN_BEAM_FRACTION * want.count)
        if count < need:
            raise InputError(where, f"{fov}, and only {count} of its beams lie inside (at least {need} needed)")
    elif count > want.count and not crop:
        raise InputError(where, f"has {count} beams per scan, more than the {want.count} of the model ({name})")
    return slice(first, first + min(count, want.count))


def scan_dt(stamps: np.ndarray, prev_stamp: float | None = None) -> np.ndarray:
    """Each scan's ``dt``, the time since the scan before it (``prev_stamp`` for the first, which
    gets 0 without one), as the step takes it: float32, never negative. The one definition, for
    logs, for a log replayed a block at a time and for the live loop's frames."""
    stamps = np.asarray(stamps, np.float64)
    first = stamps[:1] if prev_stamp is None else np.asarray([prev_stamp], np.float64)
    return np.maximum(np.diff(stamps, prepend=first), 0.0).astype(np.float32)


def frame_dt(stamp: float, prev_stamp: float | None) -> float:
    """:func:`scan_dt` of one frame, without NumPy (the live loop's path): ``stamp − prev_stamp``,
    never negative, 0 for the first frame; float32 once the step's frame buffer holds it."""
    return 0.0 if prev_stamp is None else max(float(stamp) - float(prev_stamp), 0.0)


def to_scans(log: ScanLog, n_beams: int | None = None, *, prev_stamp: float | None = None):
    """The log as one stacked :class:`~gtsjax.Scan` (leading axis: scans), float32, padded to ``n_beams``.

    ``valid`` marks beams with a return (see :meth:`ScanLog.valid`); ranges and intensities are 0
    elsewhere and in the padding. ``dt`` is :func:`scan_dt` (``prev_stamp``: the stamp of the scan
    before the log's first, when the log is a block of a longer one).
    """
    import jax.numpy as jnp

    from ..core.scan import Scan

    n = log.n_beams if n_beams is None else n_beams
    if n < log.n_beams:
        raise InputError("scan log", f"has {log.n_beams} beams, more than the {n} the sensor model allows")
    valid = log.valid()
    ranges = np.where(valid, log.ranges, 0.0).astype(np.float32)
    inten = (
        np.zeros_like(ranges) if log.intensities is None else np.where(valid, log.intensities, 0.0).astype(np.float32)
    )
    pad = ((0, 0), (0, n - log.n_beams))
    dt = scan_dt(log.stamps, prev_stamp)
    t = log.n_scans
    return Scan(
        ranges=jnp.asarray(np.pad(ranges, pad)),
        intensities=jnp.asarray(np.pad(inten, pad)),
        valid=jnp.asarray(np.pad(valid, pad)),
        angle_min=jnp.full((t,), log.angle_min, dtype=jnp.float32),
        angle_increment=jnp.full((t,), log.angle_increment, dtype=jnp.float32),
        dt=jnp.asarray(dt),
    )


def from_scans(
    scans,
    stamps: np.ndarray,
    n_beams: int,
    *,
    angle_min: float,
    angle_increment: float,
    range_min: float = DEFAULT_RANGE_MIN,
    range_max: float = DEFAULT_RANGE_MAX,
    sensor_model: str | None = None,
    with_intensities: bool = True,
) -> ScanLog:
    """Back from stacked :class:`~gtsjax.Scan` arrays to a log: the first ``n_beams`` beams, 0 where
    there was no return. Angles come as float64 arguments, since the scans hold them in float32."""
    valid = np.asarray(scans.valid)[:, :n_beams]
    ranges = np.where(valid, np.asarray(scans.ranges)[:, :n_beams], 0.0).astype(np.float32)
    inten = np.where(valid, np.asarray(scans.intensities)[:, :n_beams], 0.0).astype(np.float32)
    return ScanLog(
        ranges=ranges,
        stamps=np.asarray(stamps, dtype=np.float64),
        angle_min=float(angle_min),
        angle_increment=float(angle_increment),
        intensities=inten if with_intensities else None,
        range_min=range_min,
        range_max=range_max,
        sensor_model=sensor_model,
    )
