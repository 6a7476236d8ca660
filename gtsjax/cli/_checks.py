"""The command line's checks of values, shared by every command that takes them: each value with its
unit and the range a plausible one lies in, refused in one line (:class:`~gtsjax.errors.InputError`,
exit status 2) before any work, naming the option and what would be right."""

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


def check_length(option: str, value: float, low: float, high: float, what: str) -> float:
    """A length in metres within ``(low, high]``; a value a thousand times too large is said to look
    like millimetres, with the value in metres to give instead."""
    if not (low < value <= high):
        hint = (f" ({value:g} looks like millimetres: give metres, {value / 1000:g})"
                if high < value <= 1000 * high else "")
        raise InputError(option, f"{value:g} m is not a plausible {what}: give metres above {low:g} and at most "
                                 f"{high:g}{hint}")
    return value


#: The longest ``run --smooth-lag``: the live window holds this many seconds of every track's states;
#: a longer view of a recording is ``replay --smooth``'s (the whole of each track's life).
MAX_SMOOTH_LAG_S = 60.0
