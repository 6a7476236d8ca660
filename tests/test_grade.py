"""Grading a robot's own localisation (``gtsjax.grade``, ``gtsjax grade``).

The grade is checked against what a simulation put in, on a ground truth built from the truth itself
(no tracker in the way: each row's robot is known): tracks that break and come back under new ids,
two tracks that swap robots, beliefs with their own clocks, biases, noise, kidnaps and one in the
other team's frame (:mod:`gtsjax.sim.beliefs`, whose :func:`~gtsjax.sim.beliefs.put_in_error` reads
the error with the true offset and frame). The metrics are checked against evo's, the pieces
(interpolation, the rigid fit, the smoothing of votes) against obvious implementations, and the
command's refusals one line each."""

import dataclasses
import json
import math

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.grade import RobotSpec, grade
from gtsjax.grade.associate import ABSENT, NONE, smooth_track
from gtsjax.grade.frame import kabsch
from gtsjax.grade.metrics import Errors, ape, rpe
from gtsjax.grade.series import interpolate, invert, mirror_frame, transform
from gtsjax.io.beliefs import Beliefs
from gtsjax.io.gtd import TrackRow
from gtsjax.sensors import URG_04LX
from gtsjax.sim.beliefs import put_in_error, simulate_beliefs
from gtsjax.sim.match import FIELD, plan_match
from tests._utils import cli

CENTRE = ((FIELD[0] + FIELD[2]) / 2, (FIELD[1] + FIELD[3]) / 2)


# ---------------------------------------------------------------------------------------- pieces


def test_interpolate_against_a_loop():
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.02, 0.1, 60))
    stamps[30:] += 2.0  # a gap the series says nothing across
    poses = np.column_stack([rng.normal(size=60), rng.normal(size=60), np.cumsum(rng.normal(0, 0.8, 60))])
    poses[:, 2] = np.angle(np.exp(1j * poses[:, 2]))
    t = np.concatenate([rng.uniform(stamps[0] - 0.5, stamps[-1] + 0.5, 300), stamps[[0, 7, -1]]])
    got, ok = interpolate(t, stamps, poses, max_gap=0.5)
    for k, tk in enumerate(t):
        j = np.searchsorted(stamps, tk)
        if tk == stamps[-1]:
            assert ok[k] and np.allclose(got[k], poses[-1])
            continue
        if j == 0 and tk < stamps[0] or j >= stamps.size:
            assert not ok[k]
            continue
        if stamps[j] == tk:
            assert ok[k] and np.allclose(got[k], poses[j], atol=1e-12)
            continue
        a, b = j - 1, j
        if stamps[b] - stamps[a] > 0.5:
            assert not ok[k]
            continue
        w = (tk - stamps[a]) / (stamps[b] - stamps[a])
        turn = math.remainder(poses[b, 2] - poses[a, 2], 2 * math.pi)  # the shorter way round
        want_th = math.remainder(poses[a, 2] + w * turn, 2 * math.pi)
        assert ok[k]
        np.testing.assert_allclose(got[k, :2], poses[a, :2] + w * (poses[b, :2] - poses[a, :2]), atol=1e-12)
        assert abs(math.remainder(got[k, 2] - want_th, 2 * math.pi)) < 1e-9


def test_kabsch_recovers_a_transform_and_frames_invert():
    rng = np.random.default_rng(1)
    p = rng.uniform(-2, 2, (40, 2))
    frame = (3.2, -1.1, 2.5)
    q = transform(np.column_stack([p, np.zeros(40)]), frame)[:, :2]
    got = kabsch(p, q)
    np.testing.assert_allclose(got[:2], frame[:2], atol=1e-9)
    assert abs(math.remainder(got[2] - frame[2], 2 * math.pi)) < 1e-9
    back = transform(transform(np.column_stack([p, rng.normal(size=40)]), frame), invert(frame))
    np.testing.assert_allclose(back[:, :2], p, atol=1e-9)
    m = mirror_frame((4.5, 3.0))  # the other team's frame is its own inverse
    x = np.array([[1.0, 2.0, 0.3]])
    np.testing.assert_allclose(transform(transform(x, m), m), x, atol=1e-12)
    np.testing.assert_allclose(transform(x, m)[0, :2], [8.0, 4.0], atol=1e-12)


