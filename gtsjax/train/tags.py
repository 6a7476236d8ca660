"""Training the tag reader (issue 43, stage e″, :mod:`gtsjax.core.e_tags`) from labelled logs of robots
wearing tags: the site says each robot's code (its ``tags`` entry), the log which labelled object is
which robot (``truth_names``).

* **Where along the band.** Each mobile class's table of arc length by polar angle comes from its
  learnt outline (stage e′'s distance field, its zero contour; :func:`arc_from_field`), origin at its
  furthest front-right point, as the bands are laid (``docs/tags.md``).
* **Tape or body.** Each labelled robot's returns within :data:`NEAR_OUTLINE` of its outline at its
  true pose, placed along its band, in the middle of a cell (away from the cell edges by
  :data:`CELL_MARGIN` of a cell), are tape or body by its code. Their log intensity is fitted as
  ``a_tape | a_body − β log r`` (one range exponent ``β``, least squares); the range-normalised
  ``log I + β log r`` of each kind is taken as a Gaussian (mean and standard deviation).

Every learnt value has a sanity range, and the report says where it came from. The reader is left out
(the model reads no tags, and the report says why in one line) where the logs carry no intensity,
where no site has tags or no log names its robots, where there are fewer than :data:`MIN_RETURNS`
returns of either kind, or where tape and body are less than :data:`MIN_SEPARATION` pooled standard
deviations apart (tape no brighter than the robots' own surface).
"""

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..core.e_refine import Outline, lookup
from ..core.e_tags import ARC_ANGLES, TagReader, arc_table, band_place, patterns
from ..core.geometry import relative
from ..io.logs import ScanLog
from .labels import Examples, per_log_sites
from .outline import candidate_points, truth_in_sensor

#: Returns further than this (m) from the robot's outline at its true pose are not its surface.
NEAR_OUTLINE = 0.03
#: Returns nearer a cell's edge than this share of a cell are left out (which cell is uncertain).
CELL_MARGIN = 0.15
#: The fewest returns of tape, and of body, to learn from.
MIN_RETURNS = 200
#: Tape and body must be at least this many pooled standard deviations apart.
MIN_SEPARATION = 2.0
#: The range exponent's sanity range: intensity falls with range, by at most r⁻².
RANGE_EXP = (0.0, 2.0)
#: The reading's settings (not learnt from the user's data): cells' worth of band in view to read, the clip
#: of one return's log-likelihood ratio, the squash of one bin's, and what one detection's read counts for.
#: ``MIN_CELLS`` and ``READ_WEIGHT`` were chosen on a 30 s two-laser match of seed 3 (weights 1, 0.1,
#: 0.05, 0.02, 0.01, 0.005; 1, 2, 2.5 and 3 cells): at weight 1 a few confident misreads floored the right
#: identity and 5 % of rows were named wrong; at 0.02 none were. Not on the seeds measured in docs/tags.md.
MIN_CELLS, POINT_CAP, BIN_CAP, READ_WEIGHT = 2.0, 5.0, 3.0, 0.02


def arc_from_field(field: np.ndarray, lo: np.ndarray, cell: float, angles: int = ARC_ANGLES) -> np.ndarray:
    """A class's ``arc`` table from its learnt outline (``Outline.field[k]``): the zero contour of the
    signed distance (the longest closed line), counter-clockwise, through :func:`~gtsjax.core.e_tags.arc_table`."""
    import contourpy

    g = field.shape[0]
    xs = lo[0] + cell * np.arange(g)
    ys = lo[1] + cell * np.arange(g)
    lines = contourpy.contour_generator(xs, ys, np.asarray(field[..., 0], np.float64).T).lines(0.0)
    verts = max(lines, key=len)
    if np.allclose(verts[0], verts[-1]):
        verts = verts[:-1]
    area = 0.5 * np.sum(verts[:, 0] * np.roll(verts[:, 1], -1) - np.roll(verts[:, 0], -1) * verts[:, 1])
    return arc_table(verts if area > 0 else verts[::-1], angles)


def fit_intensity(intensity: np.ndarray, rng: np.ndarray, tape: np.ndarray) -> tuple[float, float, float, float,
                                                                                    float, float]:
    """The intensity model from returns known tape or body: ``log I = a_tape | a_body − β log r`` by least
    squares; returns ``β`` as fitted, ``β`` within :data:`RANGE_EXP`, and the mean and standard deviation
    (at least 0.05) of ``log I + β log r`` of tape, then of body."""
    logi, logr, tape = np.log(intensity), np.log(rng), np.asarray(tape, bool)
    design_m = np.stack([tape.astype(float), (~tape).astype(float), -logr], -1)
    coef, *_ = np.linalg.lstsq(design_m, logi, rcond=None)
    beta = float(np.clip(coef[2], *RANGE_EXP))
    u = logi + beta * logr
    return (float(coef[2]), beta, float(u[tape].mean()), float(max(u[tape].std(), 0.05)), float(u[~tape].mean()),
            float(max(u[~tape].std(), 0.05)))


