"""``run --smooth-lag S`` (``gtsjax.drivers.fixed_lag``): each scan's row written ``L`` scans late with
its pose smoothed over the scans up to then. Against second implementations: a NumPy RTS loop over
the filtered states up to ``t + L`` (``tests/test_smooth.py``'s), and the fixed-interval smoother
over a real forward pass's states up to ``t + L`` with the replay's cuts and resets, each evaluated
at ``t``; end to end, ``gtsjax run`` against the emulated sensor writes both CSVs, the same rows, the
smoothed ones no further from the truth; and a bad lag is one line, exit 2."""

import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.core.geometry import wrap
from gtsjax.core.smooth import smooth_tracks
from gtsjax.drivers.batch import process_log
from gtsjax.drivers.fixed_lag import FixedLag, lag_scans, pack_filtered, smoothed_path
from gtsjax.drivers.live import pack_tracks, rows_from_packed
from gtsjax.drivers.several import site_poses
from gtsjax.drivers.smoothing import cuts, resets
from gtsjax.io import save_site
from gtsjax.io.gtd import COLUMN, PACKED, TrackRow, read_gtd
from gtsjax.io.logs import to_scans
from gtsjax.io.modelfile import load_model
from gtsjax.sensors import URG_04LX
from gtsjax.sim import simulate
from gtsjax.sim.emulator import SensorEmulator, log_source
from tests._utils import offset_and_floor, without_offset_and_floor
from tests.test_several import _Frame, _Link, match  # noqa: F401  (the fixture: two lasers on the match's field)
from tests.test_smooth import _filter, _params, _rts_numpy, _simulate


class _Rows:
    """A writer that keeps what it is given, scan by scan."""

    def __init__(self):
        self.scans: list[list[TrackRow]] = []

    def write(self, rows):
        self.scans.append(list(rows))

    def close(self):
        pass


def _packed(mean, cov, main, ids, live, reported):
    """One scan's packed table as the live step with ``filtered`` returns it, built on the host:
    ``[M + 1, PACKED + filtered]``, the rows' columns from the filtered means and covariances."""
    M = mean.shape[0]
    block = np.asarray(pack_filtered(_Tracker(mean, cov, main)))
    t = np.zeros((M + 1, len(PACKED) + block.shape[1]), np.float32)
    c = COLUMN
    t[:M, c["track_id"]], t[:M, c["live"]], t[:M, c["reported"]] = ids, live, reported
    t[:M, c["x"]], t[:M, c["y"]], t[:M, c["theta"]] = mean[:, 0], mean[:, 1], mean[:, 2]
    t[:M, c["var_x"]], t[:M, c["var_y"]], t[:M, c["var_theta"]] = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    t[:M, c["cov_xy"]] = cov[:, 0, 1]
    t[:M, len(PACKED):] = block
    return t


class _Tracker:
    def __init__(self, mean, cov, main):
        self.mean, self.cov, self.main = jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(main)


def _row_values(r):
    return [r.x, r.y, r.theta, r.var_x, r.var_y, r.var_theta, r.cov_xy]


@pytest.mark.parametrize("lag", [1, 5])
def test_rows_equal_a_numpy_rts_loop_over_the_scans_up_to_t_plus_lag(lag):
    """One track's filtered states (a NumPy EKF, headings crossing ±π): the row of scan ``t`` is the
    NumPy RTS loop's over scans ``0 … t + L`` at ``t`` (``0 … T − 1`` for the rows flushed at the end)."""
    params = _params(True)
    T = 40
    _, dt, z = _simulate(T, params, seed=4)
    m, P = _filter(z, dt, params)
    rows_out = _Rows()
    lagger = FixedLag(params, lag, 1, None, writer=rows_out)
    for t in range(T):
        table = _packed(m[t:t + 1].astype(np.float32), P[t:t + 1].astype(np.float32), np.zeros(1), [7], [1], [1])
        rows = [TrackRow(float(t), 7, "robot", 0, 0, 0, 0, 0, 0)]
        lagger.push(table, rows, 0.0 if t == 0 else float(dt[t]))
        assert len(rows_out.scans) == max(0, t + 1 - lag)  # the row of t − L, once t is in
    lagger.close()
    assert [s[0].stamp for s in rows_out.scans] == [float(t) for t in range(T)]
    moved = max(abs(s[0].x - m[t, 0]) for t, s in enumerate(rows_out.scans[:-1]))
    assert moved > 1e-3  # the rows are smoothed, not the filtered states passed through
    m32, P32 = m.astype(np.float32).astype(np.float64), P.astype(np.float32).astype(np.float64)
    for t, scan in enumerate(rows_out.scans):
        end = min(t + lag, T - 1) + 1
        ms, Ps = _rts_numpy(m32[:end], P32[:end], dt[:end], params)
        got = np.array(_row_values(scan[0]))
        want = np.array([*ms[t, :3], *np.diag(Ps[t])[:3], Ps[t, 0, 1]])
        d = got - want
        d[2] = wrap(d[2])
        np.testing.assert_allclose(d[:3], 0, atol=2e-5, err_msg=f"scan {t}")
        np.testing.assert_allclose(got[3:], want[3:], rtol=2e-4, atol=1e-9, err_msg=f"scan {t}")


