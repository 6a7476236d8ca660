"""Stages a–c (segmentation, ORS, characteristic vector, binary filters) against a plain NumPy
reference written here the obvious way: a loop over beams, the Cartesian form of eq. 9, and eq. 11–12
with ``exp(−dist)`` weights in float64."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.core.b_features import characterise
from gtsjax.core.frontend import FrontEndConfig, front_end_batch
from gtsjax.core.frontend import front_end as front_end_pure
from gtsjax.core.scan import Scan
from gtsjax.io.logs import ScanLog, to_scans
from gtsjax.sensors import URG_04LX, UTM_30LX
from tests._utils import assert_allclose

TOL = dict(rtol=1e-5, atol=1e-5)

front_end = jax.jit(front_end_pure)  # the tests' own jit: the core's front end is pure


# ----------------------------------------------------------------------------- NumPy reference


def ref_segments(ranges, valid, angles, d0, g):
    """Segments as (start, length), by walking the beams."""
    segs, cur, prev = [], None, None
    for i in range(len(ranges)):
        if not valid[i]:
            if cur is not None:
                segs.append((cur, i - cur))
            cur = None
            continue
        p = (ranges[i] * math.cos(angles[i]), ranges[i] * math.sin(angles[i]))
        if cur is None:
            cur = i
        else:
            d = math.hypot(p[0] - prev[0], p[1] - prev[1])
            if d > d0 + g * min(ranges[i], ranges[i - 1]):
                segs.append((cur, i - cur))
                cur = i
        prev = p
    if cur is not None:
        segs.append((cur, len(ranges) - cur))
    return segs


def ref_features(r, th, inten, cfg):
    """ORS (eq. 8–9), width, height and vector (eq. 11–12) of one candidate's beams, float64."""
    r, th, inten = (np.asarray(a, np.float64) for a in (r, th, inten))
    rj = (r.max() + r.min()) / 2
    tj = (th.max() + th.min()) / 2
    o = np.array([rj * math.cos(tj), rj * math.sin(tj)])
    p = np.stack([r * np.cos(th), r * np.sin(th)], -1)
    rot = np.array([[math.cos(-tj), -math.sin(-tj)], [math.sin(-tj), math.cos(-tj)]])
    q = (p - o) @ rot.T
    x, y = q[:, 0], q[:, 1]
    width, height = y.max() - y.min(), x.max() - x.min()

    def prof(n, vals):
        if bool(cfg.cells_on_bbox):
            lo, hi = y.min(), y.max()
        else:
            lo, hi = -float(cfg.cell_span) / 2, float(cfg.cell_span) / 2
        cw = (hi - lo) / n
        sigma = max(float(cfg.sigma_cells) * cw, float(cfg.sigma_min))
        out = []
        for k in range(n):
            c = lo + (k + 0.5) * cw
            w = np.exp(-((c - y) ** 2) / (2 * sigma**2))
            if w.sum() > 0:
                out.append((w * vals).sum() / w.sum())
            elif c < y.min() or c > y.max():  # documented fallback: the nearest point's value
                out.append(vals[np.argmin(np.abs(c - y))])
            else:  # documented fallback inside the extent: 0
                out.append(0.0)
        return out

    vec = np.array([width] + prof(cfg.n_dist, x) + prof(cfg.n_intensity, inten))
    return dict(origin=o, heading=tj, points=q, width=width, height=height, vector=vec)


