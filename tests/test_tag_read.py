"""Stage e″, reading tags (``gtsjax.core.e_tags``), against a brute-force reader in NumPy (every
identity, every side, every return, the band's cell found from the return's arc length by
``np.interp``), and on returns ray-cast here in NumPy from a laser at 2–9 m to a tagged outline: the
cells read right, and the true identity among the most likely."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.core.e_tags import BINS, TagReader, arc_table, band_place, patterns, read_tags
from gtsjax.sim.scene import NAO_OUTLINE
from gtsjax.tags.codes import design

TAPE, BODY = 3.0, 0.5  # reflectivities: tape six times the body
MIN_SEEN = 2.5  # cells in view for a read to count (a convex outline shows under half its band)


def reader_for(codes, offsets, arc, sd=0.25, min_cells=2.0):
    return TagReader(
        pattern=patterns(codes, offsets), arc=jnp.asarray(arc, jnp.float32)[None], has_arc=jnp.array([True]),
        range_exp=jnp.float32(0.5), tape_mean=jnp.float32(math.log(6000 * TAPE)), tape_sd=jnp.float32(sd),
        body_mean=jnp.float32(math.log(6000 * BODY)), body_sd=jnp.float32(sd), cells=jnp.int32(codes.shape[1]),
        min_cells=jnp.float32(min_cells), point_cap=jnp.float32(5.0), bin_cap=jnp.float32(3.0),
        weight=jnp.float32(1.0))


def _edges_from_origin(vertices):
    """The polygon's vertices from its origin (the largest ``x − y``), each edge's end, length and the
    arc length at its start."""
    v = np.asarray(vertices, float)
    v = np.roll(v, -int(np.argmax(v[:, 0] - v[:, 1])), axis=0)
    nxt = np.roll(v, -1, axis=0)
    seg = np.linalg.norm(nxt - v, axis=1)
    return v, nxt, seg, np.concatenate([[0.0], np.cumsum(seg)[:-1]])


def arc_length_of(vertices, q):
    """Brute force: the arc length (fraction, from the origin vertex, counter-clockwise) of the polygon
    point nearest ``q``."""
    v, nxt, seg, start = _edges_from_origin(vertices)
    best, s_best = np.inf, 0.0
    for i in range(len(v)):
        e = nxt[i] - v[i]
        u = np.clip(np.dot(q - v[i], e) / np.dot(e, e), 0, 1)
        d = np.linalg.norm(v[i] + u * e - q)
        if d < best:
            best, s_best = d, (start[i] + u * seg[i]) / seg.sum()
    return s_best % 1.0


def test_band_place_is_the_arc_length():
    arc = arc_table(NAO_OUTLINE)
    v = np.asarray(NAO_OUTLINE)
    rng = np.random.default_rng(0)
    for _ in range(200):  # points on the outline's edges
        i = rng.integers(len(v))
        q = v[i] + rng.uniform(0.02, 0.98) * (v[(i + 1) % len(v)] - v[i])
        got = float(band_place(jnp.asarray(arc, jnp.float32), jnp.asarray(q, jnp.float32)))
        want = arc_length_of(v, q)
        assert min(abs(got - want), 1 - abs(got - want)) < 0.01  # within the table's resolution


def cast(vertices, pose, laser, beam=math.radians(0.25)):
    """Returns of a laser at ``laser`` (x, y) on the polygon at ``pose``: points (sensor frame = field
    here), ranges and the arc length along the band of each, by ray-casting every beam in NumPy."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    w = np.asarray(vertices) @ np.array([[c, s], [-s, c]]) + pose[:2]
    centre = np.arctan2(pose[1] - laser[1], pose[0] - laser[0])
    pts, rng_, arcs = [], [], []
    for a in np.arange(centre - 0.2, centre + 0.2, beam):
        d = np.array([math.cos(a), math.sin(a)])
        best = np.inf
        for i in range(len(w)):
            e = w[(i + 1) % len(w)] - w[i]
            m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, w[i] - laser)
            if t > 0 and 0 <= u <= 1:
                best = min(best, t)
        if np.isfinite(best):
            p = laser + best * d
            q = np.array([[c, -s], [s, c]]).T @ (p - pose[:2])
            pts.append(p)
            rng_.append(best)
            arcs.append(arc_length_of(vertices, q))
    return np.array(pts), np.array(rng_), np.array(arcs)