def fit_tags(logs: Sequence[ScanLog], ex: Examples, site, classes: tuple[str, ...], mobiles: tuple[str, ...],
             outline: Outline | None, window: int, rng: np.random.Generator, max_examples: int = 4000
             ) -> tuple[TagReader | None, dict]:
    """The tag reader learnt from the labelled logs (see the module), and its report: what was learnt,
    from what, or in one line why nothing was."""
    def none(why: str):
        return None, {"tags": False, "why": why}

    sites = per_log_sites(site, len(logs))
    tagged = [s.tags for s in sites if getattr(s, "tags", None) is not None]
    if not tagged:
        return none("the site has no tags")
    if all(log.intensities is None for log in logs):
        return none("the logs carry no intensity (a scanner without it cannot read tags)")
    if outline is None:
        return none("no mobile class has a learnt outline to read the band along")
    names = [log.extra.get("truth_names") for log in logs]
    if all(n is None for n in names):
        return none("no log names its robots (truth_names), so no return can be told tape or body")
    arc = np.zeros((len(classes), ARC_ANGLES), np.float32)
    has = np.zeros(len(classes), bool)
    fld = np.asarray(outline.field)
    for name in mobiles:
        k = classes.index(name)
        if bool(outline.has[k]):
            arc[k] = arc_from_field(fld[k], np.asarray(outline.lo[k]), float(outline.cell[k]))
            has[k] = True
    # Examples of tagged robots: a mobile class with an outline, a named object whose site knows its code.
    code = np.full(len(ex.cls), -1)
    codes, offs = [], []
    obj = ex.obj if ex.obj is not None else np.full(len(ex.cls), -1)
    for i in np.flatnonzero((obj >= 0) & (ex.where[:, 0] >= 0) & has[ex.cls]):
        li = int(ex.where[i, 0])
        tags, nm = sites[li].tags, names[li]
        if tags is None or nm is None:
            continue
        wearer = next((w for w in tags.robots if w.name == str(nm[obj[i]])), None)
        if wearer is None:
            continue
        code[i] = len(codes)
        codes.append((np.asarray(wearer.bits, bool), tags.cells))
        offs.append(wearer.offset_cells / tags.cells)
    idx = np.flatnonzero(code >= 0)
    if idx.size == 0:
        return none("no labelled view is of a robot the site gives a code")
    if idx.size > max_examples:
        idx = rng.choice(idx, max_examples, replace=False)
    sub = ex.take(idx)
    pts, mask, inten = candidate_points(logs, sub, window, intensities=True)
    r = np.hypot(pts[..., 0], pts[..., 1])
    truth = truth_in_sensor(sub)
    q = relative(np.broadcast_to(truth[:, None, :], pts.shape[:2] + (3,)), pts.astype(np.float64))
    d, _ = lookup(outline, jnp.asarray(np.broadcast_to(sub.cls[:, None], mask.shape), jnp.int32),
                  jnp.asarray(q, jnp.float32))
    place = np.asarray(jax.jit(jax.vmap(band_place))(jnp.asarray(arc[sub.cls]), jnp.asarray(q, jnp.float32)))
    is_tape = np.zeros(mask.shape, bool)
    middle = np.zeros(mask.shape, bool)
    for j, i in enumerate(idx):
        bits, n = codes[code[i]]
        u = np.mod(place[j] - offs[code[i]], 1.0) * n
        c = np.minimum(u.astype(int), n - 1)
        is_tape[j] = bits[c]
        frac = u - np.floor(u)
        middle[j] = (frac > CELL_MARGIN) & (frac < 1 - CELL_MARGIN)
    use = mask & (np.abs(np.asarray(d)) < NEAR_OUTLINE) & middle & (inten > 0) & (r > 0)
    n_tape, n_body = int((use & is_tape).sum()), int((use & ~is_tape).sum())
    if min(n_tape, n_body) < MIN_RETURNS:
        return none(f"too few returns to learn tape from body ({n_tape} of tape, {n_body} of body; "
                    f"{MIN_RETURNS} of each needed): longer logs of the tagged robots")
    fitted, beta, mt, st, mb, sb = fit_intensity(inten[use], r[use], is_tape[use])
    sep = (mt - mb) / float(np.sqrt(0.5 * (st**2 + sb**2)))
    report = {"tags": sep >= MIN_SEPARATION, "returns": {"tape": n_tape, "body": n_body}, "views": int(idx.size),
              "range_exp": round(beta, 3), "range_exp_fitted": round(fitted, 3),
              "tape": {"mean": round(mt, 3), "sd": round(st, 3)}, "body": {"mean": round(mb, 3), "sd": round(sb, 3)},
              "separation": round(sep, 2), "tape_over_body": round(float(np.exp(mt - mb)), 2),
              "source": "returns of the labelled robots' tape and body cells in the training logs (their true "
                        "poses, the site's codes), within 3 cm of the learnt outline"}
    if not RANGE_EXP[0] <= fitted <= RANGE_EXP[1]:
        report["warning"] = (f"tags: the intensity's range exponent fitted {fitted:.2f}, outside "
                             f"{RANGE_EXP[0]:g}–{RANGE_EXP[1]:g}; clipped to {beta:.2f}")
    if sep < MIN_SEPARATION:
        report["why"] = (f"tape is {sep:.1f} standard deviations brighter than the robots' surface "
                         f"({MIN_SEPARATION:g} needed): the tags cannot be read; is the tape retro-reflective?")
        return None, report
    first = tagged[0]
    reader = TagReader(
        pattern=patterns(np.stack([w.bits for w in first.robots]),
                         np.asarray([w.offset_cells / first.cells for w in first.robots], np.float32)),
        arc=jnp.asarray(arc), has_arc=jnp.asarray(has), range_exp=jnp.float32(beta),
        tape_mean=jnp.float32(mt), tape_sd=jnp.float32(st), body_mean=jnp.float32(mb), body_sd=jnp.float32(sb),
        cells=jnp.int32(first.cells), min_cells=jnp.float32(MIN_CELLS), point_cap=jnp.float32(POINT_CAP),
        bin_cap=jnp.float32(BIN_CAP), weight=jnp.float32(READ_WEIGHT))
    return reader, report