def check_scan(cfg, scan, out):
    """Compare one scan's front-end output with the reference."""
    ranges = np.asarray(scan.ranges)
    valid = np.asarray(scan.valid)
    angles = np.asarray(scan.angles())
    inten = np.asarray(scan.intensities)
    segs = ref_segments(ranges, valid, angles, float(cfg.break_distance), float(cfg.break_growth))
    k_max, win = cfg.max_candidates, cfg.window
    c, f = out.candidates, out.features
    d = out.diagnostics
    assert int(d.n_segments) == len(segs)
    assert int(d.n_overflow) == max(len(segs) - k_max, 0)
    # Beyond K segments, the K whose first return is nearest (ties: the lower beam), in beam order.
    kept = segs if len(segs) <= k_max else sorted(sorted(segs, key=lambda sg: (ranges[sg[0]], sg[0]))[:k_max])
    assert int(d.n_too_long) == sum(length > win for _, length in kept)
    live = np.asarray(c.live)
    assert live.sum() == len(kept) and live[: len(kept)].all()
    keep = np.asarray(out.keep)
    for k in range(k_max):
        if k >= len(kept):
            assert not keep[k] and not np.asarray(c.mask[k]).any()
            np.testing.assert_array_equal(np.asarray(f.vector[k]), 0)
            continue
        start, length = kept[k]
        assert int(c.start[k]) == start and int(c.length[k]) == length
        if length > win:
            assert bool(c.too_long[k]) and not keep[k] and not np.asarray(c.mask[k]).any()
            assert int(f.n_points[k]) == 0
            continue
        assert not bool(c.too_long[k])
        mask = np.asarray(c.mask[k])
        np.testing.assert_array_equal(mask, np.arange(win) < length)
        np.testing.assert_array_equal(np.asarray(c.index[k])[:length], np.arange(start, start + length))
        sl = slice(start, start + length)
        ref = ref_features(ranges[sl], angles[sl], inten[sl], cfg)
        np.testing.assert_allclose(np.asarray(f.origin[k]), ref["origin"], **TOL)
        np.testing.assert_allclose(float(f.heading[k]), ref["heading"], **TOL)
        np.testing.assert_allclose(np.asarray(f.points[k])[:length], ref["points"], **TOL)
        np.testing.assert_array_equal(np.asarray(f.points[k])[length:], 0)
        np.testing.assert_allclose(float(f.width[k]), ref["width"], **TOL)
        np.testing.assert_allclose(float(f.height[k]), ref["height"], **TOL)
        np.testing.assert_allclose(np.asarray(f.vector[k]), ref["vector"], **TOL)
        assert int(f.n_points[k]) == length
        w = ref["width"]
        ref_keep = length >= int(cfg.min_points) and float(cfg.width_min) <= w <= float(cfg.width_max)
        # the width window is compared in float32; skip candidates within rounding of its edges
        if min(abs(w - float(cfg.width_min)), abs(w - float(cfg.width_max))) > 1e-5:
            assert bool(keep[k]) == ref_keep
    return segs


# ----------------------------------------------------------------------------- synthetic scenes


