"""What training learns for stage g, tracking: each tracked class's top speed and turn rate (the
tracker's plausible-motion test, :class:`~gtsjax.core.g_track.TrackerParams`) from the evidence of
that motion in its labels (:func:`motion_limits`), else the user's or the tracker's defaults, held to
their sanity ranges (:func:`tracker_limits`, :mod:`.bounds`); and the scanner's rate, which turns the
tracker's times (confirmation after half a second, …) into scans (:func:`scan_rate`).

Users label their recordings in many ways: a robot walking, put down for seconds at each pose, carried
from pose to pose, or turned on the spot through 16 headings with one scan each. Only some of these
are evidence of how fast the robot moves. A speed is learnt only from *translation*: windows of half a
second of consecutive scans at the scan period in which the labelled position went somewhere (at
least 5 cm, along a path at most twice as long: label jitter goes nowhere) and no step was a jump (a
robot lifted from one grid pose to the next between two scans). A turn rate is learnt the same way
from windows in which the heading turned consistently. A window's speed is its net displacement over
its duration, so that a label's jitter from scan to scan is not taken for speed. A step faster than
the plausible range (:mod:`.bounds`) is a placement, not motion: a robot faster than that is set with
``--max-speed`` / ``--max-turn-rate``.
"""

import math
from collections.abc import Iterator, Sequence

import numpy as np

from ..core.g_track import DEFAULT_MAX_SPEED, DEFAULT_MAX_TURN_RATE, TrackerParams
from ..core.geometry import wrap
from ..io.logs import ScanLog
from ..sensors import MODELS
from . import bounds
from .config import TrainConfig

WINDOW_S = 0.5  # s: the windows motion is measured over
MIN_TRANSLATION = 0.05  # m: a window that went less far did not translate (label jitter, a turn on the spot)
MIN_TURN = 0.1  # rad: likewise for turning
MIN_EVIDENCE_S = 2.0  # s: of translating (turning) windows, at least, before a limit is learnt from them
TURN_NOISE_LAG_S = 0.1  # s: the shorter lag of the turn-rate noise's second differences (the longer: twice it)


def _runs(stamps: np.ndarray, present: np.ndarray, period: float) -> Iterator[tuple[int, int]]:
    """Runs ``[a, b)`` of consecutive scans with the object present, each step at the scan period
    (within half of it): a log that keeps a scan every few seconds, or frames lost, break runs."""
    dt = np.diff(stamps)
    ok = present[:-1] & present[1:] & (dt > 0.5 * period) & (dt < 1.5 * period)
    edges = np.diff(np.concatenate([[0], ok.astype(int), [0]]))
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        yield int(a), int(b) + 1  # steps a..b-1 join scans a..b


def _labelled_runs(logs: Sequence[ScanLog], period: float, k: int, *,
                   with_heading: bool) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """``(class, poses [n, 3], stamps [n])`` of each labelled object's runs (:func:`_runs`) longer than
    ``k`` steps, present where its position is labelled (and its heading, ``with_heading``)."""
    for log in logs:
        for m, name in enumerate(log.truth_classes):
            p = log.truth_poses[:, m]
            present = np.isfinite(p).all(axis=1) if with_heading else ~np.isnan(p[:, 0]) & ~np.isnan(p[:, 1])
            for a, b in _runs(log.stamps, present, period):
                if b - a > k:
                    yield str(name), p[a:b], log.stamps[a:b]


def _windows(values: np.ndarray, k: int) -> np.ndarray:
    """Sliding windows of ``k`` consecutive values, ``[n - k + 1, k]``."""
    return np.lib.stride_tricks.sliding_window_view(values, k)


def _moved(step: np.ndarray, net: np.ndarray, duration: np.ndarray, minimum: float, fastest: float) -> np.ndarray:
    """Which windows moved: net change at least ``minimum`` and at least half the path (a consistent
    motion, not jitter back and forth), no step over three times the window's median step (a jump:
    carried to the next pose between two scans), and no step faster than ``fastest`` per second (a log
    of one scan per pose, stamped at the scan period, jumps between poses at every step)."""
    path = step.sum(1)
    smooth = step.max(1) <= 3.0 * np.median(step, axis=1) + 1e-3
    return (net >= minimum) & (net >= 0.5 * path) & smooth & (step.max(1) <= fastest * duration / step.shape[1])