def ray_arc(vertices, q):
    """Brute force: the arc length (fraction, from the origin vertex, counter-clockwise) where the ray
    from the centre through ``q`` leaves the polygon."""
    v, nxt, seg, start = _edges_from_origin(vertices)
    d = q / np.linalg.norm(q)
    for i in range(len(v)):
        e = nxt[i] - v[i]
        m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
        if abs(np.linalg.det(m)) < 1e-12:
            continue
        t, u = np.linalg.solve(m, v[i])
        if t > 0 and 0 <= u < 1:
            return ((start[i] + u * seg[i]) / seg.sum()) % 1.0
    raise AssertionError("the centre is outside the polygon")


def brute_read(codes, offsets, vertices, xy, ranges, inten, mask, side_pose, side_logp, rd):
    """Every candidate, side, identity and return in turn, the band's cell of each return from the
    exact arc length where its polar angle leaves the outline; no squash per bin (``bin_cap`` large)."""
    n_ids, n_cells = codes.shape
    out = np.zeros((xy.shape[0], n_ids))
    for k in range(xy.shape[0]):
        used = np.isfinite(side_logp[k])
        w = side_logp[k] - np.logaddexp.reduce(side_logp[k][used])
        tot = np.full(n_ids, -np.inf)
        for h in np.flatnonzero(used):
            x, y, th = side_pose[k, h]
            ll = np.zeros(n_ids)
            for i in np.flatnonzero(mask[k]):
                d = xy[k, i] - [x, y]
                q = np.array([math.cos(th) * d[0] + math.sin(th) * d[1], -math.sin(th) * d[0] + math.cos(th) * d[1]])
                s = ray_arc(vertices, q)
                u = math.log(max(inten[k, i], 1.0)) + 0.5 * math.log(max(ranges[k, i], 0.05))
                lt = -0.5 * ((u - float(rd.tape_mean)) / float(rd.tape_sd)) ** 2
                lb = -0.5 * ((u - float(rd.body_mean)) / float(rd.body_sd)) ** 2
                llr = float(np.clip(lt - lb, -5, 5))
                for j in range(n_ids):
                    cell = int(((s - offsets[j]) % 1.0) * n_cells)
                    ll[j] += 0.5 * llr * (1 if codes[j, cell] else -1)
            tot = np.logaddexp(tot, w[h] + ll)
        out[k] = tot - tot.max()
    return out


def test_read_tags_matches_the_brute_force_reader():
    rng = np.random.default_rng(3)
    d = design(6, 8)
    offsets = np.array([0, 8, 16, 24, 32, 40]) / BINS  # whole bins: cell edges on bin edges
    arc = arc_table(NAO_OUTLINE)
    rd = reader_for(d.codes, offsets, arc)
    rd = TagReader(**{**{f: getattr(rd, f) for f in rd.__dataclass_fields__}, "bin_cap": jnp.float32(1e6)})
    n, win, sides = 5, 24, 4
    xy = rng.uniform(-0.2, 0.2, (n, win, 2)) + rng.uniform(1, 6, (n, 1, 2))
    pose = np.concatenate([xy.mean(1) + rng.normal(0, 0.01, (n, 2)), rng.uniform(-3, 3, (n, 1))], 1)
    side_pose = np.repeat(pose[:, None], sides, 1)
    side_pose[..., 2] += np.array([0, math.pi / 2, math.pi, -math.pi / 2])
    side_logp = np.log(rng.dirichlet(np.ones(sides), n))
    side_logp[:, 3] = -np.inf
    ranges = np.linalg.norm(xy, axis=-1)
    inten = 6000 * rng.choice([TAPE, BODY], (n, win)) / np.sqrt(ranges) * np.exp(rng.normal(0, 0.3, (n, win)))
    mask = rng.random((n, win)) < 0.9
    # Returns within the arc table's error of a cell edge at any side go: there the two readers may
    # place them in neighbouring cells, both right.
    for k in range(n):
        for i in range(win):
            for h in range(3):
                x, y, th = side_pose[k, h]
                dd = xy[k, i] - [x, y]
                q = np.array([math.cos(th) * dd[0] + math.sin(th) * dd[1], -math.sin(th) * dd[0] + math.cos(th) * dd[1]])
                s = ray_arc(NAO_OUTLINE, q) * 8
                if abs(s - round(s)) < 0.08:
                    mask[k, i] = False
    got, readable, _ = read_tags(rd, jnp.zeros(n, jnp.int32), jnp.asarray(xy, jnp.float32),
                                 jnp.asarray(ranges, jnp.float32), jnp.asarray(inten, jnp.float32),
                                 jnp.asarray(mask), jnp.asarray(side_pose, jnp.float32), jnp.asarray(side_logp, jnp.float32))
    want = brute_read(d.codes, offsets, NAO_OUTLINE, xy, ranges, inten, mask, side_pose, side_logp, rd)
    ok = np.asarray(readable)
    assert ok.any()
    np.testing.assert_allclose(np.asarray(got)[ok], want[ok], atol=2e-3 * max(1.0, np.abs(want).max()))


