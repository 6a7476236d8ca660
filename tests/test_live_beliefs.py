"""Issue 41 item 6, ``run --beliefs``: the robots' own poses over UDP (a real socket), the live
association against hand-built cases and a brute-force assignment, the GTD CSV's optional ``robot``
column, and a live run against the emulated sensor with docs/live-beliefs.md's sender on three robots."""

import itertools
import json
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gtsjax.errors import InputError
from gtsjax.grade.online import GATE_M, OnlineIdentity, window_winners
from gtsjax.io.beliefs_udp import BeliefListener, parse_beliefs_address
from gtsjax.io.gtd import HEADER, UNITS_HEADER, GTDWriter, TrackRow, read_gtd

DOC = Path(__file__).resolve().parents[1] / "docs" / "live-beliefs.md"


# ------------------------------------------------------------------------------------ the listener

def free_listening_port() -> int:
    """A UDP port free now and below Linux's ephemeral range (32768 and up): a port from ``bind(0)``,
    closed and handed to ``run``, could meanwhile become the source port of a sender's first datagram
    (unbound sockets take an ephemeral port when they send), and ``run`` then finds it in use."""
    rng = np.random.default_rng()
    for port in rng.permutation(np.arange(20000, 32000))[:200]:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", int(port)))
            except OSError:
                continue
            return int(port)
    raise RuntimeError("no free UDP port in 20000-32000")

def _wait_for(cond, what: str, timeout: float = 10.0) -> None:
    """Polls ``cond`` (what a thread does arrives when it arrives); fails naming ``what``."""
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_listener_takes_lines_merged_and_split_across_datagrams_and_counts_the_malformed():
    with BeliefListener("udp:127.0.0.1:0") as lis:
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        to = ("127.0.0.1", lis.port)
        line = lambda r, s, x: json.dumps({"robot": r, "stamp": s, "x": x, "y": 2.0, "theta": 0.1})  # noqa: E731
        out.sendto((line("a", 1.0, 0.1) + "\n" + line("b", 7.0, 5.0) + "\n" + line("a", 1.1, 0.2) + "\n").encode(), to)
        whole = line("b", 7.1, 5.1)
        out.sendto(whole[:17].encode(), to)  # one line cut across two datagrams of one sender
        out.sendto((whole[17:] + "\n").encode(), to)
        out.sendto(line("a", 1.2, 0.3).encode(), to)  # no newline at all: a whole line by itself
        bad = [b"\xff\xfe", b"[1, 2]\n", b'{"robot": "a", "stamp": 1.3, "x": "one", "y": 0, "theta": 0}\n',
               b'{"robot": "b", "stamp": 7.2, "x": 1, "y": 0}\n', b'{"stamp": 1, "x": 1, "y": 0, "theta": 0}\n',
               b'{"robot": "a", "stamp": 1.4, "x": NaN, "y": 0, "theta": 0}\n', b"not json at all\n"]
        for b in bad:
            out.sendto(b, to)
        out.sendto((line("a", 1.05, 9.0) + "\n").encode(), to)  # older than a's last: a reordered datagram
        _wait_for(lambda: lis.counts_copy().datagrams == 4 + len(bad) + 1, "every datagram")
        snap = lis.snapshot()
        counts = lis.counts_copy()
    out.close()
    np.testing.assert_allclose(snap["a"][:, 1:4], [[1.0, 0.1, 2.0], [1.1, 0.2, 2.0], [1.2, 0.3, 2.0]])
    np.testing.assert_allclose(snap["b"][:, 1:4], [[7.0, 5.0, 2.0], [7.1, 5.1, 2.0]])
    # Receive times strictly increase per robot, and a batch's earlier line lies its stamps' gap before.
    assert np.all(np.diff(snap["a"][:, 0]) > 0)
    assert snap["a"][1, 0] - snap["a"][0, 0] == pytest.approx(0.1, abs=1e-6)
    assert counts.poses == {"a": 3, "b": 2}
    assert counts.malformed == {"not UTF-8": 1, "not a JSON object": 1, "x not a number": 1, "no theta": 1,
                                "no robot name (a non-empty string)": 1, "x not finite": 1, "not JSON": 1}
    assert counts.malformed_by_robot == {"a": 2, "b": 1}
    assert counts.out_of_order == 1


