"""The whole pipeline: one step traced once per model shape, replay and live equal to stepping, model files,
and the replay command's contract (CSV per spec; bad input is one line and exit 2)."""

import csv
import dataclasses

import equinox as eqx
import jax
import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.cli import main
from gtsjax.core.pipeline import init_state, step
from gtsjax.drivers.batch import process_log
from gtsjax.io import save_log, save_site, to_scans
from gtsjax.io.gtd import HEADER
from gtsjax.io.logs import ScanLog, fit_to_model
from gtsjax.io.modelfile import load_model, read_header
from gtsjax.sensors import UTM_30LX
from gtsjax.sim import simulate
from tests._utils import cli


def test_training_report_is_complete(tiny):
    """The small model's held-out figures, against what guessing gives and what docs/speed.md reports for
    the shipped model (98.9 % accuracy, 1.8 cm; this one sees 60 examples a class and 80 poses):
    accuracy ≥ 95 %, well above always answering the commonest class; every class found in ≥ 85 % of its
    examples; position RMSE ≤ 5 cm (the README's target for a moving robot); a heading median under
    45°, where a guessed heading's is 90°."""
    rep = tiny["report"]
    assert rep["classes"] == ["background", "post", "robot"]
    assert all(rep["examples_used"][c] > 0 for c in rep["classes"])
    held = rep["heldout"]
    per_class = held["per_class"]
    assert sum(per_class[c]["n"] for c in rep["classes"]) == held["n"] > 100
    commonest = max(per_class[c]["n"] for c in rep["classes"]) / held["n"]
    assert held["accuracy"] >= max(0.95, commonest + 0.5 * (1 - commonest)), held
    assert all(per_class[c]["recall"] >= 0.85 for c in rep["classes"]), per_class
    pose = held["pose"]["robot"]
    assert pose["n"] > 20 and pose["rmse_xy_m"] <= 0.05 and pose["median_theta_deg"] < 45.0, pose