def _rates(step: np.ndarray, net: np.ndarray, duration: np.ndarray, minimum: float, fastest: float) -> np.ndarray:
    """Rates of the windows that moved (:func:`_moved`)."""
    moved = _moved(step, net, duration, minimum, fastest)
    return net[moved] / duration[moved]


def motion_limits(logs: Sequence[ScanLog], classes: tuple[str, ...], *, period: float | None = None,
                  quantile: float = 0.995, margin: float = 1.25) -> dict[str, dict]:
    """Each labelled class's top speed (m/s) and turn rate (rad/s) from the evidence of that motion
    in its labels, where there is enough (``MIN_EVIDENCE_S`` of it): the ``quantile`` of its windows'
    speeds (turn rates) times ``margin``. Per class, ``speed_windows_s`` and ``turn_windows_s`` say how
    many seconds of translating and turning windows there were (0 where none), and ``max_speed`` /
    ``max_turn_rate`` are present only where learnt. ``period``: the scan period (:func:`scan_rate`)."""
    period = period if period is not None else 1.0 / scan_rate(logs)
    k = max(2, round(WINDOW_S / period))
    speeds: dict[str, list] = {}
    turns: dict[str, list] = {}
    for name, q, t in _labelled_runs(logs, period, k, with_heading=False):
        step = np.hypot(*np.diff(q[:, :2], axis=0).T)
        duration = t[k:] - t[:-k]
        net = np.hypot(*(q[k:, :2] - q[:-k, :2]).T)
        speeds.setdefault(name, []).append(_rates(_windows(step, k), net, duration, MIN_TRANSLATION,
                                                  bounds.MAX_SPEED.plausible[1]))
        if np.isfinite(q[:, 2]).all():
            turn = wrap(np.diff(q[:, 2]))
            net_turn = np.abs(_windows(turn, k).sum(1))
            turns.setdefault(name, []).append(
                _rates(np.abs(_windows(turn, k)), net_turn, duration, MIN_TURN, bounds.MAX_TURN_RATE.plausible[1]))
    out = {}
    window_s = k * period
    for name in classes:
        v = np.concatenate(speeds.get(name, [np.zeros(0)]))
        w = np.concatenate(turns.get(name, [np.zeros(0)]))
        # Overlapping windows: each adds a step's worth of time.
        info = {"speed_windows_s": round(float(v.size * period), 2), "turn_windows_s": round(float(w.size * period), 2),
                "window_s": round(window_s, 3)}
        if v.size * period >= MIN_EVIDENCE_S:
            info["max_speed"] = round(float(margin * np.quantile(v, quantile)), 3)
        if w.size * period >= MIN_EVIDENCE_S:
            info["max_turn_rate"] = round(float(margin * np.quantile(w, quantile)), 3)
        if name in speeds or name in turns:
            out[name] = info
    return out


KAPPA_MAX = 1e5  # the fit's concentration at most (a spread of 0.18°): labels that follow their travel exactly


def travel_offsets(logs: Sequence[ScanLog], classes: tuple[str, ...], *, period: float) -> dict[str, np.ndarray]:
    """Per labelled class, its heading less its direction of travel (rad) in each translating window
    (:func:`_moved`, as :func:`motion_limits` counts them): the direction of the window's net
    displacement, the heading the circular mean of the window's labelled headings."""
    k = max(2, round(WINDOW_S / period))
    out: dict[str, list] = {}
    for name, q, t in _labelled_runs(logs, period, k, with_heading=True):
        if name not in classes:
            continue
        step = np.hypot(*np.diff(q[:, :2], axis=0).T)
        d = q[k:, :2] - q[:-k, :2]
        moved = _moved(_windows(step, k), np.hypot(*d.T), t[k:] - t[:-k], MIN_TRANSLATION,
                       bounds.MAX_SPEED.plausible[1])
        heading = np.angle(_windows(np.exp(1j * q[:, 2]), k + 1).mean(1))
        out.setdefault(name, []).append(wrap(heading - np.arctan2(d[:, 1], d[:, 0]))[moved])
    return {c: np.concatenate(v) for c, v in out.items()}