def test_lagged_rows_have_the_class_pose_offset_taken_off_and_the_floor_added():
    """A tracker with a class's mean error to take off (``pose_offset``) and a variance floor
    (``var_floor``): each lagged row is the row smoothed without them, moved back by the offset along
    the smoothed pose's own axes and with the floor added to its variances, as the forward rows and
    ``replay --smooth``'s are (``TrackerParams.off``, ``TrackerParams.widened``)."""

    log, site = simulate("spl-crossing", seed=2003, n_scans=40)
    model = without_offset_and_floor(load_model(demo_model_path()).with_site(site))
    scans = to_scans(log, model.n_beams)
    _, (out, filt) = process_log(model, scans, filtered=True)
    offset, floor, params = offset_and_floor(model)
    T, M = out.track_live.shape
    plain_rows, shifted_rows = _Rows(), _Rows()
    plain, shifted = FixedLag(model.tracker, 3, M, None, writer=plain_rows), FixedLag(params, 3, M, None, writer=shifted_rows)
    dt = np.asarray(scans.dt, np.float32)
    for t in range(T):
        packed = np.asarray(pack_tracks(jax.tree.map(lambda a, t=t: a[t], out)))
        block = np.asarray(pack_filtered(_Tracker(filt.mean[t], filt.cov[t], filt.main[t])))
        table = np.concatenate([packed, np.pad(block, ((0, 1), (0, 0)))], axis=1)
        rows = rows_from_packed(float(log.stamps[t]), packed, model.classes)
        plain.push(table, rows, float(dt[t]))
        shifted.push(table, rows, float(dt[t]))
    plain.close()
    shifted.close()
    a = [r for scan in plain_rows.scans for r in scan]
    b = [r for scan in shifted_rows.scans for r in scan]
    assert len(a) > 20 and [(r.stamp, r.track_id) for r in a] == [(r.stamp, r.track_id) for r in b]
    k = np.asarray([model.class_index(r.cls) for r in a])
    want = np.asarray(params.off(jnp.asarray(k), jnp.asarray([[r.x, r.y, r.theta] for r in a], jnp.float32)))
    np.testing.assert_allclose([[r.x, r.y] for r in b], want[:, :2], atol=2e-6)
    np.testing.assert_allclose(wrap(np.asarray([r.theta for r in b]) - want[:, 2]), 0.0, atol=2e-6)
    added = floor[k][:, [0, 0, 1]]
    np.testing.assert_allclose([[r.var_x, r.var_y, r.var_theta] for r in b],
                               np.asarray([[r.var_x, r.var_y, r.var_theta] for r in a]) + added, rtol=1e-5)
    assert [r.cov_xy for r in a] == [r.cov_xy for r in b]


