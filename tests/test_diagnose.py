"""Why a run reports nothing (issue 38): the tracker's per-slot hold (``g_track.HOLDS``), the host's
tally of a run (``drivers.diagnose``) and its warnings, on a replay and on the command line."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.core.g_track import HOLDS, Detections, TrackerParams, TrackerState, track_step
from gtsjax.drivers.diagnose import Tally, dominant, warnings
from gtsjax.drivers.replay import replay_log
from gtsjax.io import save_log, save_site
from gtsjax.io.modelfile import load_model, save_model
from gtsjax.sim import simulate

F32 = jnp.float32
ROBOT = 1
step = jax.jit(track_step, static_argnames="explain")


def detections(robot=None, other=None, k=4):
    """One scan: a robot detection at ``robot`` (x, y, θ) in slot 0, an ``other`` candidate at ``other``
    (x, y) in slot 1."""
    pose = np.zeros((k, 3), np.float32)
    mask, oth = np.zeros(k, bool), np.zeros(k, bool)
    if robot is not None:
        pose[0], mask[0] = robot, True
    if other is not None:
        pose[1, :2], oth[1] = other, True
    cov = np.broadcast_to(np.diag(np.float32([1e-4, 1e-4, 4e-3])), (k, 3, 3)).copy()
    return Detections(jnp.asarray(pose), jnp.asarray(cov), jnp.full(k, ROBOT, jnp.int32), jnp.asarray(mask),
                      jnp.asarray(oth))


def run(params, scans, dt=0.1):
    """Per scan, the slots' (live, confirmed, hold name, speed) after it."""
    state = TrackerState.empty(3)
    hist = []
    for d in scans:
        state, _, why = step(state, d, jnp.asarray(dt, F32), params, explain=True)
        hist.append([(bool(state.live[s]), bool(state.confirmed[s]), HOLDS[int(why.hold[s])], float(why.speed[s]))
                     for s in range(3)])
    return hist


def walking(n=40, speed=0.3, dt=0.1):
    """A robot walking along x at ``speed`` m/s."""
    return [detections([1.0 + speed * dt * i, 2.0, 0.0]) for i in range(n)]


def test_a_robot_faster_than_its_limit_is_held_for_speed_and_never_confirmed():
    slow = TrackerParams.default([False, True], n_confirm=3, max_speed=0.01)
    hist = run(slow, walking())
    robot = [h[0] for h in hist]
    assert all(live for live, _, _, _ in robot)  # one track throughout, in the first slot
    assert not any(conf for _, conf, _, _ in robot)
    assert [h for _, _, h, _ in robot[-20:]] == ["speed"] * 20  # once its velocity is known: speed, every scan
    assert abs(robot[-1][3] - 0.3) < 0.05  # the estimated speed is the robot's
    assert all(h == (False, False, "none", 0.0) for scan_ in hist for h in scan_[1:])  # free slots: nothing


def test_with_a_fitting_limit_it_confirms_and_its_hold_becomes_none():
    ok = TrackerParams.default([False, True], n_confirm=3, max_speed=0.6)
    robot = [h[0] for h in run(ok, walking())]
    assert [h for _, _, h, _ in robot[:2]] == ["too few scans"] * 2
    assert robot[2][1] and robot[2][2] == "none"  # its third hit confirms it
    assert all(conf and h == "none" for _, conf, h, _ in robot[2:])


def test_a_track_mostly_seen_as_something_else_is_held_by_the_majority():
    """The robot is detected in one scan of three, an ``other`` candidate is at its place in the rest:
    by its third hit (scan 7) it has 4 contrary scans, and it waits for the majority from then on."""
    params = TrackerParams.default([False, True], n_confirm=3)
    z = [2.0, 1.5, 0.3]
    scans = [detections(z) if i % 3 == 0 else detections(other=z[:2]) for i in range(30)]
    robot = [h[0] for h in run(params, scans)]
    assert all(live and not conf for live, conf, _, _ in robot)
    holds = [h for _, _, h, _ in robot]
    assert holds[:6] == ["too few scans"] * 6 and set(holds[6:]) == {"majority"}


def test_dominant_reason_is_the_test_that_held_the_track():
    counts = np.zeros(len(HOLDS), int)
    counts[HOLDS.index("too few scans")] = 9
    assert HOLDS[dominant(counts)] == "too few scans"
    counts[HOLDS.index("speed")] = 1  # one failure among nine waiting scans: intermittent detections
    assert HOLDS[dominant(counts)] == "too few scans"
    counts[HOLDS.index("speed")] = 2  # a track that failed the speed test waits for hits after each failure
    assert HOLDS[dominant(counts)] == "speed"
    counts[HOLDS.index("majority")] = 3
    assert HOLDS[dominant(counts)] == "majority"


# ------------------------------------------------------------------------------------------ replay


@pytest.fixture(scope="module")
def scene():
    log, site = simulate("spl-trajectory", seed=1, n_scans=120)
    return log, site, load_model(demo_model_path())