def test_votes_smoothed_along_a_track():
    a, b = 0, 1
    # A single window of another robot between two runs of one: a bad belief, given back.
    assert list(smooth_track(np.array([a] * 5 + [b] + [a] * 5))) == [a] * 11
    # Windows matching nobody (a kidnapped belief) between two runs of one robot: that robot's.
    assert list(smooth_track(np.array([a] * 4 + [NONE] * 3 + [a] * 4))) == [a] * 11
    # At the track's end: the robot next to them, for a few windows only.
    assert list(smooth_track(np.array([NONE] * 2 + [a] * 6))) == [a] * 8
    assert list(smooth_track(np.array([a] * 8 + [NONE] * 5))) == [a] * 8 + [NONE] * 5
    # A long run of each: a track taken over, split where it changed.
    assert list(smooth_track(np.array([a] * 6 + [b] * 6))) == [a] * 6 + [b] * 6
    # A stretch voted for a robot in too few of its windows: nobody's (a stranger's belief crossing it).
    assert list(smooth_track(np.array([b] + [NONE] * 6 + [b]))) == [NONE] * 8
    assert ABSENT not in smooth_track(np.array([a, a, a]))


def _evo_traj(t, poses):
    from evo.core.trajectory import PoseTrajectory3D

    q = np.column_stack([np.cos(poses[:, 2] / 2), np.zeros(len(t)), np.zeros(len(t)), np.sin(poses[:, 2] / 2)])
    return PoseTrajectory3D(np.column_stack([poses[:, :2], np.zeros(len(t))]), q, t)


