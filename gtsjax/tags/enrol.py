"""Enrolment (issue 43, ``gtsjax enrol``): which code a robot's band shows, and how it is turned as mounted,
read from a log of that robot alone walking or turned in view; then stored in the site file.

**Reading the band over a whole log.** The log goes through the model offline, each track's poses
smoothed over its whole life (:mod:`gtsjax.drivers.smoothing`: the heading that says which part of the
band a return lies on is better smoothed than live). The robot is the one track of a class that reads
tags (its outline has an arc table); where two such tracks are confirmed together in more than
:data:`TWO_ROBOTS_SHARE` of the scans that show one, the log is refused: enrolment is one robot at a time.
Each scan's returns near that track's pose (within :data:`MARGIN` of the class's learnt outline) are
read as the step reads a candidate (:mod:`gtsjax.core.e_tags`): their place along the band through the
class's arc table, the log-likelihood ratio of tape against body of their range-normalised intensity
(clipped per return), summed in the reader's :data:`~gtsjax.core.e_tags.BINS` bins, each bin's sum
squashed per scan. The bins in the middle of each cell (away from its edges by
:data:`~gtsjax.train.tags.CELL_MARGIN` of a cell, where which cell a return is in is uncertain) sum,
over the log, to the cell's evidence.

**Headings on the wrong side.** Which part of the band a return lies on is read from the track's
heading, and a robot's outline is nearly the same turned (a Nao's half a turn): a track's heading can
lie on another side of the robot for a while, most of all through a model trained briefly, the kind a
site has. Summed as they come, such scans add the band turned to the band as it is, and the read is a
blend that fits no code. So each scan is read under the track's heading and under it turned by each
of the class's side hypotheses (the outline's learnt ``sides``, the headings its views are misread
as) and by half a turn (where no side is within :data:`HALF_TURN_NEAR` of it), and which of them the scan
shows is decided by the band itself, as an EM that labels scans (:func:`choose_sides`): all
scans start on the track's side; the consensus is the band summed over the scans as labelled; each
scan then takes the side under which its evidence agrees best with the consensus of the others
(``½ Σ_b e_b · tanh(½ w E_b)``: its bins' ratios, a log-likelihood ratio per bin, against the
consensus's belief of tape, the scan itself left out), the track's own side favoured by
:data:`OWN_SIDE_PRIOR` (log-odds), for at most :data:`SIDE_ITERATIONS` rounds.
It starts from the track's side only, so the band is read on the side the track holds most of the
time: a labelling that turns every scan agrees with its own consensus about as well (the outline is
nearly the same turned) and, compared by their totals, such a labelling won once the prior was
weak. A scan whose heading is off by less than a side (tens of degrees) may be taken as turned too:
its evidence is misplaced under every hypothesis, and the one that agrees best is kept. The number
of scans taken as turned is printed.

**Deciding.** A cell shown by fewer than :data:`MIN_SEEN` scans was not seen; the read stops there
(the robot must be turned so that every side faces the laser). A cell's probability of tape is
``σ(w · evidence)``, ``w`` the reader's weight (what one detection's read counts for in the step: a
scan's returns are far from independent reads); it is decided at :data:`CONFIDENT`. Each known code
(the site's wearers, the designed ones of ``gtsjax tags``'s ``tags.json``) at each rotation ``r`` (the
band's cell 0 over the outline's cell ``r``) has log-likelihood ``½ w Σ_k evidence_k · (±1)``, as the
step scores an identity; the best must beat the best of every other code, and the same code's other
rotations, by :data:`MIN_MARGIN`, and agree with every decided cell. Without known codes the read code
itself is stored where every cell is decided (offset 0: the band as it is mounted).
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..core.e_tags import BINS, TagReader, _llr, band_place
from ..core.geometry import relative, wrap
from ..errors import InputError
from ..io.site import SiteTags, TagWearer

#: Returns within this distance (m) of the class's learnt outline, at the track's smoothed pose, are its surface.
MARGIN = 0.05
#: The fewest scans that must show a cell's middle for it to count as seen.
MIN_SEEN = 5
#: A cell's probability of tape (or body) at which it is decided.
CONFIDENT = 0.95
#: The least log-likelihood (natural log: 20 to 1) by which the best code and rotation must beat the rest.
MIN_MARGIN = 3.0
#: Above this share of the scans that show a tagged robot, two of them shown at once is two robots.
TWO_ROBOTS_SHARE = 0.2
#: Side hypotheses within this angle (rad) of half a turn stand for it; else half a turn is added.
HALF_TURN_NEAR = math.radians(20.0)
#: Log-odds by which a scan is taken to show the track's own side rather than another, a priori.
OWN_SIDE_PRIOR = 1.5
#: Rounds of the side labelling (each reassigns every scan at once).
SIDE_ITERATIONS = 6
#: Scans read by one compiled call (the last padded).
CHUNK = 256


@dataclasses.dataclass(frozen=True)
class BandRead:
    """A band read over a log: per cell of the outline (cell ``k`` spans ``[k/N, (k+1)/N)`` of the band
    from the outline's origin), the evidence of tape (summed, squashed log-likelihood ratios), the
    scans that showed it and the returns read, and the reader's weight."""

    cells: int
    evidence: np.ndarray  # [N]
    seen: np.ndarray  # [N] scans
    returns: np.ndarray  # [N]
    weight: float
    scans: int  # scans that showed the robot
    turned: tuple[tuple[float, int], ...] = ()  # (heading offset in rad, scans read turned by it) per other side

    @property
    def p_tape(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.clip(self.weight * self.evidence, -50, 50)))

    @property
    def decided(self) -> np.ndarray:
        p = self.p_tape
        return (self.seen >= MIN_SEEN) & (np.maximum(p, 1 - p) >= CONFIDENT)

    def code_string(self) -> str:
        """The read code, ``1`` tape, ``0`` body, ``?`` undecided, outline cell 0 first."""
        p, d = self.p_tape, self.decided
        return "".join(("1" if p[k] > 0.5 else "0") if d[k] else "?" for k in range(self.cells))

    def unseen(self) -> list[int]:
        return [int(k) for k in np.flatnonzero(self.seen < MIN_SEEN)]

    def turned_note(self) -> str:
        """How many scans were read with the heading turned, and by how much."""
        n = sum(k for _, k in self.turned)
        if not n:
            return f"every one of the {self.scans} scans read at the track's heading"
        parts = ", ".join(f"{k} by {math.degrees(a):+.0f}°" for a, k in self.turned if k)
        return f"{n} of the {self.scans} scans read with the track's heading turned ({parts})"


