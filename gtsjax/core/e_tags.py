"""Stage e″, reading reflective tags (issue 43): for each posed candidate, how likely each robot
identity is, from the intensity of its returns along its outline (:mod:`gtsjax.tags` designs the codes).

A robot's band wraps its outline at the laser's height: ``N`` cells of equal arc length, tape or body,
starting at the outline's *origin* (the point furthest front-right, largest ``x − y`` in the robot's
frame: the front right corner of the outlines gtsjax simulates) and running counter-clockwise seen from
above; a robot's band may sit turned by ``offset`` (a fraction of the band, measured at enrolment).
For each candidate and each of its side hypotheses (stage e′'s poses, whose probabilities weigh them):

1. each return goes into the robot's frame; its polar angle gives its place along the band,
   ``s ∈ [0, 1)``, through the class's table ``arc`` (the outline's arc length from the origin, as a
   fraction of the perimeter, at ``K`` polar angles; learnt with the outline at training);
2. its intensity, normalised for range (``log I + β log r``, :class:`TagReader`), gives the
   log-likelihood ratio of tape against body, each a Gaussian learnt from the tape's and the body's
   returns, clipped to ``±point_cap`` (a glint or a dropout is one point, not a verdict);
3. the ratios are summed in ``G`` bins along the band (a one-hot product), each bin's sum squashed to
   ``±bin_cap`` (``c · tanh(x / c)``: a close robot's dozens of returns per cell are not dozens of
   independent reads);
4. each identity's log-likelihood is the bins' evidence against its band's pattern (``+1`` tape,
   ``-1`` body, at each bin's centre, turned by its offset): one ``[bins] × [bins, ids]`` product,
   halved (the ratio is tape against body, a pattern's agreement and disagreement cost each half),
   times ``weight``: a detection's returns are far from independent reads (one error of its pose
   moves them all along the band; one glint brightens a run of them), and the tracker multiplies the
   reads of every scan (:mod:`.g_identity`), so each counts for a fraction.

The identity log-likelihoods of the sides are mixed by the sides' probabilities. A candidate whose
returns cover fewer than ``min_cells`` cells' worth of bins is *unreadable*: its log-likelihoods are all
0 (it says nothing). The cells in view are the extent of its returns along the band (on its most
probable side, measured from its first return's place) times the band's cells. Fixed shapes: ``cands × sides × window`` points, ``G`` bins, one product per
identity count, no loop over identities.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .buckets import slots_of

#: Polar angles of the ``arc`` table: ``K`` evenly spaced from −π.
ARC_ANGLES = 128
#: Bins along the band the evidence is summed in (a cell of a 16-cell band spans 4).
BINS = 64


class TagReader(eqx.Module):
    """What reading tags needs: the identities' bands as patterns over ``BINS`` bins (turned by their
    offsets), the classes' arc tables, the intensity model and the reading's thresholds."""

    pattern: Float[Array, "ids bins"]  # +1 tape, -1 body, at each bin's centre
    arc: Float[Array, "classes angles"]  # arc-length fraction from the origin at each polar angle
    has_arc: Bool[Array, " classes"]  # the class has an outline to read along
    range_exp: Float[Array, ""]  # β: log I + β log r is the range-normalised log intensity
    tape_mean: Float[Array, ""]
    tape_sd: Float[Array, ""]
    body_mean: Float[Array, ""]
    body_sd: Float[Array, ""]
    cells: Int[Array, ""]  # cells per band
    min_cells: Float[Array, ""]  # cells' worth of bins to be readable
    point_cap: Float[Array, ""]
    bin_cap: Float[Array, ""]
    weight: Float[Array, ""]  # what one detection's read counts for (its returns are not independent reads)


def patterns(codes, offsets, bins: int = BINS) -> jnp.ndarray:
    """``[ids, bins]``: each code (``[ids, cells]``, 1 tape) at the centre of each bin, the band turned
    by its offset (a fraction: the band's cell 0 starts ``offset`` along from the outline's origin)."""
    codes = jnp.asarray(codes, jnp.float32)
    n = codes.shape[1]
    centre = (jnp.arange(bins, dtype=jnp.float32) + 0.5) / bins
    s = jnp.mod(centre[None, :] - jnp.asarray(offsets, jnp.float32)[:, None], 1.0)
    cell = jnp.clip(jnp.floor(s * n).astype(jnp.int32), 0, n - 1)
    return 2.0 * jnp.take_along_axis(codes, cell, axis=1) - 1.0


def band_place(arc: Float[Array, " angles"], q: Float[Array, "*n 2"]) -> Float[Array, "*n"]:
    """The place along the band, ``[0, 1)``, of robot-frame points ``q``: the class's arc table at their
    polar angle, linear between its entries (across the seam at 1 → 0 too)."""
    k = arc.shape[0]
    u = (jnp.arctan2(q[..., 1], q[..., 0]) + jnp.pi) / (2 * jnp.pi) * k
    fl = jnp.clip(jnp.floor(u), 0, k - 1)
    i0 = fl.astype(jnp.int32)
    f = u - fl
    a0, a1 = arc[i0], arc[(i0 + 1) % k]
    a1 = jnp.where(a1 < a0 - 0.5, a1 + 1.0, a1)  # the seam: 0.99 then 0.01 is 0.99 then 1.01
    return jnp.mod(a0 + f * (a1 - a0), 1.0)


def _llr(reader: TagReader, intensity, rng):
    """Per return, the clipped log-likelihood ratio of tape against body of its normalised intensity."""
    u = jnp.log(jnp.maximum(intensity, 1.0)) + reader.range_exp * jnp.log(jnp.maximum(rng, 0.05))
    lt = -0.5 * ((u - reader.tape_mean) / reader.tape_sd) ** 2 - jnp.log(reader.tape_sd)
    lb = -0.5 * ((u - reader.body_mean) / reader.body_sd) ** 2 - jnp.log(reader.body_sd)
    return jnp.clip(lt - lb, -reader.point_cap, reader.point_cap)


def read_tags(
    reader: TagReader,
    cls: Int[Array, " cands"],
    xy: Float[Array, "cands window 2"],
    ranges: Float[Array, "cands window"],
    intensities: Float[Array, "cands window"],
    mask: Bool[Array, "cands window"],
    side_pose: Float[Array, "cands sides 3"],
    side_logp: Float[Array, "cands sides"],
) -> tuple[Float[Array, "cands ids"], Bool[Array, " cands"], Float[Array, " cands"]]:
    """Each candidate's log-likelihood of each identity (0 where unreadable), whether it was readable,
    and the cells' worth of band it showed (see the module). ``xy``, ``side_pose`` in the sensor frame."""
    bins = reader.pattern.shape[1]
    th = side_pose[..., 2]
    c, s = jnp.cos(th)[..., None], jnp.sin(th)[..., None]  # [n, sides, 1]
    dx = xy[:, None, :, 0] - side_pose[..., 0:1]
    dy = xy[:, None, :, 1] - side_pose[..., 1:2]
    q = jnp.stack([c * dx + s * dy, -s * dx + c * dy], -1)  # [n, sides, window, 2]: the robot's frame
    place = jax.vmap(lambda a, qq: band_place(a, qq))(reader.arc[cls], q)  # [n, sides, window]
    b = jnp.clip(jnp.floor(place * bins).astype(jnp.int32), 0, bins - 1)
    onehot = (b[..., None] == jnp.arange(bins, dtype=jnp.int32)[None, None, None, :]) & mask[:, None, :, None]
    llr = _llr(reader, intensities, ranges)  # [n, window]
    per_bin = jnp.einsum("nw,nswb->nsb", llr, onehot.astype(llr.dtype))
    per_bin = reader.bin_cap * jnp.tanh(per_bin / reader.bin_cap)
    ll = (0.5 * reader.weight) * jnp.einsum("nsb,jb->nsj", per_bin, reader.pattern)
    used = jnp.isfinite(side_logp)
    w = jax.nn.log_softmax(jnp.where(used, side_logp, -jnp.inf), axis=-1)
    mixed = jax.nn.logsumexp(jnp.where(used[..., None], w[..., None] + ll, -jnp.inf), axis=1)
    mixed = mixed - jnp.max(mixed, axis=-1, keepdims=True)
    # The band's span in view, on the most probable side: the returns' places measured from the first
    # return's (a view shows under half the band), then their extent.
    main = jnp.argmax(jnp.where(used, side_logp, -jnp.inf), axis=-1)
    at = jnp.take_along_axis(place, main[:, None, None], axis=1)[:, 0]  # [n, window]
    ref = jnp.take_along_axis(at, jnp.argmax(mask, axis=-1)[:, None], axis=1)
    rel = jnp.mod(at - ref + 0.5, 1.0) - 0.5
    span = jnp.max(jnp.where(mask, rel, -0.5), -1) - jnp.min(jnp.where(mask, rel, 0.5), -1)
    cells_seen = jnp.maximum(span, 0.0) * reader.cells.astype(xy.dtype)
    readable = reader.has_arc[cls] & (cells_seen >= reader.min_cells) & jnp.any(mask, axis=-1)
    return jnp.where(readable[:, None], mixed, 0.0), readable, cells_seen


