"""``replay --smooth`` (``gtsjax.drivers.smoothing``): the forward pass's rows, the same stamps, ids and
classes, with each track's poses smoothed over its whole life; closer to the simulation's truth than
the forward rows, with one laser and with two; and where the forward pass reset part of a track's
state outside its Kalman filter, the smoother told so."""

import math

import numpy as np

from gtsjax.core.geometry import wrap
from gtsjax.drivers.smoothing import cuts, resets
from gtsjax.io import load_log, save_log, save_site
from gtsjax.io.gtd import read_gtd
from tests._utils import cli, offset_and_floor
from tests.test_cli_paths import match_model  # noqa: F401  (the fixture: a small model of the match's field)


class _Params:
    omega_var0 = 1.0


def test_cuts_where_a_life_begins_or_the_heading_switches_side():
    live = np.array([[1, 1], [1, 1], [1, 1], [0, 1], [1, 1]], bool)
    ids = np.array([[3, 5], [3, 5], [4, 5], [-1, 5], [6, 5]])
    heading = np.array([[0.0, 1.0], [0.05, 1.1], [0.1, 1.1 + math.pi], [0.0, 1.2 + math.pi], [0.0, 1.25 + math.pi]])
    got = cuts(live, ids, heading)
    # Slot 0: id 3 → 4 in consecutive scans (a cut); after an empty scan the new life needs none.
    # Slot 1: the heading jumped half a turn at scan 2.
    assert got.tolist() == [[False, False], [False, False], [True, True], [False, False], [False, False]]


def test_resets_where_a_turn_rate_was_forgotten_or_the_main_heading_changed():
    T, M = 5, 2
    live = np.ones((T, M), bool)
    ids = np.zeros((T, M), int) + np.arange(M)
    cov = np.tile(np.eye(6) * 0.01, (T, M, 1, 1))
    cov[..., 2, 5] = cov[..., 5, 2] = 0.001
    cov[2, 0, 5, 5], cov[2, 0, 2, 5], cov[2, 0, 5, 2] = 1.0, 0.0, 0.0  # forgotten at scan 2 (as g_track does)
    main = np.zeros((T, M), int)
    main[3:, 1] = 1  # slot 1's heading became another hypothesis at scan 3
    extra = resets(live, ids, cov, main, _Params())
    assert extra.shape == (T, M, 6)
    assert np.flatnonzero(extra[:, 0, 5]).tolist() == [2] and not extra[:, 0, 2].any()
    assert np.flatnonzero(extra[:, 1, 5]).tolist() == [3] and np.flatnonzero(extra[:, 1, 2]).tolist() == [3]
    assert not extra[..., :2].any() and not extra[..., 3:5].any()


def _errors(rows, stamps, truth):
    """Each row's position and heading error against the nearest true robot at its stamp."""
    at = {float(s): i for i, s in enumerate(stamps)}
    pos, head = [], []
    for r in rows:
        tr = truth[at[r.stamp]]
        d = np.hypot(tr[:, 0] - r.x, tr[:, 1] - r.y)
        k = int(np.nanargmin(d))
        pos.append(d[k])
        head.append(abs(wrap(r.theta - tr[k, 2])))
    return np.array(pos), np.array(head)


