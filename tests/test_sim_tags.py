"""Reflective tags on the simulated robots (issue 43 item 5): the tagged outline against the band's
definition (arc length from the first vertex, cells of P/N), the rendered intensity of each beam
against a NumPy loop that ray-casts the bare outline and finds the hit's cell from its arc length,
scenes without tags unchanged bit for bit (against the render's formula before tags, replayed here
with the same random draws), the scenarios' defaults, the site's ``tags`` and the log's
``truth_names`` round trips, and the emulator serving the tagged intensities over a real pty."""

import json
import math
import threading
import time

import numpy as np
import pytest

from gtsjax.errors import InputError
from gtsjax.io.logs import load_log, save_log
from gtsjax.io.site import Site, SiteTags, TagWearer, load_site, parse_site, save_site
from gtsjax.sensors import URG_04LX, UTM_30LX
from gtsjax.sim import simulate
from gtsjax.sim.match import simulate_match
from gtsjax.sim.scene import (
    OUTLINES,
    TAPE_INCIDENCE_EXP,
    TAPE_REFLECTIVITY,
    Effects,
    Mover,
    Scene,
    cast,
    render,
    robot_shape,
    tagged_shape,
    walls,
)
from gtsjax.tags.codes import cells_for, cyclic_distance, design

# ------------------------------------------------------------------------ a second implementation


def arc_table(vertices):
    """Each edge's start (arc length from vertex 0), its length and the perimeter."""
    v = np.asarray(vertices, float)
    seg = np.linalg.norm(np.roll(v, -1, axis=0) - v, axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)[:-1]]), seg, float(seg.sum())


def cast_one(vertices, refl, origin, direction):
    """One beam against a polygon, by a loop over its edges: distance, cosine of incidence, the hit's
    arc length along the outline (from vertex 0, counter-clockwise) and the edge's reflectivity;
    ``None`` for a miss."""
    v = np.asarray(vertices, float)
    start, seg, _ = arc_table(v)
    o, d = np.asarray(origin, float), np.asarray(direction, float)
    best = None
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        e = b - a
        den = d[0] * e[1] - d[1] * e[0]
        if abs(den) < 1e-12:
            continue
        w = a - o
        t = (w[0] * e[1] - w[1] * e[0]) / den
        s = (w[0] * d[1] - w[1] * d[0]) / den
        if t > 0 and 0 <= s <= 1 and (best is None or t < best[0]):
            best = (t, abs(den) / np.linalg.norm(e), start[i] + s * seg[i], float(refl[i]))
    return best


def world_vertices(outline_vertices, pose):
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    v = np.asarray(outline_vertices, float)
    return np.column_stack([x + c * v[:, 0] - s * v[:, 1], y + s * v[:, 0] + c * v[:, 1]])


def cell_of(arc, perimeter, n):
    """The cell a point at arc length ``arc`` lies in, and how far (in cells) from the nearest boundary."""
    u = arc / (perimeter / n)
    k = min(n - 1, int(u))
    return k, min(u - math.floor(u), math.ceil(u) - u)


# ------------------------------------------------------------------------------- the tagged outline