def read_candidates(
    reader: TagReader,
    max_objects: int,
    cls: Int[Array, " cands"],
    sel: Bool[Array, " cands"],
    scores: Float[Array, "cands classes"],
    xy: Float[Array, "cands window 2"],
    ranges: Float[Array, "cands window"],
    intensities: Float[Array, "cands window"],
    mask: Bool[Array, "cands window"],
    side_pose: Float[Array, "cands sides 3"],
    side_logp: Float[Array, "cands sides"],
) -> Float[Array, "cands ids"]:
    """:func:`read_tags` on the ``max_objects`` candidates of ``sel`` (posed candidates of tracked
    classes) that score highest for their class, as stage e′ picks its fits: the rest of the scan's
    candidate slots (background, landmarks, empty) are never read. Their log-likelihoods come back to
    the scan's slots by one gather (:func:`~.buckets.slots_of`), 0 elsewhere."""
    n = cls.shape[0]
    own = jnp.take_along_axis(scores, cls[:, None], 1)[:, 0]
    k = min(max_objects, n)
    _, idx = jax.lax.top_k(jnp.where(sel, own, -jnp.inf), k)
    chosen = sel[idx]
    ll, _, _ = read_tags(reader, cls[idx], xy[idx], ranges[idx], intensities[idx], mask[idx] & chosen[:, None],
                         side_pose[idx], side_logp[idx])
    got, src = slots_of(idx, chosen, n)
    return jnp.where(got[:, None], ll[src], 0.0)


def arc_table(vertices, angles: int = ARC_ANGLES):
    """The ``arc`` table of an outline given as a polygon (counter-clockwise, around the robot's
    centre, which it must hold): at each of ``angles`` polar angles from −π, the arc length from the
    origin vertex (the largest ``x − y``) to where the ray from the centre leaves the polygon, as a
    fraction of the perimeter. NumPy, at training."""
    import numpy as np

    v = np.asarray(vertices, np.float64)
    o = int(np.argmax(v[:, 0] - v[:, 1]))
    v = np.roll(v, -o, axis=0)
    nxt = np.roll(v, -1, axis=0)
    seg = np.linalg.norm(nxt - v, axis=1)
    start = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    perim = seg.sum()
    out = np.zeros(angles)
    for k in range(angles):
        phi = -np.pi + 2 * np.pi * k / angles
        d = np.array([np.cos(phi), np.sin(phi)])
        for i in range(len(v)):  # the ray t·d meets edge v_i + u (v_{i+1} − v_i), u ∈ [0, 1)
            e = nxt[i] - v[i]
            m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, v[i])
            if t > 0 and -1e-9 <= u < 1 - 1e-9:
                out[k] = (start[i] + u * seg[i]) / perim
                break
    return np.mod(out, 1.0)
