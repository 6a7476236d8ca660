"""Issue 13's rejection of what the model was not trained on: the open-set test against brute-force
nearest examples, the shape envelopes against plain loops, motion limits from labelled motion, training
without background and with background logs."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.core.c_filters import Envelope, envelope_pass, partial_view
from gtsjax.core.d_classify import Support, classify, nearest_d2
from gtsjax.io.logs import ScanLog
from gtsjax.train import Examples, fit_envelope, motion_limits, train

F32 = jnp.float32


def brute_nearest(x, sup_raw, mean, scale):
    """Nearest-example squared distance by two loops, in the class's scale."""
    best = np.inf
    for s in sup_raw:
        best = min(best, float(np.sum(((x - mean) / scale - s) ** 2)))
    return best


def test_nearest_d2_is_the_nearest_example_in_the_class_scale():
    rng = np.random.default_rng(0)
    n_classes, p, d = 3, 7, 5
    xs = rng.normal(size=(n_classes, p, d))
    mask = rng.random((n_classes, p)) < 0.7
    mask[0] = False  # background: no examples
    mean, scale = rng.normal(size=(n_classes, d)), rng.uniform(0.2, 2.0, (n_classes, d))
    sup = Support(jnp.asarray(np.where(mask[..., None], xs, 0), F32), jnp.asarray(mask), jnp.asarray(mean, F32),
                  jnp.asarray(1 / scale, F32), jnp.full(n_classes, 4.0, F32))
    cands = rng.normal(size=(11, d)) * 2
    got = np.asarray(nearest_d2(sup, jnp.asarray(cands, F32)))
    for i, x in enumerate(cands):
        for k in range(n_classes):
            want = brute_nearest(x, xs[k][mask[k]], mean[k], scale[k])
            if np.isinf(want):
                assert np.isinf(got[i, k])
            else:
                np.testing.assert_allclose(got[i, k], want, rtol=1e-4, atol=1e-4)


def test_a_candidate_far_from_its_class_examples_is_background(tiny):
    """With the trained model's own GPs and supports: a candidate the scores call a robot but that a
    brute-force search finds farther from every robot example than the threshold is background
    (``unlike``); the robot examples of the support themselves are robots."""
    model = tiny["model"]
    clf = model.classifier
    r = model.class_index("robot")
    sup = clf.support
    m = np.asarray(sup.mask[r])
    raw = np.asarray(sup.x[r])[m] / np.asarray(sup.inv_scale[r]) + np.asarray(sup.mean[r])  # back to inputs
    thr = float(sup.threshold[r])
    assert np.isfinite(thr) and m.sum() > 10
    rng = np.random.default_rng(1)
    scale = 1 / np.asarray(sup.inv_scale[r], np.float64)
    # Walk examples away from their class along random directions until the scores still say robot but
    # the brute force says unlike; and keep some that stay close.
    far, near = [], []
    for x in raw[:40].astype(np.float64):
        for step in (0.3, 0.6, 1.0, 1.5, 2.5, 4.0):
            y = x + step * scale * rng.normal(size=x.shape)
            d2 = min(float(np.sum(((y - s) / scale) ** 2)) for s in raw)
            if abs(d2 - thr) > 0.01 * thr:  # clear of the threshold by more than float32 rounding
                (far if d2 > thr else near).append(y)
    x = jnp.asarray(np.asarray(far + near), F32)
    dec = classify(clf, x, jnp.ones(x.shape[0], bool))
    scores = np.asarray(dec.scores)
    called_robot = (scores.argmax(1) == r) & (scores.max(1) >= np.asarray(clf.threshold)[r])
    n_far = len(far)
    assert called_robot[:n_far].sum() >= 5, "the test needs robot-scored candidates far from the examples"
    ok, unlike = np.asarray(dec.ok), np.asarray(dec.unlike)
    robot = np.asarray(dec.cls) == r
    assert not (ok & robot)[:n_far].any()  # far: never a robot, whatever the score
    np.testing.assert_array_equal(unlike[:n_far] & robot[:n_far], called_robot[:n_far])
    assert called_robot[n_far:].sum() >= 5
    assert not (unlike & robot)[n_far:].any()  # near: the open-set test passes them
    np.testing.assert_array_equal((ok & robot)[n_far:], called_robot[n_far:])


