"""Recordings made the ways users make them (issue 38): each trained model must track held-out scenes.

A model trained on a robot turned on the spot through 16 headings, one scan each, once tracked nothing
(its top speed was learnt as 0 m/s) while training reported 99.8 % held-out accuracy. These tests train
small models (small example caps: a minute or so each) on simulated recordings of other habits than
the simulator's own grid: turned on the spot, put down for seconds per pose, walking, carried between
poses with no gap; at 10 and 40 Hz; with and without clutter; the Nao-like outline and a box of another
size. Each must pass training's own tracking check (``train --strict``'s) and track held-out scenes of
its site (the robot put down for 2 s at six poses, and walking for 30 s) with recall at least 97 % once
each track had its confirmation time, and position RMSE at most 2 cm, scored by
``drivers.evaluation`` (the scorer of docs/accuracy.md's tables) against the simulator's truth.
"""

import dataclasses
import re

import numpy as np
import pytest

from gtsjax.drivers.evaluation import evaluate_log
from gtsjax.io import save_log, save_site
from gtsjax.io.modelfile import save_model
from gtsjax.sim import check_scene, recording
from gtsjax.train import TrainConfig, train
from tests._utils import cli

# Small models: enough views for 2 cm, few enough for about a minute of training on 2 cores.
SMALL = dataclasses.replace(TrainConfig(), max_per_class=100, max_pose_examples=300, max_pose_fit=150, n_inducing=300,
                            n_inducing_class=128, max_landmark_examples=100, restarts=1)
# The defaults' classifier examples with pose GPs of a size that trains in a third of the defaults' time,
# and the classifier's hyperparameters fitted on 600 of its examples instead of 1 500 (each GP still
# conditioned on all of them): the cart's training in 56 s instead of 85 here, with the same scores
# (83.3 % put down, 100 % walking) and the same shortfall said.
MID = dataclasses.replace(TrainConfig(), max_pose_examples=1000, max_pose_fit=300, n_inducing=1000, restarts=1,
                          max_class_fit=600)

CASES = {
    # The recording that broke training: 16 headings turned on the spot, one scan each, carried away between points.
    "turned on the spot, SPL field, URG-04LX 10 Hz, Nao": dict(site="spl", style="turn", rate_hz=None, outline="nao",
                                                               clutter=False, seconds=100.0),
    "turned on the spot, hall, 40 Hz, box, clutter": dict(site="hall", style="turn", rate_hz=40.0, outline="box",
                                                          clutter=True, seconds=None),
    # With the small settings' 100 examples a class, a fifth of the held-out placements' views are taken for
    # background (79 %), and training says so; the static and walking scenes are tracked all the same.
    "put down for seconds per pose, hall, 10 Hz, box": dict(site="hall", style="hold", rate_hz=None, outline="box",
                                                            clutter=False, seconds=200.0,
                                                            training_says="detected in only"),
    # A walk sees the robot side-on: training warns so. Stage e′'s search over every side reads the
    # headings of the sides it rarely showed (1.2° put down, 1.3° walking). The robot put down shows
    # sides the walk showed in a few scans only: their positions were 2.4 cm off while the labels' map
    # was scaled by the posts' surfaces (1.5 cm since it is fitted to the posts' centres, issue 55).
    "walking, SPL field, 10 Hz, Nao, clutter": dict(site="spl", style="walk", rate_hz=None, outline="nao",
                                                    clutter=True, seconds=120.0),
    # Carried from pose to pose over the whole field (450 s, 18 points): fewer points leave the robot
    # unseen where the check scenes put it, and training warns so.
    "carried between poses, SPL field, 10 Hz, Nao": dict(site="spl", style="carried", rate_hz=None, outline="nao",
                                                         clutter=False, seconds=450.0),
    # A mirror-symmetric cart: its flat side at 3.5 m looks like the flat stretches of the box beside the
    # field at that range, which the classifier learns as background. Training says so; a confirmed
    # track follows the cart past it on its guesses; a cart put down side-on there is never found.
    # Trained with the defaults' classifier (500 examples a class) on the recording of seed 5 and checked on
    # scenes of seed 6: the small settings' 100 examples a class, and seed 1's recording, happen not to show
    # it (which views of the cart the classifier gets near the box's range is down to the grid and the draw).
    # Its pose GPs are capped (MID): the defaults' 2 000-point fits and 6 144 inducing points tracked the
    # same (83.3 % / 1.0 cm / 0.8° put down, 100 % / 1.2 cm / 1.2° walking; capped 83.3 % / 1.0 cm / 0.8°,
    # 100 % / 1.2 cm / 1.1°) at twice the training time.
    "turned on the spot, SPL field, 10 Hz, cart": dict(site="spl", style="turn", rate_hz=None, outline="cart",
                                                       clutter=False, seconds=100.0, config=MID, seeds=(5, 6),
                                                       training_says="detected in only",
                                                       recall_short={"static": "put down where its side looks "
                                                                     "like the box beside the field: the "
                                                                     "classifier takes it for background "
                                                                     "(issue 38)"}),
}