def test_beliefs_address_and_a_port_in_use_are_one_line():
    assert parse_beliefs_address("udp:5600") == ("0.0.0.0", 5600)
    assert parse_beliefs_address("udp:10.0.0.2:5600") == ("10.0.0.2", 5600)
    for bad in ("5600", "tcp:5600", "udp:", "udp:port", "udp:70000"):
        with pytest.raises(InputError, match="^--beliefs: "):
            parse_beliefs_address(bad)
    with BeliefListener("udp:127.0.0.1:0") as lis, pytest.raises(InputError, match=r"^--beliefs: cannot listen"):
        BeliefListener(f"udp:127.0.0.1:{lis.port}")


def test_run_refuses_a_port_in_use_with_exit_2(tmp_path, capsys):
    from gtsjax.cli import main
    from gtsjax.io import save_site
    from gtsjax.sim import simulate

    save_site(simulate("spl-eval", seed=1, n_scans=1)[1], tmp_path / "site.json")
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    try:
        code = main(["run", "--port", "/dev/null", "--site", str(tmp_path / "site.json"), "--model",
                     str(tmp_path / "m.npz"), "--out", str(tmp_path / "gtd.csv"),
                     "--beliefs", f"udp:127.0.0.1:{busy.getsockname()[1]}"])
    finally:
        busy.close()
    err = capsys.readouterr().err
    assert code == 2, err
    assert "--beliefs: cannot listen on UDP 127.0.0.1" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err


# --------------------------------------------------------------------------------- the CSV column
def test_robot_column_is_written_last_only_when_asked_and_read_back(tmp_path):
    rows = [TrackRow(1.5, 3, "robot", 1.0, 2.0, 0.5, 1e-4, 2e-4, 1e-3, 5e-5, robot="nao3"),
            TrackRow(1.5, 4, "robot", 3.0, 1.0, -0.5, 1e-4, 2e-4, 1e-3, 0.0, robot=""),
            TrackRow(1.6, 5, "robot", 3.0, 1.0, -0.5, 1e-4, 2e-4, 1e-3, 0.0, robot="a,b")]
    for units in (False, True):
        plain, named = tmp_path / f"plain{units}.csv", tmp_path / f"named{units}.csv"
        with GTDWriter(plain, units=units) as w:
            w.write(rows)
        with GTDWriter(named, units=units, robot=True) as w:
            w.write(rows)
        head = UNITS_HEADER if units else HEADER
        assert plain.read_text().splitlines()[0] == ",".join(head)
        assert named.read_text().splitlines()[0] == ",".join(head) + ",robot"
        assert "nao3" not in plain.read_text()
        # The named file is the plain one with a last field per line.
        for p, n in zip(plain.read_text().splitlines()[1:], named.read_text().splitlines()[1:], strict=True):
            assert n.startswith(p + ",")
        back = read_gtd(named)
        assert [r.robot for r in back] == ["nao3", "", "a,b"]
        assert [r.robot for r in read_gtd(plain)] == ["", "", ""]
        want_cov = [5e-5, 0.0, 0.0] if units else [0.0, 0.0, 0.0]
        np.testing.assert_allclose([r.cov_xy for r in back], want_cov, rtol=1e-6)
        assert [(r.track_id, r.x, r.theta) for r in back] == [(r.track_id, r.x, r.theta) for r in rows]
    assert "robot" not in rows[1].as_dict() and rows[0].as_dict()["robot"] == "nao3"


# ----------------------------------------------------------------------------------- association
def _brute_force(cost: np.ndarray, gate: float) -> tuple[int, float]:
    """The most pairs within the gate, then the least total cost over them: every assignment tried."""
    R, K = cost.shape
    best = (0, 0.0)
    for perm in itertools.permutations(range(max(R, K)), K):
        pairs = [(r, c) for c, r in enumerate(perm) if r < R and cost[r, c] <= gate]
        score = (len(pairs), -sum(cost[r, c] for r, c in pairs))
        if score > (best[0], -best[1]):
            best = (len(pairs), -score[1])
    return best