def test_model_file_round_trip(tiny):
    loaded = load_model(tiny["path"])
    a, b = eqx.partition(tiny["model"], eqx.is_array), eqx.partition(loaded, eqx.is_array)
    assert jax.tree.structure(a[0]) == jax.tree.structure(b[0])
    for x, y in zip(jax.tree.leaves(a[0]), jax.tree.leaves(b[0]), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        assert x.dtype == y.dtype
    assert read_header(tiny["path"])["sensor_model"] == "URG-04LX"


def test_bad_model_files_are_one_line(tiny, tmp_path):
    cases = {}
    p = tmp_path / "text.npz"
    p.write_text("not a model")
    cases[p] = "not a gtsjax model file"
    log, _ = simulate("spl-eval", n_scans=3)
    p = tmp_path / "log.npz"
    save_log(log, p)
    cases[p] = "no model header"
    raw = tiny["path"].read_bytes()
    p = tmp_path / "cut.npz"
    p.write_bytes(raw[: len(raw) // 3])
    cases[p] = "model file"
    for path, match in cases.items():
        with pytest.raises(InputError) as exc:
            load_model(path)
        assert match in str(exc.value) and str(path) in str(exc.value) and "\n" not in str(exc.value)
    utm = ScanLog(ranges=np.ones((1, UTM_30LX.n_beams), np.float32), stamps=np.zeros(1),
                  angle_min=UTM_30LX.angle_min, angle_increment=UTM_30LX.angle_increment, sensor_model="UTM-30LX")
    with pytest.raises(InputError, match=r"^utm\.npz: scans from a UTM-30LX, but the model was trained for sensor URG-04LX$"):
        fit_to_model(utm, load_model(tiny["path"]), "utm.npz")


def test_step_traced_once_per_model_shape_and_replay_equals_stepping(tiny):
    """The pure ``step`` under a caller's jit is traced once for every scan and for a retuned model of
    the same shape; batch replay's jitted chunk compiles once for both models and both chunk fills,
    and gives the tracks of stepping scan by scan (the same computation, compiled apart: ids and
    masks equal, poses to float32 rounding); so does its vectorised form (perception ``vmap``ped over
    groups of scans, one size bucket per group, then the updates in turn)."""
    from gtsjax.drivers.batch import run_chunk

    log, site = simulate("spl-crossing", seed=21, n_scans=45)
    model = tiny["model"].with_site(site)
    retuned = eqx.tree_at(lambda m: m.classifier.threshold, model, model.classifier.threshold * 0.9)
    scans = to_scans(log, model.n_beams)
    jitted = jax.jit(eqx.debug.assert_max_traces(step, max_traces=1))
    outs = []
    for m in (model, retuned):
        state = init_state(m)
        for i in range(log.n_scans):
            state, out = jitted(m, state, jax.tree.map(lambda a, i=i: a[i], scans))
            if m is model:
                outs.append(jax.device_get(out))
    assert jitted._cache_size() == 1
    before = run_chunk._cache_size()
    final, batch = process_log(model, scans, chunk=16)  # 45 = 16 + 16 + 13: the last chunk is padded
    process_log(retuned, scans, chunk=16)
    assert run_chunk._cache_size() - before <= 1
    vfinal, vbatch = process_log(model, scans, chunk=16, vectorise=True, sub=8)
    assert sum(int(o.track_mask.sum()) for o in outs) > 40  # the robots were tracked
    for form, b in (("loop", batch), ("vectorised", vbatch)):
        for i, o in enumerate(outs):
            for name in ("track_id", "track_class", "track_mask", "det_mask"):
                np.testing.assert_array_equal(getattr(o, name), getattr(b, name)[i], err_msg=f"{form}: {name} at scan {i}")
            for name in ("track_pose", "track_var", "det_pose", "sensor_pose"):
                _close(_reported(o, name), _reported(b, name, i), name, f"{form}: {name} at scan {i}")
    for f in (final, vfinal):
        np.testing.assert_array_equal(np.asarray(state.tracker.track_id), np.asarray(f.tracker.track_id))


def test_logs_of_different_lengths_share_one_compiled_chunk(tiny):
    """A log shorter than the chunk is padded to the chunk (``chunk_for``), so logs of 35 and 45 scans
    run one compiled chunk, the one a long log runs (each length had compiled its own); and the
    shorter log's rows are the longer one's first rows, as stepping gives them."""
    from gtsjax.drivers.batch import chunk_for, run_chunk

    assert [chunk_for(n, 256) for n in (1, 2, 3, 35, 45, 64, 65, 256, 600)] == [256] * 9
    assert chunk_for(45, 16) == 16
    log, site = simulate("spl-crossing", seed=22, n_scans=45)
    model = tiny["model"].with_site(site)
    scans = to_scans(log, model.n_beams)
    before = run_chunk._cache_size()
    _, long = process_log(model, scans)
    _, short = process_log(model, jax.tree.map(lambda a: a[:35], scans))
    assert run_chunk._cache_size() - before <= 1
    assert long.track_id.shape[0] == 45 and short.track_id.shape[0] == 35
    assert long.track_mask.sum() > 20  # the robots were tracked
    for name in ("track_id", "track_class", "track_mask", "det_mask", "track_pose", "track_var", "det_pose"):
        np.testing.assert_array_equal(getattr(short, name), getattr(long, name)[:35], err_msg=name)


def _reported(out, name: str, i=None):
    """``out.name`` (scan ``i`` of a stacked output); of the detections, only those reported
    (``det_mask``): a candidate dropped (outside the field, say) keeps whatever its fit left, and a
    near-flat fit of one, out at the field's edge, ends millimetres apart on the last bit of its input."""
    value = np.asarray(getattr(out, name) if i is None else getattr(out, name)[i])
    if name != "det_pose":
        return value
    return value[np.asarray(out.det_mask if i is None else out.det_mask[i])]


def _same_tracks(a, b, what: str):
    """Stacked outputs of one log computed two ways: ids and masks equal, poses to float32 round-off."""
    for name in ("track_id", "track_class", "track_mask", "det_mask"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{what}: {name}")
    for name in ("track_pose", "track_var", "det_pose", "sensor_pose"):
        _close(_reported(a, name), _reported(b, name), name, f"{what}: {name}")


def _close(a, b, name: str, msg: str):
    """Float32 round-off apart, as two programs that fuse the same step differently give it. Poses to
    5e-4 m and 3e-4 rad: stage e′'s Gauss–Newton steps carry a last-bit difference of their input
    into a near-flat fit, a view of one flat face whose position along the face its points hardly
    fix, to some 2e-5 rad and 0.2 mm (a robot's detection, the tests' XLA flags; elsewhere 1e-5 m and
    less), and a young track's filter, whose turn rate is still its first headings' difference over a
    scan, passes the heading's on up to five times over (1.0e-4 rad at a track's sixth scan). A fault
    of either path moves poses by centimetres."""
    a, b = np.asarray(a), np.asarray(b)
    if name.endswith("pose"):
        np.testing.assert_allclose(a[..., :-1], b[..., :-1], rtol=1e-4, atol=5e-4, err_msg=msg)
        np.testing.assert_allclose(np.angle(np.exp(1j * (a[..., -1] - b[..., -1]).astype(np.float64))), 0.0,
                                   atol=3e-4, err_msg=msg)
    else:
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5, err_msg=msg)


def test_several_logs_side_by_side_give_each_logs_own_tracks(tiny):
    """``process_logs`` (logs of different lengths side by side, one tracker each, perception of all
    their scans batched) gives each log what ``process_log`` gives it alone, vectorised or step by
    step, and the logs' own final states; a log that ended passes through the later chunks."""
    from gtsjax.drivers.batch import process_logs

    # Two logs, one ending in the first of three chunks: the call with ``None`` below is the same
    # program as the vectorised pair's (a third log was a program of its own, some 15 s to compile).
    sims = [simulate("spl-crossing", seed=s, n_scans=n) for s, n in ((21, 40), (23, 9))]
    model = tiny["model"].with_site(sims[0][1])
    stacks = [to_scans(log, model.n_beams) for log, _ in sims]
    for vectorise in (True, False):
        finals, outs = process_logs(model, stacks, chunk=16, vectorise=vectorise)
        assert [len(o.track_id) for o in outs] == [40, 9]
        for k, sc in enumerate(stacks):
            final, alone = process_log(model, sc, chunk=16, vectorise=vectorise)
            _same_tracks(alone, outs[k], f"log {k}, vectorise={vectorise}")
            np.testing.assert_array_equal(np.asarray(final.tracker.track_id), np.asarray(finals[k].tracker.track_id))
    assert sum(int(o.track_mask.sum()) for o in outs) > 40  # the robots were tracked: the comparison is not empty
    _, (none, some) = process_logs(model, [None, stacks[1]], chunk=16)
    assert none is None and len(some.track_id) == 9


def test_replay_of_several_logs_writes_one_csv_each(tiny, tmp_path, capsys):
    """``gtsjax replay A B --out FOLDER`` writes FOLDER/A.csv and FOLDER/B.csv with the rows each log's
    own replay writes; two logs of one name, or a file as the folder, are one line and exit 2 before
    anything is written."""
    paths = []
    for seed, n in ((41, 30), (42, 18)):
        log, site = simulate("spl-trajectory", seed=seed, n_scans=n)
        paths.append(tmp_path / f"walk{seed}.npz")
        save_log(log, paths[-1])
    save_site(site, tmp_path / "site.json")
    common = ("--site", tmp_path / "site.json", "--model", tiny["path"])
    res = cli(capsys, "replay", *paths, *common, "--out", tmp_path / "gtd", "--sensor-out", tmp_path / "sensor")
    assert res.returncode == 0, res.stderr
    for p in paths:
        alone = cli(capsys, "replay", p, *common, "--out", tmp_path / f"{p.stem}-alone.csv")
        assert alone.returncode == 0, alone.stderr
        with open(tmp_path / "gtd" / f"{p.stem}.csv") as f, open(tmp_path / f"{p.stem}-alone.csv") as g:
            both, one = list(csv.reader(f)), list(csv.reader(g))
        assert len(both) == len(one) > 10
        assert [r[:3] for r in both] == [r[:3] for r in one]  # stamps, ids, classes
        np.testing.assert_allclose(np.array([r[3:] for r in both[1:]], float), np.array([r[3:] for r in one[1:]], float),
                                   rtol=1e-4, atol=1e-5)
        assert (tmp_path / "sensor" / f"{p.stem}.csv").exists()
    (tmp_path / "twin").mkdir()
    twin = tmp_path / "twin" / paths[0].name
    twin.write_bytes(paths[0].read_bytes())
    for args, words in (((paths[0], twin), "both write walk41.csv"), ((*paths,), "is a file")):
        out = tmp_path / "afile.csv"
        out.write_text("")
        res = cli(capsys, "replay", *args, *common, "--out", out if words == "is a file" else tmp_path / "new")
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and words in lines[0], res.stderr
    assert not (tmp_path / "new").exists()


def test_replay_writes_spec_csv(tiny, tmp_path, capsys):
    log, site = simulate("spl-trajectory", seed=31, n_scans=60)
    save_log(log, tmp_path / "log.npz")
    save_site(site, tmp_path / "site.json")
    res = cli(capsys, "replay", tmp_path / "log.npz", "--site", tmp_path / "site.json", "--model", tiny["path"],
                  "--out", tmp_path / "gtd.csv", "--sensor-out", tmp_path / "sensor.csv")
    assert res.returncode == 0, res.stderr
    with open(tmp_path / "gtd.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == HEADER
    stamps = [float(r[0]) for r in rows[1:]]
    assert stamps == sorted(stamps) and set(stamps) <= set(log.stamps.tolist())
    assert all(-np.pi < float(r[5]) <= np.pi for r in rows[1:])
    sensor = np.loadtxt(tmp_path / "sensor.csv", delimiter=",", skiprows=1)
    assert sensor.shape == (60, 6)
    # The robot walks in every scan: against its true poses (README: recall 99.7 % after the first
    # second, 0.9 cm, 2.7°, no id switch), one track, in ≥ 90 % of the scans after the first second,
    # within the README's targets for a moving robot (5 cm, 6°), the position within 3 cm.
    assert len(rows) > 1, "no track reported"
    assert {(r[1], r[2]) for r in rows[1:]} == {(rows[1][1], "robot")}
    t = np.searchsorted(log.stamps, stamps)
    assert np.sum(t >= 10) >= 0.9 * (log.n_scans - 10)
    truth = log.truth_poses[t, 0]
    est = np.array([[float(r[3]), float(r[4]), float(r[5])] for r in rows[1:]])
    e_pos = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)
    e_th = np.angle(np.exp(1j * (est[:, 2] - truth[:, 2])))
    assert np.sqrt(np.mean(e_pos**2)) <= 0.03 and np.degrees(np.sqrt(np.mean(e_th**2))) <= 6.0, (e_pos, e_th)


def _replay_with(tiny, tmp_path, capsys, scenario: str, seed: int, n_scans: int, option: str, values):
    """``replay`` of a simulated log with ``option`` at each of ``values`` (``None``: left off): the
    log and each value's GTD rows (without the header); and that ``option 0`` is a usage error (exit 2,
    naming the option)."""
    log, site = simulate(scenario, seed=seed, n_scans=n_scans)
    save_log(log, tmp_path / "log.npz")
    save_site(site, tmp_path / "site.json")
    args = ("replay", tmp_path / "log.npz", "--site", tmp_path / "site.json", "--model", tiny["path"])
    rows = {}
    for n in values:
        out = tmp_path / f"gtd-{n}.csv"
        res = cli(capsys, *args, "--out", out, *(() if n is None else (option, str(n))))
        assert res.returncode == 0, res.stderr
        with open(out, newline="") as f:
            rows[n] = list(csv.reader(f))[1:]
    res = cli(capsys, *args, "--out", tmp_path / "x.csv", option, "0")
    assert res.returncode == 2 and option.lstrip("-") in res.stderr
    return log, rows


def test_replay_confirm_scans_delays_the_first_row_only(tiny, tmp_path, capsys):
    """``--confirm-scans N``: a track is reported from its N-th scan of detections on, later than with
    the model's own confirmation, and from then on in the same scans; 0 is a usage error (exit 2)."""
    log, rows = _replay_with(tiny, tmp_path, capsys, "spl-trajectory", 33, 60, "--confirm-scans", (None, 12))
    first, stamps = {}, {}
    for n, r in rows.items():
        assert r, "the robot is tracked"
        stamps[n] = [float(x[0]) for x in r]
        first[n] = int(np.searchsorted(log.stamps, stamps[n][0]))
    n_default = int(tiny["model"].tracker.n_confirm)
    assert first[None] >= n_default - 1 and first[12] >= 11 and first[12] > first[None]
    assert stamps[12] == [t for t in stamps[None] if t >= stamps[12][0]]


def test_replay_max_tracks_bounds_the_robots_tracked_at_once(tiny, tmp_path, capsys):
    """``--max-tracks N`` (the model's track slots, 8 as trained): three robots crossing fill three
    slots; with two slots no scan reports more than two, and with twelve the rows are the trained
    model's (the slots are array sizes, nothing learnt). 0 is a usage error (exit 2)."""
    _, rows = _replay_with(tiny, tmp_path, capsys, "spl-crossing", 35, 120, "--max-tracks", (None, 2, 12))
    per_scan = {n: np.unique([x[0] for x in r], return_counts=True)[1] for n, r in rows.items()}
    assert per_scan[None].max() == 3 and per_scan[2].max() == 2
    assert [x[:3] for x in rows[12]] == [x[:3] for x in rows[None]]


def test_replay_bad_inputs_exit_2_with_one_line(tiny, tmp_path, capsys):
    log, site = simulate("spl-eval", seed=1, n_scans=5)
    good_log, good_site = tmp_path / "log.npz", tmp_path / "site.json"
    save_log(log, good_log)
    save_site(site, good_site)
    bad_site = tmp_path / "bad_site.json"
    bad_site.write_text('{"landmarks": [], "sensor_pose": [0, 0, 0]}')
    other_site = tmp_path / "other_site.json"
    other_site.write_text('{"landmarks": [{"class": "cone", "x": 0, "y": 0}, {"class": "cone", "x": 1, "y": 0},'
                          ' {"class": "cone", "x": 0, "y": 1}], "sensor_pose": [0, 0, 0]}')
    utm_log = tmp_path / "utm.npz"
    save_log(simulate("lab-eval", n_scans=3)[0], utm_log)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"PK\x03\x04 truncated zip")
    # One case per input replay reads, and per check between them; the loaders' other messages are
    # tested once, through their functions (test_io_logs.py, test_io_site.py, test_bad_model_files_...).
    cases = [
        (garbage, good_site, tiny["path"], "not a NumPy .npz archive"),
        (good_log, bad_site, tiny["path"], "at least 3 landmarks"),
        (good_log, other_site, tiny["path"], "unknown to the model"),
        (utm_log, good_site, tiny["path"], "trained for sensor URG-04LX"),
    ]
    for log_p, site_p, model_p, match in cases:
        res = cli(capsys, "replay", log_p, "--site", site_p, "--model", model_p, "--out", tmp_path / "o.csv")
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2, (match, res.stderr)
        assert len(lines) == 1 and match in lines[0] and "Traceback" not in res.stderr, (match, res.stderr)


def test_train_cli_bad_input(tmp_path):
    log, site = simulate("spl-eval", seed=1, n_scans=5)
    unlabelled = dataclasses.replace(log, truth_classes=None, truth_poses=None)
    save_log(unlabelled, tmp_path / "u.npz")
    save_site(site, tmp_path / "s.json")
    assert main(["train", str(tmp_path / "u.npz"), "--site", str(tmp_path / "s.json"), "--out",
                 str(tmp_path / "m.npz")]) == 2
    assert not (tmp_path / "m.npz").exists()


def test_live_step_rows_equal_the_replay_rows(tiny):
    """The live driver (frame arrays in, the GTD fields packed into one array out, one compiled call
    per frame) gives the rows the replay driver writes for the same scans."""
    from gtsjax.drivers.live import LiveStep, rows_from_packed
    from gtsjax.io.gtd import rows_from_output
    from gtsjax.io.logs import scan_dt
    from gtsjax.sensors import URG_04LX

    log, site = simulate("spl-crossing", seed=21, n_scans=60)
    model = tiny["model"].with_site(site)
    live = LiveStep(model, URG_04LX)
    _, batch = process_log(model, to_scans(log, model.n_beams), chunk=32)
    s_live = live.initial_state()
    dts = scan_dt(log.stamps)
    n_rows = 0
    for t in range(log.n_scans):
        s_live, _, packed = live(s_live, log.ranges[t], None, dts[t])
        got = rows_from_packed(log.stamps[t], np.asarray(packed), model.classes)
        want = rows_from_output(log.stamps[t], batch.track_id[t], batch.track_class[t], batch.track_pose[t],
                                batch.track_var[t], batch.track_mask[t], model.classes, batch.track_cov_xy[t])
        assert [(r.track_id, r.cls) for r in got] == [(r.track_id, r.cls) for r in want]
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose([a.x, a.y, a.theta, a.var_x, a.var_y, a.var_theta, a.cov_xy],
                                       [b.x, b.y, b.theta, b.var_x, b.var_y, b.var_theta, b.cov_xy], rtol=1e-4,
                                       atol=1e-5)
        assert bool(np.asarray(packed)[-1, 0] > 0.5) == bool(batch.degraded[t])
        n_rows += len(got)
    assert n_rows > 20  # the robots were tracked, so rows were compared


def test_seen_through_reads_the_beams_at_a_tracks_bearing():
    """A sensor at (3, 4) looking along −y; 181 beams over ±90°, 1° apart. Hand-placed returns: the
    spot (3, 2) lies 2 m ahead on the middle beam; (4, 3) is 1.41 m away at +45° (to the sensor's
    left, beam 135)."""
    import jax.numpy as jnp

    from gtsjax.core.f_maptransform import Transform
    from gtsjax.core.pipeline import seen_through
    from gtsjax.core.scan import Scan

    def scan(ranges):
        r = np.asarray(ranges, np.float32)
        return Scan(jnp.asarray(r), jnp.zeros_like(jnp.asarray(r)), jnp.asarray(r > 0),
                    jnp.asarray(-np.pi / 2, jnp.float32), jnp.asarray(np.pi / 180, jnp.float32),
                    jnp.asarray(0.1, jnp.float32))

    tf = Transform.from_sensor_pose(jnp.asarray([3.0, 4.0, -np.pi / 2]))
    spots = jnp.asarray([[3.0, 2.0], [4.0, 3.0], [3.0, 5.0]], jnp.float32)  # ahead, to the left, behind the sensor
    far = np.full(181, 4.0)
    assert np.asarray(seen_through(scan(far), tf, spots)).tolist() == [True, True, False]
    robot = far.copy()
    robot[89:92] = [2.0, 1.9, 2.2]  # something within 0.3 m past the spot: still there
    assert np.asarray(seen_through(scan(robot), tf, spots)).tolist() == [False, True, False]
    one_beam = far.copy()
    one_beam[136] = 1.5  # one of the three beams at +45° (135 ± 1) stops 9 cm past (4, 3)
    assert np.asarray(seen_through(scan(one_beam), tf, spots)).tolist() == [True, False, False]
    empty = np.zeros(181)  # no return at all: nothing within the sensor's range
    assert np.asarray(seen_through(scan(empty), tf, spots)).tolist() == [True, True, False]


def _dot_precisions(jaxpr) -> list:
    """The precision of every matrix product in a jaxpr, sub-jaxprs (loops, branches, jits) included."""
    from jax.extend.core import ClosedJaxpr, Jaxpr

    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                if isinstance(sub, ClosedJaxpr):
                    found += _dot_precisions(sub.jaxpr)
                elif isinstance(sub, Jaxpr):
                    found += _dot_precisions(sub)
    return found


def test_every_product_of_the_step_runs_at_full_precision_whatever_the_global_setting(tiny):
    """The package sets no process-wide option; the core asks for full-precision products where they
    are traced, so a GPU's TF32 default cannot round them (checked on the traced program, since a CPU
    computes the same either way)."""
    log, site = simulate("spl-crossing", seed=21, n_scans=2)
    model = tiny["model"].with_site(site)
    scan = jax.tree.map(lambda a: a[0], to_scans(log, model.n_beams))
    assert jax.config.jax_default_matmul_precision is None
    with jax.default_matmul_precision("bfloat16"):
        jaxpr = jax.make_jaxpr(step)(model, init_state(model), scan)
    precisions = _dot_precisions(jaxpr.jaxpr)
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert len(precisions) > 10 and all(p == highest for p in precisions), set(precisions)


def test_every_candidate_slot_says_what_became_of_it():
    """``Perception.reason`` against the stage's own flags and counters, slot by slot: no segment,
    filtered by stage c, an object (posed), and as many unlike, unposed and off-envelope verdicts as
    the counters count; ``Output.cand_xy`` each slot's ORS origin mapped by the scan's transform."""
    import jax

    from gtsjax.cli.demo import demo_model_path
    from gtsjax.core.frontend import front_end
    from gtsjax.core.pipeline import REASONS, init_state, perceive, update
    from gtsjax.io.logs import to_scans
    from gtsjax.io.modelfile import load_model
    from gtsjax.sim import simulate

    log, site = simulate("spl-legs", seed=5, n_scans=40)
    model = load_model(demo_model_path()).with_site(site)
    scans = to_scans(log, model.n_beams)
    state = init_state(model)
    code = {r: i for i, r in enumerate(REASONS)}
    seen = set()
    perceive_j = jax.jit(lambda s: (perceive(model, s), front_end(model.frontend, s)))
    update_j = jax.jit(lambda st, p, s: update(model, st, p, s))
    for t in range(0, 40, 8):
        scan = jax.tree.map(lambda a, t=t: a[t], scans)
        p, fe = perceive_j(scan)
        state, out = update_j(state, p, scan)
        reason, live, kept = np.asarray(p.reason), np.asarray(fe.candidates.live), np.asarray(fe.keep)
        for k in range(reason.size):
            if not live[k]:
                assert reason[k] == code["none"], k
            elif not kept[k]:
                assert reason[k] == code["filtered"], k
            elif bool(p.ok[k]):
                assert reason[k] == code["object"], k
            else:
                assert reason[k] in (code["background"], code["unlike"], code["off envelope"], code["unposed"]), k
        assert np.sum(reason == code["unlike"]) == int(p.unlike)
        assert np.sum(reason == code["unposed"]) == int(p.unposed)
        assert np.sum(reason == code["off envelope"]) <= int(p.off_envelope)
        np.testing.assert_allclose(np.asarray(out.cand_xy), np.asarray(out.transform.apply(fe.features.origin)),
                                   atol=1e-5)
        seen |= set(reason.tolist())
    assert {code["none"], code["object"]} <= seen and len(seen) >= 3


def test_packing_round_trips_a_tree_of_mixed_dtypes_inside_jit_and_on_the_host():
    """A tree of float32, int32 and bool arrays (scalars among them) packed into one buffer per dtype
    and unpacked, inside ``jit`` and with NumPy on the host: every leaf comes back as it was."""
    import jax.numpy as jnp

    from gtsjax.drivers.packing import Packing

    rng = np.random.default_rng(0)
    tree = {"a": jnp.asarray(rng.normal(size=(3, 4)), jnp.float32), "b": (jnp.asarray(7, jnp.int32),
            jnp.asarray(rng.random(5) > 0.5)), "c": jnp.asarray(rng.integers(-9, 9, (2, 2, 2)), jnp.int32),
            "d": jnp.asarray(2.5, jnp.float32), "e": jnp.zeros((0, 3), jnp.float32)}
    layout = Packing.of(tree)
    assert [np.dtype(d) for d in layout.dtypes] == [np.float32, np.int32, np.bool_]
    bufs = jax.jit(layout.pack)(tree)
    assert [b.shape for b in bufs] == [(13,), (9,), (5,)]
    twice = jax.jit(lambda b: layout.unpack(b))(bufs)
    for got in (twice, layout.unpack_host(bufs)):
        for x, y in zip(jax.tree.leaves(got), jax.tree.leaves(tree), strict=True):
            assert x.shape == y.shape and x.dtype == y.dtype
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="expected 3 buffers"):
        layout.unpack(bufs[:2])


def test_live_step_state_and_output_equal_the_plain_steps(tiny):
    """The live step (a frame copied as it came into one buffer; state and output packed), unpacked,
    equals ``jit(step)`` on the same frames made on the host (``frame_arrays``: valid beams, padding)
    with the pipeline's state passed from call to call, leaf by leaf; frames with beams out of range,
    non-finite and fewer than the model's (a narrower scanner) among them."""
    from gtsjax.core.scan import Scan
    from gtsjax.drivers.live import LiveStep, frame_arrays
    from gtsjax.io.logs import scan_dt
    from gtsjax.sensors import URG_04LX

    log, site = simulate("spl-crossing", seed=23, n_scans=25)
    model = tiny["model"].with_site(site)
    live = LiveStep(model, URG_04LX)
    am, ai = (jax.numpy.asarray(a, jax.numpy.float32) for a in (URG_04LX.angle_min, URG_04LX.angle_increment))
    plain = jax.jit(lambda s, r, i, v, dt: step(model, s, Scan(r, i, v, am, ai, dt)))
    s_live, s_plain = live.initial_state(), init_state(model)
    dts = scan_dt(log.stamps)
    rng = np.random.default_rng(5)
    reported = 0
    for t in range(log.n_scans):
        ranges = log.ranges[t].astype(np.float64)
        bad = rng.choice(ranges.size, 12, replace=False)
        ranges[bad] = [np.nan, np.inf, -np.inf, -1.0, 0.0, 1e-3, URG_04LX.range_max + 0.5, 1e6,
                       URG_04LX.range_min, URG_04LX.range_max, np.nan, 0.0]
        if t % 5 == 4:
            ranges = ranges[:-40]  # a frame narrower than the model's (its last beams are padding)
        inten = rng.uniform(0, 3000, ranges.size)
        s_live, o_live, _ = live(s_live, ranges, inten, dts[t])
        s_plain, o_plain = plain(s_plain, *frame_arrays(ranges, inten, URG_04LX, model.n_beams), np.float32(dts[t]))
        for got, want in ((live.pipeline_state(s_live), s_plain), (live.output(o_live), o_plain)):
            named = jax.tree_util.tree_flatten_with_path(want)[0]
            for x, (path, y) in zip(jax.tree.leaves(got), named, strict=True):
                assert x.shape == y.shape and x.dtype == y.dtype
                name = jax.tree_util.keystr(path)
                if name.endswith("pose"):  # two programs: stage e′'s near-flat fits (see ``_close``)
                    _close(x, y, name, f"scan {t}: {name}")
                else:
                    np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6, err_msg=name)
        reported += int(np.sum(np.asarray(o_plain.track_mask)))
    assert reported > 10  # the robots were tracked, so tracks were compared
    with pytest.raises(ValueError, match="more than the model's"):
        live(s_live, np.ones(model.n_beams + 1), None, 0.1)


