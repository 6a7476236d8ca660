"""Enrolment (``gtsjax.tags.enrol``, ``gtsjax enrol``): the band's evidence per cell against a NumPy loop
that places each return along the simulator's own tagged outline (the exact arc length), the match of a
read against known codes at every rotation (a band turned by 2 cells gives its code and offset 2), the
checks that refuse a read (cells not seen, a code another robot wears, a robot designed to wear another
code), the site written atomically with the rest unchanged and the previous file kept, and the command's
bad inputs as one line and exit 2."""

import json
import math
import os
import re
import stat

import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.enrol import write_site
from gtsjax.core.e_tags import BINS, TagReader, arc_table, patterns
from gtsjax.errors import InputError
from gtsjax.io.site import SiteTags, TagWearer
from gtsjax.sim.scene import NAO_OUTLINE, tagged_shape
from gtsjax.tags import enrol as E
from gtsjax.tags.codes import design
from gtsjax.train.tags import CELL_MARGIN

TAPE, BODY = 3.0, 0.5


def _reader(codes, sd=0.3):
    return TagReader(
        pattern=patterns(codes, np.zeros(len(codes))), arc=jnp.asarray(arc_table(NAO_OUTLINE), jnp.float32)[None],
        has_arc=jnp.array([True]), range_exp=jnp.float32(0.5), tape_mean=jnp.float32(math.log(6000 * TAPE)),
        tape_sd=jnp.float32(sd), body_mean=jnp.float32(math.log(6000 * BODY)), body_sd=jnp.float32(sd),
        cells=jnp.int32(codes.shape[1]), min_cells=jnp.float32(2.0), point_cap=jnp.float32(5.0),
        bin_cap=jnp.float32(3.0), weight=jnp.float32(0.02))


def _polygon_points(shape, n, rng):
    """``n`` points on the tagged outline's edges, each with its arc length (fraction from vertex 0, the
    origin) and whether it lies on tape: the simulator's own geometry."""
    v = shape.vertices
    nxt = np.roll(v, -1, axis=0)
    seg = np.linalg.norm(nxt - v, axis=1)
    start = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    i = rng.choice(len(v), size=n, p=seg / seg.sum())
    u = rng.random(n)
    return v[i] + u[:, None] * (nxt[i] - v[i]), (start[i] + u * seg[i]) / seg.sum(), shape.retro[i]