def test_window_assignment_is_the_best_one_within_the_gate():
    rng = np.random.default_rng(4)
    for _ in range(200):
        R, K = rng.integers(0, 5, 2)
        cost = rng.uniform(0.0, 1.2, (R, K))
        cost[rng.uniform(size=(R, K)) < 0.2] = np.inf
        won = window_winners(cost, GATE_M)
        used = won[won >= 0]
        assert len(set(used.tolist())) == used.size  # a robot to one track at most
        pairs = [(int(r), c) for c, r in enumerate(won) if r >= 0]
        assert all(cost[r, c] <= GATE_M for r, c in pairs)
        n, total = _brute_force(cost, GATE_M)
        assert len(pairs) == n
        assert sum(cost[r, c] for r, c in pairs) == pytest.approx(total, abs=1e-9)


class _Beliefs:
    """A listener's :meth:`snapshot` over poses given as arrays (receive time, stamp, x, y, θ)."""

    def __init__(self, poses: dict):
        self.poses = poses

    def snapshot(self, since=-np.inf):
        return {r: a[a[:, 0] > since] for r, a in self.poses.items() if np.any(a[:, 0] > since)}


def _run(tracks: dict, beliefs: dict, t: np.ndarray) -> tuple[OnlineIdentity, list]:
    """The association over scans at ``t``; ``tracks``: id -> (x, y) per scan (NaN: not reported).
    Returns it and, per scan, the names each track's row was written with; checks at every scan
    that no name is on two tracks."""
    ident = OnlineIdentity(_Beliefs(beliefs))
    written = []
    for i, stamp in enumerate(t):
        rows = [TrackRow(float(stamp), k, "robot", float(xy[i, 0]), float(xy[i, 1]), 0.0, 0, 0, 0)
                for k, xy in tracks.items() if not np.isnan(xy[i, 0])]
        rows = ident.label(rows)
        names = [r.robot for r in rows if r.robot]
        assert len(names) == len(set(names)), (stamp, names)
        assert {v: k for k, v in ident.names.items()} == ident.holder
        written.append({r.track_id: r.robot for r in rows})
        ident.observe(float(stamp), rows)
    return ident, written


def _beliefs_of(truth: np.ndarray, t: np.ndarray, rng, noise: float = 0.05, rate: float = 20.0) -> np.ndarray:
    """A robot's beliefs at ``rate`` Hz: its truth (at scans ``t``) interpolated, plus noise."""
    tb = np.arange(t[0], t[-1] + 1.0, 1.0 / rate)
    x = np.interp(tb, t, truth[:, 0]) + rng.normal(0, noise, tb.size)
    y = np.interp(tb, t, truth[:, 1]) + rng.normal(0, noise, tb.size)
    return np.stack([tb, tb - 100.0, x, y, np.zeros_like(tb)], axis=1)


T = np.arange(0.0, 20.0, 0.1)  # 10 Hz scans


def _wrong_after(written: list, want: dict, t: np.ndarray, settle: float = 2.0) -> list:
    """Scans (after ``settle`` s of each track) at which a track was written with a name not ``want``'s."""
    first: dict = {}
    bad = []
    for stamp, names in zip(t, written, strict=True):
        for k, name in names.items():
            first.setdefault(k, stamp)
            if stamp - first[k] >= settle and name != want[k]:
                bad.append((round(float(stamp), 1), k, name))
    return bad


def test_two_robots_crossing_with_noisy_beliefs_never_swap():
    rng = np.random.default_rng(0)
    # Two robots walking at 0.3 m/s towards each other, passing 10 cm apart at t = 10 s.
    a = np.stack([0.5 + 0.3 * T, np.full(T.size, 2.0)], axis=1)
    b = np.stack([6.5 - 0.3 * T, np.full(T.size, 2.1)], axis=1)
    tracks = {1: a + rng.normal(0, 0.01, a.shape), 2: b + rng.normal(0, 0.01, b.shape)}
    for seed in range(5):
        r = np.random.default_rng(seed)
        ident, written = _run(tracks, {"a": _beliefs_of(a, T, r, 0.08), "b": _beliefs_of(b, T, r, 0.08)}, T)
        assert not _wrong_after(written, {1: "a", 2: "b"}, T)
        assert ident.renames == 0
    assert written[-1] == {1: "a", 2: "b"}