def test_frame_dt_and_link_frame_ranges_equal_the_obvious_forms():
    """The live loop's ``frame_dt`` equals ``scan_dt`` of the same stamps once in float32, and a link
    frame's ``ranges_m`` (one NumPy call) the millimetres converted to float32 and then divided by
    1000 in float32, bit for bit."""
    from gtsjax.io.logs import frame_dt, scan_dt
    from gtsjax.io.scip import ScanFrame
    from gtsjax.io.serial import LinkFrame

    rng = np.random.default_rng(8)
    stamps = np.cumsum(rng.uniform(-0.01, 0.1, 200)) + 1.7e9
    want = scan_dt(stamps[1:], float(stamps[0]))
    got = np.asarray([frame_dt(s, p) for s, p in zip(stamps[1:], stamps[:-1], strict=True)], np.float32)
    np.testing.assert_array_equal(got, want)
    assert frame_dt(5.0, None) == scan_dt(np.asarray([5.0]))[0] == 0.0
    mm = rng.integers(0, 2**18, 5000).astype(np.int32)
    lf = LinkFrame(ScanFrame("MD", "99", 1234, mm, None, 0, 0, mm, mm > 0), 10.0, 10.0, 1.0, 1234, 0)
    want_m = mm.astype(np.float32) / np.float32(1000.0)
    assert lf.ranges_m.dtype == np.float32
    np.testing.assert_array_equal(lf.ranges_m.view(np.int32), want_m.view(np.int32))