def test_band_evidence_matches_a_numpy_loop_on_the_simulators_outline():
    """Scans of returns on a Nao wearing a 13-cell band turned by 2 cells: the evidence per cell (bins,
    caps, the cells' middles) against a loop that bins each return by its exact arc length on the
    simulator's tagged polygon; and the read is the band as mounted."""
    rng = np.random.default_rng(3)
    n_cells, scans, per_scan = 13, 40, 60
    code = design(4, n_cells).codes[1]
    shape = tagged_shape("nao", code, offset_cells=2)
    reader = _reader(design(4, n_cells).codes)
    q = np.zeros((scans, per_scan, 2))
    s = np.zeros((scans, per_scan))
    tape = np.zeros((scans, per_scan), bool)
    for t in range(scans):
        q[t], s[t], tape[t] = _polygon_points(shape, per_scan, rng)
    r = rng.uniform(1.0, 8.0, (scans, per_scan))
    inten = 6000 * np.where(tape, TAPE, BODY) / np.sqrt(r) * np.exp(rng.normal(0, 0.3, r.shape))
    use = rng.random(r.shape) < 0.9
    per_bin, count = E.band_evidence(reader, reader.arc[0], jnp.asarray(q, jnp.float32), jnp.asarray(inten, jnp.float32),
                                     jnp.asarray(r, jnp.float32), jnp.asarray(use))
    got = E.cell_sums(np.asarray(per_bin), np.asarray(count), n_cells)

    # The loop: each return's ratio, binned by its exact arc length, squashed per scan and bin.
    want_e, want_seen, want_n = np.zeros(n_cells), np.zeros(n_cells, int), np.zeros(n_cells, int)
    for t in range(scans):
        sums, cnt = np.zeros(BINS), np.zeros(BINS)
        for j in range(per_scan):
            if not use[t, j]:
                continue
            u = math.log(inten[t, j]) + 0.5 * math.log(r[t, j])
            lt = -0.5 * ((u - math.log(6000 * TAPE)) / 0.3) ** 2
            lb = -0.5 * ((u - math.log(6000 * BODY)) / 0.3) ** 2
            b = min(int(s[t, j] * BINS), BINS - 1)
            sums[b] += min(max(lt - lb, -5.0), 5.0)
            cnt[b] += 1
        sums = 3.0 * np.tanh(sums / 3.0)
        for k in range(n_cells):
            inside = [b for b in range(BINS) if int((b + 0.5) / BINS * n_cells) == k
                      and CELL_MARGIN < ((b + 0.5) / BINS * n_cells) % 1 < 1 - CELL_MARGIN]
            want_e[k] += sums[inside].sum()
            want_seen[k] += cnt[inside].sum() > 0
            want_n[k] += cnt[inside].sum()
    # The arc table is the polygon's at 128 angles: a few returns at a bin's edge land in the next bin.
    np.testing.assert_allclose(got[0], want_e, rtol=0.05, atol=3.0)
    assert np.abs(got[1] - want_seen).max() <= 2 and np.abs(got[2] - want_n).sum() <= 0.02 * want_n.sum() + 2
    read = E.BandRead(n_cells, got[0], got[1], got[2], 0.02, scans)
    assert read.code_string() == "".join("1" if b else "0" for b in np.roll(code, 2))


def _read_of(code, offset, strength=400.0, seen=50):
    """A clean read of ``code`` mounted turned by ``offset`` cells."""
    pattern = np.roll(np.asarray(code, bool), offset)
    n = len(pattern)
    return E.BandRead(n, np.where(pattern, strength, -strength), np.full(n, seen), np.full(n, 10 * seen), 0.02, seen)


def test_match_gives_the_code_and_its_offset():
    d = design(4, 13)
    known = [(f"nao{k + 1}", s) for k, s in enumerate(d.strings())]
    for k in range(4):
        for off in (0, 2, 7):
            m = E.match(_read_of(d.codes[k], off), known)
            E.check(_read_of(d.codes[k], off), m, True)
            assert (m.name, m.code, m.offset, m.disagree) == (f"nao{k + 1}", d.strings()[k], off, ())
            assert m.margin >= E.MIN_MARGIN and m.offset_margin >= E.MIN_MARGIN


def test_reads_that_do_not_single_out_a_code_are_refused_in_one_line():
    d = design(4, 13)
    known = [(f"nao{k + 1}", s) for k, s in enumerate(d.strings())]
    unseen = _read_of(d.codes[1], 2)
    unseen = E.BandRead(13, unseen.evidence, np.where(np.arange(13) >= 11, 1, 50), unseen.returns, 0.02, 50)
    with pytest.raises(InputError, match="cells 11, 12 of 13 were not seen.*turn the robot"):
        E.check(unseen, E.match(unseen, known), True)
    other = np.array([c == "1" for c in "1010101010100"])  # no known code: cells disagree
    read = _read_of(other, 0)
    with pytest.raises(InputError, match="read 1010101010100.*disagrees in cell"):
        E.check(read, E.match(read, known), True)
    weak = _read_of(d.codes[1], 2, strength=5.0)  # nothing decided, codes near alike
    with pytest.raises(InputError, match="margin"):
        E.check(weak, E.match(weak, known), True)
    with pytest.raises(InputError, match="every cell must be decided"):
        E.check(weak, E.match(weak, []), False)
    clean = E.match(_read_of(other, 0), [])  # no known codes: the read itself
    assert (clean.name, clean.code, clean.offset) == (None, "1010101010100", 0)