def test_ape_and_rpe_against_evo():
    from evo.core import metrics

    rng = np.random.default_rng(2)
    t = 100.0 + 0.1 * np.arange(400)  # 10 Hz: 1 s is 10 frames for evo
    s = np.cumsum(rng.uniform(0.01, 0.04, 400))
    truth = np.column_stack([np.cos(s), 0.6 * np.sin(2 * s), np.angle(np.exp(1j * (s + 1.0)))])
    belief = truth + np.column_stack([rng.normal(0, 0.05, 400), rng.normal(0, 0.05, 400), rng.normal(0, 0.05, 400)])
    belief[:, 2] = np.angle(np.exp(1j * belief[:, 2]))
    e = ape(t, belief, truth, np.full((400, 3), 1e-4))
    ref, est = _evo_traj(t, truth), _evo_traj(t, belief)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    assert np.sqrt(np.mean(e.pos**2)) == pytest.approx(m.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    for delta_s, frames in ((1.0, 10), (5.0, 50)):
        ours = rpe(e, delta_s)
        for rel, key in ((metrics.PoseRelation.translation_part, "trans"), (metrics.PoseRelation.rotation_angle_rad,
                                                                              "rot")):
            r = metrics.RPE(rel, delta=frames, delta_unit=metrics.Unit.frames, all_pairs=True)
            r.process_data((ref, est))
            assert ours[key]["rmse"] == pytest.approx(r.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
            assert ours[key]["n"] == len(r.error)


# ------------------------------------------------------------------ the grade against what was put in


def _truth_gtd(n_robots=6, seconds=60.0, seed=5, breaks=True):
    """A match's truth on its fine grid, and ground-truth rows from it at 10 Hz with 1 cm of noise:
    tracks that break (a robot unseen for 1 s comes back under a new id) and two that swap robots
    half-way; ``who``: each row's robot."""
    match = plan_match(2, URG_04LX, n_robots=n_robots, seconds=seconds, referee=False, seed=seed)
    stamps = 1.7e9 + np.arange(match.robots.shape[0]) * match.dt
    rng = np.random.default_rng(seed)
    rows, who = [], []
    scan = np.arange(0, stamps.size, int(round(0.1 / match.dt)))
    next_id = 100
    ids = {m: m for m in range(n_robots)}
    brk = {m: rng.uniform(8, seconds - 8) for m in range(n_robots)} if breaks else {}
    swap_at = seconds / 2
    swapped = False
    for i in scan:
        t = stamps[i] - stamps[0]
        if breaks and not swapped and t >= swap_at:  # tracks of robots 0 and 1 swap robots
            ids[0], ids[1] = ids[1], ids[0]
            swapped = True
        for m in range(n_robots):
            if m in brk and brk[m] <= t < brk[m] + 1.0:
                continue  # unseen for a second
            if m in brk and t >= brk[m] + 1.0 and brk[m] != -1:
                ids[m], next_id = next_id, next_id + 1
                brk[m] = -1
            x, y, th = match.robots[i, m] + [rng.normal(0, 0.01), rng.normal(0, 0.01), rng.normal(0, 0.02)]
            rows.append(TrackRow(float(stamps[i]), ids[m], "robot", x, y, math.remainder(th, 2 * math.pi),
                                 1e-4, 1e-4, 4e-4))
            who.append(m)
    return stamps, match.robots, rows, np.array(who)


def _who(rows, who, g) -> np.ndarray:
    """The true robot of each row a grade took, by its stamp and track id."""
    of = {(r.stamp, r.track_id): w for r, w in zip(rows, who, strict=True)}
    return np.array([of[(t, i)] for t, i in zip(g.errors.t, g.track_ids, strict=True)])


@pytest.fixture(scope="module")
def graded():
    stamps, truth, rows, who = _truth_gtd()
    sims = simulate_beliefs(stamps, truth, CENTRE, seed=7, mirrored=3)
    specs = [RobotSpec(Beliefs(p.name, t, poses, p.name), "fit" if p.frame == "mirrored" else "field")
             for p, t, poses in sims]
    return stamps, truth, rows, who, sims, grade(rows, specs, centre=CENTRE)


def test_identity_clock_frame_and_errors_are_what_was_put_in(graded):
    stamps, truth, rows, who, sims, grades = graded
    row_t = np.array([r.stamp for r in rows])
    for (put, bt, bp), g in zip(sims, grades, strict=True):
        # Identity: the rows graded are this robot's (known by construction), for ≥ 99 % of its rows.
        assert g.rows.size and np.mean(_who(rows, who, g) == put.truth_index) >= 0.99, put.name
        assert g.summary["seen_share"] >= 0.9
        # Its tracks: every id that carried it for more than a second is named.
        for tid in {r.track_id for r, w in zip(rows, who, strict=True) if w == put.truth_index}:
            carried = np.array([r.stamp for r, w in zip(rows, who, strict=True) if w == put.truth_index
                                and r.track_id == tid])
            if carried.size > 10:
                assert tid in {s[0] for s in g.spans}, (put.name, tid)
        # The clock: within the bootstrap's uncertainty (and 30 ms).
        assert abs(g.clock.offset - put.offset) <= max(0.03, 3 * g.clock.se), (put.name, g.clock, put.offset)
        # The error: the graded APE (net of the ground truth's own variance) against the error put in at
        # the same instants, read from the true poses with the true frame, at the clock the grade found
        # (within 5 %) and at the true clock (within 15 %: walking forwards, a clock a few hundredths of
        # a second off trades with a bias ahead, which is part of the error).
        for clock, rel in ((g.clock.offset, 0.05), (put.offset, 0.15)):
            pe, _ = put_in_error(dataclasses.replace(put, offset=clock), bt, bp, g.errors.t, stamps, truth)
            put_rmse = math.sqrt(np.nanmean(pe**2))
            assert g.summary["position_rmse_net_of_gt_m"] == pytest.approx(put_rmse, rel=rel, abs=0.002), put.name
        # Kidnaps: each found as a jump that left it lost, back when the belief was.
        lost = [j for j in g.jumps if j.lost]
        for k in put.kidnaps:
            if k.start + k.duration > row_t[-1]:
                continue
            near = [j for j in lost if abs(j.stamp - put.offset * 0 - k.start) < 0.2]
            assert near and near[0].recovery_s == pytest.approx(k.duration, abs=0.25), (put.name, k, lost)
    mirrored = next(g for (p, _, _), g in zip(sims, grades, strict=True) if p.frame == "mirrored")
    want = mirror_frame(CENTRE)
    # Within 1 cm where the robot was (the transforms compared over its path in its own frame: at the
    # field's origin, 5 m away, a tenth of a degree alone is a centimetre) and 0.5°.
    path = transform(mirrored.errors.truth, invert(want))
    moved = transform(path, mirrored.frame)[:, :2] - transform(path, want)[:, :2]
    assert np.max(np.hypot(moved[:, 0], moved[:, 1])) < 0.01
    assert abs(math.remainder(mirrored.frame[2] - want[2], 2 * math.pi)) < math.radians(0.5)


def test_given_offset_is_kept_and_a_robot_never_seen_says_so(graded):
    stamps, truth, rows, who, sims, _ = graded
    put, bt, bp = sims[0]
    far = bp.copy()
    far[:, 0] += 40.0  # off the field, nowhere near a track
    specs = [RobotSpec(Beliefs("given", bt, bp, "given"), "field", put.offset),
             RobotSpec(Beliefs("away", bt, far, "away"))]
    g = grade(rows, specs, centre=CENTRE)
    assert g[0].clock.fixed and g[0].clock.offset == put.offset and math.isnan(g[0].clock.se)
    assert np.mean(_who(rows, who, g[0]) == put.truth_index) >= 0.99
    assert g[1].rows.size == 0 and g[1].summary["seen_share"] == 0.0
    assert "no track" in g[1].hint and "--frame away=fit" in g[1].hint


def test_a_mirrored_robot_graded_in_the_field_frame_is_pointed_to_mirrored(graded):
    stamps, truth, rows, who, sims, _ = graded
    put, bt, bp = next(s for s in sims if s[0].frame == "mirrored")
    g = grade(rows, [RobotSpec(Beliefs("m", bt, bp, "m"), "field"), RobotSpec(Beliefs("ok", bt, bp, "ok"), "mirrored")],
              centre=CENTRE)
    assert g[0].summary["seen_share"] < 0.5 and "--frame m=mirrored" in g[0].hint
    assert np.mean(_who(rows, who, g[1]) == put.truth_index) >= 0.99 and not g[1].hint


# ----------------------------------------------------------------------------------- the command


def test_grade_command_writes_tables_and_figures(graded, tmp_path, capsys):
    stamps, truth, rows, who, sims, _ = graded
    from gtsjax.io.gtd import GTDWriter
    from gtsjax.sim.beliefs import write_beliefs

    gtd = tmp_path / "gtd.csv"
    with GTDWriter(gtd) as w:
        w.write(rows)
    write_beliefs(sims[:3], tmp_path / "b")
    args = ["grade", str(gtd), "--out-dir", str(tmp_path / "out")]
    for p, _, _ in sims[:3]:
        args += ["--robot", f"{p.name}={tmp_path / 'b' / (p.name + '.csv')}"]
    r = cli(capsys, *args)
    code, out, err = r.returncode, r.stdout, r.stderr
    assert code == 0, err
    doc = json.loads((tmp_path / "out" / "grade.json").read_text())
    assert [r["robot"] for r in doc["robots"]] == [p.name for p, _, _ in sims[:3]]
    for r, (p, _, _) in zip(doc["robots"], sims[:3], strict=True):
        assert abs(r["clock"]["offset_s"] - p.offset) < 0.05
        assert r["position_m"]["rmse"] > 0 and r["tracks"]
    md = (tmp_path / "out" / "grade.md").read_text()
    assert all(f"## {p.name}" in md for p, _, _ in sims[:3])
    assert all((tmp_path / "out" / f"{p.name}.png").stat().st_size > 10_000 for p, _, _ in sims[:3])
    assert sims[0][0].name in out


@pytest.mark.parametrize("args, what", [
    (["--robot", "nao3"], "is not NAME=VALUE"),
    (["--robot", "a=A", "--robot", "a=A"], "robot a given twice"),
    (["--robot", "a=A", "--frame", "b=fit"], "robot b has no --robot b=POSES"),
    (["--robot", "a=A", "--frame", "a=turned"], "the frame is one of field, mirrored, fit"),
    (["--robot", "a=A", "--offset", "a=soon"], "the offset is a number of seconds"),
    (["--robot", "a=A", "--class", "ball"], "has no rows of class ball"),
    (["--robot", "a=missing.csv"], "missing.csv"),
])
def test_grade_refuses_in_one_line(tmp_path, capsys, args, what):
    gtd = tmp_path / "gtd.csv"
    gtd.write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n1.0,1,robot,1,1,0,1e-4,1e-4,1e-4\n")
    (tmp_path / "A").write_text("stamp,x,y,theta\n1.0,1,1,0\n1.1,1,1,0\n")
    args = [a.replace("=A", f"={tmp_path / 'A'}") for a in args]
    r = cli(capsys, "grade", str(gtd), *args, "--out-dir", str(tmp_path / "o"))
    code, err = r.returncode, r.stderr
    assert code == 2 and what in err and len(err.strip().splitlines()) == 1, err


def test_grade_refuses_an_empty_ground_truth(tmp_path, capsys):
    gtd = tmp_path / "gtd.csv"
    gtd.write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n")
    (tmp_path / "a.csv").write_text("stamp,x,y,theta\n1.0,1,1,0\n")
    r = cli(capsys, "grade", str(gtd), "--robot", f"a={tmp_path / 'a.csv'}")
    code, err = r.returncode, r.stderr
    assert code == 2 and "has no track rows" in err


def test_belief_in_millimetres_is_refused_with_the_hint(tmp_path, capsys):
    gtd = tmp_path / "gtd.csv"
    gtd.write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n1.0,1,robot,1,1,0,1e-4,1e-4,1e-4\n")
    (tmp_path / "a.csv").write_text("stamp,x,y,theta\n1.0,1500,1200,0\n")
    r = cli(capsys, "grade", str(gtd), "--robot", f"a={tmp_path / 'a.csv'}")
    code, err = r.returncode, r.stderr
    assert code == 2 and "millimetres" in err and "a.csv" in err


@pytest.mark.parametrize("unit, factor", [("milliseconds", 1e3), ("nanoseconds", 1e9)])
def test_belief_stamps_in_milliseconds_are_refused_with_the_factor(tmp_path, capsys, unit, factor):
    """A robot's clock written in ms (or ns, as ROS stamps are) against a ground truth in seconds, both
    from a run's start or both epoch times: one line with the factor, nothing written (graded, no row
    met and the grade hinted at --frame fit)."""
    for t0 in (0.0, 1.7e9):
        t = t0 + np.arange(0.0, 60.0, 0.1)
        gtd = tmp_path / "gtd.csv"
        gtd.write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n"
                       + "".join(f"{s:.3f},1,robot,1,1,0,1e-4,1e-4,1e-4\n" for s in t))
        (tmp_path / "a.csv").write_text("stamp,x,y,theta\n" + "".join(f"{s * factor:.1f},1,1,0\n" for s in t))
        r = cli(capsys, "grade", str(gtd), "--robot", f"a={tmp_path / 'a.csv'}", "--out-dir", str(tmp_path / "o"))
        err = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(err) == 1 and f"look like {unit}" in err[0] and "a.csv" in err[0], err
        assert not (tmp_path / "o").exists()
    (tmp_path / "a.csv").write_text("stamp,x,y,theta\n" + "".join(f"{s + 2.0:.3f},1,1,0\n" for s in t))
    assert cli(capsys, "grade", str(gtd), "--robot", f"a={tmp_path / 'a.csv'}", "--out-dir", str(tmp_path / "o"),
               "--no-figures").returncode == 0  # seconds, 2 s off: graded


def test_ground_truth_in_millimetres_is_refused_with_the_factor(tmp_path, capsys):
    """A ground-truth CSV in millimetres, with the site's bounds or without: one line, nothing written."""
    gtd = tmp_path / "gtd.csv"
    gtd.write_text("stamp,track_id,class,x,y,theta,var_x,var_y,var_theta\n"
                   + "".join(f"{s:.1f},1,robot,{1500 + s},2100,0,1e-4,1e-4,1e-4\n" for s in range(60)))
    (tmp_path / "a.csv").write_text("stamp,x,y,theta\n" + "".join(f"{s:.1f},1.5,2.1,0\n" for s in range(60)))
    site = tmp_path / "site.json"
    site.write_text(json.dumps({"landmarks": [{"class": "post", "x": 0.0, "y": 1.3}, {"class": "post", "x": 0.0,
                                "y": 2.7}, {"class": "post", "x": 6.0, "y": 1.3}], "sensor_pose": [3.0, 4.0, -1.5708],
                                "bounds": [0.0, 0.0, 6.0, 4.0]}))
    for extra in ([], ["--site", str(site)]):
        r = cli(capsys, "grade", str(gtd), "--robot", f"a={tmp_path / 'a.csv'}", "--out-dir", str(tmp_path / "o"), *extra)
        err = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(err) == 1 and "look like millimetres" in err[0] and "gtd.csv" in err[0], err
        assert not (tmp_path / "o").exists()


def test_errors_type_is_what_the_figure_reads():
    e = ape(np.arange(3.0), np.zeros((3, 3)), np.ones((3, 3)), np.full((3, 3), 0.01))
    assert isinstance(e, Errors) and np.allclose(e.band_pos, 2 * math.sqrt(0.02))
    with pytest.raises(InputError):
        raise InputError("x", "y")


def test_grade_view_save_holds_both_poses_per_row(graded, tmp_path, capsys):
    """``grade --view-save FILE.rrd``: Rerun's own reader finds, per robot, a ground-truth and a belief
    pose and both errors for each row graded, and both paths."""
    import importlib.util

    from tests.conftest import need

    need(importlib.util.find_spec("rerun") is not None, 'the viewer extra is not installed (pip install "gtsjax[viewer]")')
    from rerun.chunk import RrdReader

    from gtsjax.io.gtd import GTDWriter
    from gtsjax.sim.beliefs import write_beliefs

    stamps, truth, rows, who, sims, _ = graded
    gtd = tmp_path / "gtd.csv"
    with GTDWriter(gtd) as w:
        w.write(rows)
    write_beliefs(sims[:2], tmp_path / "b")
    rrd = tmp_path / "grade.rrd"
    r = cli(capsys, "grade", gtd, *sum([["--robot", f"{p.name}={tmp_path / 'b' / (p.name + '.csv')}"] for p, _, _ in
                                        sims[:2]], []), "--out-dir", tmp_path / "out", "--no-figures", "--view-save", rrd)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "out" / "grade.json").read_text())
    per_entity: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        per_entity[str(chunk.entity_path)] = per_entity.get(str(chunk.entity_path), 0) + chunk.num_rows
    for robot in doc["robots"]:
        n, name = robot["rows"], robot["robot"]
        assert n > 100
        for e in (f"/field/robots/{name}/truth", f"/field/robots/{name}/belief", f"/errors/position_cm/{name}",
                  f"/errors/heading_deg/{name}"):
            assert per_entity.get(e) == n, (e, per_entity.get(e), n)
        for e in (f"/field/robots/{name}/truth_path", f"/field/robots/{name}/belief_path"):
            assert per_entity.get(e, 0) > 0, e