def test_envelope_pass_matches_a_loop():
    rng = np.random.default_rng(2)
    n_classes, n_bins = 3, 4
    lo = rng.uniform(0, 1, (n_classes, n_bins, 3))
    hi = lo + rng.uniform(0.2, 1.5, (n_classes, n_bins, 3))
    lo[0], hi[0] = -np.inf, np.inf
    env = Envelope(jnp.asarray(0.7, F32), jnp.asarray(lo, F32), jnp.asarray(hi, F32), jnp.zeros(3, bool))
    q = rng.uniform(0, 2, (50, 3))
    r = rng.uniform(0, 4, 50)
    got = np.asarray(envelope_pass(env, jnp.asarray(q, F32), jnp.asarray(r, F32)))
    for i in range(50):
        b = min(int(r[i] // 0.7), n_bins - 1)
        for k in range(n_classes):
            want = all(lo[k, b, j] <= q[i, j] <= hi[k, b, j] for j in range(3))
            assert got[i, k] == want


def test_envelope_rules_the_classes_out_of_the_argmax():
    """A candidate outside its best class's envelope takes the best class whose envelope it is in
    (background always qualifies), and is counted as off its envelope."""
    from gtsjax.gp import Hyperparameters, SparseGP

    def const_gp(value):  # a GP whose mean is the constant ``value``
        z = jnp.zeros((1, 2), F32)
        hp = Hyperparameters(jnp.zeros(2, F32), jnp.asarray(0.0, F32), jnp.asarray(0.0, F32))
        one = jnp.ones((1, 1), F32)
        return SparseGP(z, jnp.zeros(1, bool), hp, jnp.zeros(1, F32), one, one, jnp.asarray(value, F32),
                        jnp.zeros(2, F32), jnp.ones(2, F32), jnp.asarray(1.0, F32))

    from gtsjax.core.d_classify import Classifier

    clf = Classifier((const_gp(0.1), const_gp(0.5), const_gp(0.9)), jnp.full(3, 0.35, F32), Support.none(3, 2))
    x = jnp.zeros((3, 2), F32)
    env = jnp.asarray([[True, True, True], [True, True, False], [True, False, False]])
    dec = classify(clf, x, jnp.ones(3, bool), env)
    np.testing.assert_array_equal(np.asarray(dec.cls), [2, 1, 0])
    np.testing.assert_array_equal(np.asarray(dec.ok), [True, True, False])
    np.testing.assert_array_equal(np.asarray(dec.off_envelope), [False, True, True])


def examples(cls, shape, rng_, occluded=None):
    n = len(cls)
    occluded = np.zeros(n, bool) if occluded is None else np.asarray(occluded)
    return Examples(np.zeros((n, 2)), np.asarray(cls), np.full((n, 3), np.nan), np.zeros(n, int), np.zeros((n, 2)),
                    np.zeros(n), np.asarray(shape, float), np.asarray(rng_, float), occluded)


def test_fit_envelope_holds_the_class_and_extends_to_unseen_ranges():
    rng = np.random.default_rng(3)
    n = 400
    r = rng.uniform(1.0, 3.0, n)
    shape = np.column_stack([rng.uniform(0.15, 0.3, n), rng.uniform(0.02, 0.2, n), rng.uniform(40, 80, n)])
    occluded = np.arange(n) < 4  # 1 %: the class is seen whole
    ex = examples(np.full(n, 1), shape, r, occluded)
    env, rep = fit_envelope(ex, 2, np.radians(0.35), n_bins=6)
    assert rep[1]["whole_required"]
    inside = np.asarray(envelope_pass(env, jnp.asarray(shape, F32), jnp.asarray(r, F32)))
    assert inside[:, 1].mean() > 0.97 and inside[:, 0].all()
    cls = jnp.asarray([0, 1, 1], jnp.int32)
    np.testing.assert_array_equal(np.asarray(partial_view(env, cls, jnp.asarray([True, True, False]))),
                                  [False, True, False])  # an occluded robot is a partial view
    # A leg-sized candidate (10 cm) and a table top (0.7 m) are outside the class at every range,
    # including ranges the class was never seen at (0.3 m, 6 m).
    for rr in (0.3, 2.0, 6.0):
        q = jnp.asarray([[0.10, 0.05, 60.0], [0.7, 0.05, 200.0], [0.22, 0.1, 60.0]], F32)
        got = np.asarray(envelope_pass(env, q, jnp.full(3, rr, F32)))
        np.testing.assert_array_equal(got[:, 1], [False, False, True])
    assert rep[1]["width_m"][0] < 0.15 < 0.3 < rep[1]["width_m"][1]


def log_with_motion(period=0.1):
    """A labelled robot held still for 3 scans at each of 20 grid poses (it jumps between them), then
    walking 100 scans at 0.3 m/s while turning at 0.5 rad/s."""
    grid = np.repeat(np.column_stack([np.arange(20) * 0.5, np.zeros(20), np.zeros(20)]), 3, axis=0)
    t = np.arange(100) * period
    walk = np.column_stack([10 + 0.3 * t, np.zeros(100), 0.5 * t])
    poses = np.concatenate([grid, walk])[:, None, :]
    n = len(poses)
    return ScanLog(ranges=np.ones((n, 5), np.float32), stamps=np.arange(n) * period, angle_min=0.0,
                   angle_increment=0.01, truth_classes=np.array(["robot"]), truth_poses=poses)


def test_motion_limits_from_labelled_motion_not_from_grid_jumps():
    lim = motion_limits([log_with_motion()], ("background", "robot"))
    # 0.3 m/s and 0.5 rad/s with the margin (1.25); the grid's 5 m/s jumps are not motion.
    assert lim["robot"]["max_speed"] == pytest.approx(1.25 * 0.3, rel=1e-3)
    assert lim["robot"]["max_turn_rate"] == pytest.approx(1.25 * 0.5, rel=1e-3)
    grid_only = dataclasses.replace(log_with_motion(), truth_poses=log_with_motion().truth_poses[:60],
                                    ranges=np.ones((60, 5), np.float32), stamps=np.arange(60) * 0.1)
    got = motion_limits([grid_only], ("background", "robot"))["robot"]
    assert "max_speed" not in got and "max_turn_rate" not in got and got["speed_windows_s"] == 0


def test_background_log_with_another_step_is_refused(tiny):
    log, site = tiny["train_log"], tiny["site"]
    sick = ScanLog(ranges=np.full((20, 181), 3.0, np.float32), stamps=np.arange(20) * 0.2,
                   angle_min=-np.pi / 2, angle_increment=np.radians(1.0))
    with pytest.raises(InputError, match=r"sick\.log.*angular step"):
        train([log], site, tiny["config"], background=[sick], background_names=["sick.log"])


def test_training_on_a_clean_hall_without_background_succeeds_and_tracks(tiny):
    """A hall with the robot, thin posts and long walls only: no background examples at all. Training
    warns and succeeds; the model finds the posts and tracks the robot walking in the same hall."""
    from gtsjax.drivers.batch import process_log
    from gtsjax.io import to_scans
    from gtsjax.sim import simulate

    log, site = simulate("hall-train", seed=5, n_scans=600)
    # Only the robot and the posts: every return from beyond the field (the walls) removed.
    sx, sy, sth = log.extra["truth_sensor_pose"][0]
    a = sth + log.angles()[None, :]
    hx, hy = sx + log.ranges * np.cos(a), sy + log.ranges * np.sin(a)
    x0, y0, x1, y1 = site.bounds
    far = (hx < x0 - 0.6) | (hx > x1 + 0.6) | (hy < y0 - 0.6) | (hy > y1 + 0.6)
    log = dataclasses.replace(log, ranges=np.where(far, 0.0, log.ranges).astype(np.float32))
    model, report = train([log], site, tiny["config"])
    assert any("background" in w for w in report["warnings"])
    assert report["examples_used"]["background"] == 0
    walk, site2 = simulate("hall-trajectory", seed=6, n_scans=150)
    m = model.with_site(site2)
    _, out = process_log(m, to_scans(walk, m.n_beams))
    assert np.mean(np.asarray(out.degraded)) < 0.2
    truth = walk.truth_poses[:, 0, :2]
    rows = np.asarray(out.track_mask)
    t, j = np.nonzero(rows)
    assert len(np.unique(t)) > 0.7 * walk.n_scans
    err = np.linalg.norm(np.asarray(out.track_pose)[t, j, :2] - truth[t], axis=1)
    assert np.median(err) < 0.05


def without_robot(log):
    """The log with every return within 0.35 m of a labelled robot removed: a background log."""
    sx, sy, sth = log.extra["truth_sensor_pose"][0]
    a = sth + log.angles()[None, :]
    hx, hy = sx + log.ranges * np.cos(a), sy + log.ranges * np.sin(a)
    p = log.truth_poses[:, 0]
    near = np.hypot(hx - np.nan_to_num(p[:, :1], nan=1e9), hy - np.nan_to_num(p[:, 1:2], nan=1e9)) < 0.35
    return dataclasses.replace(log, ranges=np.where(near, 0.0, log.ranges).astype(np.float32), truth_classes=None,
                               truth_poses=None, extra={})


def test_train_cli_takes_several_background_logs_and_refuses_another_step(tmp_path, capsys):
    import json

    from gtsjax.cli import main
    from gtsjax.io import save_log, save_site
    from gtsjax.sim import simulate

    lab, site = simulate("spl-train", seed=11, n_scans=300)
    save_log(lab, tmp_path / "lab.npz")
    save_site(site, tmp_path / "site.json")
    for i, seed in enumerate((3, 4)):
        save_log(without_robot(simulate("spl-legs", seed=seed, n_scans=80)[0]), tmp_path / f"bg{i}.npz")
    small = ["--max-per-class", "60", "--max-background", "120", "--max-mobile", "60", "--max-pose", "80",
             "--inducing", "32", "--restarts", "1", "--no-check"]  # the tracking check is tested apart
    code = main(["train", str(tmp_path / "lab.npz"), "--site", str(tmp_path / "site.json"), "--background",
                 str(tmp_path / "bg0.npz"), str(tmp_path / "bg1.npz"), "--out", str(tmp_path / "m.npz"),
                 "--report", str(tmp_path / "r.json"), *small])
    assert code == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    assert [b["log"] for b in rep["background_logs"]] == [str(tmp_path / "bg0.npz"), str(tmp_path / "bg1.npz")]
    assert all(b["candidates"] > 0 for b in rep["background_logs"])
    assert rep["examples_used"]["background"] == 120 and rep["examples_used"]["robot"] == 60  # the caps as given
    capsys.readouterr()
    sick = ScanLog(ranges=np.full((20, 181), 3.0, np.float32), stamps=np.arange(20) * 0.2,
                   angle_min=-np.pi / 2, angle_increment=np.radians(1.0))
    save_log(sick, tmp_path / "sick.npz")
    code = main(["train", str(tmp_path / "lab.npz"), "--site", str(tmp_path / "site.json"), "--background",
                 str(tmp_path / "sick.npz"), "--out", str(tmp_path / "m2.npz"), *small])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not (tmp_path / "m2.npz").exists()
    assert len(err) == 1 and "sick.npz" in err[0] and "angular step" in err[0], err


def test_a_range_seen_from_few_placements_is_no_narrower_than_the_class():
    """A robot put down at a handful of poses: at 3-3.5 m the class was seen from one placement only (one
    width). The envelope there still holds the widths seen at other ranges."""
    rng = np.random.default_rng(8)
    n = 300
    r = np.concatenate([rng.uniform(1.0, 2.0, n), rng.uniform(3.0, 3.5, 40)])
    widths = np.concatenate([rng.uniform(0.15, 0.3, n), rng.normal(0.2, 0.002, 40)])
    shape = np.column_stack([widths, np.full(n + 40, 0.1), np.full(n + 40, 60.0)])
    env, _ = fit_envelope(examples(np.full(n + 40, 1), shape, r, np.zeros(n + 40, bool)), 2, np.radians(0.35),
                          n_bins=8, min_per_bin=20)
    q = jnp.asarray([[0.16, 0.1, 60.0], [0.29, 0.1, 60.0], [0.6, 0.1, 60.0]], F32)
    got = np.asarray(envelope_pass(env, q, jnp.full(3, 3.2, F32)))[:, 1]
    np.testing.assert_array_equal(got, [True, True, False])  # a table top's width is still out
