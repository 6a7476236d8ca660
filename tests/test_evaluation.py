"""Accuracy metrics (``gtsjax.drivers.evaluation``) on outputs whose errors are known by construction, and the
``gtsjax evaluate`` command's tables."""

import json
from types import SimpleNamespace

import numpy as np

from gtsjax.drivers.evaluation import evaluate_outputs
from gtsjax.io.logs import ScanLog

T, M = 40, 4  # scans, track slots
ROBOT = 2  # class index of "robot" in the fake model


def _scene():
    """One robot, present in scans 0-29, picked up for scans 30-34, put down elsewhere for 35-39;
    10 Hz. The tracker's output: a track (id 7) 2 cm east of it with a 3° heading error from scan 2
    to 29, none while it is away, a new track (id 9) once it is back from scan 37; a false track
    (id 8) far away in scans 10-14. Detections: the same 2 cm / 3° off, every scan it is there."""
    stamps = 100.0 + 0.1 * np.arange(T)
    truth = np.full((T, 1, 3), np.nan)
    truth[:30, 0] = [2.0, 1.5, 0.4]
    truth[35:, 0] = [4.0, 2.5, -1.0]
    log = ScanLog(ranges=np.zeros((T, 5), np.float32), stamps=stamps, angle_min=0.0, angle_increment=0.01,
                  truth_classes=np.array(["robot"]), truth_poses=truth)
    pose = np.zeros((T, M, 3), np.float32)
    mask = np.zeros((T, M), bool)
    tid = np.full((T, M), -1, np.int32)
    off = np.array([0.02, 0.0, np.radians(3)], np.float32)
    pose[2:30, 0] = truth[2:30, 0] + off
    mask[2:30, 0], tid[2:30, 0] = True, 7
    pose[37:, 0] = truth[37:, 0] + off
    mask[37:, 0], tid[37:, 0] = True, 9
    pose[10:15, 1] = [5.0, 0.5, 0.0]
    mask[10:15, 1], tid[10:15, 1] = True, 8
    present = ~np.isnan(truth[:, 0, 0])
    det_pose = np.zeros((T, 3, 3), np.float32)
    det_pose[present, 0] = truth[present, 0] + off
    det_mask = np.zeros((T, 3), bool)
    det_mask[present, 0] = True
    out = SimpleNamespace(track_pose=pose, track_mask=mask, track_id=tid, track_class=np.full((T, M), ROBOT),
                          det_pose=det_pose, det_mask=det_mask, det_class=np.full((T, 3), ROBOT),
                          degraded=np.zeros(T, bool))
    model = SimpleNamespace(classes=("background", "post", "robot"), pose=(None, None, None),
                            site=SimpleNamespace(bounds=np.array([0.0, 0.0, 6.0, 4.0]), has_bounds=True))
    return log, out, model, present


def test_metrics_match_the_construction():
    log, out, model, present = _scene()
    res = evaluate_outputs(model, log, out, settle_s=0.95)  # stamps are float: 10 steps of 0.1 s may sum below 1
    # Settled object-scans: 10 s after each placement (scans 10-29 and none of 35-39: only 0.4 s).
    assert res["objects_present"] == int(present.sum()) == 35
    assert res["recall"] == 1.0  # scans 10-29 all matched
    assert res["recall_incl_initiation"] == (28 + 3) / 35  # scans 2-29 and 37-39 of 35
    assert res["false_tracks_per_scan"] == 5 / T
    assert res["id_switches"] == 0  # the new id came after the robot was away: no switch
    np.testing.assert_allclose(res["position_rmse_m"], 0.02, rtol=1e-5)
    np.testing.assert_allclose(res["heading_rmse_deg"], 3.0, rtol=1e-4)
    assert res["n_errors"] == 20  # errors only once settled
    assert res["det_recall"] == 1.0
    np.testing.assert_allclose(res["det_position_rmse_m"], 0.02, rtol=1e-5)
    assert res["det_misread_fraction"] == 0.0