def test_one_bad_window_does_not_swap_and_two_do():
    rng = np.random.default_rng(1)
    a = np.stack([np.full(T.size, 1.0), np.linspace(1, 3, T.size)], axis=1)
    b = np.stack([np.full(T.size, 4.0), np.linspace(3, 1, T.size)], axis=1)
    for bad_s, swaps in ((1.0, False), (3.0, True)):
        ba, bb = _beliefs_of(a, T, rng), _beliefs_of(b, T, rng)
        during = (ba[:, 0] >= 8.0) & (ba[:, 0] < 8.0 + bad_s)  # the two beliefs exchanged
        ba[during, 2:4], bb[during, 2:4] = bb[during, 2:4].copy(), ba[during, 2:4].copy()
        ident, written = _run({1: a, 2: b}, {"a": ba, "b": bb}, T)
        wrong = _wrong_after(written, {1: "a", 2: "b"}, T)
        if swaps:  # the beliefs really were each other's for 3 s: the names follow, then come back
            assert wrong and ident.renames >= 2
            assert written[-1] == {1: "a", 2: "b"}
        else:
            assert not wrong, wrong
            assert ident.renames == 0


def test_a_belief_1_m_off_for_3_s_keeps_its_name():
    rng = np.random.default_rng(2)
    a = np.stack([np.linspace(1, 5, T.size), np.full(T.size, 2.0)], axis=1)
    b = np.stack([np.full(T.size, 3.0), np.linspace(0.5, 1.0, T.size)], axis=1)
    ba = _beliefs_of(a, T, rng)
    off = (ba[:, 0] >= 7.0) & (ba[:, 0] < 10.0)
    ba[off, 3] += 1.0  # kidnapped: a metre off for 3 s
    ident, written = _run({1: a, 2: b}, {"a": ba, "b": _beliefs_of(b, T, rng)}, T)
    assert not _wrong_after(written, {1: "a", 2: "b"}, T)
    assert ident.named_share()["a"] == pytest.approx(1.0, abs=0.1)


def test_a_robot_picked_up_gets_its_name_back_on_its_new_track():
    rng = np.random.default_rng(3)
    a = np.stack([np.linspace(1, 2, T.size), np.full(T.size, 2.0)], axis=1)
    a[T >= 10.0] += [2.0, 1.0]  # put down elsewhere at 10 s
    b = np.stack([np.full(T.size, 5.0), np.linspace(1, 3, T.size)], axis=1)
    first, second = a.copy(), a.copy()
    first[T >= 9.0] = np.nan  # lifted at 9 s: its track ends ...
    second[T < 10.0] = np.nan  # ... and a new one begins where it is put down
    ba = _beliefs_of(a, T, rng)
    ba = ba[(ba[:, 0] < 9.0) | (ba[:, 0] >= 10.0)]  # carried: its localisation lost, nothing sent
    ident, written = _run({1: first, 2: b, 7: second}, {"a": ba, "b": _beliefs_of(b, T, rng)}, T)
    assert not _wrong_after(written, {1: "a", 2: "b", 7: "a"}, T)
    assert written[-1] == {2: "b", 7: "a"}
    # Named within 2 s of the new track's first row.
    assert next(i for i, w in enumerate(written) if w.get(7) == "a") - int(np.argmax(T >= 10.0)) <= 20


def test_a_track_nobody_believes_in_stays_unnamed():
    rng = np.random.default_rng(5)
    a = np.stack([np.linspace(1, 4, T.size), np.full(T.size, 2.0)], axis=1)
    person = np.stack([np.full(T.size, 1.0), np.linspace(0.0, 4.0, T.size)], axis=1)
    _, written = _run({1: a, 3: person}, {"a": _beliefs_of(a, T, rng)}, T)
    assert not _wrong_after(written, {1: "a", 3: ""}, T)


# ------------------------------------------------------------------------------ the doc's sender
def doc_sender() -> dict:
    """The sender of docs/live-beliefs.md, its one Python block run as a module's code."""
    blocks = re.findall(r"^```python\n(.*?)^```", DOC.read_text(), re.S | re.M)
    assert len(blocks) == 1
    code = blocks[0]
    assert 15 <= len([ln for ln in code.splitlines() if ln.strip()]) <= 30  # "a 20-line sender"
    ns = {"__name__": "sender"}
    exec(compile(code, str(DOC), "exec"), ns)
    return ns