def fit_von_mises_uniform(delta: np.ndarray, iters: int = 500) -> tuple[float, float, float]:
    """``(μ, κ, u)`` of the mixture ``(1 - u)·VM(μ, κ) + u/2π`` fitted to the angles ``delta`` by
    maximum likelihood (EM; κ's M-step solves A(κ) = I1(κ)/I0(κ) = R̄, :func:`_inverse_a`). The share
    ``u`` is what travels in any other direction: a robot's sidesteps, all of a holonomic robot's."""
    from scipy import special  # here, not at the top: every command imports this module, few fit

    delta = np.asarray(delta, np.float64)
    mu = float(np.angle(np.mean(np.exp(1j * delta))))
    kappa, u = 1.0, 0.5
    for _ in range(iters):
        vm = np.exp(kappa * (np.cos(delta - mu) - 1.0)) / special.i0e(kappa)  # 2π·VM
        r = (1.0 - u) * vm / ((1.0 - u) * vm + u)
        if r.sum() < 1e-9:
            return mu, 0.0, 1.0
        u_new = float(np.clip(1.0 - r.mean(), 1e-3, 1.0))
        z = np.sum(r * np.exp(1j * delta))
        mu_new = float(np.angle(z))
        kappa_new = _inverse_a(abs(z) / r.sum())
        done = (abs(u_new - u) < 1e-9 and abs(kappa_new - kappa) < 1e-8 * max(1.0, kappa)
                and abs(wrap(mu_new - mu)) < 1e-10)
        mu, kappa, u = mu_new, kappa_new, u_new
        if done:
            break
    return mu, kappa, u


def _a(kappa: float) -> float:
    """A(κ) = I1(κ)/I0(κ), from the exponentially scaled functions (finite for any κ)."""
    from scipy import special

    return float(special.i1e(kappa) / special.i0e(kappa))


def _inverse_a(rbar: float) -> float:
    """κ with A(κ) = ``rbar``, at most :data:`KAPPA_MAX` (A rises from 0 to 1: one root, bracketed)."""
    from scipy import optimize

    if rbar >= _a(KAPPA_MAX):
        return KAPPA_MAX
    return float(optimize.brentq(lambda k: _a(k) - rbar, 0.0, KAPPA_MAX, xtol=1e-12, rtol=1e-12))


def motion_heading(logs: Sequence[ScanLog], classes: tuple[str, ...], mobiles: tuple[str, ...], *,
                   period: float) -> tuple[np.ndarray | None, list[dict]]:
    """Each mobile class's heading against its direction of travel (lever 2 of issue 55), for
    ``TrackerParams.motion_heading``: ``[classes, 3]`` rows ``(μ, κ, u)`` (:func:`fit_von_mises_uniform`
    on :func:`travel_offsets`), its spread ``1/√κ`` held to :data:`.bounds.MOTION_SPREAD`; κ = 0 (no
    evidence) for a class with less than ``MIN_EVIDENCE_S`` of translating windows. None if no class
    learnt it. Also the learnt-parameter table's rows."""
    offsets = travel_offsets(logs, classes, period=period)
    table = np.zeros((len(classes), 3))
    table[:, 2] = 1.0
    rows = []
    for i, c in enumerate(classes):
        if c not in mobiles:
            continue
        d = offsets.get(c, np.zeros(0))
        seconds = round(float(d.size * period), 2)
        if seconds < MIN_EVIDENCE_S:
            why = (f"only {seconds:g} s of translation in the labels (at least {MIN_EVIDENCE_S:g} s needed)" if seconds
                   else "no translation in the labels")
            rows.append(bounds.entry(bounds.MOTION_SPREAD, c, 180.0, "default", why + ": its travel is no evidence"))
            continue
        mu, kappa, u = fit_von_mises_uniform(d)
        raw = float(np.degrees(1.0 / np.sqrt(max(kappa, 1e-9))))
        spread = bounds.clamp(bounds.MOTION_SPREAD, raw)
        evidence = f"{seconds:g} s of translation in the labels ({WINDOW_S:g} s windows)"
        held = f"; fitted {raw:.2g}°, held to {spread:g}°" if spread != raw else ""
        table[i] = [mu, 1.0 / np.radians(spread) ** 2 if spread < 180.0 else 0.0, u]
        rows += [bounds.entry(bounds.MOTION_SPREAD, c, round(spread, 2), "learnt", evidence + held, learnt=round(raw, 2)),
                 bounds.entry(bounds.MOTION_OFFSET, c, round(float(np.degrees(mu)), 2), "learnt", evidence),
                 bounds.entry(bounds.MOTION_OTHER, c, round(u, 3), "learnt", evidence)]
    return (table if np.any(table[:, 1] > 0) else None), rows