def test_replay_smooth_keeps_the_rows_and_comes_closer_to_the_truth(tiny, tmp_path, capsys):
    d = tmp_path
    assert cli(capsys, "simulate", "spl-trajectory", "--seed", 1007, "--scans", 300, "--out", d / "w.npz", "--site",
               d / "s.json").returncode == 0
    for out, extra in (("f.csv", []), ("s.csv", ["--smooth"])):
        r = cli(capsys, "replay", d / "w.npz", "--site", d / "s.json", "--model", tiny["path"], "--out", d / out,
                *extra)
        assert r.returncode == 0, r.stderr
    fwd, sm = read_gtd(d / "f.csv"), read_gtd(d / "s.csv")
    assert len(fwd) > 200 and [(r.stamp, r.track_id, r.cls) for r in fwd] == [(r.stamp, r.track_id, r.cls) for r in sm]
    log = load_log(d / "w.npz")
    pf, hf = _errors(fwd, log.stamps, log.truth_poses)
    ps, hs = _errors(sm, log.stamps, log.truth_poses)
    rmse = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rmse(ps) < 0.9 * rmse(pf), (rmse(ps), rmse(pf))
    assert rmse(hs) < rmse(hf), (rmse(hs), rmse(hf))
    # Variances are the smoother's: no larger than the filter's, row by row.
    assert all(s.var_x <= f.var_x * (1 + 1e-4) + 1e-9 and s.var_theta <= f.var_theta * (1 + 1e-4) + 1e-9
               for f, s in zip(fwd, sm, strict=True))


def test_replay_smooth_stopped_before_its_rows_leaves_no_csv(tiny, tmp_path, capsys, monkeypatch):
    """Ctrl-C while ``replay --smooth`` smooths (after the forward pass, before any row is written):
    exit 130 and no CSV, where a header with no rows was left; the forward replay's CSV of the same
    log is made as before."""
    import gtsjax.drivers.smoothing as smoothing

    d = tmp_path
    assert cli(capsys, "simulate", "spl-trajectory", "--seed", 1008, "--scans", 40, "--out", d / "w.npz", "--site",
               d / "s.json").returncode == 0

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(smoothing, "smooth_output", stopped)
    r = cli(capsys, "replay", d / "w.npz", "--site", d / "s.json", "--model", tiny["path"], "--out", d / "s.csv",
            "--smooth")
    assert r.returncode == 130 and r.stderr.strip().splitlines()[-1] == "gtsjax: interrupted", r.stderr
    assert not (d / "s.csv").exists()
    r = cli(capsys, "replay", d / "w.npz", "--site", d / "s.json", "--model", tiny["path"], "--out", d / "f.csv")
    assert r.returncode == 0 and len(read_gtd(d / "f.csv")) > 0, r.stderr


def test_smooth_memory_estimate_covers_what_the_forward_pass_keeps(tiny):
    """The estimate ``replay --smooth`` is refused by is at least what the forward pass keeps a scan
    for the smoother (its outputs and filtered states, summed array by array: a second count), and
    within the multiple the smoother's own arrays add."""
    import jax

    from gtsjax.drivers.batch import process_log
    from gtsjax.drivers.smoothing import SMOOTH_BYTES_PER_STATE_BYTE, memory_needed
    from gtsjax.io.logs import to_scans

    model = tiny["model"].with_site(tiny["site"])
    n = 24
    scans = to_scans(tiny["train_log"].slice(0, n), model.n_beams)
    # replay --smooth's program (its chunk, vectorised, with filtered states): compiled once for the module
    _, kept = process_log(model, scans, chunk=256, vectorise=True, filtered=True)
    kept_bytes = sum(a.nbytes for a in jax.tree.leaves(kept))
    need = memory_needed(model, n)
    assert kept_bytes <= need <= SMOOTH_BYTES_PER_STATE_BYTE * kept_bytes, (kept_bytes, need)
    assert memory_needed(model, 10 * n) == 10 * need