def test_simulate_replay_grade_from_the_command_line(tiny, tmp_path, capsys):
    """The commands as a user runs them: ``simulate spl-trajectory --out-beliefs``, ``replay`` with a small
    model, ``grade``: the one robot found on the tracks, its clock and error what was put in."""
    from gtsjax.io import load_log
    from gtsjax.sim.beliefs import read_put_in

    d = tmp_path
    assert cli(capsys, "simulate", "spl-trajectory", "--seed", 1003, "--scans", 400, "--out", d / "w.npz", "--site",
               d / "s.json", "--out-beliefs", d / "b").returncode == 0
    assert cli(capsys, "replay", d / "w.npz", "--site", d / "s.json", "--model", tiny["path"], "--out",
               d / "gtd.csv").returncode == 0
    r = cli(capsys, "grade", d / "gtd.csv", "--robot", f"nao={d / 'b' / 'robot1.csv'}", "--site", d / "s.json",
            "--out-dir", d / "g")
    assert r.returncode == 0, r.stderr
    (put,) = read_put_in(d / "b")
    robot = json.loads((d / "g" / "grade.json").read_text())["robots"][0]
    assert robot["unseen_share"] < 0.2 and robot["tracks"]
    assert abs(robot["clock"]["offset_s"] - put.offset) < 0.06
    log = load_log(d / "w.npz")
    import csv

    b = np.array([[float(v) for v in row] for row in list(csv.reader(open(d / "b" / "robot1.csv")))[1:]])
    g = robot["position_m"]["rmse"]
    from gtsjax.grade.series import interpolate

    truth = log.truth_poses[:, 0]
    ok = np.all(np.isfinite(truth), 1)
    # The error put in, at the scans' stamps, read with the true clock and frame: the grade's raw figure
    # holds the ground truth's own centimetre or two as well.
    bel, okb = interpolate(log.stamps[ok] + put.offset, b[:, 0], b[:, 1:], 0.1)
    put_rmse = float(np.sqrt(np.nanmean(np.sum((bel[okb, :2] - truth[ok][okb, :2]) ** 2, -1))))
    assert put_rmse * 0.9 < g < put_rmse * 1.2 + 0.01, (g, put_rmse)