def _in_motion(q: np.ndarray, t: np.ndarray, step: np.ndarray, turn: np.ndarray, k: int) -> np.ndarray:
    """``[n - 1]``: which steps of a run (``step``: their lengths, ``turn``: their wrapped turns) lie in a
    window of ``k`` steps that translated or turned (:func:`_moved`, as :func:`motion_limits` counts them)."""
    duration = t[k:] - t[:-k]
    moved = _moved(_windows(step, k), np.hypot(*(q[k:, :2] - q[:-k, :2]).T), duration, MIN_TRANSLATION,
                   bounds.MAX_SPEED.plausible[1])
    turns = _windows(turn, k)
    moved |= _moved(np.abs(turns), np.abs(turns.sum(1)), duration, MIN_TURN, bounds.MAX_TURN_RATE.plausible[1])
    # a step is in motion where any window holding it moved
    return np.convolve(moved.astype(int), np.ones(k, int))[: step.size] > 0


def turn_second_differences(logs: Sequence[ScanLog], mobiles: tuple[str, ...], *, period: float,
                            max_speed: dict[str, float], max_turn_rate: dict[str, float],
                            lags: tuple[int, ...] = (1, 2)) -> dict[str, list[np.ndarray]]:
    """Per mobile class and lag ``L`` (scans), the labelled headings' second differences
    ``θ(t + 2L) - 2 θ(t + L) + θ(t)`` over the steps in which the robot moved (:func:`_in_motion`) and
    no step was a placement: faster than the class's ``max_speed`` or ``max_turn_rate`` (carried or
    turned by hand between two scans)."""
    k = max(2, round(WINDOW_S / period))
    out: dict[str, list[list]] = {}
    for name, q, t in _labelled_runs(logs, period, max(k, 2 * max(lags)), with_heading=True):
        if name not in mobiles:
            continue
        dt = np.diff(t)
        step, turn = np.hypot(*np.diff(q[:, :2], axis=0).T), wrap(np.diff(q[:, 2]))
        placed = (np.abs(turn) > max_turn_rate[name] * dt) | (step > max_speed[name] * dt)
        good = _in_motion(q, t, step, turn, k) & ~placed
        per = out.setdefault(name, [[] for _ in lags])
        for i, lag in enumerate(lags):
            later = _windows(turn, lag).sum(1)  # θ(s + L) - θ(s), s = 0 … n - 1 - L
            d = later[lag:] - later[:-lag]
            ok = _windows(good, 2 * lag).all(1)
            per[i].append(d[ok])
    return {c: [np.concatenate(v) for v in per] for c, per in out.items()}


