"""Training checks that the model can track, not only classify (``gtsjax.train.check``): the tracker
on a simulated stay and walk, and ``train --strict`` failing, with the stage named, on a model built
to track nothing."""

from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from gtsjax.io import save_log, save_site
from gtsjax.io.modelfile import load_model
from gtsjax.sim import simulate
from gtsjax.train.check import ROWS_PER_DETECTION, check_tracker, verdict

from ._utils import run_cli

DEMO_MODEL = Path(__file__).resolve().parents[1] / "gtsjax" / "data" / "demo-model.npz"
ERRORS = dict(detection_rate=0.95, position_sigma=0.01, heading_sigma=np.radians(2.0), misread=0.03)


def test_the_shipped_tracker_follows_a_simulated_stay_and_walk():
    model = load_model(DEMO_MODEL)
    got = check_tracker(model, "robot", rate_hz=10.0, **ERRORS)
    assert got["rows_per_detected_scan"] >= 0.97
    assert got["position_rmse_m"] < 0.02
    assert verdict({}, {"robot": got}) == []


def test_a_tracker_with_a_top_speed_of_a_snail_is_caught_and_named():
    model = load_model(DEMO_MODEL)
    slow = eqx.tree_at(lambda m: m.tracker.max_speed, model, jnp.full_like(model.tracker.max_speed, 0.01))
    got = check_tracker(slow, "robot", rate_hz=10.0, **ERRORS)
    assert got["rows_per_detected_scan"] < ROWS_PER_DETECTION
    assert max(got["lost"], key=got["lost"].get) == "speed"
    (line,) = verdict({}, {"robot": got})
    assert "speed" in line and "--max-speed" in line


def test_at_40_hz_the_confirmation_is_half_a_second_too():
    """The check scores each appearance after the tracker's confirmation time: at 40 Hz the model's own
    (the shipped one's is 10 Hz scans) must not be needed in scans four times over."""
    model = load_model(DEMO_MODEL)
    from gtsjax.core.g_track import TrackerParams

    params = TrackerParams.default(np.asarray(model.tracker.tracked), rate_hz=40.0)
    assert int(params.n_confirm) == 20  # half a second at 40 Hz
    m40 = eqx.tree_at(lambda m: m.tracker, model, params)
    got = check_tracker(m40, "robot", rate_hz=40.0, **ERRORS)
    assert got["rows_per_detected_scan"] >= 0.97


def test_train_strict_fails_on_a_model_that_cannot_track(tmp_path):
    log, site = simulate("spl-train", seed=21, n_scans=300)
    walk, _ = simulate("spl-trajectory", seed=22, n_scans=150)
    save_log(log, tmp_path / "grid.npz")
    save_log(walk, tmp_path / "walk.npz")
    save_site(site, tmp_path / "site.json")
    out = tmp_path / "m.npz"
    small = ["--max-per-class", "60", "--max-pose", "80", "--max-pose-fit", "80", "--inducing", "32",
             "--inducing-class", "64", "--restarts", "1"]
    proc = run_cli("train", str(tmp_path / "grid.npz"), str(tmp_path / "walk.npz"), "--site", str(tmp_path / "site.json"),
                   "--out", str(out), "--max-speed", "robot=0.01", "--strict", *small)
    assert proc.returncode == 1, proc.stderr
    assert out.exists()  # written all the same: the user may look at it
    problem = [line for line in proc.stderr.splitlines() if "cannot track" in line]
    assert problem and "speed" in problem[0] and "--max-speed" in problem[0], proc.stderr
