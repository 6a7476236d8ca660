"""Sanity ranges of what training learns from a user's data, and where each value came from.

A user's recording can teach a model something no robot does: a robot turned on the spot at each
grid point has no translation in its labels, and a top speed learnt from it was 0 m/s, so every track
moved "faster than its class can" and none was ever confirmed. So every parameter learnt from data is
held to a physical range (:class:`Bound`): a value outside its *hard* range (``floor``–``ceiling``) is
clamped to it, one outside its *plausible* range is kept but warned about, and either way the report
says where the value came from (learnt from how much evidence, the default, or set by the user) and
which option overrides it (:func:`entry`, kept in the training report's ``"learnt"`` list and printed
by ``gtsjax train``).
"""

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class Bound:
    """What a learnt value may be: clamped to ``[floor, ceiling]``, warned about outside ``plausible``."""

    what: str  # a reader's name for it
    unit: str
    floor: float
    ceiling: float
    plausible: tuple[float, float]
    option: str | None  # the option of ``gtsjax train`` that sets it, where there is one
    why: str  # why the range is what it is, for the documentation and the warning


# Motion limits of a tracked class (the tracker's plausible-motion test). The floors keep a model
# whose labels hold no motion from confirming nothing: a robot is carried or pushed at least this fast
# now and then; the ceilings keep a recording of a robot carried or spun by hand from switching the test
# off. A Nao walks at about 0.35 m/s and turns at about 1 rad/s; wheeled SPL/SSL robots reach 3 m/s.
MAX_SPEED = Bound("max speed", "m/s", 0.3, 5.0, (0.3, 2.0), "--max-speed",
                  "a walking robot is slower than 2 m/s; people's legs (1-1.5 m/s) are told from robots by it")
MAX_TURN_RATE = Bound("max turn rate", "rad/s", 1.0, 12.0, (1.0, 2 * math.pi), "--max-turn-rate",
                      "a humanoid turns at about 1 rad/s, a wheeled robot at up to one turn a second")
# The tracker's turn-rate process noise (``TrackerParams.q_theta``, the density of the white angular
# acceleration of its constant-velocity model): how fast a robot's turn rate changes. Too small, a track
# lags a robot that starts or stops turning and rejects its right reads; too large, a still robot's
# heading follows its reads' noise. The simulator's walking robots show 0.07-0.10 rad²/s³, its match
# 0.25. The floor is the tracker's default: labels that turn more steadily (a robot turned on the spot
# by a fixed step each scan, a hand-drawn path) are no evidence that a robot does.
TURN_RATE_NOISE = Bound("turn-rate noise", "rad²/s³", 0.02, 5.0, (0.0, 1.0), None,
                        "how fast the robots' turn rate changes while they move: the simulator's 0.07-0.25; "
                        "above 1 a hand's, and the tracker's default is kept")
# A mobile class's heading against its direction of travel (the tracker's motion evidence,
# ``core.g_heading.motion_evidence``): the spread of its heading about its travel, the offset, and the
# share of travel in other directions. The floor keeps labels steadier than any robot walks (a
# simulator's, a hand-drawn path) from making one second of walking outweigh every view; at 180° the
# travel says nothing (a holonomic robot).
MOTION_SPREAD = Bound("heading's spread about its travel", "°", 5.0, 180.0, (0.5, 180.0), None,
                      "a robot that walks along its heading does so within some degrees; at 180° its travel "
                      "says nothing of its heading (a holonomic robot, or labels without translation)")
MOTION_OFFSET = Bound("heading less its travel", "°", -180.0, 180.0, (-180.0, 180.0), None,
                      "any offset: a robot may walk forwards, backwards or sideways")
MOTION_OTHER = Bound("share of travel off its heading", "", 0.0, 1.0, (0.0, 1.0), None,
                     "sidesteps and turns on the spot; 1 for a robot that travels any way it likes")
# The scanner's rate: the tracker's confirmation, reporting and deletion times are seconds, turned into
# scans by it. Hokuyo's scanners run at 10-40 Hz.
SCAN_RATE = Bound("scan rate", "Hz", 1.0, 100.0, (5.0, 50.0), "--scan-rate",
                  "Hokuyo's scanners run at 10-40 Hz; the tracker's times in scans follow from it")
