"""Why a run reports nothing: a host-side tally of the step's outputs, and the warnings it gives.

A model whose tracked class's top speed was learnt as 0 m/s detects the robot in every scan, yet
every track of it stays tentative (its motion "implausible") and no ground-truth row is written;
without a word, the run looks like a clean one. :class:`Tally` counts, scan by scan (or a stack of
scans at a time), what tells such a run apart, and :func:`warnings` turns the counts into one line
per problem, with its likely cause and the option to change.

The tally (:meth:`Tally.finish`, a JSON-able dict; the ``"diagnosis"`` object of the summaries):

- ``scans``: scans counted;
- ``degraded``: scans without a new map transformation (too few landmarks found);
- ``slots``: the model's track slots, ``slots_full``: scans in which every one was live;
- ``classes``: per tracked class, ``detected`` (scans with a detection of it: ``det_mask`` and
  ``det_class``), ``reported`` (scans with a reported row of it), ``tracks`` (tracks started),
  ``never_confirmed`` (tracks that died, or were alive when the run ended, without ever being
  confirmed), ``held`` (those counted under their dominant reason, :data:`~gtsjax.core.g_track.HOLDS`
  but "none": the test that held the track in most of its scans, "too few scans" where no test
  ever did), ``confirmed`` (tracks confirmed at least once), ``held_scans`` (per reason, the scans
  in which a live track of the class was held unconfirmed by it, every track: one confirmed and
  then unconfirmed by an implausible speed counts too), ``speed_median`` (m/s: the median over the
  tracks ever held for speed of each one's mean estimated speed in those scans; ``None`` without
  any) against ``max_speed``, and ``turn_rate_median`` (rad/s) against ``max_turn_rate`` likewise.

Fed with :meth:`Tally.add` (an :class:`~gtsjax.Output` of one scan or stacked scans, NumPy or JAX)
or :meth:`Tally.add_packed` (the live loop's :func:`~gtsjax.drivers.live.pack_tracks` table, which
carries what the tally needs; buffered and counted a block of scans at a time, off the frame's
path). A track's slot and id stay the same for its life and ids are never reused, so a track has
ended once its id is no longer live.
"""

import math

import numpy as np

from ..core.g_track import DEFAULT_MAX_SPEED, DEFAULT_MAX_TURN_RATE, HOLDS
from ..io.gtd import COLUMN, STATUS_AT

_TOO_FEW, _MAJORITY, _SPEED, _TURN = (HOLDS.index(h) for h in ("too few scans", "majority", "speed", "turn rate"))

# Thresholds of :func:`warnings`.
DETECTED_MIN = 0.5  # a class detected in at least this share of the scans …
REPORTED_MIN = 0.5  # … and reported in fewer than this share of those: warn
DEGRADED_MAX = 0.5  # scans without a new map transformation: more than this share, warn
FULL_MAX = 0.05  # scans with every track slot live: more than this share, warn
# A test (speed, turn rate, majority) is blamed for tracks left unconfirmed where it held them in at
# least this share of the scans they waited for hits (:func:`dominant`): each failure restarts the
# count, so a track held by a test also waits up to ``n_confirm`` scans a failure; a test failed once
# among many waiting scans (intermittent detections) is not why.
BLAME_SHARE = 0.2