def test_rows_equal_the_fixed_interval_smoother_of_a_real_forward_pass():
    """Three robots crossing, the shipped model's forward pass (the live step's computation, each
    scan's filtered state kept): every reported row of scan ``t`` smoothed over ``t … t + L`` equals
    ``smooth_tracks`` (the associative form, a program of its own) over all scans up to ``t + L``
    with the replay's cuts and resets, evaluated at ``t``; and the rows are the live rows."""
    log, site = simulate("spl-crossing", seed=2003, n_scans=90)
    # the rows as the filter gives them (the shipped model's pose bias off: the smoother's raw states)
    model = without_offset_and_floor(load_model(demo_model_path()).with_site(site))
    scans = to_scans(log, model.n_beams)
    _, (out, filt) = process_log(model, scans, filtered=True)
    T, M = out.track_live.shape
    lag = 4
    rows_out = _Rows()
    lagger = FixedLag(model.tracker, lag, M, None, writer=rows_out)
    dt = np.asarray(scans.dt, np.float32)
    live_rows = []
    for t in range(T):
        packed = np.asarray(pack_tracks(jax.tree.map(lambda a, t=t: a[t], out)))
        block = np.asarray(pack_filtered(_Tracker(filt.mean[t], filt.cov[t], filt.main[t])))
        table = np.concatenate([packed, np.pad(block, ((0, 1), (0, 0)))], axis=1)
        rows = rows_from_packed(float(log.stamps[t]), packed, model.classes)
        live_rows.append(rows)
        lagger.push(table, rows, float(dt[t]))
    lagger.close()
    with_rows = [r for r in live_rows if r]
    assert len(with_rows) > 40 and len({r.track_id for rows in live_rows for r in rows}) >= 3
    assert [[(r.stamp, r.track_id, r.cls) for r in s] for s in rows_out.scans] == \
        [[(r.stamp, r.track_id, r.cls) for r in s] for s in with_rows]

    live = np.asarray(out.track_live, bool)
    ids = np.asarray(out.track_id)
    mean, cov, main = np.asarray(filt.mean, np.float32), np.asarray(filt.cov, np.float32), np.asarray(filt.main)
    cut = cuts(live, ids, mean[..., 2])
    extra = resets(live, ids, cov, main, model.tracker)
    slot_of = [{int(ids[t, k]): k for k in np.flatnonzero(np.asarray(out.track_mask[t]))} for t in range(T)]
    emitted = iter(rows_out.scans)
    checked = 0
    for t in range(T):
        if not live_rows[t]:
            continue
        scan = next(emitted)
        upto = np.arange(T) <= min(t + lag, T - 1)
        ms, ps = smooth_tracks(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(dt), jnp.asarray(live & upto[:, None]),
                               model.tracker, parallel=True, cut=jnp.asarray(cut), extra=jnp.asarray(extra))
        ms, ps = np.asarray(ms[t], np.float64), np.asarray(ps[t], np.float64)
        for r in scan:
            k = slot_of[t][r.track_id]
            want = np.array([*ms[k, :3], *np.diag(ps[k])[:3], ps[k, 0, 1]])
            got = np.array(_row_values(r))
            d = got - want
            d[2] = wrap(d[2])
            np.testing.assert_allclose(d[:3], 0, atol=5e-5, err_msg=f"scan {t}, track {r.track_id}")
            scale = np.abs(want[3:6]).max()
            np.testing.assert_allclose(got[3:] / scale, want[3:] / scale, atol=5e-4, err_msg=f"scan {t}")
            checked += 1
    assert checked > 100


def test_lag_in_scans_and_the_smoothed_csv_beside_the_live_one(tmp_path):
    assert lag_scans(0.5, 10.0) == 5 and lag_scans(1.0, 40.0) == 40 and lag_scans(0.01, 10.0) == 1
    assert lag_scans(0.04, 10.0) == 1 and lag_scans(0.26, 10.0) == 3
    assert smoothed_path(tmp_path / "gtd.csv") == tmp_path / "gtd-smoothed.csv"
    assert smoothed_path(tmp_path / "run.1.csv") == tmp_path / "run.1-smoothed.csv"


def _errors(rows, served, truth):
    """Each row's position and heading error against the true pose of the scan served nearest its stamp
    (the emulator's host clock, as the rows' stamps), where the robot is there."""
    t_served, i_served = np.array(served).T
    stamps = np.array([r.stamp for r in rows])
    nearest = i_served[np.abs(t_served[None, :] - stamps[:, None]).argmin(axis=1)].astype(int)
    true_pose = truth[nearest % len(truth)]
    there = ~np.isnan(true_pose[:, 0])
    xy = np.array([[r.x, r.y] for r in rows])
    pos = np.linalg.norm(xy[there] - true_pose[there, :2], axis=1)
    head = np.abs(wrap(np.array([r.theta for r in rows])[there] - true_pose[there, 2]))
    return pos, head