# The open-set test's threshold (a squared distance in the classifier's input space, per feature):
# learnt as a quantile of held-out distances to the class's own examples. Below the floor a class
# rejects its own held-out views; the ceiling keeps it a test.
OPEN_SET_D2 = Bound("open-set threshold d²", "", 1e-3, 1e6, (1e-2, 1e3), None,
                    "a quantile of the class's own held-out distances; outside this it rejects its own views "
                    "or nothing")
# Shape envelope: the width of a tracked class's candidates (m). A robot narrower than 3 cm or wider
# than 2 m is not a robot a 2-D laser sees as one segment.
WIDTH = Bound("width", "m", 0.0, 3.0, (0.03, 2.0), None,
              "a robot seen as one segment is between 3 cm and 2 m wide")


# How far a mobile class's outline lies from its own half-turn (mm): within ``train.outline.HALF_TURN_M``
# the class is taken as alike turned half a turn. Any distance is plausible; the row says what it decided.
HALF_TURN = Bound("distance from its half-turn", "mm", 0.0, 1e3, (0.0, 1e3), "--heading-turns",
                  "within 3 mm of its half-turn a class's heading is read modulo 180°")


# Stage e′'s side posterior (``train.outline.calibrate_outline``), learnt on the class's held-out views:
# the prior that the GP read the right side, and of the rest the share of the search over every 45°.
# The search's share never falls below 5 %: held-out views come from the recording the GP learnt from
# and cannot show how often it misreads the sides that recording rarely showed.
SIDE_PRIOR = Bound("prior of the GP's side", "", 0.3, 0.99, (0.3, 0.99), None,
                   "the share of held-out views whose side the GP read right, from 0.3 to 0.99")
SEARCH_PRIOR = Bound("prior of the searched sides", "", 0.05, 0.8, (0.05, 0.8), None,
                     "never below 0.05: held-out views cannot show how often sides the labels rarely showed are "
                     "misread")


# The radius of the site's round landmarks (``train.labels.landmark_centres``): the first labelling
# pass places each landmark candidate at the centre of a circle of this radius through its points, the
# radius that leaves the map rigid. RoboCup's goal and field posts are 5 cm in radius.
LANDMARK_RADIUS = Bound("radius of the round landmarks", "mm", 10.0, 300.0, (15.0, 150.0), None,
                        "a post a laser places by its centre is 1.5-15 cm in radius")
# How far from rigid (1) the first pass's map may be before the labels are warned about: a share of
# every label's range.
MAP_SCALE_WARN = 0.005


def landmark_rows(centres: list[dict], names: list[str], landmarks: tuple[str, ...]) -> list[dict]:
    """Rows of the learnt-parameter table for each labelled log's landmark radius
    (``train.labels.landmark_centres``'s evidence), and a warning where its map stayed far from rigid."""
    rows = []
    who = ", ".join(landmarks) or None
    for ev, name in zip(centres, names, strict=True):
        before, after = ev["scale_before"], ev["scale_after"]
        if not math.isfinite(before):
            continue  # never three landmarks in view: no map to measure
        if math.isfinite(ev["radius"]):
            rows.append(entry(LANDMARK_RADIUS, who, round(1e3 * ev["radius"], 1), "learnt",
                              f"{ev['candidates']} candidates near the landmarks in {name}: the map's scale "
                              f"{before:.4f} from their surfaces, {after:.4f} from circles of this radius"))
            continue
        row = {"class": who, "parameter": LANDMARK_RADIUS.what, "unit": LANDMARK_RADIUS.unit, "value": 0.0,
               "source": "default", "evidence": f"no radius within {LANDMARK_RADIUS.floor:g}-{LANDMARK_RADIUS.ceiling:g} "
               f"mm makes the map of {name} rigid: it is fitted to the candidates' surfaces (scale {before:.4f})",
               "hard_range": None, "plausible": list(LANDMARK_RADIUS.plausible)}  # none learnt: nothing to hold
        if abs(before - 1.0) > MAP_SCALE_WARN:
            row["warning"] = (f"the map of {name} from its landmarks scales by {before:.4f}, not 1 (landmarks that are "
                              f"not round, or a tilted laser): its labels sit {100 * abs(before - 1):.1f} % of their "
                              "range off, and the learnt outlines are that much off in size")
        rows.append(row)
    return rows