def test_the_doc_sender_reaches_the_listener():
    ns = doc_sender()
    stop = threading.Event()
    with BeliefListener("udp:127.0.0.1:0") as lis:
        th = threading.Thread(target=ns["send_forever"], kwargs=dict(
            pose=lambda: (1.0, 2.0, 0.5), laptop=("127.0.0.1", lis.port), robot="nao3", rate_hz=50.0,
            stop=stop.is_set), daemon=True)
        th.start()
        _wait_for(lambda: lis.counts_copy().poses.get("nao3", 0) >= 5, "five poses")
        stop.set()
        th.join(5.0)
        snap = lis.snapshot()
    np.testing.assert_allclose(snap["nao3"][:, 2:], [[1.0, 2.0, 0.5]] * len(snap["nao3"]))
    assert lis.counts_copy().n_malformed == 0


# ------------------------------------------------------------------------------------ end to end
def test_run_with_beliefs_names_the_tracks_of_three_crossing_robots(tmp_path, capsys):
    """``gtsjax run --beliefs`` against the emulated sensor over a real pseudo-terminal, serving three
    robots on crossing paths, while the doc's sender runs once per robot sending its true pose (at
    the scan the emulator serves) plus 3 cm of noise at 25 Hz: the robot column right for ≥ 99 % of
    rows after each track's first 2 s (the right robot: the true one nearest the row)."""
    from gtsjax.cli import main
    from gtsjax.cli.demo import demo_model_path
    from gtsjax.io import save_site
    from gtsjax.sensors import URG_04LX
    from gtsjax.sim import simulate
    from gtsjax.sim.emulator import SensorEmulator, log_source

    log, site = simulate("spl-crossing", seed=5)
    save_site(site, tmp_path / "site.json")
    truth = log.truth_poses  # [T, 3 robots, 3]
    # Where a robot is out of view (before it walks in, after it walks out) it believes it stands
    # where it was last (or will be first) seen: a robot does not know it is out of the laser's view.
    held = truth.copy()
    for r in range(truth.shape[1]):
        ok = np.flatnonzero(~np.isnan(truth[:, r, 0]))
        held[:, r] = truth[ok[np.abs(np.arange(len(truth))[:, None] - ok[None, :]).argmin(axis=1)], r]
    base, served = log_source(log), []

    def source(i):
        served.append((time.time(), i))
        return base(i)

    port = free_listening_port()
    ns = doc_sender()
    stop = threading.Event()
    rng = np.random.default_rng(9)

    def pose_of(r):
        def pose():
            i = served[-1][1] if served else 0
            x, y, th = held[i % len(held), r]
            return float(x + rng.normal(0, 0.03)), float(y + rng.normal(0, 0.03)), float(th)
        return pose

    names = ["nao1", "nao2", "nao3"]
    senders = [threading.Thread(target=ns["send_forever"], daemon=True, kwargs=dict(
        pose=pose_of(r), laptop=("127.0.0.1", port), robot=names[r], rate_hz=25.0, stop=stop.is_set))
        for r in range(3)]
    try:
        with SensorEmulator(URG_04LX, source) as emu:
            for th in senders:
                th.start()
            code = main(["run", "--port", emu.path, "--site", str(tmp_path / "site.json"), "--model",
                         str(demo_model_path()), "--out", str(tmp_path / "gtd.csv"), "--frames", "250", "--quiet",
                         "--beliefs", f"udp:127.0.0.1:{port}", "--summary", str(tmp_path / "run.json")])
    finally:
        stop.set()
        for th in senders:
            th.join(5.0)
    err = capsys.readouterr().err
    assert code == 0, err
    assert (tmp_path / "gtd.csv").read_text().splitlines()[0] == ",".join(HEADER) + ",robot"
    rows = read_gtd(tmp_path / "gtd.csv")
    stamps = np.array([r.stamp for r in rows])
    t_served, i_served = np.array(served).T
    nearest = i_served[np.abs(t_served[None, :] - stamps[:, None]).argmin(axis=1)].astype(int) % len(truth)
    xy = np.array([[r.x, r.y] for r in rows])
    d = np.linalg.norm(truth[nearest, :, :2] - xy[:, None, :], axis=2)  # [rows, robots], NaN: not in view
    d = np.where(np.isnan(d), np.inf, d)
    true_robot = d.argmin(axis=1)
    there = d.min(axis=1) < 0.3  # a track is still reported for a moment after its robot walks out
    first: dict = {}
    for r in rows:
        first.setdefault(r.track_id, r.stamp)
    settled = np.array([r.stamp - first[r.track_id] >= 2.0 for r in rows])
    judged = there & settled
    right = np.array([r.robot == names[k] for r, k in zip(rows, true_robot, strict=True)])
    share = float(right[judged].mean())
    wrong = [(round(r.stamp - stamps[0], 1), r.track_id, r.robot, names[k])
             for r, k, j, ok in zip(rows, true_robot, judged, right, strict=True) if j and not ok]
    print(f"robot column right for {share:.4f} of {int(judged.sum())} rows after each track's first 2 s")
    print(err[-800:])
    assert judged.sum() >= 200, (judged.sum(), len(rows))
    assert share >= 0.99, (share, wrong[:20])
    summary = json.loads((tmp_path / "run.json").read_text())["beliefs"]
    assert set(summary["robots"]) == set(names)
    assert all(summary["robots"][n]["poses"] > 100 and summary["robots"][n]["malformed"] == 0 for n in names)
    assert "nao1:" in err and "named on a track" in err


