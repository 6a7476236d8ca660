"""Scenes and their rendering into laser scans.

A :class:`Scene` is what stands on the field at the laser's height: static circles and polygons
(posts, walls, clutter) and moving things (robots as polygons with a pose per scan, people's legs as
circles with a position per scan). :func:`render` casts a sensor model's beams from a sensor pose
per scan and returns ranges as the sensor reports them: nearest hit, stretched by a tilted scan
plane, with the model's range noise and 1 mm quantisation, dropouts, grazing-angle misses, 0 for no
return; and intensities from reflectivity, incidence and range where the model reports them.

Robots may wear reflective tags (issue 43, ``docs/tags.md``): :func:`tagged_shape` cuts an outline's
edges at the cells of a band of retro-reflective tape, each piece of a tape cell as bright as
:data:`TAPE_REFLECTIVITY` and falling off less with incidence than paint does.
"""

import dataclasses

import numpy as np

from ..errors import InputError
from ..sensors import SensorModel
from .geometry import beam_directions, polygon_edges, ray_circles, ray_segments

# Nao at the height of the body extension, just below the shoulders: a chest 0.27 m wide and 0.12 m
# deep, and behind its left shoulder a fin reaching 0.12 m further back (the paper's "body extension").
# The outline is convex and no two of its faces look alike from the laser: the front is one flat face
# 0.27 m wide, each side a 0.12 m face joined to a differently slanted face of the fin, the back two
# slanted faces meeting off-centre. A concave outline (an earlier L-shaped one) split into two
# candidates whenever the notch faced the laser, and its front and left views were both flat faces of
# nearly the same width. Edge order: front, left side, fin (left face), fin (right face), right side.
NAO_OUTLINE = np.array([[0.06, -0.135], [0.06, 0.135], [-0.06, 0.135], [-0.18, 0.06], [-0.06, -0.135]])
NAO_REFLECTIVITY = np.array([0.5, 0.45, 0.9, 0.75, 0.45])  # the fin carries reflective tape

# A second robot: a rectangular wheeled base 0.36 m long and 0.24 m wide, centred on its pose (front at
# +x). Both longer and narrower than the Nao (0.24 × 0.27 m with its fin), with four plain faces and
# the same kind of surfaces (reflectivity 0.45–0.5, no tape). Edge order: front, left, back, right.
BOX_OUTLINE = np.array([[0.18, -0.12], [0.18, 0.12], [-0.18, 0.12], [-0.18, -0.12]])
BOX_REFLECTIVITY = np.array([0.5, 0.45, 0.5, 0.45])

# A third: a wheeled base 0.30 m long and 0.26 m wide with its front corners cut off at 45° (0.06 m),
# mirror-symmetric about its long axis as most robots are. Its left and right views are mirror images
# of each other, and its back and sides are plain faces: the outline's cue to the heading is the
# chamfered front. Edge order: front, front-left chamfer, left, back, right, front-right chamfer.
CART_OUTLINE = np.array([[0.15, -0.07], [0.15, 0.07], [0.09, 0.13], [-0.15, 0.13], [-0.15, -0.13], [0.09, -0.13]])
CART_REFLECTIVITY = np.array([0.5, 0.5, 0.45, 0.5, 0.45, 0.5])

OUTLINES: dict[str, tuple[np.ndarray, np.ndarray]] = {
    "nao": (NAO_OUTLINE, NAO_REFLECTIVITY),
    "box": (BOX_OUTLINE, BOX_REFLECTIVITY),
    "cart": (CART_OUTLINE, CART_REFLECTIVITY),
}
"""The robot outlines the simulator renders, by name: vertices (counter-clockwise, body frame) and
reflectivity per edge."""

#: Reflectivity of retro-reflective tape seen square on: 5× the Nao's front (0.5), 5.6× its sides
#: (0.45), the render's ``6000 · reflectivity · falloff(incidence) / √range`` in the same units.
TAPE_REFLECTIVITY = 2.5
#: Tape's incidence falloff is ``cos^TAPE_INCIDENCE_EXP`` where paint's is ``cos^0.5``: retro-reflective
#: glass beads send the beam back towards the laser over a wide cone of incidences, so a tape cell seen
#: at 60° keeps 87 % of its square-on return where paint keeps 71 %.
TAPE_INCIDENCE_EXP = 0.2


@dataclasses.dataclass(frozen=True)
class Circle:
    x: float
    y: float
    radius: float
    reflectivity: float = 0.7