def test_grade_reads_a_robots_poses_from_a_bag_topic(graded, tmp_path, capsys):
    """``--robot NAME=BAG:TOPIC``: the same robot graded from a ROS 2 bag's Odometry topic as from its
    CSV gives the same grade."""
    from gtsjax.io.gtd import GTDWriter
    from gtsjax.sim.beliefs import write_beliefs
    from tests.test_beliefs import ODOM_T, write_pose_bag

    stamps, truth, rows, who, sims, _ = graded
    put, bt, bp = sims[1]
    gtd = tmp_path / "gtd.csv"
    with GTDWriter(gtd) as w:
        w.write(rows)
    write_beliefs([sims[1]], tmp_path / "b")
    bag = write_pose_bag(tmp_path / "match", "mcap", {"/robot2/odom": (ODOM_T, [tuple(map(float, (t, *p)))
                                                                               for t, p in zip(bt, bp, strict=True)])})
    out = {}
    for key, source in (("csv", tmp_path / "b" / f"{put.name}.csv"), ("bag", f"{bag}:/robot2/odom")):
        r = cli(capsys, "grade", gtd, "--robot", f"r2={source}", "--out-dir", tmp_path / key, "--no-figures")
        assert r.returncode == 0, r.stderr
        out[key] = json.loads((tmp_path / key / "grade.json").read_text())["robots"][0]
    assert out["bag"]["rows"] == out["csv"]["rows"] > 100
    assert out["bag"]["clock"]["offset_s"] == pytest.approx(out["csv"]["clock"]["offset_s"], abs=1e-3)
    assert out["bag"]["position_m"]["rmse"] == pytest.approx(out["csv"]["position_m"]["rmse"], rel=1e-3)