@pytest.fixture(scope="module", params=list(CASES), ids=lambda s: re.sub(r"[^a-z0-9]+", "-", s.lower()).strip("-"))
def trained(request):
    case = CASES[request.param]
    log, site = recording(case["site"], case["style"], seed=case.get("seeds", (1, 2))[0], rate_hz=case["rate_hz"], clutter=case["clutter"],
                          outline=case["outline"], seconds=case["seconds"])
    model, report = train([log], site, case.get("config", SMALL))
    return case, model, report


def test_training_checks_that_its_model_tracks(trained):
    case, model, report = trained
    if "training_says" in case:  # train --strict would fail, saying why
        assert any(case["training_says"] in p for p in report["pipeline_problems"]), report["pipeline_problems"]
    else:
        assert report["pipeline_problems"] == []  # train --strict would pass
    for row in report["learnt"]:
        lo, hi = row["hard_range"] or (float("-inf"), float("inf"))
        assert lo <= row["value"] <= hi, row
    motion = report["motion_limits"]["robot"]
    if case["style"] in ("turn", "hold"):  # no translation in the labels: never a speed learnt from them
        assert motion["max_speed_from"] == "default"
    # The walk's labels see the robot side-on, and training says so; the others see it from every side.
    side_warnings = [w for w in report["warnings"] if "sides" in w]
    assert bool(side_warnings) == (case["style"] == "walk"), report["warnings"]
    # The box looks the same turned half a turn (its outline typed in gtsjax.sim.scene, a rectangle), the
    # Nao and the cart do not: training says which, and reads the box's heading modulo π.
    half = [w for w in report["warnings"] if "half a turn" in w]
    assert bool(half) == (case["outline"] == "box"), report["warnings"]
    assert (model.pose[model.classes.index("robot")].turns is not None) == (case["outline"] == "box")
    (row,) = [r for r in report["learnt"] if r["parameter"] == "distance from its half-turn"]
    assert row["source"] == "learnt" and (row["value"] <= 3.0) == (case["outline"] == "box"), row
    # The robot's mean pose error in its own frame on the check's held-out detections: a few millimetres
    # and a fraction of a degree for every recording here, and what the tracker takes off its rows.
    bias = {r["parameter"]: r for r in report["learnt"] if r["parameter"].startswith("pose bias")}
    assert sorted(bias) == ["pose bias ahead", "pose bias heading", "pose bias left"]
    assert all(r["class"] == "robot" and r["source"] == "learnt" for r in bias.values()), bias
    got = np.asarray(model.tracker.pose_offset)[model.classes.index("robot")]
    want = [bias["pose bias ahead"]["value"] / 1e3, bias["pose bias left"]["value"] / 1e3,
            np.radians(bias["pose bias heading"]["value"])]
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert np.all(np.abs(got[:2]) < 0.01) and abs(np.degrees(got[2])) < 1.0, got
    # The rows' position variance floor (lever 6) where the check had rows enough: what the table lists
    # is what the tracker adds; the heading's is listed as measured and not added.
    floor = {r["parameter"]: r for r in report["learnt"] if r["parameter"].endswith("sd floor")}
    if floor:
        assert [floor[p]["source"] for p in ("row position sd floor", "row heading sd floor")] == ["learnt", "measured"]
        added = np.asarray(model.tracker.var_floor)[model.classes.index("robot")] if model.tracker.var_floor is not None \
            else np.zeros(2)
        np.testing.assert_allclose(np.sqrt(added[0]) * 1e3, floor["row position sd floor"]["value"], atol=0.006)
        assert added[1] == 0