def test_enrolled_adds_replaces_and_refuses():
    d = design(4, 13)
    s = d.strings()
    tags = SiteTags(13, 0.88, (TagWearer("nao1", s[0], 0), TagWearer("nao2", s[2], 1)), 5.0)
    m = E.match(_read_of(d.codes[1], 2), [(f"nao{k + 1}", c) for k, c in enumerate(s)])
    new, notes = E.enrolled(tags, "nao2", m)
    assert new.robots == (TagWearer("nao1", s[0], 0), TagWearer("nao2", s[1], 2)) and "replaced" in notes[0]
    new, _ = E.enrolled(tags, "nao3", m)
    assert new.robots[-1] == TagWearer("nao3", s[1], 2) and new.cells == 13 and new.range_m == 5.0
    worn = SiteTags(13, 0.88, (TagWearer("nao5", s[1], 0),), 5.0)
    with pytest.raises(InputError, match="already worn by nao5.*--replace"):
        E.enrolled(worn, "nao2", m)
    new, notes = E.enrolled(worn, "nao2", m, replace=True)
    assert new.robots == (TagWearer("nao2", s[1], 2),) and "removed nao5" in notes[0]
    with pytest.raises(InputError, match="nao2 was designed to wear .*nao3's"):
        E.enrolled(None, "nao2", E.match(_read_of(d.codes[2], 0), [("nao3", s[2])]),
                   designed={"nao2": s[1], "nao3": s[2]}, base=SiteTags(13, 0.88, (), 5.0))


def test_site_written_atomically_the_rest_unchanged_and_the_previous_kept(tmp_path):
    """In place: the previous file kept as .bak, every other entry as it was, the file's permission bits
    kept (a temporary file's 0600 once replaced a site's 0644); to --out: a new file with the mode the
    umask gives a new file; no temporary file left behind."""
    site = tmp_path / "site.json"
    doc = {"landmarks": [{"class": "post", "x": 0.0, "y": 1.3, "note": "ünïcode"}], "sensor_pose": [3.0, 4.0, -1.5708],
           "bounds": [0.0, 0.0, 6.0, 4.0], "operator": {"name": "x", "list": [1, 2.5]}}
    before = json.dumps(doc, indent=2) + "\n"
    site.write_text(before)
    site.chmod(0o640)
    new = dict(doc, tags=SiteTags(13, 0.88, (TagWearer("nao2", "1101011101000", 2),), 5.0).to_json())
    assert write_site(new, site, None) == site
    assert stat.S_IMODE(site.stat().st_mode) == 0o640
    assert (tmp_path / "site.json.bak").read_text() == before
    got = json.loads(site.read_text())
    assert got.pop("tags")["robots"] == [{"name": "nao2", "code": "1101011101000", "offset_cells": 2}]
    assert got == doc and list(got) == list(doc)
    out = tmp_path / "other.json"
    write_site(new, site, out)
    assert json.loads(out.read_text()) == new
    umask = os.umask(0)
    os.umask(umask)
    fresh = tmp_path / "fresh"
    fresh.touch()  # what open() gives a new file here
    assert stat.S_IMODE(out.stat().st_mode) == stat.S_IMODE(fresh.stat().st_mode) == 0o666 & ~umask
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith((".tmp", ".part"))] == []