def test_replay_smooth_refused_where_its_states_would_not_fit(tiny, tmp_path, capsys, monkeypatch):
    """Where the machine has less memory available than smoothing the log needs: refused in one line
    before any work, naming --smooth, what it needs and what to do; nothing written."""
    import gtsjax.cli._checks as checks
    from gtsjax.drivers.smoothing import memory_needed

    d = tmp_path
    assert cli(capsys, "simulate", "spl-trajectory", "--seed", 1009, "--scans", 40, "--out", d / "w.npz", "--site",
               d / "s.json").returncode == 0
    need = memory_needed(tiny["model"].with_site(tiny["site"]), 40)
    monkeypatch.setattr(checks, "available_memory", lambda: need // 2)
    r = cli(capsys, "replay", d / "w.npz", "--site", d / "s.json", "--model", tiny["path"], "--out", d / "s.csv",
            "--smooth")
    assert r.returncode == 2, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "--smooth" in line and "40 scans" in line and "without --smooth" in line, line
    assert not (d / "s.csv").exists()
    monkeypatch.setattr(checks, "available_memory", lambda: None)  # unknown: never refused
    checks.check_memory("--smooth", 1e15, "smoothing", "no fix")


def test_replay_smooth_with_two_lasers(match_model, tmp_path, capsys):  # noqa: F811
    """Two lasers' detections smoothed together (a model of the match's field, trained as
    docs/several-lasers.md trains one, small): the same rows, positions closer to the truth."""
    from gtsjax.sim.match import simulate_match

    logs, site = simulate_match("spl-match-2", seed=17, n_robots=3, seconds=8.0, referee=False)
    for name, log in logs.items():
        save_log(log, tmp_path / f"m-{name}.npz")
    save_site(site, tmp_path / "site.json")
    args = ["--log", f"north={tmp_path / 'm-north.npz'}", "--log", f"south={tmp_path / 'm-south.npz'}", "--site",
            tmp_path / "site.json", "--model", match_model]
    outs = {}
    for key, extra in (("f", []), ("s", ["--smooth"])):
        r = cli(capsys, "replay", *args, "--out", tmp_path / f"{key}.csv", *extra)
        assert r.returncode == 0, r.stderr
        outs[key] = read_gtd(tmp_path / f"{key}.csv")
    assert len(outs["f"]) > 100
    assert [(r.stamp, r.track_id) for r in outs["f"]] == [(r.stamp, r.track_id) for r in outs["s"]]
    stamps = np.concatenate([lg.stamps for lg in logs.values()])
    truth = np.concatenate([lg.truth_poses for lg in logs.values()])
    pf, _ = _errors(outs["f"], stamps, truth)
    ps, _ = _errors(outs["s"], stamps, truth)
    rmse = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rmse(ps) < 0.95 * rmse(pf), (rmse(ps), rmse(pf))


def test_smoothed_rows_have_the_class_pose_offset_taken_off_and_the_floor_added(tiny):
    """A tracker with a class's mean error to take off (``pose_offset``) and a variance floor
    (``var_floor``): the smoother's rows are the same smoothing (the filtered states carry neither)
    with the offset taken off each live slot's smoothed pose along its own axes and the floor added to
    its smoothed variances, as the forward rows have them."""
    import jax.numpy as jnp

    from gtsjax.drivers.batch import process_log
    from gtsjax.drivers.smoothing import smooth_output
    from gtsjax.io.logs import to_scans

    model = tiny["model"].with_site(tiny["site"])
    log = tiny["train_log"].slice(0, 24)
    scans = to_scans(log, model.n_beams)
    _, (out, filtered) = process_log(model, scans, chunk=256, vectorise=True, filtered=True)
    offset, floor, params = offset_and_floor(model)
    plain = smooth_output(out, filtered, log.stamps, model.tracker)
    shifted = smooth_output(out, filtered, log.stamps, params)
    live = np.asarray(out.track_live, bool)
    assert live.sum() > 10
    want = np.asarray(params.off(jnp.asarray(np.asarray(out.track_class)), jnp.asarray(np.asarray(plain.track_pose))))
    np.testing.assert_allclose(np.asarray(shifted.track_pose)[live], want[live], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(shifted.track_pose)[~live], np.asarray(out.track_pose)[~live])
    assert np.abs(np.asarray(shifted.track_pose)[live] - np.asarray(plain.track_pose)[live]).max() > 0.005
    added = floor[np.asarray(out.track_class)[live]][:, [0, 0, 1]]
    np.testing.assert_allclose(np.asarray(shifted.track_var)[live], np.asarray(plain.track_var)[live] + added, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(shifted.track_var)[~live], np.asarray(out.track_var)[~live])