@pytest.mark.parametrize("outline", list(OUTLINES))
def test_tagged_outline_keeps_the_perimeter_and_cuts_at_k_p_over_n(outline):
    base = robot_shape(outline)
    b_start, b_seg, perim = arc_table(base.vertices)
    rng = np.random.default_rng(0)
    for n in (2, 5, 6, 8, 11, 16):
        code = rng.random(n) < 0.5
        code[0], code[-1] = True, False
        shape = tagged_shape(outline, code)
        start, seg, p = arc_table(shape.vertices)
        assert p == pytest.approx(perim, abs=1e-12)
        # Every vertex on the outline: the original ones and the cell boundaries, by arc length, once each.
        want = np.unique(np.round(np.concatenate([b_start, np.arange(n) * perim / n]), 9))
        np.testing.assert_allclose(np.sort(start), want, atol=1e-9)
        assert np.all(np.diff(start) > 0) and np.all(seg > 1e-9)
        for k, (s0, ln) in enumerate(zip(start, seg, strict=True)):
            mid = s0 + ln / 2
            edge = int(np.searchsorted(b_start, mid, side="right") - 1)
            # collinear: the piece lies on its edge of the bare outline
            a, b = base.vertices[edge], base.vertices[(edge + 1) % len(base.vertices)]
            for q in (shape.vertices[k], shape.vertices[(k + 1) % len(shape.vertices)]):
                e, w = b - a, q - a
                assert abs(e[0] * w[1] - e[1] * w[0]) < 1e-12
            cell, _ = cell_of(mid, perim, n)
            assert shape.retro[k] == code[cell]
            assert shape.reflectivity[k] == (TAPE_REFLECTIVITY if code[cell] else base.reflectivity[edge])
    # All body: the outline's edges as they were (no cut changes their reflectivity), none retro.
    plain = tagged_shape(outline, np.zeros(4, bool))
    assert not plain.retro.any() and set(plain.reflectivity) == set(base.reflectivity)


def test_tape_is_several_times_brighter_than_every_painted_face():
    body = np.concatenate([r for _, r in OUTLINES.values()])
    assert TAPE_REFLECTIVITY > 2.5 * body.max()  # brighter than the Nao's fin, tape of its own
    plain = body[body <= 0.5]  # the plain faces of every outline
    assert np.all((3.0 <= TAPE_REFLECTIVITY / plain) & (TAPE_REFLECTIVITY / plain <= 6.0))
    assert 0 < TAPE_INCIDENCE_EXP < 0.5  # flatter than paint's √cos


@pytest.mark.parametrize("dist", [2.0, 5.0, 9.0])
def test_rendered_intensity_is_tape_or_body_as_the_arc_length_says(dist):
    """A tagged Nao turned every 30° at ``dist`` m from a UTM-30LX, rendered without noise: every beam
    that a NumPy loop finds on the bare outline has the range and intensity of its cell (tape: the
    tape's reflectivity and falloff; body: the edge's), away from cell boundaries."""
    code = design(6, 8).codes[3]
    n = code.size
    model = UTM_30LX
    base = robot_shape("nao")
    _, _, perim = arc_table(base.vertices)
    headings = np.radians(np.arange(0, 360, 30.0))
    poses = np.column_stack([np.full(headings.size, dist), np.full(headings.size, 0.3), headings])
    scene = Scene(movers=[Mover(tagged_shape("nao", code), poses)])
    sensor = np.zeros((headings.size, 3))
    ranges, inten = render(scene, model, sensor, rng=np.random.default_rng(0), effects=Effects(noise=False))
    checked = {True: 0, False: 0}
    for t, pose in enumerate(poses):
        wv = world_vertices(base.vertices, pose)
        for j in np.flatnonzero(np.abs(model.angles - math.atan2(0.3, dist)) < 0.1):
            a = model.angles[j]
            hit = cast_one(wv, base.reflectivity, (0.0, 0.0), (math.cos(a), math.sin(a)))
            if hit is None or hit[1] < 0.1:
                assert hit is not None or ranges[t, j] == 0.0
                continue
            r, cos_inc, arc, body_refl = hit
            cell, edge_dist = cell_of(arc, perim, n)
            if edge_dist * perim / n < 1e-3:  # within 1 mm of a boundary: either cell
                continue
            tape = bool(code[cell])
            refl, falloff = (TAPE_REFLECTIVITY, cos_inc ** TAPE_INCIDENCE_EXP) if tape else (body_refl, math.sqrt(cos_inc))
            assert ranges[t, j] == pytest.approx(r, rel=1e-6)
            assert inten[t, j] == pytest.approx(6000.0 * refl * falloff / math.sqrt(max(r, 0.5)), rel=1e-5)
            checked[tape] += 1
    assert checked[True] > 10 and checked[False] > 10, checked