def test_outputs_naming_an_input_are_refused_before_any_work(tmp_path, capsys):
    """``--out`` naming the log, the model or the tags file, ``--record`` naming the site or the model
    (directly or through a link), an --out in a folder that cannot be made: each one line, exit 2,
    before anything is read or written: every input as it was, in content and mode (``enrol --out
    LOG`` once replaced a 22 MB log with the site, ``--record SITE`` the site with a recording)."""
    files = {name: tmp_path / name for name in ("site.json", "model.npz", "log.npz", "tags.json")}
    for i, p in enumerate(files.values()):
        p.write_bytes(f"input {i}\n".encode())  # never read: the guard comes first
        p.chmod(0o644)
    (tmp_path / "link.npz").symlink_to(files["log.npz"])
    base = ["enrol", "--robot", "nao3", "--site", files["site.json"], "--model", files["model.npz"]]
    cases = [
        (["--log", files["log.npz"], "--out", files["log.npz"]], "is both --out and the input --log"),
        (["--log", files["log.npz"], "--out", tmp_path / "link.npz"], "is both --out and the input --log"),
        (["--log", files["log.npz"], "--out", files["model.npz"]], "is both --out and the input --model"),
        (["--log", files["log.npz"], "--codes", files["tags.json"], "--out", files["tags.json"]], "the input --codes"),
        (["--port", "/dev/null", "--record", files["site.json"]], "is both --record and the input --site"),
        (["--port", "/dev/null", "--record", files["model.npz"]], "is both --record and the input --model"),
        (["--log", files["log.npz"], "--record", tmp_path / "r.npz"], "with --log there is nothing to record"),
        (["--log", files["log.npz"], "--out", "/proc/no/site.json"], "cannot create the folder"),
        (["--log", files["log.npz"], "--out", files["log.npz"] / "site.json"], "is a file, not a folder"),
    ]
    for args, says in cases:
        capsys.readouterr()
        assert main([str(a) for a in [*base, *args]]) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], (args, err)
        for i, p in enumerate(files.values()):
            assert p.read_bytes() == f"input {i}\n".encode() and stat.S_IMODE(p.stat().st_mode) == 0o644, (args, p)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*files, "link.npz"])