class Tally:
    """The counts of :mod:`gtsjax.drivers.diagnose` for one run of ``model`` (one track table)."""

    def __init__(self, model, *, block: int = 256):
        self.classes = list(model.classes)
        self.tracked = [i for i, t in enumerate(np.asarray(model.tracker.tracked)) if t]
        self.max_speed = np.asarray(model.tracker.max_speed, np.float64)
        self.max_turn_rate = np.asarray(model.tracker.max_turn_rate, np.float64)
        self.slots = int(model.max_tracks)
        n_cls = len(self.classes)
        self.scans = self.degraded = self.full = 0
        self.detected = np.zeros(n_cls, np.int64)
        self.reported = np.zeros(n_cls, np.int64)
        self.started = np.zeros(n_cls, np.int64)
        self.confirmed = np.zeros(n_cls, np.int64)
        self.held = np.zeros((n_cls, len(HOLDS)), np.int64)
        self.held_scans = np.zeros((n_cls, len(HOLDS)), np.int64)
        self.speeds: list[list[float]] = [[] for _ in range(n_cls)]
        self.turns: list[list[float]] = [[] for _ in range(n_cls)]
        # Live tracks by id: [class, ever confirmed, scans per hold, speed sum and scans, turn sum and scans].
        self.open: dict[int, list] = {}
        self.block = block
        self.pending: list = []

    # ------------------------------------------------------------------------------------------ input
    def add(self, out) -> None:
        """One scan's :class:`~gtsjax.Output`, or stacked scans' (a leading scan axis)."""
        self._flush()
        tid = np.asarray(out.track_id)
        one = tid.ndim == 1
        get = (lambda a: np.asarray(a)[None]) if one else np.asarray  # noqa: E731
        tid, cls, live = get(out.track_id), get(out.track_class), get(out.track_live)
        n_cls = len(self.classes)
        k = np.arange(n_cls)
        det = get(out.det_mask)[..., None] & (get(out.det_class)[..., None] == k)
        rep = get(out.track_mask)[..., None] & (cls[..., None] == k)
        self._count(tid, live, cls, get(out.track_hold), get(out.track_speed), get(out.track_turn_rate),
                    det.any(axis=1), rep.any(axis=1), get(out.degraded))

    def add_packed(self, table) -> None:
        """One scan's :func:`~gtsjax.drivers.live.pack_tracks` table (array or ``tolist()``). Kept
        until ``block`` scans have come (or :meth:`finish`), then counted together."""
        self.pending.append(table)
        if len(self.pending) >= self.block:
            self._flush()

    def _flush(self) -> None:
        if not self.pending:
            return
        t = np.asarray(self.pending, np.float64)  # [n, M + 1, columns]
        self.pending = []
        col = COLUMN
        tracks, status = t[:, :-1], t[:, -1]
        cls = tracks[..., col["class"]].astype(np.int64)
        k = np.arange(len(self.classes))
        rep = ((tracks[..., col["reported"]] > 0.5)[..., None] & (cls[..., None] == k)).any(axis=1)
        bits = status[:, STATUS_AT["detected"]].astype(np.int64)
        det = ((bits[:, None] >> k) & 1).astype(bool)
        self._count(tracks[..., col["track_id"]].astype(np.int64), tracks[..., col["live"]] > 0.5, cls,
                    tracks[..., col["hold"]].astype(np.int64), tracks[..., col["speed"]],
                    tracks[..., col["turn_rate"]], det, rep, status[:, STATUS_AT["degraded"]] > 0.5)

    def _count(self, tid, live, cls, hold, speed, turn, detected, reported, degraded) -> None:
        """Stacked scans: per scan and slot ``[n, M]`` (ids, live, class, hold, speed, turn rate), per
        scan and class ``[n, C]`` (detected, reported), per scan ``[n]`` (degraded)."""
        n = tid.shape[0]
        if n == 0:
            return
        live = live & (tid >= 0)
        self.scans += n
        self.degraded += int(np.sum(degraded))
        self.full += int(np.sum(np.all(live, axis=1)))
        self.detected += np.sum(detected, axis=0)
        self.reported += np.sum(reported, axis=0)
        ids, h, c = tid[live], hold[live], cls[live]
        if ids.size:
            uniq, first, inv = np.unique(ids, return_index=True, return_inverse=True)
            u = uniq.size
            counts = np.zeros((u, len(HOLDS)), np.int64)
            np.add.at(counts, (inv, h), 1)
            is_sp, is_tr = h == _SPEED, h == _TURN
            sp_sum = np.bincount(inv, np.where(is_sp, speed[live], 0.0), minlength=u)
            tr_sum = np.bincount(inv, np.where(is_tr, turn[live], 0.0), minlength=u)
            for j, i in enumerate(uniq.tolist()):
                rec = self.open.get(i)
                if rec is None:
                    rec = self.open[i] = [int(c[first[j]]), False, np.zeros(len(HOLDS), np.int64), 0.0, 0, 0.0, 0]
                    self.started[rec[0]] += 1
                rec[1] = rec[1] or bool(counts[j, 0])  # held by nothing while live: confirmed
                rec[2] += counts[j]
                rec[3] += float(sp_sum[j])
                rec[4] += int(counts[j, _SPEED])
                rec[5] += float(tr_sum[j])
                rec[6] += int(counts[j, _TURN])
        still = set(tid[-1][live[-1]].tolist())
        for i in [i for i in self.open if i not in still]:
            self._close(i)

    def _close(self, i: int) -> None:
        cls, confirmed, counts, sp, n_sp, tr, n_tr = self.open.pop(i)
        self.held_scans[cls] += counts
        if n_sp:
            self.speeds[cls].append(sp / n_sp)
        if n_tr:
            self.turns[cls].append(tr / n_tr)
        if confirmed:
            self.confirmed[cls] += 1
        else:
            self.held[cls, dominant(counts)] += 1

    # ----------------------------------------------------------------------------------------- output
    def finish(self) -> dict:
        """The tally (see the module docstring), with the tracks still live counted as ended. The
        tally may be fed on afterwards: tracks still live then are counted again when it ends."""
        self._flush()
        saved = {i: [r[0], r[1], r[2].copy(), *r[3:]] for i, r in self.open.items()}
        held, confirmed, held_scans = self.held.copy(), self.confirmed.copy(), self.held_scans.copy()
        speeds, turns = [list(s) for s in self.speeds], [list(t) for t in self.turns]
        for i in list(self.open):
            self._close(i)
        doc = {"scans": self.scans, "degraded": self.degraded, "slots": self.slots, "slots_full": self.full,
               "classes": {}}
        for c in self.tracked:
            never = self.held[c]
            doc["classes"][self.classes[c]] = {
                "detected": int(self.detected[c]), "reported": int(self.reported[c]),
                "tracks": int(self.started[c]), "confirmed": int(self.confirmed[c]),
                "never_confirmed": int(never.sum()),
                "held": {HOLDS[h]: int(never[h]) for h in range(1, len(HOLDS))},
                "held_scans": {HOLDS[h]: int(self.held_scans[c, h]) for h in range(1, len(HOLDS))},
                "speed_median": _median(self.speeds[c]), "max_speed": _limit(self.max_speed, c),
                "turn_rate_median": _median(self.turns[c]), "max_turn_rate": _limit(self.max_turn_rate, c),
            }
        self.open, self.held, self.confirmed, self.speeds, self.turns = saved, held, confirmed, speeds, turns
        self.held_scans = held_scans
        return doc


