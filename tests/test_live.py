"""Live tracking end to end over a real pseudo-terminal: the emulated sensor, pyserial, `gtsjax run`'s
loop, the GTD CSV with the robot tracked; and the raw recording it writes alongside."""

import time
from fractions import Fraction

import numpy as np

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.io import load_log, save_site
from gtsjax.io.gtd import read_gtd
from gtsjax.sensors import URG_04LX
from gtsjax.sim import simulate
from gtsjax.sim.emulator import Faults, SensorEmulator, log_source

from ._utils import read_mcap


def test_run_tracks_the_emulated_robot(tmp_path):
    # spl-eval begins with the robot put down at one point: 1 s away, 3 s at each heading, 1 s away, ...
    log, site = simulate("spl-eval", seed=77)
    save_site(site, tmp_path / "site.json")
    faults = Faults(checksum_p=0.05, seed=3)
    base, served = log_source(log), []

    def source(i):  # which scan of the log the emulator served, and when (host clock, as the rows' stamps)
        served.append((time.time(), i))
        return base(i)

    with SensorEmulator(URG_04LX, source, faults=faults) as emu:
        code = main(
            [
                "run",
                "--port",
                emu.path,
                "--site",
                str(tmp_path / "site.json"),
                "--model",
                str(demo_model_path()),
                "--out",
                str(tmp_path / "gtd.csv"),
                "--record",
                str(tmp_path / "raw.npz"),
                "--frames",
                "60",
                "--quiet",
                "--out-bag",
                str(tmp_path / "gt"),
            ]
        )
        injected = emu.faults.checksum
    assert code == 0
    rows = read_gtd(tmp_path / "gtd.csv")
    # 60 frames: the robot is there in about 40, less 2 each time it is put down, before confirmation.
    assert len(rows) >= 25
    # One track per time the robot is put down: a new id only after a gap (the robot carried away for
    # 1 s). How many put-downs the 60 frames span depends on how long the start took (the emulator
    # scans on from its own start, as a sensor does), so count the gaps rather than assume them.
    stamps = np.array([r.stamp for r in rows])
    ids = [r.track_id for r in rows]
    gaps = int(np.sum(np.diff(stamps) > 0.5))
    assert len(set(ids)) <= gaps + 1, list(zip(stamps.round(1), ids, strict=True))
    changes = np.flatnonzero(np.diff(ids) != 0)
    assert np.all(np.diff(stamps)[changes] > 0.5)  # ...and only across such a gap
    truth = log.truth_poses[:, 0]
    # Each row against the pose of the scan served nearest its stamp (the emulator scans on from its own
    # start, so which points and headings the rows see depends on how long `run` took to start).
    t_served, i_served = np.array(served).T
    nearest = i_served[np.abs(t_served[None, :] - stamps[:, None]).argmin(axis=1)].astype(int)
    true_pose = truth[nearest % len(truth)]
    there = ~np.isnan(true_pose[:, 0])  # a track is still reported for 0.3 s after the robot is lifted
    assert there.sum() >= 20
    xy = np.array([[r.x, r.y] for r in rows])
    # docs/accuracy.md: 1.0 cm position RMSE and a 1.0° heading median on spl-eval. Here one point and the
    # few headings the 60 frames happen to span (how long `run` took to start decides which): medians of
    # 0.7–1.2 cm and 0.8–2.3° measured over seven runs; bounds of 1.5 cm and 3.5°.
    off = np.linalg.norm(xy[there] - true_pose[there, :2], axis=1)
    err = np.degrees(np.abs(np.angle(np.exp(1j * (np.array([r.theta for r in rows])[there] - true_pose[there, 2])))))
    medians = (round(float(np.median(off)), 4), round(float(np.median(err)), 2))
    assert medians[0] < 0.015 and medians[1] < 3.5, (medians, np.round(off, 3), np.round(err, 1))
    raw = load_log(tmp_path / "raw.npz")
    assert raw.n_scans >= len({r.stamp for r in rows}) and raw.n_beams == URG_04LX.n_beams
    assert injected > 0  # frames with bad sums were sent, their good lines kept, and survived
    # --out-bag: every frame processed is a LaserScan, every row an Odometry of its track's frame at its
    # stamp to the nanosecond (read back with the mcap library; the float64 stamp's exact value)
    msgs = read_mcap(next((tmp_path / "gt").glob("*.mcap")))
    assert sum(m.channel.topic == "/scan" for m in msgs) == 60
    poses = sorted(
        (m.log_time_ns, m.ros_msg.child_frame_id, m.ros_msg.pose.pose.position.x)
        for m in msgs
        if m.channel.topic == "/gtsjax/track_odom"
    )
    want = sorted((round(Fraction(r.stamp) * 10**9), f"robot_{r.track_id}", r.x) for r in rows)
    assert [p[:2] for p in poses] == [w[:2] for w in want]
    np.testing.assert_allclose([p[2] for p in poses], [w[2] for w in want], atol=1e-6)  # the CSV's 6 decimals