def test_grade_on_a_real_log_odometry_against_corrected_poses(shared_file, tmp_path, capsys):
    """A real robot's belief against a real ground truth: the Intel Research Lab's CARMEN log, its raw
    odometry (``ODOM`` lines, about 5 Hz) graded against its SLAM-corrected poses (one per ``FLASER``
    scan, every 3 s) with ``--frame fit``. The odometry lies in the map's frame, on the scans' clock
    (the log's one clock), within decimetres: the fit finds the identity, the clock near 0, and the
    sparse ground truth does not read as the robot unseen."""
    import gzip

    log = shared_file("data", "logs", "carmen_intel-corrected.log.gz")
    gt = ["stamp,track_id,class,x,y,theta,var_x,var_y,var_theta"]
    odom, last = ["stamp,x,y,theta"], -math.inf
    with gzip.open(log, "rt") as f:
        for line in f:
            tok = line.split()
            if tok and tok[0] == "FLASER":
                b = int(tok[1]) + 2  # after the ranges: x y θ (corrected), odometry x y θ, the stamp
                gt.append(f"{tok[b + 6]},1,robot,{tok[b]},{tok[b + 1]},{tok[b + 2]},1e-4,1e-4,1e-4")
            elif tok and tok[0] == "ODOM" and float(tok[7]) > last:
                last = float(tok[7])
                odom.append(f"{tok[7]},{tok[1]},{tok[2]},{tok[3]}")
    (tmp_path / "gtd.csv").write_text("\n".join(gt) + "\n")
    (tmp_path / "odom.csv").write_text("\n".join(odom) + "\n")
    r = cli(capsys, "grade", tmp_path / "gtd.csv", "--robot", f"odom={tmp_path / 'odom.csv'}", "--frame", "odom=fit",
            "--out-dir", tmp_path / "g", "--no-figures")
    assert r.returncode == 0, r.stderr
    robot = json.loads((tmp_path / "g" / "grade.json").read_text())["robots"][0]
    assert len(gt) - 1 == 910 and robot["rows"] >= 800  # not where the odometry paused for over a second
    assert robot["unseen_share"] < 0.1
    assert abs(robot["frame"]["tx_m"]) < 0.05 and abs(robot["frame"]["ty_m"]) < 0.05
    assert abs(robot["frame"]["phi_rad"]) < math.radians(0.5)
    assert abs(robot["clock"]["offset_s"]) < 0.1
    assert 0.03 < robot["position_m"]["rmse"] < 0.2 and robot["lost_share"] < 0.02
    assert len(robot["jumps"]) < 30


def test_a_robot_never_seen_shows_no_clock_offset():
    """A robot none of whose beliefs met a ground-truth row has no clock offset to show (the search's
    start is not an estimate); one seen shows its offset and its standard error."""
    from types import SimpleNamespace as NS

    from gtsjax.grade.report import COLUMNS, table_rows

    nan = float("nan")
    stats = {"rmse": nan, "median": nan, "p95": nan, "max": nan}
    summary = {"position_m": stats, "heading_rad": stats, "within_gt_2sigma_share": nan, "lost_share": nan,
               "rpe": {"1s": {"trans": {"rmse": nan}}, "5s": {"trans": {"rmse": nan}}}, "recovery_s": {"median": nan}}

    def grade(seen, se):
        return NS(name="nao", frame_kind="given", clock=NS(offset=4.9, se=se, fixed=False), spans=[], jumps=[],
                  summary={**summary, "seen_share": seen})

    never, seen = table_rows([grade(0.0, nan), grade(0.8, 0.004)])
    clock = COLUMNS.index("clock offset [s]")
    assert never[clock] == "– (never seen)" and never[COLUMNS.index("unseen")] == "100 %"
    assert seen[clock] == "+4.900 ± 4 ms"
