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


def test_in_view_means_returns_on_it_not_behind_another_nor_out_of_reach():
    """``seen``: a scan ray-cast by hand (a NumPy loop over beams and discs, the laser at the origin
    facing +x with a 180° view): a robot in the open is in view, one straight behind it is not (its
    disc gets no ray), nor one behind the laser, nor one past the range window; a robot beside a
    post is in view, the post's returns being the post's."""
    from gtsjax.io import ScanLog
    from gtsjax.train.check import seen

    n = 721
    angle_min, inc = -np.pi / 2, np.pi / (n - 1)
    discs = {"open": (2.0, 1.0), "behind": (3.5, 1.75), "back": (-2.0, 0.0), "far": (0.0, -5.0), "by post": (2.0, -1.0)}
    post = np.array([[2.0, -1.3]])
    r_disc = 0.12
    ranges = np.zeros(n, np.float32)
    for i in range(n):
        a = angle_min + i * inc
        u = np.array([np.cos(a), np.sin(a)])
        best = np.inf
        for c in [*discs.values(), tuple(post[0])]:
            c = np.asarray(c)
            along = c @ u
            off2 = c @ c - along**2
            if along > 0 and off2 <= r_disc**2:
                best = min(best, along - np.sqrt(r_disc**2 - off2))
        ranges[i] = best if best <= 4.0 else 0.0  # a 4 m range window: "far" is beyond it
    log = ScanLog(ranges=ranges[None], stamps=np.array([0.0]), angle_min=angle_min, angle_increment=inc,
                  range_min=0.02, range_max=4.0)
    truth = np.array([list(discs.values())], float)
    got = seen(log, np.zeros((1, 3)), truth, np.ones((1, len(discs)), bool), post, radius=0.3)
    assert dict(zip(discs, got[0].tolist(), strict=True)) == {
        "open": True, "behind": False, "back": False, "far": False, "by post": True}