def test_a_new_id_while_the_object_stays_is_a_switch():
    log, out, model, _ = _scene()
    out.track_id[20:30, 0] = 11  # the robot's track changes id mid-way while it stays put
    res = evaluate_outputs(model, log, out)
    assert res["id_switches"] == 1


def test_evaluate_command_writes_both_tables(tmp_path):
    """The shipped model on docs/accuracy.md's bumped-sensor scenario (spl-bumped:2005) gives its
    figures (recall 100 %, 0.9 cm, 2.5°, heading median 0.8°, no false track or id switch, the bump
    recovered in the first scan after it; per scan 98.5 % detected, 1.0 cm), within twice their error."""
    from gtsjax.cli import main
    from gtsjax.cli.demo import demo_model_path

    code = main(["evaluate", "--model", str(demo_model_path()), "--scenario", "spl-bumped:2005", "--out-dir",
                 str(tmp_path)])
    assert code == 0
    md = (tmp_path / "results.md").read_text()
    assert "Ground truth (confirmed tracks)" in md and "Per scan, before tracking" in md
    res = json.loads((tmp_path / "results.json").read_text())["spl-bumped:2005"]
    assert res["recall"] >= 0.99, res
    assert res["position_rmse_m"] <= 0.018 and res["heading_rmse_deg"] <= 5.0, res
    assert res["heading_median_deg"] <= 1.6, res
    assert res["false_tracks_per_scan"] <= 0.005 and res["id_switches"] == 0, res
    assert res["bump_recovered_after_s"] is not None and res["bump_recovered_after_s"] <= 0.2, res  # two scans
    assert res["det_recall"] >= 0.97 and res["det_position_rmse_m"] <= 0.02, res


def test_error_bars_and_bias_against_a_row_by_row_count():
    """``error_bar_figures`` against the obvious computation, row by row (each row's covariance inverted
    by NumPy, χ² quantiles from SciPy, the error turned into the robot's frame by its rotation matrix),
    on errors drawn from each row's own Gaussian around a known bias: about 95 % inside, NEES about 2
    and 1, and the bias recovered."""
    from scipy.stats import chi2

    from gtsjax.drivers.evaluation import error_bar_figures

    rng = np.random.default_rng(5)
    n = 4000
    th = rng.uniform(-np.pi, np.pi, n)
    sx, sy = rng.uniform(0.005, 0.03, n), rng.uniform(0.005, 0.03, n)
    rho = rng.uniform(-0.8, 0.8, n)
    vth = rng.uniform(0.01, 0.05, n) ** 2
    bias_robot = np.array([-0.008, 0.0012])  # behind and to the left, as issue 55 measured
    rows = []
    for k in range(n):
        cov = np.array([[sx[k] ** 2, rho[k] * sx[k] * sy[k]], [rho[k] * sx[k] * sy[k], sy[k] ** 2]])
        c, s = np.cos(th[k]), np.sin(th[k])
        d = np.array([[c, -s], [s, c]]) @ bias_robot + rng.multivariate_normal(np.zeros(2), cov)
        e_th = 0.002 + rng.normal(0, np.sqrt(vth[k]))
        rows.append((d[0], d[1], e_th, cov[0, 0], cov[1, 1], cov[0, 1], vth[k], th[k]))
    e = np.array(rows)
    got = error_bar_figures(e)
    nees_p, nees_t, ahead, left = [], [], [], []
    for dx, dy, eth, vx, vy, cxy, vt, t in e:
        d = np.array([dx, dy])
        nees_p.append(d @ np.linalg.solve(np.array([[vx, cxy], [cxy, vy]]), d))
        nees_t.append(eth**2 / vt)
        c, s = np.cos(t), np.sin(t)
        a, b = np.array([[c, s], [-s, c]]) @ d
        ahead.append(a)
        left.append(b)
    np.testing.assert_allclose(got["position_within_95"], np.mean(np.array(nees_p) <= chi2.ppf(0.95, 2)))
    np.testing.assert_allclose(got["heading_within_95"], np.mean(np.array(nees_t) <= chi2.ppf(0.95, 1)))
    np.testing.assert_allclose(got["position_nees"], np.mean(nees_p), rtol=1e-9)
    np.testing.assert_allclose(got["heading_nees"], np.mean(nees_t), rtol=1e-9)
    np.testing.assert_allclose([got["bias_ahead_m"], got["bias_left_m"]], [np.mean(ahead), np.mean(left)], atol=1e-12)
    np.testing.assert_allclose(got["heading_bias_deg"], np.degrees(np.mean(e[:, 2])))
    # and the figures mean what they say: the bias put in is found, the ellipses hold their share
    np.testing.assert_allclose([got["bias_ahead_m"], got["bias_left_m"]], bias_robot, atol=8e-4)
    assert abs(got["heading_within_95"] - 0.95) < 0.015
    assert 0.80 < got["position_within_95"] < 0.95  # the bias, outside the ellipses' model, pushes errors out
    assert all(np.isnan(v) for v in error_bar_figures(np.zeros((0, 8))).values())  # no rows: NaN, not a share