def test_several_lasers_live_loop_writes_the_robot_column(tmp_path):
    """Two lasers' frames through ``run_live_several`` (the several-laser run's loop) with the live
    association over two robots' beliefs (their truth on the frames' clock): the CSV has the robot
    column, and each settled row carries the robot nearest it."""
    import dataclasses

    from gtsjax.cli.demo import demo_model_path
    from gtsjax.drivers.live_several import run_live_several, warm_up_several
    from gtsjax.drivers.several import site_poses
    from gtsjax.io.logs import fit_to_model
    from gtsjax.io.modelfile import load_model
    from gtsjax.io.site import one_sensor
    from gtsjax.sensors import URG_04LX
    from gtsjax.sim.match import simulate_match

    from .test_several import _Frame, _Link

    logs, site = simulate_match("spl-match-2", seed=11, n_robots=2, seconds=6.0, referee=False)
    truth_pose = {n: tuple(map(float, log.extra["truth_sensor_pose"][0])) for n, log in logs.items()}
    site = dataclasses.replace(site, sensors=tuple(dataclasses.replace(s, pose=truth_pose[s.name]) for s in site.sensors))
    model = load_model(demo_model_path()).with_site(one_sensor(site, "north"))
    logs = {n: fit_to_model(log, model, n) for n, log in logs.items()}
    poses = site_poses(site, ["north", "south"])
    compiled = warm_up_several(model, URG_04LX, poses)
    n = logs["north"].n_scans
    t0, wall0 = time.monotonic() + 0.05, time.time() + 0.05
    s0 = logs["north"].stamps[0]
    links = {}
    for name, log in logs.items():
        since = log.stamps - s0
        frames = [_Frame(np.where(log.valid()[i], log.ranges[i], 0.0).astype(np.float32), wall0 + since[i])
                  for i in range(n)]
        links[name] = _Link(URG_04LX, frames, [t0 + s for s in since])
    north = logs["north"]
    t_truth = wall0 + north.stamps - s0
    rng = np.random.default_rng(3)
    beliefs = {}
    for r, name in enumerate(("nao1", "nao2")):
        b = _beliefs_of(north.truth_poses[:, r, :2], t_truth, rng, noise=0.03)
        beliefs[name] = b[b[:, 0] <= t_truth[-1]]
    ident = OnlineIdentity(_Beliefs(beliefs))
    out = tmp_path / "gtd.csv"
    stats, _, _ = run_live_several(links, model, poses, out, compiled=compiled, max_frames=2 * n, duration=30.0,
                                   identity=ident)
    assert out.read_text().splitlines()[0] == ",".join(HEADER) + ",robot"
    rows = read_gtd(out)
    assert stats.frames == 2 * n and rows
    first: dict = {}
    judged = right = 0
    for row in rows:
        first.setdefault(row.track_id, row.stamp)
        i = int(np.abs(t_truth - row.stamp).argmin())
        d = np.hypot(*(north.truth_poses[i, :, :2] - [row.x, row.y]).T)
        if row.stamp - first[row.track_id] >= 2.0 and np.nanmin(d) < 0.3:
            judged += 1
            right += row.robot == ("nao1", "nao2")[int(np.nanargmin(d))]
    assert judged >= 40 and right >= 0.99 * judged, (judged, right)