def test_bad_inputs_are_one_line_and_exit_2(tmp_path, capsys):
    from gtsjax.cli.demo import demo_model_path

    site = tmp_path / "site.json"
    site.write_text(json.dumps({"landmarks": [{"class": "post", "x": 0.0, "y": 1.3}, {"class": "post", "x": 0.0,
                                "y": 2.7}, {"class": "post", "x": 6.0, "y": 1.3}], "sensor_pose": [3.0, 4.0, -1.5708],
                                "bounds": [0.0, 0.0, 6.0, 4.0]}))
    log = tmp_path / "log.npz"
    cases = [
        (["--site", str(tmp_path / "missing.json"), "--model", str(demo_model_path()), "--log", str(log)],
         "no such file"),
        (["--site", str(site), "--model", str(demo_model_path()), "--log", str(log)], "reads no tags"),
        (["--site", str(site), "--model", str(demo_model_path())], "give --log LOG or --port PORT"),
        (["--site", str(site), "--model", str(demo_model_path()), "--log", str(log), "--codes",
          str(tmp_path / "nope.json")], "no such file"),
    ]
    for args, says in cases:
        capsys.readouterr()
        assert main(["enrol", "--robot", "nao3", *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
    assert not (tmp_path / "site.json.bak").exists()


# ------------------------------------------------------------------------------------------ end to end
TURNED = 2  # cells the simulated band is turned as mounted


@pytest.fixture(scope="session")
def tagged(tmp_path_factory):
    """A cheap model that reads tags (300 ``spl-train`` scans rendered for a UTM-30LX, the tiny fixture's
    training settings: a model as weak as a site's first), and logs of one robot wearing the first
    code of 13 cells turned by :data:`TURNED` cells: turned once round in place in view (8 s, after
    1 s still), and standing still as long (one side shown). The cheap training's views part tape from
    body by 1.6 standard deviations, under the 2 the training asks of a site's logs: the gate is
    lowered for it here (what is read is tested, not the gate)."""
    import dataclasses

    from gtsjax.io import save_log, save_site
    from gtsjax.io.modelfile import save_model
    from gtsjax.sensors import UTM_30LX
    from gtsjax.sim import scenarios, simulate
    from gtsjax.train import TrainConfig, train
    from gtsjax.train import tags as train_tags

    d = tmp_path_factory.mktemp("enrol")
    config = dataclasses.replace(TrainConfig(), max_per_class=60, max_pose_examples=80, n_inducing=32, restarts=1,
                                 check_pipeline=False)  # a model to run; training's tracking check is tested apart
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(train_tags, "MIN_SEPARATION", 1.5)
        train_log, train_site = simulate("spl-train", seed=11, n_scans=300, sensor="UTM-30LX")
        model, report = train([train_log], train_site, config)
    assert model.tags is not None, report.get("tags")
    save_model(model, d / "model.npz", summary=report)

    base = scenarios.plan_scenario("spl-eval", seed=1)
    plain = scenarios.plan_tags

    def render(heading: np.ndarray, name: str):
        t = heading.size
        robots = np.stack([np.full(t, 2.4), np.full(t, 2.0), heading], -1)[:, None]
        plan = scenarios.Plan(base.layout, np.repeat(base.sensor_poses[:1], t, 0), robots, [], None, base.outline)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(scenarios, "plan_tags", lambda p, m: dataclasses.replace(plain(p, m), offsets=(TURNED,)))
            log, site = scenarios.render_plan(plan, seed=1, model=UTM_30LX)
        save_log(log, d / f"{name}.npz")
        return log, site

    rate = 1.0 / UTM_30LX.period
    turning = np.concatenate([np.zeros(int(rate)), np.linspace(0.0, 2 * math.pi, int(8 * rate))])
    _, site = render(turning, "turning")
    render(np.full(turning.size, 0.3), "standing")  # as long: the replay compiled once serves both
    assert site.tags is not None and site.tags.robots[0].offset_cells == TURNED
    save_site(site, d / "truth.json")
    return {"dir": d, "model": d / "model.npz", "site": site}


def test_choose_sides_finds_the_scans_whose_heading_lay_half_a_turn_off():
    """Scans of a band whose track's heading lay half a turn off in a third of them (under that heading
    they show the band half turned, a blend of other cells): the labelling finds them (all but the
    few whose window of the band reads alike half turned), and the read summed under the chosen sides is the band; summed at the tracks'
    headings it is a blend that fits no code."""
    rng = np.random.default_rng(5)
    scans, n_cells = 300, 13
    code = design(4, n_cells).codes[2]
    band = np.repeat(np.where(code, 1.0, -1.0), -(-BINS // n_cells))[:BINS]  # each bin's truth, ±1
    right = np.zeros((scans, BINS))
    for t in range(scans):  # each scan shows a quarter to a half of the band
        a, w = rng.integers(BINS), rng.integers(BINS // 4, BINS // 2)
        shown = (np.arange(BINS) - a) % BINS < w
        right[t] = np.where(shown, np.clip(2.0 * band + rng.normal(0, 1.5, BINS), -3, 3), 0.0)
    off = rng.random(scans) < 1 / 3
    half = np.roll(right, BINS // 2, axis=1)  # the same returns read half a turn off
    per_bin = np.stack([np.where(off[:, None], half, right), np.where(off[:, None], right, half)], 1)
    side = E.choose_sides(per_bin, 0.02)
    assert np.mean((side == 1) == off) > 0.9, np.mean((side == 1) == off)  # a few windows read alike half turned
    evidence, _, _ = E.cell_sums(per_bin[np.arange(scans), side], np.ones((scans, BINS)), n_cells)
    assert ((evidence > 0) == code).all()
    blend, _, _ = E.cell_sums(per_bin[:, 0], np.ones((scans, BINS)), n_cells)
    assert ((blend > 0) != code).any() or np.abs(blend).min() < 0.5 * np.abs(evidence).min()


def _site_doc(site) -> dict:
    """The site file a user has before enrolling: robot1's code as designed (offset 0), another robot's."""
    from gtsjax.tags.codes import design

    tags = site.tags
    mine = tags.robots[0].code
    other = next(s for s in design(4, tags.cells).strings() if s != mine)
    doc = {"landmarks": [{"class": lm.cls, "x": lm.x, "y": lm.y} for lm in site.landmarks],
           "sensor_pose": list(site.sensor_pose), "bounds": list(site.bounds), "operator": {"note": "kept"}}
    doc["tags"] = SiteTags(tags.cells, tags.perimeter_m, (TagWearer("robot1", mine, 0), TagWearer("robot2", other, 1)),
                           tags.range_m).to_json()
    return doc


def test_enrol_reads_a_band_turned_by_two_cells_from_a_replayed_log(tagged, tmp_path, capsys):
    """The robot turned once round in view, through a weak model: its code and offset 2 are stored in
    place of the designed entry (offset 0), every other entry as it was, the previous file kept."""
    doc = _site_doc(tagged["site"])
    site = tmp_path / "site.json"
    before = json.dumps(doc, indent=2) + "\n"
    site.write_text(before)
    assert main(["enrol", "--site", str(site), "--model", str(tagged["model"]), "--robot", "robot1",
                 "--log", str(tagged["dir"] / "turning.npz")]) == 0
    out, err = capsys.readouterr()
    mine = tagged["site"].tags.robots[0].code
    assert out.strip().split("\t") == ["robot1", mine, str(TURNED)], err
    assert "scans read" in err and f"turned {TURNED} cells" in err
    assert (tmp_path / "site.json.bak").read_text() == before
    got = json.loads(site.read_text())
    robots = got["tags"].pop("robots")
    assert robots == [{"name": "robot1", "code": mine, "offset_cells": TURNED}, doc["tags"]["robots"][1]]
    want = json.loads(before)
    want["tags"].pop("robots")
    assert got == want


def test_enrol_refuses_a_log_that_shows_one_side_and_names_the_cells_not_seen(tagged, tmp_path, capsys):
    site = tmp_path / "site.json"
    site.write_text(json.dumps(_site_doc(tagged["site"])))
    before = site.read_text()
    assert main(["enrol", "--site", str(site), "--model", str(tagged["model"]), "--robot", "robot1",
                 "--log", str(tagged["dir"] / "standing.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert re.search(r"cells? [0-9, ]+ of 13 (were|was) not seen", err[-1]) and "turn the robot so that every side faces the laser" in err[-1], err
    assert site.read_text() == before and not (tmp_path / "site.json.bak").exists()


def test_enrol_reads_the_band_where_the_tracks_heading_lay_half_a_turn_off(tagged, tmp_path, capsys, monkeypatch):
    """The smoothed heading turned half a turn over 40 % of the log (a block in the middle: a weak
    model's track on the wrong side of the robot for a while): read at the track's headings, the band
    is a blend of itself and its half-turned self and the command refuses; with each scan's side
    chosen, those scans are counted as turned and the code and offset 2 are stored."""
    import equinox as eqx

    replay = E.replay_smoothed

    def off(model, log):
        out = replay(model, log)
        pose = np.array(out.track_pose)
        t = pose.shape[0]
        pose[int(0.3 * t):int(0.7 * t), :, 2] += math.pi
        return eqx.tree_at(lambda o: o.track_pose, out, pose)

    monkeypatch.setattr(E, "replay_smoothed", off)
    site = tmp_path / "site.json"
    site.write_text(json.dumps(_site_doc(tagged["site"])))
    args = ["enrol", "--site", str(site), "--model", str(tagged["model"]), "--robot", "robot1", "--log",
            str(tagged["dir"] / "turning.npz"), "--out", str(tmp_path / "new.json")]
    with monkeypatch.context() as mp:  # every scan read at the track's heading, as before the sides were chosen
        mp.setattr(E, "choose_sides", lambda per_bin, weight: np.zeros(per_bin.shape[0], int))
        assert main(args) == 2
    capsys.readouterr()
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert out.strip().split("\t") == ["robot1", tagged["site"].tags.robots[0].code, str(TURNED)], err
    turned, shown = map(int, re.search(r"(\d+) of the (\d+) scans read with the track's heading turned", err).groups())
    assert 0.3 * shown < turned < 0.5 * shown, err


def test_enrol_from_the_emulated_sensor_over_a_pseudo_terminal(tagged, tmp_path, capsys):
    """``--port``: the turning log served by the emulated UTM-30LX over a real pseudo-terminal (ranges
    and intensities, in a loop), recorded for 10 s (the log once round) through the live run's machinery, then read: the
    code and offset 2, and the recording kept where ``--record`` says."""
    from gtsjax.io import load_log
    from gtsjax.sensors import UTM_30LX
    from gtsjax.sim.emulator import SensorEmulator, log_source

    site = tmp_path / "site.json"
    site.write_text(json.dumps(_site_doc(tagged["site"])))
    with SensorEmulator(UTM_30LX, log_source(load_log(tagged["dir"] / "turning.npz"))) as emu:
        code = main(["enrol", "--site", str(site), "--model", str(tagged["model"]), "--robot", "robot1",
                     "--port", emu.path, "--seconds", "10", "--record", str(tmp_path / "rec.npz")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert out.strip().split("\t") == ["robot1", tagged["site"].tags.robots[0].code, str(TURNED)], err
    rec = load_log(tmp_path / "rec.npz")
    assert rec.intensities is not None and rec.n_scans > 100
    assert json.loads(site.read_text())["tags"]["robots"][0]["offset_cells"] == TURNED


def test_run_names_the_robot_by_its_tag_live(tagged, tmp_path, capsys):
    """Identities live (issue 43 item 3): ``gtsjax run`` on the emulated UTM-30LX over a real
    pseudo-terminal, the site listing the robot's band as mounted and another robot's: the CSV gains the
    ``robot`` column, the robot is named by its tag once its reads add up, and never as the other
    robot; the JSON lines on stdout carry the same names."""
    from gtsjax.io import load_log
    from gtsjax.io.gtd import read_gtd
    from gtsjax.sensors import UTM_30LX
    from gtsjax.sim.emulator import SensorEmulator, log_source

    site = tmp_path / "site.json"
    doc = _site_doc(tagged["site"])
    doc["tags"]["robots"][0]["offset_cells"] = TURNED  # as enrolled
    site.write_text(json.dumps(doc))
    out = tmp_path / "live.csv"
    # The log from its start whenever the run starts streaming, however long it took to start (the
    # emulator's clock runs from its creation). Which side of the robot a new track sees first matters to
    # a reader this weak: replayed from each 12th scan of the turn, starting 264-288 scans of 360 in
    # named it robot2 in 13-33 of 341 rows; every other start never did.
    # That is issue 56's to mend; here a busy machine's slow start is kept from choosing the phase.
    base, first = log_source(load_log(tagged["dir"] / "turning.npz")), []

    def from_the_start(i: int):
        if not first:
            first.append(i)
        return base(i - first[0])

    with SensorEmulator(UTM_30LX, from_the_start) as emu:
        code = main(["run", "--port", emu.path, "--site", str(site), "--model", str(tagged["model"]), "--out", str(out),
                     "--seconds", "9", "--json", "--quiet"])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    assert out.read_text().splitlines()[0].endswith(",robot")
    rows = read_gtd(out)
    assert len(rows) > 100, err
    t0 = rows[0].stamp
    late = [r for r in rows if r.stamp - t0 > 3.0]
    names = [r.robot for r in late]
    assert names.count("robot1") > 0.8 * len(late), sorted(set(names))
    assert "robot2" not in {r.robot for r in rows}
    sent = [json.loads(x) for x in stdout.splitlines() if x.startswith("{")]
    named = [row.get("robot", "") for line in sent for row in line["tracks"]]
    assert named and named.count("robot1") >= len(names)