def test_view_figures_split_each_views_bias_from_its_noise():
    """``view_figures`` against a count by hand: rows drawn at six still views (poses), each view with a
    heading bias and a position bias of its own (in the robot's frame) plus noise of known size, and
    rows of a moving robot (one row per pose) that make no view: the six views found, and each
    figure equal to the mean over views of the per-view means and spreads computed directly."""
    from gtsjax.drivers.evaluation import view_figures

    rng = np.random.default_rng(8)
    rows, want_hb, want_hn, want_pb, want_pn = [], [], [], [], []
    for v in range(6):
        x, y, th = rng.uniform(0, 6), rng.uniform(0, 4), rng.uniform(-3, 3)
        hb, pb = np.radians(rng.uniform(-4, 4)), rng.uniform(-0.01, 0.01, 2)
        n = 20 + 5 * v
        eth = hb + rng.normal(0, np.radians(0.8), n)
        robot = pb + rng.normal(0, 0.004, (n, 2))  # ahead, left
        c, s = np.cos(th), np.sin(th)
        field = robot @ np.array([[c, s], [-s, c]])  # back to the field frame: R(θ) applied to each row
        for k in range(n):
            rows.append((field[k, 0], field[k, 1], eth[k], 1e-4, 1e-4, 0.0, 1e-3, th, x, y))
        want_hb.append(np.mean(eth))
        want_hn.append(np.mean((eth - np.mean(eth)) ** 2))
        mean = robot.mean(axis=0)
        want_pb.append(np.hypot(*mean))
        want_pn.append(np.mean(np.sum((robot - mean) ** 2, axis=1)))
    for _ in range(50):  # a robot on the move: every pose once
        rows.append((0.01, 0.0, 0.02, 1e-4, 1e-4, 0.0, 1e-3, rng.uniform(-3, 3), rng.uniform(0, 6), rng.uniform(0, 4)))
    got = view_figures(np.asarray(rows)[rng.permutation(len(rows))])
    assert got["views"] == 6
    np.testing.assert_allclose(got["view_heading_bias_rms_deg"], np.degrees(np.sqrt(np.mean(np.square(want_hb)))))
    np.testing.assert_allclose(got["view_heading_bias_max_deg"], np.degrees(np.max(np.abs(want_hb))))
    np.testing.assert_allclose(got["view_heading_noise_rms_deg"], np.degrees(np.sqrt(np.mean(want_hn))))
    np.testing.assert_allclose(got["view_position_bias_rms_m"], np.sqrt(np.mean(np.square(want_pb))))
    np.testing.assert_allclose(got["view_position_noise_rms_m"], np.sqrt(np.mean(want_pn)))
    assert view_figures(np.asarray(rows[-50:]))["views"] == 0  # moving all the time: no view