@dataclasses.dataclass(frozen=True)
class Match:
    """The best known code and rotation for a read: its owner's name (``None``: the read itself), code,
    offset in cells, the log-likelihood margins to the best other code and to the code's best other
    rotation, that other code's owner and code, and the decided cells that disagree with it."""

    name: str | None
    code: str
    offset: int
    margin: float
    offset_margin: float
    next_name: str | None
    next_code: str | None
    disagree: tuple[int, ...]


# ------------------------------------------------------------------------------------------ device
@jax.jit
def band_evidence(reader: TagReader, arc: Float[Array, " angles"], q: Float[Array, "scans beams 2"],
                  intensity: Float[Array, "scans beams"], rng: Float[Array, "scans beams"],
                  use: Bool[Array, "scans beams"]) -> tuple[Float[Array, "scans bins"], Float[Array, "scans bins"]]:
    """Each scan's evidence per bin along the band, as the step sums it (:func:`~gtsjax.core.e_tags.read_tags`:
    each return's clipped log-likelihood ratio of tape against body, summed per bin, each bin squashed to
    ``±bin_cap``), from robot-frame points ``q``; and the returns per bin. ``use``: the robot's returns."""
    bins = BINS
    place = band_place(arc, q)
    b = jnp.clip(jnp.floor(place * bins).astype(jnp.int32), 0, bins - 1)
    ok = use & jnp.isfinite(intensity) & (intensity > 0)
    llr = jnp.where(ok, _llr(reader, jnp.where(ok, intensity, 1.0), jnp.where(ok, rng, 1.0)), 0.0)

    def one(bb, v, m):
        return (jnp.zeros(bins, v.dtype).at[bb].add(v), jnp.zeros(bins, v.dtype).at[bb].add(m.astype(v.dtype)))

    per_bin, count = jax.vmap(one)(b, llr, ok)
    return reader.bin_cap * jnp.tanh(per_bin / reader.bin_cap), count


@jax.jit
def side_evidence(reader: TagReader, arc: Float[Array, " angles"], offsets: Float[Array, " sides"],
                  q: Float[Array, "scans beams 2"], intensity: Float[Array, "scans beams"],
                  rng: Float[Array, "scans beams"], use: Bool[Array, "scans beams"]
                  ) -> tuple[Float[Array, "scans sides bins"], Float[Array, "scans sides bins"]]:
    """:func:`band_evidence` with the heading turned by each of ``offsets``: the points ``q`` (in the
    frame of the track's pose) in the frame of the pose turned by each."""
    def turned(a):
        c, s = jnp.cos(a), jnp.sin(a)  # the frame turned by a: points turned by −a
        qa = jnp.stack([c * q[..., 0] + s * q[..., 1], -s * q[..., 0] + c * q[..., 1]], -1)
        return band_evidence(reader, arc, qa, intensity, rng, use)

    per_bin, count = jax.vmap(turned)(offsets)
    return jnp.moveaxis(per_bin, 0, 1), jnp.moveaxis(count, 0, 1)