def dominant(counts) -> int:
    """The index into ``HOLDS`` a never-confirmed track is counted under, from its scans per hold:
    the test (speed, turn rate, majority: the first of them on a tie) that held it in most scans, if
    it did in at least ``BLAME_SHARE`` of the scans it waited for hits (a track that failed a test
    also waits for hits after each failure: those waiting scans are the test's doing, up to
    ``n_confirm`` a failure); else "too few scans" (the detections came and went)."""
    tests = (_SPEED, _TURN, _MAJORITY)
    best = max(tests, key=lambda h: (counts[h], -tests.index(h)))
    return best if counts[best] > 0 and counts[best] >= BLAME_SHARE * counts[_TOO_FEW] else _TOO_FEW


def _median(values) -> float | None:
    return float(np.median(values)) if values else None


def _limit(values: np.ndarray, c: int) -> float:
    return float(values.reshape(-1)[c] if values.size > 1 else values.reshape(-1)[0])


def tally_outputs(model, out) -> dict:
    """The tally of stacked outputs (a replay's) at once."""
    t = Tally(model)
    t.add(out)
    return t.finish()


def merge(tallies: "list[dict]") -> dict:
    """Tallies of several runs (logs) of one model summed into one (medians: of the runs' medians)."""
    if len(tallies) == 1:
        return tallies[0]
    doc = {k: sum(t[k] for t in tallies) for k in ("scans", "degraded", "slots_full")}
    doc["slots"] = tallies[0]["slots"]
    doc["classes"] = {}
    for name, first in tallies[0]["classes"].items():
        rows = [t["classes"][name] for t in tallies]
        c = {k: sum(r[k] for r in rows) for k in ("detected", "reported", "tracks", "confirmed", "never_confirmed")}
        for k in ("held", "held_scans"):
            c[k] = {h: sum(r[k][h] for r in rows) for h in first[k]}
        for k in ("speed_median", "turn_rate_median"):
            vals = [r[k] for r in rows if r[k] is not None]
            c[k] = _median(vals)
        c["max_speed"], c["max_turn_rate"] = first["max_speed"], first["max_turn_rate"]
        doc["classes"][name] = c
    return doc