def slowed(model, limit=0.01):
    return eqx.tree_at(lambda m: m.tracker.max_speed, model, jnp.full_like(model.tracker.max_speed, limit))


def replayed(model, log, site, tmp_path):
    totals = replay_log(log, model.with_site(site), tmp_path / "gtd.csv")
    return totals["diagnosis"], totals


def test_replay_with_a_top_speed_too_low_warns_of_speed(scene, tmp_path):
    log, site, model = scene
    doc, totals = replayed(slowed(model), log, site, tmp_path)
    robot = doc["classes"]["robot"]
    assert doc["scans"] == log.n_scans and totals["rows"] == 0
    assert robot["detected"] >= 0.8 * log.n_scans and robot["reported"] == 0
    assert robot["never_confirmed"] >= 1 and robot["held"]["speed"] == robot["never_confirmed"]
    # The simulated robot's own speed, from its truth: the estimate is near it.
    xy = log.truth_poses[:, 0, :2]
    true_speed = np.nanmedian(np.linalg.norm(np.diff(xy, axis=0), axis=1) / np.diff(log.stamps))
    assert abs(robot["speed_median"] - true_speed) < 0.1
    lines = warnings(doc)
    assert len(lines) == 1
    assert "speed" in lines[0] and "0.01 m/s" in lines[0] and "--max-speed robot=" in lines[0], lines
    json.dumps(doc)  # the summaries' object


def test_replay_with_the_shipped_limits_gives_no_warning(scene, tmp_path):
    log, site, model = scene
    doc, totals = replayed(model, log, site, tmp_path)
    assert totals["rows"] > 0.8 * log.n_scans
    assert doc["classes"]["robot"]["reported"] > 0.8 * log.n_scans
    assert warnings(doc) == []


def test_replay_with_the_landmarks_elsewhere_warns_of_the_map_transformation(scene, tmp_path):
    log, site, model = scene
    moved = dataclasses.replace(site, landmarks=tuple(dataclasses.replace(lm, x=lm.x + 3.0) for lm in site.landmarks))
    doc, _ = replayed(model, log, moved, tmp_path)
    assert doc["degraded"] > 0.5 * doc["scans"]
    lines = [w for w in warnings(doc) if "map transformation" in w]
    assert len(lines) == 1 and lines[0].startswith(f"{doc['degraded']} of {log.n_scans} scans"), lines


def test_the_tally_fed_scan_by_scan_or_packed_equals_the_stacked_one():
    """The live loops feed the tally one packed table a scan (``pack_tracks``); replay, stacked
    outputs: a hand-made run of two tracks gives the same tally either way."""
    from types import SimpleNamespace

    from gtsjax.drivers.live import pack_tracks

    model = SimpleNamespace(classes=("background", "post", "robot"), max_tracks=2,
                            tracker=SimpleNamespace(tracked=np.array([False, False, True]),
                                                    max_speed=np.full(3, 0.1), max_turn_rate=np.full(3, 1.0)))
    T, speed_h, few = 12, HOLDS.index("speed"), HOLDS.index("too few scans")
    tid = np.full((T, 2), -1)
    live = np.zeros((T, 2), bool)
    hold = np.zeros((T, 2), np.int32)
    # Track 0 in slot 0, scans 0-5: tentative, then held for speed at 0.5 m/s, dies. Track 1 in slot 1,
    # scans 2-11: confirmed from scan 4, reported. Track 2 in slot 0 from scan 9: tentative at the end.
    tid[0:6, 0], live[0:6, 0], hold[0:2, 0], hold[2:6, 0] = 0, True, few, speed_h
    tid[2:, 1], live[2:, 1], hold[2:4, 1] = 1, True, few
    tid[9:, 0], live[9:, 0], hold[9:, 0] = 2, True, few
    speed = np.where(hold == speed_h, 0.5, 0.05).astype(np.float32)
    det_mask = np.zeros((T, 3), bool)
    det_mask[:, 0] = True
    out = SimpleNamespace(
        track_id=tid.astype(np.int32), track_class=np.full((T, 2), 2, np.int32), track_live=live, track_hold=hold,
        track_speed=speed, track_turn_rate=np.zeros((T, 2), np.float32), track_mask=live & (tid == 1) & (hold == 0),
        track_pose=np.zeros((T, 2, 3), np.float32), track_var=np.zeros((T, 2, 3), np.float32),
        track_cov_xy=np.zeros((T, 2), np.float32),
        det_mask=det_mask, det_class=np.full((T, 3), 2, np.int32), degraded=np.arange(T) < 7,
        n_objects=np.zeros(T, np.int32), unlike=np.zeros(T, np.int32), off_envelope=np.zeros(T, np.int32))
    stacked = Tally(model)
    stacked.add(out)
    by_scan, packed = Tally(model), Tally(model, block=5)
    for t in range(T):
        one = SimpleNamespace(**{k: v[t] for k, v in vars(out).items()})
        by_scan.add(one)
        packed.add_packed(np.asarray(pack_tracks(SimpleNamespace(**{k: jnp.asarray(v) for k, v in vars(one).items()}))
                                     ).tolist())
    doc = stacked.finish()
    assert by_scan.finish() == doc == packed.finish()
    robot = doc["classes"]["robot"]
    assert (doc["scans"], doc["degraded"], doc["slots_full"]) == (T, 7, 4 + 3)  # scans 2-5 and 9-11: both live
    assert (robot["detected"], robot["reported"], robot["tracks"], robot["confirmed"]) == (T, 8, 3, 1)
    assert robot["held"] == {"too few scans": 1, "majority": 0, "speed": 1, "turn rate": 0}
    assert robot["speed_median"] == pytest.approx(0.5)
    lines = warnings(doc)
    assert any(w.startswith("7 of 12 scans without a new map transformation") for w in lines)
    assert any(w.startswith("all 2 track slots were full in 7 scans") and "--max-tracks 4" in w for w in lines)
    # reported in 8 of 12 scans: more than half of the 12 in which it was detected, no warning of it
    assert not any(w.startswith("robot") for w in lines)