def test_run_writes_the_smoothed_csv_with_the_same_rows_no_further_from_the_truth(tmp_path):
    """``gtsjax run --smooth-lag 0.5`` against the emulated URG-04LX (10 Hz: 5 scans late) with a robot
    walking: both CSVs, the smoothed one every live row (the last 5 scans' flushed at the end), its
    positions no further from the truth than the live ones but for a small margin."""
    log, site = simulate("spl-trajectory", seed=2011)
    save_site(site, tmp_path / "site.json")
    base, served = log_source(log), []

    def source(i):
        served.append((time.time(), i))
        return base(i)

    with SensorEmulator(URG_04LX, source) as emu:
        code = main(["run", "--port", emu.path, "--site", str(tmp_path / "site.json"), "--model", str(demo_model_path()),
                     "--out", str(tmp_path / "gtd.csv"), "--frames", "80", "--quiet", "--smooth-lag", "0.5",
                     "--summary", str(tmp_path / "run.json")])
    assert code == 0
    live, smoothed = read_gtd(tmp_path / "gtd.csv"), read_gtd(tmp_path / "gtd-smoothed.csv")
    assert len(live) >= 40
    assert [(r.stamp, r.track_id, r.cls) for r in smoothed] == [(r.stamp, r.track_id, r.cls) for r in live]
    assert (tmp_path / "gtd.csv").read_text().splitlines()[0] == (tmp_path / "gtd-smoothed.csv").read_text().splitlines()[0]
    truth = log.truth_poses[:, 0]
    pl, hl = _errors(live, served, truth)
    ps, hs = _errors(smoothed, served, truth)
    assert pl.size >= 30
    rmse = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rmse(ps) <= rmse(pl) + 0.002, (rmse(ps), rmse(pl))  # 2 mm of margin
    assert rmse(hs) <= rmse(hl) + np.radians(0.5), (np.degrees(rmse(hs)), np.degrees(rmse(hl)))
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["smoothing"]["lag_scans"] == 5 and doc["smoothing"]["rows"] == len(smoothed)


@pytest.mark.parametrize("value", ["0", "-0.5", "abc", "nan", "inf"])
def test_a_bad_lag_is_one_line_and_exit_2(value, tmp_path, capsys):
    site = tmp_path / "site.json"
    _, s = simulate("spl-eval", seed=1, n_scans=2)
    save_site(s, site)
    code = main(["run", "--port", str(tmp_path / "nothing"), "--site", str(site), "--model", str(demo_model_path()),
                 "--out", str(tmp_path / "gtd.csv"), "--smooth-lag", value])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--smooth-lag" in err[0], err
    assert not (tmp_path / "gtd.csv").exists() and not (tmp_path / "gtd-smoothed.csv").exists()


def test_several_lasers_smoothed_rows_are_the_live_rows_late(match, tmp_path):  # noqa: F811
    """Two lasers' frames merged into one track table (``run_live_several``), 10 Hz each: the lag counts
    the merged scans (0.3 s: 6), and the smoothed CSV holds every live row, smoothed near it."""
    from gtsjax.drivers.live_several import run_live_several, warm_up_several

    logs, site, model = match
    poses = site_poses(site, ["north", "south"])
    compiled = warm_up_several(model, URG_04LX, poses, filtered=True)
    n = 30
    t0, wall0 = time.monotonic() + 0.05, time.time() + 0.05
    links = {}
    for name in ("north", "south"):
        log = logs[name]
        since = log.stamps[:n] - logs["north"].stamps[0]
        frames = [_Frame(np.where(log.valid()[i], log.ranges[i], 0.0).astype(np.float32), wall0 + since[i])
                  for i in range(n)]
        links[name] = _Link(URG_04LX, frames, [t0 + t for t in since])
    out = tmp_path / "gtd.csv"
    stats, _, _ = run_live_several(links, model, poses, out, compiled=compiled, max_frames=2 * n, duration=30.0,
                                   smooth_lag=0.3)
    assert stats.frames == 2 * n and stats.smoothing.lag == 6
    live, smoothed = read_gtd(out), read_gtd(tmp_path / "gtd-smoothed.csv")
    assert len(live) > 20 and stats.smoothing.rows == len(live)
    assert [(r.stamp, r.track_id, r.cls) for r in smoothed] == [(r.stamp, r.track_id, r.cls) for r in live]
    moved = np.array([np.hypot(a.x - b.x, a.y - b.y) for a, b in zip(live, smoothed, strict=True)])
    assert moved.max() < 0.05 and moved.max() > 0, moved.max()