def side_offsets(outline, cls: int) -> np.ndarray:
    """The heading offsets (rad) a scan of class ``cls`` is read under: the track's own (0), the class's
    other side hypotheses, and half a turn where none is within :data:`HALF_TURN_NEAR` of it."""
    sides = np.asarray(outline.sides[cls], np.float64)[np.asarray(outline.side_mask[cls], bool)]
    out = [0.0] + [float(wrap(a)) for a in sides if abs(float(wrap(a))) > 1e-6]
    if all(abs(float(wrap(a - math.pi))) > HALF_TURN_NEAR for a in out):
        out.append(math.pi)
    return np.asarray(out)


def choose_sides(per_bin: np.ndarray, weight: float, prior: float = OWN_SIDE_PRIOR,
                 iterations: int = SIDE_ITERATIONS) -> np.ndarray:
    """Per scan, the side (index into the offsets, 0 the track's own) its evidence ``per_bin`` ``[scans,
    sides, bins]`` is read under: the EM of the module, started from the track's side."""
    t, n_sides, _ = per_bin.shape
    rows = np.arange(t)
    bias = np.where(np.arange(n_sides) == 0, 0.0, -prior)
    side = np.zeros(t, int)
    for _ in range(iterations):
        own = per_bin[rows, side]  # [T, B]
        others = own.sum(0)[None] - own  # the consensus without the scan itself
        new = np.argmax(0.5 * np.einsum("tsb,tb->ts", per_bin, np.tanh(0.5 * weight * others)) + bias, 1)
        if np.array_equal(new, side):
            break
        side = new
    return side