def test_a_robot_put_down_is_reported_with_its_heading_within_half_a_second(tmp_path):
    """Issue 15's target, live: against the emulated sensor, every time the robot is put down at a new
    pose (spl-eval: a new heading every 4 s, after 1 s away), the rows from 0.5 s after the first scan
    that sees it there carry a heading within 10° of the truth, and for most put-downs within 5°."""
    log, site = simulate("spl-eval", seed=78)
    save_site(site, tmp_path / "site.json")
    base, served = log_source(log), []

    def source(i):
        served.append((time.time(), i))
        return base(i)

    with SensorEmulator(URG_04LX, source) as emu:
        code = main(
            [
                "run",
                "--port",
                emu.path,
                "--site",
                str(tmp_path / "site.json"),
                "--model",
                str(demo_model_path()),
                "--out",
                str(tmp_path / "gtd.csv"),
                "--frames",
                "130",
                "--quiet",
            ]
        )
    assert code == 0
    rows = read_gtd(tmp_path / "gtd.csv")
    stamps = np.array([r.stamp for r in rows])
    theta = np.array([r.theta for r in rows])
    truth = log.truth_poses[:, 0]
    t_served, i_served = (np.array(v) for v in zip(*served, strict=True))
    i_served = i_served.astype(int) % len(truth)
    there = ~np.isnan(truth[i_served, 0])
    # Put-downs: a served scan that sees the robot after one that did not (the first is often missed:
    # the emulator runs before `run` opens the port).
    downs = np.flatnonzero(there[1:] & ~there[:-1]) + 1
    checked, within_5 = 0, 0
    for j in downs:
        t_a, true_theta = t_served[j], truth[i_served[j], 2]
        rest = there[j:]
        gone = np.inf if rest.all() else t_served[j + np.argmin(rest)]  # the robot is lifted again
        sel = (stamps >= t_a + 0.5) & (stamps < min(t_a + 1.0, gone))
        if not sel.any() or t_served[-1] < t_a + 1.0:
            continue
        err = np.degrees(np.abs(np.angle(np.exp(1j * (theta[sel] - true_theta)))))
        # Issue 15's target is 5°; replayed, 92–98 % of spl-eval's put-downs meet it and the worst is
        # 9.6° (docs/accuracy.md): every put-down within 10° (before the outline: 30–73° off for two seconds),
        # most within 5°.
        assert err.max() < 10.0, (round(t_a - t_served[0], 2), np.round(err, 1))
        within_5 += bool(err.max() < 5.0)
        checked += 1
    assert checked >= 2, (len(downs), len(rows))
    assert within_5 >= 0.5 * checked, (within_5, checked)