@pytest.fixture(scope="module", params=["static", "walking"])
def scored(request, trained):
    case, model, _ = trained
    log, site = check_scene(case["site"], request.param, seed=case.get("seeds", (1, 2))[1], rate_hz=case["rate_hz"], outline=case["outline"],
                            clutter=case["clutter"])
    return case, request.param, evaluate_log(model.with_site(site), log)


def test_the_model_finds_the_robot_in_held_out_scenes(scored, request):
    case, kind, res = scored
    if kind in case.get("recall_short", {}):  # a known shortfall: strict, so that its fix is noticed
        request.applymarker(pytest.mark.xfail(strict=True, reason=case["recall_short"][kind]))
    assert res["recall"] >= 0.97, res
    assert res["false_tracks_per_scan"] <= 0.01, res


def test_the_model_reads_the_heading(scored, request):
    """Issue 38's heading targets on a held-out scene: RMSE at most 3° put down, 4° walking (the box's
    modulo a half-turn, all its outline can tell: ``drivers.evaluation.heading_error``)."""
    case, kind, res = scored
    if kind in case.get("heading_short", {}):  # a known shortfall: strict, so that its fix is noticed
        request.applymarker(pytest.mark.xfail(strict=True, reason=case["heading_short"][kind]))
    assert res["heading_rmse_deg"] <= (3.0 if kind == "static" else 4.0), res


def test_the_model_places_the_robot_within_2_cm(scored, request):
    case, kind, res = scored
    if kind in case.get("position_short", {}):  # a known shortfall: strict, so that its fix is noticed
        request.applymarker(pytest.mark.xfail(strict=True, reason=case["position_short"][kind]))
    assert res["position_rmse_m"] <= 0.02, res


def test_evaluate_says_when_headings_are_judged_modulo_a_half_turn(trained, tmp_path, capsys):
    """``gtsjax evaluate`` with a model of a class alike turned half a turn (the box) says that its
    headings are judged modulo 180°, in the terminal and in results.md, and ``gtsjax info`` that the
    model reads it so; with the others neither says it."""
    case, model, _ = trained
    log, site = check_scene(case["site"], "static", seed=case.get("seeds", (1, 2))[1], rate_hz=case["rate_hz"],
                            outline=case["outline"], clutter=case["clutter"])
    save_model(model, tmp_path / "m.npz")
    save_log(log.slice(0, 40), tmp_path / "check.npz")  # what is said is the model's: a few seconds of the scene
    save_site(site, tmp_path / "site.json")
    res = cli(capsys, "evaluate", "--model", tmp_path / "m.npz", tmp_path / "check.npz", "--site", tmp_path / "site.json",
              "--out-dir", tmp_path / "out")
    assert res.returncode == 0, res.stderr
    said = "judged modulo 180°" in " ".join(res.stdout.split())
    written = "judged modulo 180°" in (tmp_path / "out" / "results.md").read_text()
    assert said == written == (case["outline"] == "box"), res.stdout
    shown = cli(capsys, "info", tmp_path / "m.npz")
    modulo = "heading modulo 180°" in " ".join(shown.stdout.split())
    assert shown.returncode == 0 and modulo == (case["outline"] == "box"), shown.stdout


def test_heading_turns_overrides_what_the_outline_shows(tmp_path, capsys):
    """``--heading-turns robot=1`` for the box: its heading is regressed as any other's, without the warning,
    and the table of learnt values says it was set; a value other than 1 or 2 is one line, exit 2."""
    log, site = recording("hall", "hold", seed=1, outline="box", seconds=200.0)
    model, report = train([log], site, dataclasses.replace(SMALL, heading_turns={"robot": 1}, check_pipeline=False))
    assert model.pose[model.classes.index("robot")].turns is None
    assert not [w for w in report["warnings"] if "half a turn" in w], report["warnings"]
    (row,) = [r for r in report["learnt"] if r["parameter"] == "distance from its half-turn"]
    assert row["source"] == "set" and row["value"] <= 3.0, row  # the box is alike turned, as measured
    save_log(log, tmp_path / "box.npz")
    save_site(site, tmp_path / "site.json")
    res = cli(capsys, "train", tmp_path / "box.npz", "--site", tmp_path / "site.json", "--out", tmp_path / "m.npz",
              "--heading-turns", "robot=3")
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "--heading-turns" in lines[0], res.stderr
    assert not (tmp_path / "m.npz").exists()