def test_untagged_scenes_render_as_before_bit_for_bit():
    """Without tags the render is the formula it was before tags, bit for bit: the same random draws
    (range noise, dropouts, intensity noise) replayed here on :func:`cast`'s geometry."""
    model = UTM_30LX
    t = 40
    th = np.linspace(0, 2 * np.pi, t)
    poses = np.column_stack([2.0 + 0.5 * np.cos(th), 1.0 + 0.5 * np.sin(th), th])
    scene = Scene(polygons=walls(-3, -3, 6, 6), movers=[Mover(robot_shape("nao"), poses)])
    sensor = np.zeros((t, 3))
    eff = Effects()
    ranges, inten = render(scene, model, sensor, rng=np.random.default_rng(7), effects=eff)
    rng = np.random.default_rng(7)
    r, cos_inc, refl = cast(scene, model, sensor)
    hit = np.isfinite(r)
    r = np.where(hit, r, 0.0)
    r = r + rng.standard_normal(r.shape) * model.noise.std(r)
    r = np.round(r / model.noise.resolution) * model.noise.resolution
    hit &= rng.random(r.shape) >= eff.dropout
    hit &= (cos_inc >= eff.grazing_cos) & (r >= model.range_min) & (r <= model.range_max)
    i = 6000.0 * refl * np.sqrt(np.clip(cos_inc, 0, 1)) / np.sqrt(np.maximum(r, 0.5))
    i = i * (1 + eff.intensity_noise * rng.standard_normal(i.shape))
    np.testing.assert_array_equal(ranges, np.where(hit, r, 0.0).astype(np.float32))
    np.testing.assert_array_equal(inten, np.where(hit, np.maximum(i, 0.0), 0.0).astype(np.float32))


# ---------------------------------------------------------------------------------------- scenarios


@pytest.mark.parametrize("name", ["spl-trajectory", "hall-eval", "spl-crossing"])
def test_urg_scenarios_are_unchanged_and_untagged(name):
    log, site = simulate(name, seed=3, n_scans=25)
    bare, bare_site = simulate(name, seed=3, n_scans=25, tags=False)
    assert log.intensities is None and site.tags is None and "truth_names" not in log.extra
    for k, v in bare.to_dict().items():
        np.testing.assert_array_equal(log.to_dict()[k], v, err_msg=k)
    assert site.to_json() == bare_site.to_json()
    with pytest.raises(InputError, match="URG-04LX reports no intensity"):
        simulate(name, seed=3, n_scans=5, tags=True)


def test_a_utm_scenario_wears_one_code_sized_for_the_farthest_field_corner():
    log, site = simulate("lab-eval", seed=1, n_scans=40)
    bare, _ = simulate("lab-eval", seed=1, n_scans=40, tags=False)
    sx, sy = 0.3, 0.3  # lab_layout's laser
    far = max(math.dist((sx, sy), c) for c in ((1.0, 0.8), (7.2, 0.8), (7.2, 4.4), (1.0, 4.4)))
    _, _, perim = arc_table(robot_shape("nao").vertices)
    cells = cells_for(perim, far, UTM_30LX.angle_increment)
    assert site.tags is not None and site.tags.cells == cells and site.tags.range_m == pytest.approx(far, abs=1e-3)
    assert site.tags.perimeter_m == pytest.approx(perim, abs=1e-6)
    assert [(w.name, w.code, w.offset_cells) for w in site.tags.robots] == [("robot1", design(1, cells).strings()[0], 0)]
    assert list(log.extra["truth_names"]) == ["robot1"]
    np.testing.assert_array_equal(log.ranges, bare.ranges)  # the tape changes what is bright, not where
    lit = log.intensities > bare.intensities * 2
    assert lit.any() and not (log.intensities < bare.intensities * 0.5).any()
    # Another scanner given to a URG-04LX scenario: tags, sized for it.
    _, s2 = simulate("spl-eval", seed=1, n_scans=5, sensor="UTM-30LX")
    assert s2.tags is not None and s2.tags.range_m == pytest.approx(math.dist((3.0, 4.0), (0.0, 0.0)), abs=1e-3)