def turn_rate_noise(logs: Sequence[ScanLog], mobiles: tuple[str, ...], *, period: float,
                    max_speed: dict[str, float], max_turn_rate: dict[str, float]) -> tuple[float, dict]:
    """The tracker's turn-rate process noise ``q`` (``TrackerParams.q_theta``, rad²/s³) from the mobile
    classes' labelled headings while they move, and its row of the learnt-parameter table. Under the
    tracker's own model (the heading's second derivative white, of density ``q``) with labels of
    independent noise ``σ²``, a second difference over ``L`` scans of ``dt`` has variance
    ``2/3 q (L dt)³ + 6 σ²``: lags of ``TURN_NOISE_LAG_S`` and twice that give both, whatever the
    labels' noise (over one scan of a 40 Hz scanner, half a degree of label noise is 400 times the
    turn rate's changes). The
    largest over the classes with ``MIN_EVIDENCE_S`` of such differences (one ``q`` serves every track,
    and the tracker must keep up with the most agile); else the tracker's default. Means, not robust
    statistics: a robot's turn rate changes now and then, in a few scans, and those changes are what
    ``q`` must allow for."""
    lag = max(1, round(TURN_NOISE_LAG_S / period))
    diffs = turn_second_differences(logs, mobiles, period=period, max_speed=max_speed, max_turn_rate=max_turn_rate,
                                    lags=(lag, 2 * lag))
    default = round(float(TrackerParams.default([True]).q_theta), 6)
    tau = lag * period
    found = []
    for c in mobiles:
        d1, d2 = diffs.get(c, [np.zeros(0), np.zeros(0)])
        seconds = d1.size * period
        if seconds < MIN_EVIDENCE_S or d2.size < 2:
            continue
        v1, v2 = float(np.mean(d1**2)), float(np.mean(d2**2))
        q = max(3.0 * (v2 - v1) / (14.0 * tau**3), 0.0)  # below 0: the labels' noise alone, no change of turn rate
        sigma = math.sqrt(max(v1 - 2.0 / 3.0 * q * tau**3, 0.0) / 6.0)
        found.append((q, c, seconds, sigma))
    if not found:
        return default, bounds.entry(bounds.TURN_RATE_NOISE, None, default, "default",
                                     f"less than {MIN_EVIDENCE_S:g} s of a mobile class moving in the labels")
    raw, c, seconds, sigma = max(found)
    value = bounds.clamp(bounds.TURN_RATE_NOISE, raw)
    others = "; ".join(f"{o}: {qo:.3g}" for qo, o, _, _ in sorted(found, reverse=True)[1:])
    held = f"; fitted {raw:.2g}, held to {value:g}" if value != raw else ""
    if raw > bounds.TURN_RATE_NOISE.plausible[1]:
        # A turn rate that jumps like that is a hand's (a robot carried from pose to pose, its turns
        # started and stopped within a scan), not the robot's own: taken, it left a still robot's heading
        # following its reads' noise (the tests' carried Nao: 1.2° -> 1.7°). Warned, and the default kept.
        value = default
        held = "; a robot carried or turned by hand, not turning itself: the default kept"
    evidence = (f"{c}'s labelled headings over {seconds:.3g} s of motion (second differences over {tau:.2g} and "
                f"{2 * tau:.2g} s; the labels' own noise {math.degrees(sigma):.2g}°){held}"
                + (f"; {others}" if others else ""))
    return value, bounds.entry(bounds.TURN_RATE_NOISE, None, round(value, 4), "learnt", evidence, learnt=round(raw, 4))


def _one_limit(bound, cls: str, set_value: float | None, info: dict, key: str, default: float, seconds_key: str,
               what: str) -> tuple[float, dict]:
    if set_value is not None:
        return set_value, bounds.entry(bound, cls, set_value, "set", "the command line")
    seconds = info.get(seconds_key, 0.0)
    if key in info:
        raw = info[key]
        value = bounds.clamp(bound, raw)
        return value, bounds.entry(bound, cls, value, "learnt",
                                   f"{seconds:g} s of {what} in the labels ({info['window_s']:g} s windows)", learnt=raw)
    why = (f"only {seconds:g} s of {what} in the labels (at least {MIN_EVIDENCE_S:g} s needed)" if seconds
           else f"no {what} in the labels")
    return default, bounds.entry(bound, cls, default, "default", why)