@dataclasses.dataclass(frozen=True)
class Polygon:
    vertices: np.ndarray  # [V, 2] counter-clockwise, in O (static) or in the body frame (moving)
    reflectivity: np.ndarray  # [V] per edge (edge i joins vertex i and i+1)
    retro: np.ndarray | None = None  # [V] bool per edge: retro-reflective tape (None: none)


@dataclasses.dataclass
class Mover:
    """A polygon with a pose per scan ``[T, 3]`` in O; NaN rows where absent."""

    shape: Polygon
    poses: np.ndarray


@dataclasses.dataclass
class MovingCircle:
    """A circle with a centre per scan ``[T, 2]`` (legs); NaN rows where absent."""

    radius: float
    centres: np.ndarray
    reflectivity: float = 0.4


@dataclasses.dataclass
class Scene:
    circles: list[Circle] = dataclasses.field(default_factory=list)
    polygons: list[Polygon] = dataclasses.field(default_factory=list)
    movers: list[Mover] = dataclasses.field(default_factory=list)
    moving_circles: list[MovingCircle] = dataclasses.field(default_factory=list)


def robot_shape(outline: str = "nao") -> Polygon:
    """The robot's outline at the laser's height, by name (:data:`OUTLINES`: ``"nao"``, ``"box"``, ``"cart"``)."""
    if outline not in OUTLINES:
        raise InputError(outline, f"unknown robot outline; known: {', '.join(OUTLINES)}")
    vertices, reflectivity = OUTLINES[outline]
    return Polygon(vertices, reflectivity)


def outline_perimeter(outline: "str | Polygon") -> float:
    """The length of a robot's outline (its band's length), metres."""
    v = (robot_shape(outline) if isinstance(outline, str) else outline).vertices
    return float(np.linalg.norm(np.roll(v, -1, axis=0) - v, axis=1).sum())