def _read_one(rd, pts, rr, inten, pose, win=96):
    """One candidate's read, its returns padded to the window, the true pose its only side."""
    m = np.zeros(win, bool)
    m[: len(rr)] = True

    def pad(a, shape):
        return jnp.asarray(np.concatenate([a, np.zeros((win - len(a),) + shape)])[None], jnp.float32)

    sp = jnp.asarray(np.tile(pose, (4, 1))[None], jnp.float32)
    lp = jnp.asarray([[0.0, -np.inf, -np.inf, -np.inf]], jnp.float32)
    ll, _, seen = read_tags(rd, jnp.zeros(1, jnp.int32), pad(pts, (2,)), pad(rr, ()), pad(inten, ()), jnp.asarray(m[None]),
                            sp, lp)
    return np.asarray(ll)[0], float(seen[0])


@pytest.mark.parametrize("distance", [2.0, 5.0, 9.0])
def test_reads_ray_cast_returns(distance):
    """A tagged Nao (six cells, the band ``gtsjax tags`` gives 10 robots at 9 m) seen from ``distance``
    at random headings, the reader given the true pose: where at least ``MIN_SEEN`` cells are in view,
    each cell in full view reads right (the reader prefers the code with its true bit there to the same
    code with the other) in at least 90 % of reads, and the true identity is among the most likely (a
    six-cell band's 10 codes share their 3-cell windows, so one view need not single one out) in at
    least 90 %."""
    rng = np.random.default_rng(int(distance))
    d = design(10, 6)
    rd = reader_for(d.codes, np.zeros(10), arc_table(NAO_OUTLINE))
    fields = {f: getattr(rd, f) for f in rd.__dataclass_fields__}
    cells_right = cells_total = top = readable_n = 0
    for trial in range(100):
        j = trial % 10
        pose = np.array([distance, rng.uniform(-0.5, 0.5), rng.uniform(-math.pi, math.pi)])
        pts, rr, arcs = cast(NAO_OUTLINE, pose, np.zeros(2))
        cell = np.minimum((arcs * 6).astype(int), 5)
        inten = 6000 * np.where(d.codes[j][cell], TAPE, BODY) / np.sqrt(rr) * (1 + 0.02 * rng.standard_normal(rr.shape))
        ll, seen = _read_one(rd, pts, rr, inten, pose)
        if seen < MIN_SEEN:
            continue
        readable_n += 1
        top += int(ll[j] >= ll.max() - 1e-3)
        for c in np.unique(cell):  # cells in full view: returns from both of its ends
            a = arcs[cell == c] * 6 - c
            if a.min() < 0.15 and a.max() > 0.85:
                cells_total += 1
                with_tape, with_body = np.array(d.codes[j]), np.array(d.codes[j])
                with_tape[c], with_body[c] = True, False
                rd2 = TagReader(**{**fields, "pattern": patterns(np.stack([with_tape, with_body]), np.zeros(2))})
                l2, _ = _read_one(rd2, pts, rr, inten, pose)
                cells_right += int((l2[0] > l2[1]) == bool(d.codes[j][c]))
    assert readable_n >= 10
    assert cells_total > 0 and cells_right / cells_total >= 0.9
    assert top / readable_n >= 0.9