def _one_track(holds, reported):
    """A hand-made run of one robot track in slot 0 of 2 (slot 1 free), one hold per scan."""
    from types import SimpleNamespace

    T = len(holds)
    slot0 = np.arange(2) == 0
    both = lambda a: np.where(slot0, np.asarray(a)[:, None], 0)  # noqa: E731
    out = SimpleNamespace(
        track_id=np.where(slot0, 0, -1) + np.zeros((T, 2), np.int32), track_class=np.full((T, 2), 2, np.int32),
        track_live=both(np.ones(T, bool)).astype(bool), track_hold=both(holds).astype(np.int32),
        track_speed=both(np.full(T, 0.3, np.float32)).astype(np.float32), track_turn_rate=np.zeros((T, 2), np.float32),
        track_mask=both(reported).astype(bool), det_mask=np.ones((T, 1), bool), det_class=np.full((T, 1), 2, np.int32),
        degraded=np.zeros(T, bool))
    model = SimpleNamespace(classes=("background", "post", "robot"), max_tracks=2,
                            tracker=SimpleNamespace(tracked=np.array([False, False, True]),
                                                    max_speed=np.full(3, 0.0), max_turn_rate=np.full(3, 1.0)))
    t = Tally(model)
    t.add(out)
    return t.finish()


def test_a_track_confirmed_then_held_for_speed_is_blamed_on_speed():
    """The user's case: a top speed of 0 m/s; the robot stood still for its first scans (confirmed,
    reported), then walked: unconfirmed for speed for the rest of the run, never reported again."""
    none, few, speed = (HOLDS.index(h) for h in ("none", "too few scans", "speed"))
    holds = [few, few, none, none] + [speed] * 36
    doc = _one_track(holds, [h == none for h in holds])
    robot = doc["classes"]["robot"]
    assert (robot["confirmed"], robot["never_confirmed"], robot["held_scans"]["speed"]) == (1, 0, 36)
    (line,) = warnings(doc)
    assert line.startswith("robot detected in 100 % of scans but reported in 5 %: its tracks were confirmed, then "
                           "held unconfirmed in 36 scans for implausible speed"), line
    assert "estimated 0.30 m/s against the model's limit 0.00 m/s" in line and "--max-speed robot=0.6" in line


def test_intermittent_detections_with_a_rare_speed_failure_are_blamed_on_too_few_scans():
    none, few, speed = (HOLDS.index(h) for h in ("none", "too few scans", "speed"))
    holds = ([few] * 9 + [speed]) * 4
    (line,) = warnings(_one_track(holds, [False] * 40))
    assert "1 track never confirmed, 1 for too few scans" in line and "--confirm-scans" in line


# --------------------------------------------------------------------------------------------- CLI


def test_cli_replay_warns_on_stderr_and_exits_0(scene, tmp_path, capsys):
    log, site, model = scene
    save_log(log, tmp_path / "log.npz")
    save_site(site, tmp_path / "site.json")
    save_model(slowed(model), tmp_path / "slow.npz")
    code = main(["replay", str(tmp_path / "log.npz"), "--site", str(tmp_path / "site.json"), "--model",
                 str(tmp_path / "slow.npz"), "--out", str(tmp_path / "gtd.csv"), "--summary",
                 str(tmp_path / "summary.json")])
    err = capsys.readouterr().err
    assert code == 0
    lines = [ln for ln in err.splitlines() if ln.startswith("warning: ")]
    assert len(lines) == 1 and "implausible speed" in lines[0] and "0.01 m/s" in lines[0], err
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc["rows"] == 0 and doc["diagnosis"]["classes"]["robot"]["held"]["speed"] >= 1