def _pct(n: int, d: int) -> str:
    return f"{100.0 * n / max(d, 1):.0f} %"


def _suggest(median: float | None, limit: float, default: float) -> float:
    """A limit to retrain with: the default, or half again the median estimate, rounded up to 0.1."""
    guess = 1.5 * (median or 0.0)
    return max(default, math.ceil(guess * 10.0 - 1e-9) / 10.0, limit)


def warnings(tally: dict, model=None) -> list[str]:
    """One line per problem the tally shows, each with its likely cause and the option to change:
    a tracked class detected in at least half of the scans yet reported in fewer than half of those
    (why its tracks were not confirmed); more than half of the scans without a new map
    transformation; every track slot live in more than 5 % of the scans. ``model``: unused but for
    its track slots where the tally lacks them (the limits are in the tally)."""
    out = []
    scans = tally["scans"]
    if not scans:
        return out
    for name, c in tally["classes"].items():
        det, rep = c["detected"], c["reported"]
        if det < DETECTED_MIN * scans or rep >= REPORTED_MIN * det:
            continue
        head = f"{name} detected in {_pct(det, scans)} of scans but reported in {_pct(rep, scans)}"
        never, held, scans_held = c["never_confirmed"], c["held"], c["held_scans"]
        # The test that kept the class's tracks unconfirmed in the most scans (a track confirmed once
        # and then held by a test for the rest of its life lost as many rows as one never confirmed),
        # unless the tracks mostly waited for hits (:func:`dominant`).
        why = max(("speed", "turn rate", "majority"), key=lambda h: scans_held[h])
        if not scans_held[why] or scans_held[why] < BLAME_SHARE * scans_held["too few scans"]:
            if not never:
                out.append(f"{head}: its tracks were confirmed ({c['confirmed']}) but seldom reported (coasting "
                           "outside the site's bounds, or missed in most scans); check the site's bounds")
                continue
            why = "too few scans"
        plural = "s" if never != 1 else ""
        if held[why]:
            head = f"{head}: {never} track{plural} never confirmed, {held[why]}"
        elif never:
            head = (f"{head}: {never} track{plural} never confirmed; its tracks were held unconfirmed in "
                    f"{scans_held[why]} scans")
        else:
            head = (f"{head}: its tracks were confirmed, then held unconfirmed in {scans_held[why]} scans")
        if why == "speed":
            est = c["speed_median"]
            at = f"estimated {est:.2f} m/s" if est is not None else "estimated speed unknown"
            fix = _suggest(est, c["max_speed"], DEFAULT_MAX_SPEED)
            out.append(f"{head} for implausible speed ({at} against the model's limit {c['max_speed']:.2f} m/s): "
                       f"the model's max speed is too low; retrain with --max-speed {name}={fix:g}")
        elif why == "turn rate":
            est = c["turn_rate_median"]
            at = f"estimated {est:.2f} rad/s" if est is not None else "estimated turn rate unknown"
            fix = _suggest(est, c["max_turn_rate"], DEFAULT_MAX_TURN_RATE)
            out.append(f"{head} for implausible turn rate ({at} against the model's limit "
                       f"{c['max_turn_rate']:.2f} rad/s): the model's max turn rate is too low; retrain with "
                       f"--max-turn-rate {name}={fix:g}")
        elif why == "majority":
            out.append(f"{head} by the majority test (the scans at their place mostly saw something not {name}): "
                       f"the classifier calls the {name} something else in many scans; record more views of it and "
                       "retrain")
        else:
            out.append(f"{head} for too few scans (their detections came and went before confirmation): "
                       "the detections are intermittent; --confirm-scans N with a smaller N confirms sooner")
    deg = tally["degraded"]
    if deg > DEGRADED_MAX * scans:
        out.append(f"{deg} of {scans} scans without a new map transformation: the site's landmarks were "
                   f"{'never' if deg == scans else 'seldom'} found (wrong site file, sensor_pose guess off by more "
                   "than the gate, or landmarks the model was not trained on)")
    full = tally["slots_full"]
    slots = tally.get("slots") or (model.max_tracks if model is not None else 0)
    if full > FULL_MAX * scans:
        out.append(f"all {slots} track slots were full in {full} scans: more objects than slots; give "
                   f"--max-tracks {2 * slots}")
    return out