def test_whole_run_latency_quantiles_follow_numpy():
    """``LiveStats``'s whole-run latency (binned, for ``run --summary``) against ``np.quantile`` of every
    latency: never below it, at most one bin (6 %) above; the recent window keeps its last 2 000."""
    from gtsjax.drivers.live import LiveStats

    rng = np.random.default_rng(0)
    lat = np.concatenate([rng.lognormal(0.0, 0.4, 20_000), rng.uniform(20, 300, 60)])  # ms, with a slow tail
    stats = LiveStats()
    for v in lat:
        stats.add_latency(float(v))
    for q in (0.5, 0.9, 0.99, 0.999):
        exact = np.quantile(lat, q, method="inverted_cdf")
        assert exact <= stats.latency_quantile(q) <= exact * 10 ** (1 / 40) + 1e-12, q
    assert stats.latency_max_ms == lat.max() and stats.latency_quantile(1.0) == lat.max()
    assert len(stats.latencies_ms) == 2000 and stats.latency()[0] == np.median(lat[-2000:])
    assert np.isnan(LiveStats().latency_quantile(0.5))


def test_keep_warm_runs_throwaway_steps_and_changes_no_row(tiny, tmp_path):
    """``run_live`` on a link that delivers a simulated log's frames once per period: with
    ``keep_warm`` a throwaway step runs before most frames are due (counted), and the GTD rows are
    those of the run without it, row for row (the warm-ups are pure: nothing they compute is kept)."""
    import dataclasses

    from gtsjax.drivers.live import run_live, warm_up

    log, site = simulate("spl-crossing", seed=31, n_scans=25)
    model = tiny["model"].with_site(site)
    period = URG_04LX.period  # as the loop expects the frames

    @dataclasses.dataclass
    class Frame:
        stamp: float
        recv_perf: float
        ranges_m: np.ndarray
        intensities: None = None

    class TimedLink:
        """A link whose frame ``i`` arrives ``i`` periods after the first ``get`` that waits (the loop's
        first, which takes the frames queued before it began, finds none)."""

        model = URG_04LX

        def __init__(self):
            self.i, self.t0 = 0, None

        def get(self, timeout=None):
            now = time.perf_counter()
            if self.t0 is None and not timeout:
                return None
            self.t0 = now if self.t0 is None else self.t0
            if self.i >= log.n_scans:
                time.sleep(timeout or 0)
                return None
            due = self.t0 + self.i * period
            if due - now > (timeout or 0):
                time.sleep(timeout or 0)
                return None
            time.sleep(max(due - now, 0.0))
            f = Frame(float(log.stamps[self.i]), time.perf_counter(), log.ranges[self.i])
            self.i += 1
            return f

    compiled = warm_up(model, URG_04LX)
    got = {}
    for keep in (False, True):
        out = tmp_path / f"gtd-{keep}.csv"
        stats = run_live(TimedLink(), model, out, compiled=compiled, max_frames=log.n_scans, keep_warm=keep)
        got[keep] = (read_gtd(out), stats)
    assert got[False][1].warm_ups == 0
    assert got[True][1].warm_ups >= log.n_scans // 2  # most frames found the step warmed just before
    assert got[True][1].frames == got[False][1].frames == log.n_scans
    rows_off, rows_on = got[False][0], got[True][0]
    assert len(rows_off) > 10  # the robots were tracked, so rows were compared
    assert rows_on == rows_off


def test_rows_from_packed_equal_rows_from_output():
    """The live loop's plain-Python rows (one ``tolist()``) equal ``rows_from_output``'s NumPy rows
    exactly, field by field: ids, classes, order, and the headings wrapped the same way."""
    from gtsjax.drivers.live import rows_from_packed
    from gtsjax.io.gtd import rows_from_output, wrap_angle

    rng = np.random.default_rng(5)
    classes = ("robot", "post", "ball")
    for trial in range(200):
        m = int(rng.integers(1, 12))
        packed = np.zeros((m + 1, 10), np.float32)
        packed[:m, 0] = rng.permutation(np.arange(1, 3 * m + 1))[:m]
        packed[:m, 1] = rng.integers(0, len(classes), m)
        packed[:m, 2:5] = rng.normal(0.0, 3.0, (m, 3))
        packed[:m, 4] = np.where(rng.random(m) < 0.2, rng.choice([np.pi, -np.pi, 3 * np.pi, 0.0], m), packed[:m, 4])
        packed[:m, 5:8] = rng.random((m, 3)) * 1e-3
        packed[:m, 8] = rng.normal(0.0, 1e-4, m)
        packed[:m, 9] = rng.random(m) < 0.6
        packed[m, :4] = rng.random(4)
        got = rows_from_packed(12.5 + trial, packed, classes)
        t = packed[:-1]
        want = rows_from_output(
            12.5 + trial,
            t[:, 0].astype(np.int64),
            t[:, 1].astype(np.int64),
            t[:, 2:5],
            t[:, 5:8],
            t[:, 9] > 0.5,
            classes,
            t[:, 8],
        )
        assert got == want
        assert rows_from_packed(12.5 + trial, packed.tolist(), classes) == want
    from gtsjax.core.geometry import wrap

    a = np.concatenate([np.linspace(-20.0, 20.0, 4001), [np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 0.0, -0.0, 1e-300]])
    assert [wrap_angle(float(x)) for x in a] == wrap(a).tolist()


