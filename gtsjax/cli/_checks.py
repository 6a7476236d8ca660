"""The command line's checks of values, shared by every command that takes them: each value with its
unit and the range a plausible one lies in, refused in one line (:class:`~gtsjax.errors.InputError`,
exit status 2) before any work, naming the option and what would be right."""

import os

import numpy as np

from ..errors import InputError

#: Seeds of simulated scenes: NumPy's generators take any integer from 0 up.
SEED_MAX = 2**63 - 1
#: A held-out scenario's seed when ``--scenario NAME`` names none (never one a model was trained on).
HELD_OUT_SEED = 1000


def scenario_spec(spec: str, option: str = "--scenario") -> tuple[str, int]:
    """``NAME`` or ``NAME:SEED`` as ``(name, seed)``; the seed an integer from 0 up
    (:data:`HELD_OUT_SEED` where none is given). ``NAME:`` with nothing after the colon, a seed that is
    not an integer or is negative, is one line."""
    name, colon, seed = spec.partition(":")
    if not name:
        raise InputError(option, f"{spec!r} names no scenario: give NAME or NAME:SEED (gtsjax simulate --list)")
    if not colon:
        return name, HELD_OUT_SEED
    if not seed.strip():
        raise InputError(option, f"{spec!r} has no seed after the colon: give {name}:SEED (an integer from 0 up), "
                                 f"or {name} alone for seed {HELD_OUT_SEED}")
    try:
        value = int(seed)
    except ValueError:
        raise InputError(option, f"{spec!r}: the seed {seed!r} is not an integer (give {name}:SEED, SEED from 0 "
                                 "up)") from None
    return name, check_seed(value, f"{option} {spec}")


def check_seed(seed: int, option: str = "--seed") -> int:
    """A simulation's seed: an integer from 0 to 2⁶³ − 1."""
    if not 0 <= seed <= SEED_MAX:
        raise InputError(option, f"the seed {seed} is out of range: seeds are integers from 0 to {SEED_MAX}")
    return seed


def check_class_names(option: str, given, known, where: str) -> None:
    """Every class named in ``given`` (``CLASS=VALUE`` options, as a dict or names) is one of
    ``known``: a name the model or its labels do not have is refused with the ones they do, not
    ignored."""
    unknown = [c for c in given if c not in known]
    if unknown:
        raise InputError(option, f"no class {', '.join(map(repr, unknown))} in {where}; the classes are "
                                 f"{', '.join(known) or 'none'}")


#: Per unit symbol: its name, and the name of the unit a thousand times smaller that a value given by
#: mistake is likely in.
_THOUSANDTHS = {"m": ("metres", "millimetres"), "s": ("seconds", "milliseconds")}


def check_length(option: str, value: float, low: float, high: float, what: str, unit: str = "m") -> float:
    """A length in metres (or a time in seconds: ``unit="s"``) within ``(low, high]``; a value a
    thousand times too large is said to look like millimetres (milliseconds), with the value to give
    instead."""
    if not (low < value <= high):
        name, small = _THOUSANDTHS[unit]
        hint = (f" ({value:g} looks like {small}: give {name}, {value / 1000:g})"
                if high < value <= 1000 * high else "")
        raise InputError(option, f"{value:g} {unit} is not a plausible {what}: give {name} above {low:g} and at most "
                                 f"{high:g}{hint}")
    return value


#: The longest scenario ``evaluate`` simulates (``--seconds``): an hour of a match, some 72 000 scans of
#: two lasers at 10 Hz, many minutes of rendering and replay.
MAX_SCENARIO_S = 3600.0


#: The longest ``run --smooth-lag``: the live window holds this many seconds of every track's states;
#: a longer view of a recording is ``replay --smooth``'s (the whole of each track's life).
MAX_SMOOTH_LAG_S = 60.0


def available_memory() -> int | None:
    """Bytes of memory this machine can give a new allocation without swapping (Linux's
    ``MemAvailable``; elsewhere the free physical pages); None where neither can be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return None


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.0f} MB"


def check_memory(option: object, need: float, what: str, fix: str) -> None:
    """Refuses, before any work, a run whose ``need`` (bytes, an estimate of what it will hold at once)
    exceeds the memory the machine has available now: it would swap the machine to a standstill or be
    killed after minutes of work, its outputs unwritten. ``what`` says what takes the memory, ``fix``
    what to do instead."""
    have = available_memory()
    if have is not None and need > have:
        raise InputError(option, f"{what} needs about {_gb(need)} of memory, and this machine has {_gb(have)} "
                                 f"available: {fix}")


#: Units a clock or a length is commonly written in by mistake, as factors of seconds or metres.
_TIME_UNITS = ((1e3, "milliseconds"), (1e6, "microseconds"), (1e9, "nanoseconds"))
_LENGTH_UNITS = ((1e3, "millimetres"), (1e2, "centimetres"))


def _share_within(values: np.ndarray, lo: float, hi: float) -> float:
    return float(np.mean((values >= lo) & (values <= hi))) if values.size else 0.0


def check_stamp_units(where: object, stamps: np.ndarray, ref: tuple[float, float], slack: float,
                      what: str = "the ground truth's") -> None:
    """Stamps that lie outside ``ref`` (the seconds another input spans, widened by ``slack``) but
    inside it once read as milliseconds (or µs, ns) are refused with the factor: graded as seconds,
    no row would meet, and the grade would blame the robot's frame."""
    stamps = np.asarray(stamps, np.float64)
    lo, hi = ref[0] - slack, ref[1] + slack
    if _share_within(stamps, lo, hi) >= 0.1:
        return
    for factor, unit in _TIME_UNITS:
        if _share_within(stamps / factor, lo, hi) >= 0.5:
            raise InputError(where, f"its stamps ({stamps.min():.6g} … {stamps.max():.6g}) look like {unit}: "
                                    f"{what} run from {ref[0]:.6g} to {ref[1]:.6g} s; give them in seconds "
                                    f"(divided by {factor:g})")


def check_length_units(where: object, xy: np.ndarray, bounds: "tuple[float, float, float, float] | None",
                       margin: float = 5.0) -> None:
    """Positions that lie outside the field (its ``bounds`` widened by ``margin`` metres; without
    bounds, beyond a kilometre) but inside it once read as millimetres (or centimetres) are refused with
    the factor."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if not xy.size:
        return
    if bounds is None:
        def inside(p):
            return float(np.mean(np.all(np.abs(p) <= 1000.0, axis=1)))
    else:
        x0, y0, x1, y1 = bounds

        def inside(p):
            return float(np.mean((p[:, 0] >= x0 - margin) & (p[:, 0] <= x1 + margin) & (p[:, 1] >= y0 - margin)
                                 & (p[:, 1] <= y1 + margin)))
    if inside(xy) >= 0.1:
        return
    for factor, unit in _LENGTH_UNITS:
        if inside(xy / factor) >= 0.5:
            field = "the field" if bounds is None else f"the field ({bounds[0]:g}, {bounds[1]:g}) – ({bounds[2]:g}, {bounds[3]:g}) m"
            raise InputError(where, f"its positions (x up to {np.abs(xy[:, 0]).max():.6g}) look like {unit}: they "
                                    f"lie in {field} only divided by {factor:g}; give them in metres")