def test_matches_tag_every_robot_when_a_laser_reads_intensity():
    logs, site = simulate_match("spl-match-2-utm", seed=4, n_robots=10, seconds=0.5)
    t = site.tags
    assert t is not None and [w.name for w in t.robots] == [f"robot{m + 1}" for m in range(10)]
    codes = np.array([w.bits for w in t.robots])
    assert len({w.code for w in t.robots}) == 10 and t.cells == codes.shape[1] == 8
    assert min(cyclic_distance(a, b) for i, a in enumerate(codes) for b in codes[i + 1:]) >= 1
    assert t.range_m == pytest.approx(math.hypot(4.5, 6.5), abs=1e-3)  # a field corner from a tripod
    for log in logs.values():
        assert list(log.extra["truth_names"]) == [w.name for w in t.robots]
    # Mixed: the robots wear tags whatever the laser; the URG-04LX's log is as without them.
    mixed, msite = simulate_match("spl-match-2-mixed", seed=4, n_robots=3, seconds=1.0)
    bare, bsite = simulate_match("spl-match-2-mixed", seed=4, n_robots=3, seconds=1.0, tags=False)
    assert msite.tags is not None and bsite.tags is None
    assert mixed["north"].sensor_model == "URG-04LX" and mixed["north"].intensities is None
    np.testing.assert_array_equal(mixed["north"].ranges, bare["north"].ranges)
    np.testing.assert_array_equal(mixed["south"].ranges, bare["south"].ranges)
    assert not np.array_equal(mixed["south"].intensities, bare["south"].intensities)
    # URG-04LX only: as before, no tags anywhere.
    urg, usite = simulate_match("spl-match-2", seed=4, n_robots=3, seconds=1.0)
    assert usite.tags is None and all("truth_names" not in lg.extra for lg in urg.values())
    with pytest.raises(InputError, match="no intensity"):
        simulate_match("spl-match-2", seed=4, n_robots=3, seconds=1.0, tags=True)


# ------------------------------------------------------------------------------ files round trips


def test_site_tags_round_trip_and_old_sites_still_load(tmp_path):
    _, site = simulate("lab-eval", seed=2, n_scans=5)
    save_site(site, tmp_path / "site.json")
    doc = json.loads((tmp_path / "site.json").read_text())
    assert set(doc["tags"]) == {"cells", "perimeter_m", "range_m", "robots"}
    assert doc["tags"]["robots"][0] == {"name": "robot1", "code": site.tags.robots[0].code, "offset_cells": 0}
    back = load_site(tmp_path / "site.json")
    assert back == site and back.tags == site.tags and "tags" not in back.extra
    old = {k: v for k, v in doc.items() if k != "tags"}
    assert parse_site(old).tags is None
    minimal = {**old, "tags": {"cells": 4, "perimeter_m": 1.2, "robots": [{"name": "a", "code": "1100"}]}}
    got = parse_site(minimal).tags
    assert got == SiteTags(4, 1.2, (TagWearer("a", "1100", 0),), None)
    assert got.code_of("a").tolist() == [True, True, False, False] and got.code_of("b") is None
    site2 = Site(site.landmarks, site.sensor_pose, site.bounds, tags=got)
    assert parse_site(site2.to_json()) == site2