def tagged_shape(outline: "str | Polygon", code, offset_cells: int = 0) -> Polygon:
    """The outline wearing a band of ``N = len(code)`` cells (``docs/tags.md``): the band wraps the
    outline, its length the perimeter ``P``, cell ``k`` spanning arc lengths ``[k·P/N, (k+1)·P/N)``
    from the first vertex (the front right corner of the shipped outlines), counter-clockwise (the
    vertices' order). Each edge is cut at the cell boundaries that fall inside it (collinear extra
    vertices, none where a boundary meets a vertex); a piece in a tape cell (``code[k]`` True) has
    reflectivity :data:`TAPE_REFLECTIVITY` and is marked ``retro``, the others keep their edge's.
    ``offset_cells``: a band mounted turned, its cell 0 over the outline's cell ``offset_cells``."""
    base = robot_shape(outline) if isinstance(outline, str) else outline
    code = np.asarray(code, bool)
    n = code.shape[0]
    if code.ndim != 1 or n < 1:
        raise InputError("tag code", f"must be a 1-D array of cells, got shape {list(code.shape)}")
    v = np.asarray(base.vertices, np.float64)
    nxt = np.roll(v, -1, axis=0)
    seg = np.linalg.norm(nxt - v, axis=1)
    start = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    perim = float(seg.sum())
    cell = perim / n
    tape = np.roll(code, offset_cells)  # tape[k]: the outline's cell k has tape
    body_retro = np.zeros(len(v), bool) if base.retro is None else np.asarray(base.retro, bool)
    verts, refl, retro = [], [], []
    eps = 1e-9 * perim
    for i in range(len(v)):
        cuts = [start[i]] + [k * cell for k in range(1, n) if start[i] + eps < k * cell < start[i] + seg[i] - eps]
        ends = cuts[1:] + [start[i] + seg[i]]
        for a, b in zip(cuts, ends, strict=True):
            verts.append(v[i] + (a - start[i]) / seg[i] * (nxt[i] - v[i]) if a != start[i] else v[i])
            k = min(n - 1, int((a + b) / 2 // cell))
            refl.append(TAPE_REFLECTIVITY if tape[k] else float(base.reflectivity[i]))
            retro.append(bool(tape[k]) or bool(body_retro[i]))
    return Polygon(np.asarray(verts, np.float64), np.asarray(refl, np.float64), np.asarray(retro, bool))


def box(x0, y0, x1, y1, reflectivity=0.6) -> Polygon:
    v = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
    return Polygon(v, np.full(4, reflectivity))


def walls(x0, y0, x1, y1, reflectivity=0.5) -> list[Polygon]:
    """A rectangular room as four thin wall segments (each a degenerate polygon of 2 vertices)."""
    c = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return [Polygon(np.array([c[i], c[(i + 1) % 4]], np.float64), np.array([reflectivity, reflectivity]))
            for i in range(4)]


def _segments(scene: Scene, sl: slice, t: int):
    """All segments for scans ``sl`` as arrays ``[T, S]`` (x0, y0, x1, y1), reflectivity ``[S]`` and
    whether each is retro-reflective tape ``[S]``."""
    xs, refl, retro = [], [], []
    for poly in scene.polygons:
        v = poly.vertices
        n = len(v)
        if n == 2:  # a wall: one segment
            e = [np.full((t, 1), v[0, 0]), np.full((t, 1), v[0, 1]), np.full((t, 1), v[1, 0]), np.full((t, 1), v[1, 1])]
            r = poly.reflectivity[:1]
        else:
            nxt = np.roll(v, -1, axis=0)
            e = [np.broadcast_to(a[None, :], (t, n)) for a in (v[:, 0], v[:, 1], nxt[:, 0], nxt[:, 1])]
            r = poly.reflectivity
        xs.append(e)
        refl.append(r)
        retro.append(_retro(poly)[: len(r)])
    for mv in scene.movers:
        xs.append(list(polygon_edges(mv.shape.vertices, mv.poses[sl])))
        refl.append(mv.shape.reflectivity)
        retro.append(_retro(mv.shape))
    if not xs:
        z = np.zeros((t, 0))
        return (z, z, z, z), np.zeros(0), np.zeros(0, bool)
    cat = [np.concatenate([e[i] for e in xs], axis=1) for i in range(4)]
    return cat, np.concatenate(refl), np.concatenate(retro)


def _retro(poly: Polygon) -> np.ndarray:
    return np.zeros(len(poly.reflectivity), bool) if poly.retro is None else np.asarray(poly.retro, bool)


def _circles(scene: Scene, sl: slice, t: int):
    cx = [np.full((t, 1), c.x) for c in scene.circles] + [m.centres[sl, 0:1] for m in scene.moving_circles]
    cy = [np.full((t, 1), c.y) for c in scene.circles] + [m.centres[sl, 1:2] for m in scene.moving_circles]
    r = [c.radius for c in scene.circles] + [m.radius for m in scene.moving_circles]
    refl = [c.reflectivity for c in scene.circles] + [m.reflectivity for m in scene.moving_circles]
    if not r:
        z = np.zeros((t, 0))
        return z, z, np.zeros(0), np.zeros(0)
    return np.concatenate(cx, 1), np.concatenate(cy, 1), np.asarray(r, float), np.asarray(refl, float)


def cast(scene: Scene, model: SensorModel, sensor_poses: np.ndarray, tilt: np.ndarray | None = None,
         sl: slice | None = None):
    """Noise-free geometry for scans ``sl``: true range ``[T, N]`` (inf for no hit), cosine of the
    incidence angle and the reflectivity of what each beam hit."""
    return _cast(scene, model, sensor_poses, tilt, sl)[:3]


#: Elements of the ``[scans, beams, segments]`` arrays one ray cast holds at a time (2 MB of float64
#: each): a chunk of scans is cast in parts of at most this many, the same numbers either way. The cast
#: is a dozen element-wise passes over these arrays, so parts small enough to stay in the CPU's caches
#: cast faster than large ones (``docs/speed.md`` has the measurement).
_CAST_ELEMENTS = 1 << 18


def _cast(scene: Scene, model: SensorModel, sensor_poses: np.ndarray, tilt: np.ndarray | None = None,
          sl: slice | None = None):
    """:func:`cast`, and whether each beam hit retro-reflective tape; scans cast in parts of at most
    :data:`_CAST_ELEMENTS` beam-segment pairs (every scan's numbers are its own)."""
    sl = slice(None) if sl is None else sl
    start, stop, _ = sl.indices(sensor_poses.shape[0])
    per_scan = model.n_beams * max(1, len(scene.circles) + len(scene.moving_circles)
                                   + sum(len(p.vertices) for p in scene.polygons)
                                   + sum(len(m.shape.vertices) for m in scene.movers))
    step = max(1, _CAST_ELEMENTS // per_scan)
    if sl.step not in (None, 1) or stop - start <= step:
        return _cast_part(scene, model, sensor_poses, tilt, sl)
    parts = [_cast_part(scene, model, sensor_poses, tilt, slice(a, min(a + step, stop)))
             for a in range(start, stop, step)]
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))


def _cast_part(scene: Scene, model: SensorModel, sensor_poses: np.ndarray, tilt: np.ndarray | None, sl: slice):
    poses = sensor_poses[sl]
    t = poses.shape[0]
    tilt = np.zeros((t, 2)) if tilt is None else tilt[sl]
    dx, dy, stretch = beam_directions(model.angles, poses[:, 2], tilt[:, 0], tilt[:, 1])
    ox, oy = poses[:, 0:1], poses[:, 1:2]
    best = np.full(dx.shape, np.inf)
    cos_inc = np.zeros(dx.shape)
    refl = np.zeros(dx.shape)
    retro = np.zeros(dx.shape, bool)
    cx, cy, cr, crefl = _circles(scene, sl, t)
    if cr.size:
        tc, cc = ray_circles(ox, oy, dx, dy, cx, cy, cr)
        i = np.argmin(tc, axis=-1)
        tmin = np.take_along_axis(tc, i[..., None], -1)[..., 0]
        upd = tmin < best
        best = np.where(upd, tmin, best)
        cos_inc = np.where(upd, np.take_along_axis(cc, i[..., None], -1)[..., 0], cos_inc)
        refl = np.where(upd, crefl[i], refl)
    (x0, y0, x1, y1), srefl, sretro = _segments(scene, sl, t)
    if srefl.size:
        ts, cs = ray_segments(ox, oy, dx, dy, x0, y0, x1, y1)
        ts = np.where(np.isnan(ts), np.inf, ts)
        i = np.argmin(ts, axis=-1)
        tmin = np.take_along_axis(ts, i[..., None], -1)[..., 0]
        upd = tmin < best
        best = np.where(upd, tmin, best)
        cos_inc = np.where(upd, np.take_along_axis(cs, i[..., None], -1)[..., 0], cos_inc)
        refl = np.where(upd, srefl[i], refl)
        retro = np.where(upd, sretro[i], retro)
    return best * stretch, cos_inc, refl, retro


@dataclasses.dataclass(frozen=True)
class Effects:
    """What makes a simulated scan imperfect. ``noise=False`` gives exact, unquantised ranges."""

    noise: bool = True
    dropout: float = 0.003  # probability that any beam returns nothing
    grazing_cos: float = 0.08  # below this cosine of incidence the return is lost
    intensity_noise: float = 0.02  # relative


def render(scene: Scene, model: SensorModel, sensor_poses: np.ndarray, *, tilt: np.ndarray | None = None,
           rng: np.random.Generator, effects: Effects = Effects(), chunk: int = 512):
    """Scans as the sensor reports them: ranges ``[T, N]`` float32 (0 = no return) and intensities
    (``None`` for a model without them), rendered ``chunk`` scans at a time."""
    t_total = sensor_poses.shape[0]
    ranges = np.zeros((t_total, model.n_beams), np.float32)
    inten = np.zeros((t_total, model.n_beams), np.float32) if model.has_intensity else None
    for start in range(0, t_total, chunk):
        sl = slice(start, min(start + chunk, t_total))
        r, cos_inc, refl, retro = _cast(scene, model, sensor_poses, tilt, sl)
        hit = np.isfinite(r)
        r = np.where(hit, r, 0.0)
        if effects.noise:
            r = r + rng.standard_normal(r.shape) * model.noise.std(r)
            res = model.noise.resolution
            r = np.round(r / res) * res
            hit &= rng.random(r.shape) >= effects.dropout
        hit &= cos_inc >= effects.grazing_cos
        hit &= (r >= model.range_min) & (r <= model.range_max)
        ranges[sl] = np.where(hit, r, 0.0)
        if inten is not None:
            falloff = np.sqrt(np.clip(cos_inc, 0, 1))
            if retro.any():  # tape: a flatter falloff with incidence; every other hit's numbers as before
                falloff = np.where(retro, np.clip(cos_inc, 0, 1) ** TAPE_INCIDENCE_EXP, falloff)
            i = 6000.0 * refl * falloff / np.sqrt(np.maximum(r, 0.5))
            if effects.noise:
                i = i * (1 + effects.intensity_noise * rng.standard_normal(i.shape))
            inten[sl] = np.where(hit, np.maximum(i, 0.0), 0.0)
    return ranges, inten