def cell_sums(per_bin: np.ndarray, count: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bins (``[scans, BINS]``) to cells: the evidence, the scans showing, the returns of the bins in each
    cell's middle (each bin by its centre)."""
    from ..train.tags import CELL_MARGIN

    centre = (np.arange(BINS) + 0.5) / BINS * cells
    cell = np.minimum(np.floor(centre).astype(int), cells - 1)
    frac = centre - np.floor(centre)
    middle = (frac > CELL_MARGIN) & (frac < 1 - CELL_MARGIN)
    evidence, seen, returns = np.zeros(cells), np.zeros(cells, int), np.zeros(cells, int)
    for k in range(cells):
        sel = (cell == k) & middle
        if not sel.any():  # a cell narrower than a bin's middle share: all its bins
            sel = cell == k
        evidence[k] = float(per_bin[:, sel].sum())
        seen[k] = int((count[:, sel].sum(1) > 0).sum())
        returns[k] = int(count[:, sel].sum())
    return evidence, seen, returns


# ------------------------------------------------------------------------------------------ host
def robot_track(out, has_arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From a replay's stacked outputs: per scan, the slot of the one confirmed track of a class that
    reads tags (``-1``: none, or two at once) and its class. Two at once in more than
    :data:`TWO_ROBOTS_SHARE` of the scans that show one is refused in one line."""
    mask = np.asarray(out.track_mask, bool)
    cls = np.asarray(out.track_class)
    tagged = mask & has_arc[np.clip(cls, 0, len(has_arc) - 1)]
    n = tagged.sum(1)
    shown = int((n >= 1).sum())
    if shown == 0:
        raise InputError("enrol", "no robot of a class that reads tags was tracked in the log: is the robot in the "
                                  "laser's view, and the model trained for it?")
    both = int((n >= 2).sum())
    if both > TWO_ROBOTS_SHARE * shown:
        raise InputError("enrol", f"two robots were tracked at once in {both} of the {shown} scans that show one "
                                  f"({100 * both / shown:.0f} %): enrolment is one robot at a time, alone in view")
    slot = np.where(n == 1, np.argmax(tagged, 1), -1)
    return slot, np.where(slot >= 0, np.take_along_axis(cls, np.maximum(slot, 0)[:, None], 1)[:, 0], -1)


def replay_smoothed(model, log):
    """The log through the model in compiled chunks, each track's poses then smoothed over its life:
    the stacked outputs (NumPy)."""
    from ..drivers.batch import process_log
    from ..drivers.smoothing import smooth_output
    from ..io.logs import to_scans

    scans = to_scans(log, model.n_beams)
    _, (out, filtered) = process_log(model, scans, vectorise=True, filtered=True)
    return smooth_output(out, filtered, log.stamps, model.tracker)


def read_log(reader: TagReader, model, log, out, cells: int) -> BandRead:
    """The band of the log's one tagged robot read over the whole log (see the module), from the
    replay's outputs ``out`` (smoothed) and the reader's intensity model, arc tables and caps."""
    from ..core.e_refine import lookup

    if log.intensities is None or not np.any(np.nan_to_num(log.intensities) > 0):
        raise InputError("enrol", "the log carries no intensities: tags are read from a scanner that reports them "
                                  "(UTM-30LX), recorded with them")
    has_arc = np.asarray(reader.has_arc, bool)
    slot, cls = robot_track(out, has_arc)
    keep = np.flatnonzero(slot >= 0)
    pose = np.take_along_axis(np.asarray(out.track_pose)[keep], slot[keep, None, None], 1)[:, 0]  # [T, 3] in O
    sensor = np.asarray(out.sensor_pose)[keep]
    xy = relative(sensor.astype(np.float64), pose[:, :2].astype(np.float64))
    in_sensor = np.concatenate([xy, wrap(pose[:, 2:3] - sensor[:, 2:3])], -1)  # the robot in the sensor's frame
    angles = log.angles()
    valid = log.valid()
    outline = model.outline
    evidence = np.zeros(cells)
    seen, returns = np.zeros(cells, int), np.zeros(cells, int)
    turned: dict[float, int] = {}
    for c in np.unique(cls[keep]):
        rows = keep[cls[keep] == c]
        rp = in_sensor[cls[keep] == c]
        offsets = side_offsets(outline, int(c))
        bins, counts = [], []
        for a in range(0, len(rows), CHUNK):
            t, p = rows[a:a + CHUNK], rp[a:a + CHUNK]
            pad = CHUNK - len(t)
            rng = np.where(valid[t], log.ranges[t], 0.0)
            pts = np.stack([rng * np.cos(angles), rng * np.sin(angles)], -1)
            q = relative(p[:, None, :], pts)
            d, _ = lookup(outline, jnp.full(q.shape[:2], int(c), jnp.int32), jnp.asarray(q, jnp.float32))
            use = valid[t] & (np.asarray(d) < MARGIN)
            args = [np.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1)) for x in
                    (q.astype(np.float32), np.nan_to_num(log.intensities[t]).astype(np.float32),
                     rng.astype(np.float32), use)]
            per_bin, count = side_evidence(reader, reader.arc[int(c)], jnp.asarray(offsets, jnp.float32),
                                           *map(jnp.asarray, args))
            bins.append(np.asarray(per_bin)[:len(t)])
            counts.append(np.asarray(count)[:len(t)])
        per_bin, count = np.concatenate(bins), np.concatenate(counts)
        side = choose_sides(per_bin, float(reader.weight))
        pick = np.arange(len(side))
        e, s, r = cell_sums(per_bin[pick, side], count[pick, side], cells)
        evidence, seen, returns = evidence + e, seen + s, returns + r
        for j in range(1, len(offsets)):
            turned[float(offsets[j])] = turned.get(float(offsets[j]), 0) + int((side == j).sum())
    return BandRead(cells, evidence, seen, returns, float(reader.weight), int(len(keep)), tuple(turned.items()))


def match(read: BandRead, known: list[tuple[str, str]]) -> Match:
    """The best of the ``known`` codes (owner, code string) at every rotation against the read (see the
    module); with none known, the read itself (offset 0)."""
    n = read.cells
    d, p = read.decided, read.p_tape
    bits = p > 0.5
    if not known:
        return Match(None, "".join("1" if b else "0" for b in bits), 0, math.inf, math.inf, None, None, ())
    hyp = []  # (log-likelihood, owner, code, offset)
    for name, code in known:
        c = np.array([ch == "1" for ch in code], bool)
        for r in range(n):
            pattern = np.roll(c, r)  # the outline's cell k wears the band's cell k − r
            hyp.append((0.5 * read.weight * float((read.evidence * np.where(pattern, 1.0, -1.0)).sum()), name, code, r))
    hyp.sort(key=lambda h: -h[0])
    best = hyp[0]
    other = next((h for h in hyp if h[2] != best[2]), None)
    turned = next((h for h in hyp if h[2] == best[2] and h[3] != best[3]), None)
    pattern = np.roll(np.array([ch == "1" for ch in best[2]], bool), best[3])
    disagree = tuple(int(k) for k in np.flatnonzero(d & (bits != pattern)))
    return Match(best[1], best[2], best[3], math.inf if other is None else best[0] - other[0],
                 math.inf if turned is None else best[0] - turned[0], None if other is None else other[1],
                 None if other is None else other[2], disagree)


def check(read: BandRead, m: Match, known: bool) -> None:
    """Refuse, in one line, a read that does not single out a code: cells not seen, a known code not
    matched clearly, or (without known codes) a cell undecided."""
    if unseen := read.unseen():
        raise InputError("enrol", f"cell{'s' if len(unseen) > 1 else ''} {', '.join(map(str, unseen))} of {read.cells} "
                                  f"{'were' if len(unseen) > 1 else 'was'} not seen (fewer than {MIN_SEEN} scans "
                                  "showed them): turn the robot so that every side faces the laser")
    what = f"read {read.code_string()} (outline cell 0 first, ? undecided)"
    if not known:
        if "?" in read.code_string():
            raise InputError("enrol", f"{what}: with no known codes every cell must be decided; record longer, "
                                      "nearer the laser, or give the designed codes (--tags tags.json)")
        return
    if m.disagree:
        raise InputError("enrol", f"{what}: no known code fits; the nearest, {m.code} turned {m.offset} "
                                  f"({m.name}), disagrees in cell{'s' if len(m.disagree) > 1 else ''} "
                                  f"{', '.join(map(str, m.disagree))}")
    if m.margin < MIN_MARGIN:
        raise InputError("enrol", f"{what}: {m.code} ({m.name}) and {m.next_code} ({m.next_name}) fit almost as well "
                                  f"(margin {m.margin:.1f}, {MIN_MARGIN:g} needed): record longer, turning the robot")
    if m.offset_margin < MIN_MARGIN:
        raise InputError("enrol", f"{what}: {m.code} ({m.name}) fits turned by more than one number of cells "
                                  f"(margin {m.offset_margin:.1f}, {MIN_MARGIN:g} needed): record longer, turning "
                                  "the robot")


def enrolled(tags: SiteTags | None, robot: str, m: Match, *, designed: dict[str, str] | None = None,
             replace: bool = False, base: SiteTags | None = None) -> tuple[SiteTags, list[str]]:
    """The site's ``tags`` entry with ``robot`` wearing the matched code and offset (added, or replacing
    its entry), and what changed, one line each. Refused in one line: a robot designed (``tags.json``)
    to wear another code; a code another robot of the site wears (unless ``replace``: that robot's
    entry goes). ``base``: the entry to start from where the site has none (cells, perimeter, range)."""
    notes = []
    if designed is not None and robot in designed and designed[robot] != m.code:
        owner = next((n for n, c in designed.items() if c == m.code), None)
        raise InputError("enrol", f"{robot} was designed to wear {designed[robot]} (tags.json) but its band reads as "
                                  f"{m.code}" + (f", {owner}'s" if owner else "") + ": is it wearing the right band?")
    start = tags if tags is not None else base
    assert start is not None
    robots = list(tags.robots) if tags is not None else []
    for w in [w for w in robots if w.name != robot and w.code == m.code]:
        if not replace:
            raise InputError("enrol", f"the code {m.code} is already worn by {w.name} in the site; two robots wearing "
                                      f"one code cannot be told apart (--replace gives it to {robot}, removing "
                                      f"{w.name})")
        robots.remove(w)
        notes.append(f"removed {w.name}, who wore {w.code}")
    new = TagWearer(robot, m.code, int(m.offset))
    old = next((w for w in robots if w.name == robot), None)
    if old is not None:
        robots[robots.index(old)] = new
        notes.append(f"replaced {robot}'s entry (was {old.code}, offset {old.offset_cells})")
    else:
        robots.append(new)
        notes.append(f"added {robot}")
    return dataclasses.replace(start, robots=tuple(robots)), notes


def outline_perimeter(model, cls: int) -> float:
    """The length (m) of class ``cls``'s learnt outline (its zero contour), for a band sized to it."""
    import contourpy

    o = model.outline
    field, lo, cell = np.asarray(o.field[cls]), np.asarray(o.lo[cls]), float(o.cell[cls])
    g = field.shape[0]
    xs, ys = lo[0] + cell * np.arange(g), lo[1] + cell * np.arange(g)
    verts = max(contourpy.contour_generator(xs, ys, field[..., 0].astype(np.float64).T).lines(0.0), key=len)
    return float(np.linalg.norm(np.diff(np.vstack([verts, verts[:1]]), axis=0), axis=1).sum())