def cast(sensor, circles=(), walls=(), *, noise=0.0, seed=0, reflect=None):
    """Ranges (and intensities) of a sensor at the origin of S looking at circles ``(cx, cy, R)`` and
    wall segments ``(x0, y0, x1, y1)``; 0 where nothing is hit."""
    ang = sensor.angles
    u = np.stack([np.cos(ang), np.sin(ang)], -1)
    best = np.full(len(ang), np.inf)
    refl = np.zeros(len(ang))
    for j, (cx, cy, rad) in enumerate(circles):
        b = u @ np.array([cx, cy])
        disc = b * b - (cx * cx + cy * cy - rad * rad)
        t = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
        t = np.where(t > 0, t, np.inf)
        hit = t < best
        best = np.where(hit, t, best)
        refl = np.where(hit, 3000.0 + 500.0 * j if reflect is None else reflect[j], refl)
    for x0, y0, x1, y1 in walls:
        e = np.array([x1 - x0, y1 - y0])
        den = u[:, 0] * (-e[1]) - u[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (x0 * (-e[1]) - y0 * (-e[0])) / den
            s = (u[:, 0] * y0 - u[:, 1] * x0) / den
        ok = np.isfinite(t) & (t > 0) & (s >= 0) & (s <= 1)
        t = np.where(ok, t, np.inf)
        hit = t < best
        best = np.where(hit, t, best)
        refl = np.where(hit, 1500.0, refl)
    rng = np.random.default_rng(seed)
    r = best + noise * rng.standard_normal(len(ang))
    r = np.where(np.isfinite(best), r, 0.0)
    return r.astype(np.float32), (refl / np.maximum(r, 0.1)).astype(np.float32)


def make_scan(sensor, ranges, intensities=None, *, range_min=None, range_max=None) -> Scan:
    ranges = np.asarray(ranges, np.float32)[None]
    log = ScanLog(
        ranges=ranges,
        stamps=np.zeros(1),
        angle_min=sensor.angle_min,
        angle_increment=sensor.angle_increment,
        intensities=None if intensities is None else np.asarray(intensities, np.float32)[None],
        range_min=sensor.range_min if range_min is None else range_min,
        range_max=sensor.range_max if range_max is None else range_max,
    )
    scans = to_scans(log, sensor.n_beams)
    return jax.tree_util.tree_map(lambda a: a[0], scans)


def scene(sensor, seed):
    rng = np.random.default_rng(seed)
    circles = []
    for _ in range(int(rng.integers(1, 7))):
        rr, th = rng.uniform(0.8, 3.6), rng.uniform(-1.8, 1.8)
        circles.append((rr * math.cos(th), rr * math.sin(th), rng.choice([0.05, 0.15, 0.25])))
    walls = [(-1.0, 4.0, 5.0, 4.0), (5.0, 4.0, 5.0, -3.0), (-1.0, -3.0, 5.0, -3.0)]
    r, inten = cast(sensor, circles, walls, noise=0.01, seed=seed)
    return make_scan(sensor, r, inten if sensor.has_intensity else None)


# ----------------------------------------------------------------------------- tests


@pytest.mark.parametrize("sensor", [URG_04LX, UTM_30LX], ids=lambda s: s.name)
@pytest.mark.parametrize("bbox", [False, True])
def test_synthetic_scenes_match_reference(sensor, bbox):
    cfg = FrontEndConfig(cells_on_bbox=bbox)
    n_kept = 0
    for seed in range(4):
        scan = scene(sensor, seed)
        out = front_end(cfg, scan)
        check_scan(cfg, scan, out)
        n_kept += int(out.diagnostics.n_kept)
        assert out.features.vector.dtype == jnp.float32 and out.features.vector.shape == (32, 21)
        assert np.isfinite(np.asarray(out.features.vector)).all()
    assert n_kept > 0


def test_every_simulated_scenario_matches_reference():
    from gtsjax.sensors import get_model
    from gtsjax.sim import SCENARIOS, simulate  # part of the package: an import error is a failure, not a skip

    assert {"spl-train", "spl-eval", "lab-eval", "hall-eval"} <= set(SCENARIOS)  # docs/accuracy.md's sites: not a vacuous loop
    cfg = FrontEndConfig()
    for name in SCENARIOS:
        log, _site = simulate(name, seed=0, n_scans=3)
        n_beams = get_model(log.sensor_model).n_beams if log.sensor_model else log.n_beams
        scans = to_scans(log, n_beams)
        for t in range(log.n_scans):
            scan = jax.tree_util.tree_map(lambda a, t=t: a[t], scans)
            check_scan(cfg, scan, front_end(cfg, scan))


def test_all_beams_invalid():
    cfg = FrontEndConfig()
    out = front_end(cfg, make_scan(URG_04LX, np.zeros(URG_04LX.n_beams)))
    assert int(out.diagnostics.n_segments) == 0 and not np.asarray(out.candidates.live).any()
    assert not np.asarray(out.keep).any()
    np.testing.assert_array_equal(np.asarray(out.features.vector), 0)
    np.testing.assert_array_equal(np.asarray(out.features.origin), 0)


def test_one_valid_beam():
    cfg = FrontEndConfig()
    r = np.zeros(URG_04LX.n_beams)
    r[200] = 2.0
    scan = make_scan(URG_04LX, r)
    out = front_end(cfg, scan)
    check_scan(cfg, scan, out)
    f = out.features
    assert int(f.n_points[0]) == 1 and float(f.width[0]) == 0.0 and float(f.height[0]) == 0.0
    np.testing.assert_allclose(float(f.heading[0]), float(scan.angles()[200]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(f.vector[0]), 0.0, atol=1e-6)  # x′ = 0 everywhere
    assert not bool(out.keep[0])  # fewer than min_points
    cfg_bbox = FrontEndConfig(cells_on_bbox=True)
    check_scan(cfg_bbox, scan, front_end(cfg_bbox, scan))  # zero-width bounding box: σ floored


def test_candidates_touching_first_and_last_beam():
    cfg = FrontEndConfig()
    n = URG_04LX.n_beams
    r = np.zeros(n)
    r[:20] = 1.0
    r[-15:] = 1.2
    scan = make_scan(URG_04LX, r)
    segs = check_scan(cfg, scan, front_end(cfg, scan))
    assert segs == [(0, 20), (n - 15, 15)]


def test_more_than_k_candidates_counted():
    cfg = FrontEndConfig()
    n = URG_04LX.n_beams
    r = np.where(np.arange(n) % 3 == 0, 0.0, 1.0 + 0.5 * (np.arange(n) % 7 == 1))
    scan = make_scan(URG_04LX, r)
    out = front_end(cfg, scan)
    segs = check_scan(cfg, scan, out)
    assert len(segs) > 32 and int(out.diagnostics.n_overflow) == len(segs) - 32


def test_beyond_k_candidates_the_nearest_are_kept():
    """More segments than slots: a robot-sized object near the end of the scan is kept and far clutter
    (short pieces of a distant wall, earlier in beam order) is dropped, whatever their order."""
    cfg = FrontEndConfig()
    n = URG_04LX.n_beams
    r = np.zeros(n)
    for i in range(40):  # 40 pieces of a wall 5 m away, each 6 beams, in the first part of the scan
        r[10 * i: 10 * i + 6] = 5.0 + 0.01 * i
    r[600:620] = 2.0  # a robot 2 m away near the end
    scan = make_scan(URG_04LX, r)
    out = front_end(cfg, scan)
    segs = check_scan(cfg, scan, out)
    assert len(segs) == 41 and int(out.diagnostics.n_overflow) == 9
    starts = np.asarray(out.candidates.start)[np.asarray(out.candidates.live)]
    assert 600 in starts.tolist() and max(starts[starts < 600]) == 10 * 30  # the 9 farthest pieces dropped


def test_wall_longer_than_window_is_flagged_not_truncated():
    cfg = FrontEndConfig()
    n = URG_04LX.n_beams
    r = np.full(n, 2.0)
    r[500:520] = 1.0  # a small object in front of the wall
    scan = make_scan(URG_04LX, r)
    out = front_end(cfg, scan)
    segs = check_scan(cfg, scan, out)
    assert segs == [(0, 500), (500, 20), (520, n - 520)]
    np.testing.assert_array_equal(np.asarray(out.candidates.too_long[:3]), [True, False, True])
    assert int(out.diagnostics.n_too_long) == 2
    np.testing.assert_array_equal(np.asarray(out.keep[:3]), [False, True, False])


def test_nan_zero_and_out_of_window_ranges():
    cfg = FrontEndConfig()
    n = UTM_30LX.n_beams
    r, inten = cast(UTM_30LX, [(1.5, 0.3, 0.15), (2.0, -1.0, 0.05)], [(3.0, -5.0, 3.0, 5.0)], noise=0.01)
    r = r.copy()
    r[100] = np.nan
    r[530:533] = 0.0  # a hole inside an object
    r[700] = 50.0  # beyond range_max
    r[701] = 0.05  # below range_min
    r[900:905] = np.inf
    scan = make_scan(UTM_30LX, r, inten)
    assert not np.asarray(scan.valid)[[100, 530, 700, 701, 900]].any()
    out = front_end(cfg, scan)
    check_scan(cfg, scan, out)
    assert np.isfinite(np.asarray(out.features.vector)).all()
    assert n == scan.n_beams


def test_bad_ranges_marked_valid_are_treated_as_invalid():
    """A Scan built by hand (not through to_scans) that marks NaN, inf, 0 and negative ranges valid."""
    cfg = FrontEndConfig()
    r, inten = cast(UTM_30LX, [(1.5, 0.3, 0.15), (2.0, -1.0, 0.05)], [(3.0, -5.0, 3.0, 5.0)], noise=0.01)
    bad = {100: np.nan, 531: 0.0, 532: -1.0, 700: np.inf}
    r = r.copy()
    for i, v in bad.items():
        r[i] = v
    good = make_scan(UTM_30LX, r, inten)
    raw = eqx.tree_at(
        lambda s: (s.ranges, s.valid),
        good,
        (jnp.asarray(r), jnp.ones(r.shape, bool)),  # every beam claims a return
    )
    a, b = front_end(cfg, raw), front_end(cfg, good)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    check_scan(cfg, good, a)


def test_no_intensity_gives_zero_intensity_profile():
    cfg = FrontEndConfig()
    r, _ = cast(URG_04LX, [(1.5, 0.3, 0.15)], [])
    out = front_end(cfg, make_scan(URG_04LX, r))
    assert bool(out.keep[0])
    np.testing.assert_array_equal(np.asarray(out.features.vector[:, 1 + cfg.n_dist :]), 0)


def test_far_cells_fall_back_to_nearest_point():
    """A narrow candidate and a small σ: cells far from every point underflow exp(−dist) in float32;
    the defined value is the nearest point's x′, never NaN."""
    r = np.full(12, 2.0, np.float32)
    th = (np.arange(12) * 1e-3).astype(np.float32)
    kw = dict(n_dist=8, n_intensity=4, cells_on_bbox=jnp.asarray(False), cell_span=jnp.float32(2.0))
    xy = np.stack([r * np.cos(th), r * np.sin(th)], -1)
    f = characterise(
        jnp.asarray(r),
        jnp.asarray(th),
        jnp.asarray(xy),
        jnp.zeros(12, jnp.float32),
        jnp.ones(12, bool),
        sigma_cells=jnp.float32(0.01),
        sigma_min=jnp.float32(1e-4),
        **kw,
    )
    v = np.asarray(f.vector)
    assert np.isfinite(v).all()
    pts = np.asarray(f.points)
    np.testing.assert_allclose(v[1], pts[np.argmin(pts[:, 1]), 0], atol=1e-6)
    np.testing.assert_allclose(v[8], pts[np.argmax(pts[:, 1]), 0], atol=1e-6)


def test_cell_inside_a_wide_gap_is_zero():
    """Two clusters 1 m apart in one window (segmentation would split them; characterise is told
    not to) and a tiny σ: the middle cell's weights all underflow, and its value is 0, not NaN."""
    th = np.array([-0.26, -0.255, -0.25, 0.25, 0.255, 0.26], np.float32)
    r = np.full(6, 2.0, np.float32)
    xy = np.stack([r * np.cos(th), r * np.sin(th)], -1)
    f = characterise(
        jnp.asarray(r),
        jnp.asarray(th),
        jnp.asarray(xy),
        jnp.asarray(np.arange(6, dtype=np.float32)),
        jnp.ones(6, bool),
        n_dist=3,
        n_intensity=3,
        cells_on_bbox=jnp.asarray(False),
        cell_span=jnp.float32(2.0),  # centres at −2/3, 0, 2/3: outside, inside the gap, outside
        sigma_cells=jnp.float32(0.01),
        sigma_min=jnp.float32(1e-4),
    )
    v = np.asarray(f.vector)  # (w, d0, d1, d2, I0, I1, I2)
    pts = np.asarray(f.points)
    assert np.isfinite(v).all()
    assert v[2] == 0.0 and v[5] == 0.0  # the middle cells
    np.testing.assert_allclose(v[[1, 3]], pts[[0, 5], 0], atol=1e-6)  # outer cells: nearest point
    np.testing.assert_allclose(v[[4, 6]], [0.0, 5.0], atol=1e-6)


def test_compiles_once_for_twenty_scans_and_retuning():
    counted = jax.jit(eqx.debug.assert_max_traces(front_end_pure, max_traces=1))
    for seed in range(20):
        cfg = FrontEndConfig(break_distance=0.05 + 0.01 * seed, width_max=0.5 + 0.1 * seed, cells_on_bbox=seed % 2 == 0)
        scan = scene(URG_04LX, 100 + seed)
        a = counted(cfg, scan)
        b = front_end(cfg, scan)
        np.testing.assert_array_equal(np.asarray(a.features.vector), np.asarray(b.features.vector))
    assert counted._cache_size() == 1


def test_log_level_matches_scan_level():
    cfg = FrontEndConfig()
    scans = [scene(UTM_30LX, s) for s in range(5)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *scans)
    batch = jax.jit(front_end_batch, static_argnames=("chunk", "windows"))
    out = batch(cfg, stacked, chunk=2, windows=True)  # 5 scans: two full chunks and a remainder
    compact = batch(cfg, stacked, chunk=2)
    assert compact.candidates.mask is None and compact.features.points is None
    for t, scan in enumerate(scans):
        one = front_end(cfg, scan)
        got = jax.tree_util.tree_map(lambda a, t=t: a[t], out)
        for x, y in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(one), strict=True):
            assert_allclose(np.asarray(x), np.asarray(y))
        for name in ("vector", "origin", "heading", "width", "height", "n_points"):
            a, b = getattr(compact.features, name)[t], getattr(one.features, name)
            assert_allclose(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(compact.keep[t]), np.asarray(one.keep))
        np.testing.assert_array_equal(np.asarray(compact.candidates.start[t]), np.asarray(one.candidates.start))


def test_gradients_finite_through_empty_slots():
    cfg = FrontEndConfig()
    scan = scene(URG_04LX, 3)

    def loss(r):
        out = front_end_pure(cfg, eqx.tree_at(lambda s: s.ranges, scan, r))
        return jnp.sum(out.features.vector)

    g = jax.grad(loss)(scan.ranges)
    assert np.isfinite(np.asarray(g)).all()


def test_trainings_front_end_pads_a_short_log_and_drops_the_padding():
    """Training runs stages a–c over whole logs (``train.labels.run_front_end``), a short log or a long
    log's last chunk padded to a power of two (``padded_size``) so that logs of every length share a
    few compiled programs: every scan's candidates are the per-scan front end's, and logs of 23 and
    50 scans run one program."""
    from gtsjax.sim import simulate
    from gtsjax.train import labels

    cfg = FrontEndConfig()
    assert [labels.padded_size(n, 1024) for n in (1, 64, 65, 700, 1024, 1500)] == [64, 64, 128, 1024, 1024, 1500]
    log, _ = simulate("spl-trajectory", seed=5, n_scans=50)
    before = labels._front_end_batch._cache_size()
    for n in (23, 50):
        got = labels.run_front_end(log.slice(0, n), cfg, log.n_beams, chunk=32)  # 23: one padded chunk; 50: 32 + 18
        for t in (0, n // 2, n - 1):
            one = front_end(cfg, jax.tree.map(lambda a, t=t: a[t], to_scans(log.slice(0, n), log.n_beams)))
            np.testing.assert_array_equal(got["keep"][t], np.asarray(one.keep))
            np.testing.assert_array_equal(got["start"][t], np.asarray(one.candidates.start))
            assert_allclose(got["origin"][t], np.asarray(one.features.origin, np.float64))
        assert got["keep"].shape[0] == n
    assert labels._front_end_batch._cache_size() - before == 1  # 32 scans each time: one program