def tracker_limits(logs: Sequence[ScanLog], classes: tuple[str, ...], mobiles: tuple[str, ...],
                   cfg: TrainConfig, period: float | None = None) -> tuple[list[float], list[float], dict[str, dict], list[dict]]:
    """Every class's top speed and turn rate for :meth:`~gtsjax.core.g_track.TrackerParams.default`: the
    user's (``cfg.max_speed``, ``cfg.max_turn_rate``), else from the evidence of motion in the labels
    (:func:`motion_limits`), clamped to :data:`.bounds.MAX_SPEED` and :data:`.bounds.MAX_TURN_RATE`,
    else the tracker's defaults. Also, for the report, each tracked or set class's limits and where they
    came from, and the rows of the learnt-parameter table (:func:`.bounds.entry`)."""
    learnt = motion_limits(logs, classes, period=period)
    motion, rows = {}, []
    speed, turn = [], []
    for c in classes:
        if c in cfg.max_speed or c in cfg.max_turn_rate or c in mobiles:
            info = learnt.get(c, {"window_s": WINDOW_S})
            v, row_v = _one_limit(bounds.MAX_SPEED, c, cfg.max_speed.get(c), info, "max_speed", DEFAULT_MAX_SPEED,
                                  "speed_windows_s", "translation")
            w, row_w = _one_limit(bounds.MAX_TURN_RATE, c, cfg.max_turn_rate.get(c), info, "max_turn_rate",
                                  DEFAULT_MAX_TURN_RATE, "turn_windows_s", "turning")
            rows += [row_v, row_w]
            motion[c] = {"max_speed": v, "max_speed_from": row_v["source"], "max_speed_evidence": row_v["evidence"],
                         "max_turn_rate": w, "max_turn_rate_from": row_w["source"],
                         "max_turn_rate_evidence": row_w["evidence"],
                         "translation_s": info.get("speed_windows_s", 0.0), "turning_s": info.get("turn_windows_s", 0.0)}
        speed.append(motion.get(c, {}).get("max_speed", DEFAULT_MAX_SPEED))
        turn.append(motion.get(c, {}).get("max_turn_rate", DEFAULT_MAX_TURN_RATE))
    return speed, turn, motion, rows


def log_period(logs: Sequence[ScanLog]) -> float | None:
    """The scan period the logs' stamps show, or None where they have none: the median of the positive
    intervals under 1.5 times their median. Lost frames and pauses only lengthen intervals, and are left
    out even where they are half of them; stamps taken on the host jitter both ways (the real BreezySLAM
    URG-04LX log: intervals 0.088-0.109 s between their quartiles, 0.076 s at the 10th percentile), so a
    low quantile would take jitter for the rate."""
    dts = np.concatenate([np.diff(log.stamps) for log in logs if log.n_scans > 1] or [np.zeros(0)])
    dts = dts[dts > 0]
    if not dts.size:
        return None
    return float(np.median(dts[dts < 1.5 * np.median(dts)]))


def scan_rate(logs: Sequence[ScanLog], set_hz: float | None = None) -> float:
    """Scans per second of the scanner the logs were recorded with (see :func:`scan_rate_entry`)."""
    return scan_rate_entry(logs, set_hz)[0]


def scan_rate_entry(logs: Sequence[ScanLog], set_hz: float | None = None) -> tuple[float, dict]:
    """The scanner's rate and its row of the learnt-parameter table: ``set_hz`` where given; else the
    rate the logs' stamps show (:func:`log_period`), unless the logs name a known scanner and their
    stamps are sparser than its rate (a recording that kept one scan per pose: the tracker runs at
    the scanner's rate, not at the user's pace); else the named scanner's; else 10 Hz."""
    if set_hz is not None:
        return set_hz, bounds.entry(bounds.SCAN_RATE, None, set_hz, "set", "the command line")
    known = [MODELS[log.sensor_model] for log in logs if log.sensor_model in MODELS]
    period = log_period(logs)
    if period is not None and not (known and period > 1.5 * known[0].period):
        raw = 1.0 / period
        rate = bounds.clamp(bounds.SCAN_RATE, raw)
        return rate, bounds.entry(bounds.SCAN_RATE, None, rate, "learnt",
                                  "the logs' stamps (their intervals' median, pauses left out)", learnt=raw)
    if known:
        how = (f"a {known[0].name}'s rate: the logs' stamps are {period:.3g} s apart, sparser than its scans"
               if period is not None else f"a {known[0].name}'s rate: the logs have one scan each")
        return known[0].rate_hz, bounds.entry(bounds.SCAN_RATE, None, known[0].rate_hz, "default", how)
    return 10.0, bounds.entry(bounds.SCAN_RATE, None, 10.0, "default", "no stamps and no known scanner")


def confirmation_entry(n_confirm: int, rate_hz: float) -> dict:
    """The tracker's confirmation, in seconds and in scans at ``rate_hz``, as a row of the report."""
    return {"class": None, "parameter": "confirmation", "unit": "s", "value": round(n_confirm / rate_hz, 3),
            "source": "default", "evidence": f"{n_confirm} scans at {rate_hz:.3g} Hz (half a second, at least 3 scans)",
            "hard_range": None, "plausible": None}