def test_packed_rows_carry_the_tag_identity_as_batch_replay_names_it():
    """A model that reads tags: the live rows' ``robot`` (the packed table's robot column, named with the
    model's ``tag_names``) equals batch replay's naming (:meth:`Sink.name_rows` of the rows from the
    output arrays, by track id), and a track that reports no identity (-1) stays unnamed."""
    from gtsjax.drivers.live import rows_from_packed
    from gtsjax.drivers.sink import Sink
    from gtsjax.io.gtd import COLUMN, PACKED, rows_from_output

    rng = np.random.default_rng(6)
    classes, names = ("robot", "post"), ("nao1", "nao2", "nao3")
    sink = Sink.__new__(Sink)
    sink.tag_names = names
    for trial in range(100):
        m = int(rng.integers(1, 10))
        packed = np.zeros((m + 1, len(PACKED)), np.float32)
        packed[:m, COLUMN["track_id"]] = rng.permutation(np.arange(1, 3 * m + 1))[:m]
        packed[:m, COLUMN["class"]] = rng.integers(0, len(classes), m)
        packed[:m, COLUMN["x"]:COLUMN["theta"] + 1] = rng.normal(0.0, 3.0, (m, 3))
        packed[:m, COLUMN["reported"]] = rng.random(m) < 0.7
        packed[:m, COLUMN["robot"]] = rng.integers(-1, len(names), m)
        t = packed[:-1]
        got = rows_from_packed(3.0 + trial, packed, classes, names)
        plain = rows_from_output(3.0 + trial, t[:, 0].astype(np.int64), t[:, 1].astype(np.int64), t[:, 2:5],
                                 t[:, 5:8], t[:, COLUMN["reported"]] > 0.5, classes, t[:, 8])
        want = sink.name_rows(plain, t[:, 0].astype(np.int64), t[:, COLUMN["robot"]].astype(np.int64))
        assert got == want
        for row in got:  # and directly: the slot's identity by name, or nothing
            j = int(t[t[:, 0] == row.track_id][0, COLUMN["robot"]])
            assert row.robot == (names[j] if j >= 0 else "")
        assert rows_from_packed(3.0 + trial, packed, classes) == plain  # a model without tags: no names


def test_decoder_sample_is_a_block_of_the_links_kind():
    """The warm-up's sample data block decodes (by the link's own decoder) to a frame of the link's
    command: its beams, intensities exactly when the link streams ``ME``; a link that does not say
    what it streams gets none."""
    from types import SimpleNamespace

    from gtsjax.drivers.live import decoder_sample
    from gtsjax.io import scip
    from gtsjax.sensors import URG_04LX, UTM_30LX

    for sensor, build, inten in (
        (UTM_30LX, scip.me_command, True),
        (UTM_30LX, scip.md_command, False),
        (URG_04LX, scip.md_command, False),
    ):
        link = SimpleNamespace(model=sensor, command=build(sensor.amin, sensor.amax, 1, 0, 0))
        (frame,) = scip.StreamDecoder().feed(decoder_sample(link))
        assert isinstance(frame, scip.ScanFrame) and frame.n_values == sensor.n_beams
        assert (frame.intensities is not None) == inten
    assert decoder_sample(SimpleNamespace(model=URG_04LX)) is None
    assert decoder_sample(SimpleNamespace(model=URG_04LX, command=b"QT\n")) is None