@pytest.mark.parametrize("tags, words", [
    ([1], "must be an object"),
    ({"cells": 4, "robots": []}, "missing 'perimeter_m'"),
    ({"cells": 4.0, "perimeter_m": 1, "robots": [{"name": "a", "code": "1100"}]}, "'cells' must be a whole number"),
    ({"cells": 4, "perimeter_m": -1, "robots": [{"name": "a", "code": "1100"}]}, "'perimeter_m' must be a positive"),
    ({"cells": 4, "perimeter_m": 1, "robots": []}, "non-empty list"),
    ({"cells": 4, "perimeter_m": 1, "robots": [{"name": "a", "code": "110"}]}, "string of 4 '0'"),
    ({"cells": 4, "perimeter_m": 1, "robots": [{"name": "a", "code": "11x0"}]}, "string of 4 '0'"),
    ({"cells": 4, "perimeter_m": 1, "robots": [{"name": "a", "code": "1100"}, {"name": "a", "code": "1000"}]},
     "used twice"),
    ({"cells": 4, "perimeter_m": 1, "robots": [{"name": "a", "code": "1100", "offset_cells": 4}]},
     "'offset_cells' must be a whole number from 0 to 3"),
])
def test_bad_site_tags_are_one_line(tmp_path, tags, words):
    _, site = simulate("spl-eval", n_scans=2)
    doc = {**site.to_json(), "tags": tags}
    (tmp_path / "s.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=words) as err:
        load_site(tmp_path / "s.json")
    assert "\n" not in str(err.value) and "s.json" in str(err.value)


def test_truth_names_round_trip_and_old_logs_still_load(tmp_path):
    log, _ = simulate("lab-eval", seed=2, n_scans=6)
    save_log(log, tmp_path / "a.npz")
    back = load_log(tmp_path / "a.npz")
    assert back.extra["truth_names"].dtype.kind == "U" and list(back.extra["truth_names"]) == ["robot1"]
    old = dict(np.load(tmp_path / "a.npz"))
    del old["truth_names"]
    np.savez(tmp_path / "old.npz", **old)
    assert "truth_names" not in load_log(tmp_path / "old.npz").extra
    np.savez(tmp_path / "bad.npz", **{**old, "truth_names": np.array(["a", "b"])})
    with pytest.raises(InputError, match=r"'truth_names' must be a string array of shape \[1\]"):
        load_log(tmp_path / "bad.npz")
    unlabelled = {k: v for k, v in old.items() if not k.startswith("truth_")}
    np.savez(tmp_path / "bad2.npz", **unlabelled, truth_names=np.array(["a"]))
    with pytest.raises(InputError, match="needs 'truth_classes'"):
        load_log(tmp_path / "bad2.npz")


def test_simulate_command_tags_flags(tmp_path, capsys):
    from gtsjax.cli import main

    args = ["simulate", "lab-eval", "--scans", "5"]
    assert main([*args, "--out", str(tmp_path / "a.npz"), "--site", str(tmp_path / "a.json")]) == 0
    assert load_site(tmp_path / "a.json").tags is not None and "tagged" in capsys.readouterr().err
    assert main([*args, "--no-tags", "--out", str(tmp_path / "b.npz"), "--site", str(tmp_path / "b.json")]) == 0
    assert load_site(tmp_path / "b.json").tags is None and "truth_names" not in load_log(tmp_path / "b.npz").extra
    capsys.readouterr()
    assert main(["simulate", "spl-eval", "--scans", "5", "--tags", "--out", str(tmp_path / "c.npz"), "--site",
                 str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no intensity" in err[0] and not (tmp_path / "c.npz").exists()
    assert main(["info", str(tmp_path / "a.json")]) == 0
    assert "tags: 1 robots" in capsys.readouterr().out


# ------------------------------------------------------------------------------------- the emulator


def tape_mask(log, site, t):
    """Beams of scan ``t`` whose return lies on a robot's tape cell (True) or body cell (False), well
    inside the cell; other beams -1. By arc length on the bare outline, from the truth poses."""
    base = robot_shape("nao")
    b_start, b_seg, perim = arc_table(base.vertices)
    sx, sy, sth = log.extra["truth_sensor_pose"][t]
    a = sth + log.angles()
    r = log.ranges[t].astype(float)
    p = np.column_stack([sx + r * np.cos(a), sy + r * np.sin(a)])
    out = np.full(r.size, -1)
    for m, name in enumerate(log.extra["truth_names"]):
        code = site.tags.code_of(str(name))
        x, y, th = log.truth_poses[t, m]
        c, s = math.cos(th), math.sin(th)
        for j in np.flatnonzero((r > 0) & (np.hypot(p[:, 0] - x, p[:, 1] - y) < 0.3)):
            q = np.array([c * (p[j, 0] - x) + s * (p[j, 1] - y), -s * (p[j, 0] - x) + c * (p[j, 1] - y)])
            best = (np.inf, 0.0)
            for i in range(len(base.vertices)):
                v0, v1 = base.vertices[i], base.vertices[(i + 1) % len(base.vertices)]
                e = v1 - v0
                u = float(np.clip(np.dot(q - v0, e) / np.dot(e, e), 0, 1))
                best = min(best, (float(np.linalg.norm(v0 + u * e - q)), b_start[i] + u * b_seg[i]))
            cell, edge = cell_of(best[1], perim, code.size)
            if best[0] < 0.03 and edge > 0.2:
                out[j] = int(code[cell])
    return out


def test_emulate_a_utm_match_serves_the_tagged_intensities(tmp_path):
    """``serve_match("spl-match-2-utm")`` over a real pty: a frame's intensities are its log's, and on
    it the robots' tape cells (found from the truth and the site's codes by arc length) return more
    than twice the body's."""
    from gtsjax.io import scip
    from gtsjax.sim.emulator import serve_match

    from .test_emulator import Client

    kw = dict(seed=6, n_robots=6, seconds=2.0)
    logs, site = simulate_match("spl-match-2-utm", **kw)
    lines, stop = [], threading.Event()
    th = threading.Thread(target=serve_match, args=("spl-match-2-utm",),
                          kwargs=dict(**kw, print_fn=lines.append, stop=stop, link_dir=tmp_path), daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 60
        while len(lines) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        path = {ln.split(":")[0]: ln.split(" on ")[1].split(" ")[0] for ln in lines[:2]}["north"]
        log = logs["north"]
        c = Client(path)
        ack, f = c.ask(scip.me_command(UTM_30LX.amin, UTM_30LX.amax, count=1), n=2)
        c.close()
        assert ack.status == "00" and f.intensities is not None
        mm = np.where(log.valid(), np.rint(log.ranges * 1000.0), 0).astype(np.int64)
        (t,) = np.flatnonzero((mm == np.asarray(f.ranges_mm, np.int64)[None]).all(1))[:1]
        np.testing.assert_array_equal(f.intensities, np.rint(log.intensities[t]).astype(np.int64))
        mask = tape_mask(log, site, t)
        inten = np.asarray(f.intensities, float)
        assert (mask == 1).sum() >= 5 and (mask == 0).sum() >= 5, mask
        assert np.median(inten[mask == 1]) > 2.0 * np.median(inten[mask == 0])
    finally:
        stop.set()
        th.join(timeout=10)
    assert not th.is_alive()


def test_emulate_a_one_laser_utm_scenario_serves_its_tagged_log(tmp_path):
    from gtsjax.io import scip
    from gtsjax.sim.emulator import serve

    from .test_emulator import Client

    log, _ = simulate("lab-trajectory", seed=0)
    bare, _ = simulate("lab-trajectory", seed=0, tags=False)
    lines, stop = [], threading.Event()
    th = threading.Thread(target=serve, args=("lab-trajectory",),
                          kwargs=dict(print_fn=lines.append, stop=stop, link_dir=tmp_path), daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 60
        while not lines and time.monotonic() < deadline:
            time.sleep(0.05)
        c = Client(lines[0].split(" on ")[1].split(" ")[0])
        ack, f = c.ask(scip.me_command(UTM_30LX.amin, UTM_30LX.amax, count=1), n=2)
        c.close()
        mm = np.where(log.valid(), np.rint(log.ranges * 1000.0), 0).astype(np.int64)
        (t,) = np.flatnonzero((mm == np.asarray(f.ranges_mm, np.int64)[None]).all(1))[:1]
        np.testing.assert_array_equal(f.intensities, np.rint(log.intensities[t]).astype(np.int64))
        assert not np.array_equal(log.intensities, bare.intensities)  # the tagged log served, not the bare one
    finally:
        stop.set()
        th.join(timeout=10)
    assert URG_04LX.has_intensity is False