def outline_rows(outline_report: dict) -> list[dict]:
    """Rows of the learnt-parameter table for each class's calibrated side posterior and where a fit on
    another side takes its position from (``train.outline.fit_outlines``'s report)."""
    rows = []
    for c, rep in outline_report.items():
        cal = rep.get("calibration")
        if cal is None or not rep.get("used", False):
            continue
        n = f"{cal['examples']} held-out views"
        rows.append(entry(SIDE_PRIOR, c, cal["prior_right"], "learnt", n))
        rows.append(entry(SEARCH_PRIOR, c, cal["prior_search"], "learnt", n))
        off = cal["off_side"]
        if "gp_rmse_cm" in off:
            ev = (f"{off['examples']} held-out views refined to another side than the GP read: its position "
                  f"{off['gp_rmse_cm']:g} cm off, the fit's {off['fit_rmse_cm']:g} cm")
        else:
            ev = "no held-out view refined to another side than the GP read"
        rows.append({"class": c, "parameter": "position on another side", "unit": "",
                     "value": 1.0 if off["position_from"] == "fit" else 0.0, "source": "learnt",
                     "evidence": ev + f" (1: the fit's, with {off['min_examples']} such views or more; 0: the GP's)",
                     "hard_range": [0.0, 1.0], "plausible": [0.0, 1.0]})
    return rows


def clamp(bound: Bound, value: float) -> float:
    return float(min(max(value, bound.floor), bound.ceiling))


def entry(bound: Bound, cls: str | None, value: float, source: str, evidence: str, *,
          learnt: float | None = None) -> dict:
    """One row of the training report's table of learnt parameters: the value used, where it came from
    (``source``: "learnt", "default", "set"), the evidence in words, the ranges, and a one-line
    ``warning`` where ``learnt`` (the value before clamping; ``value`` when it was not clamped) lies
    outside the plausible range, naming the option that overrides it."""
    raw = value if learnt is None else learnt
    row = {"class": cls, "parameter": bound.what, "unit": bound.unit, "value": value, "source": source,
           "evidence": evidence, "hard_range": [bound.floor, bound.ceiling], "plausible": list(bound.plausible)}
    lo, hi = bound.plausible
    if source != "set" and not (lo <= raw <= hi):
        who = f"{cls}'s " if cls else ""
        clamped = f", {'raised' if value > raw else 'lowered'} to {value:g}" if value != raw else ""
        fix = f"; set it with {bound.option} {cls + '=' if cls else ''}VALUE" if bound.option else ""
        row["warning"] = (f"{who}{bound.what} {source} as {raw:.3g} {bound.unit} from {evidence} is outside its "
                          f"plausible range {lo:g}-{hi:g} {bound.unit} ({bound.why}){clamped}{fix}")
    return row


def shape_rows(envelopes: dict, open_set: dict, classes, mobiles) -> list[dict]:
    """Rows of the learnt-parameter table for each tracked class's shape envelope (its widths) and
    open-set threshold, from the reports of :func:`~gtsjax.train.classifier.fit_envelope` and
    :func:`~gtsjax.train.classifier.fit_support` (keyed by class index)."""
    rows = []
    for k, c in enumerate(classes):
        if c not in mobiles:
            continue
        if (env := envelopes.get(k)) is not None:
            lo, hi = env["width_m"]
            row = entry(WIDTH, c, hi, "learnt", f"its labelled views at {env['range_bins_seen'][0]:g}-"
                        f"{env['range_bins_seen'][1]:g} m (widths {lo:g}-{hi:g} m)")
            row["parameter"] = "widest view"
            rows.append(row)
        if (op := open_set.get(k)) is not None:
            row = entry(OPEN_SET_D2, c, op["threshold_d2"], "learnt", f"{op['threshold_from']} examples")
            if op["class_rejected"] > 0.1 and "warning" not in row:
                row["warning"] = (f"{c}'s open-set test rejects {100 * op['class_rejected']:.0f} % of its own "
                                  f"{op['threshold_from']} examples: its views vary more than its training examples "
                                  "cover; record more views of it")
            rows.append(row)
    return rows
