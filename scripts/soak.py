"""Soak: ``gtsjax run --record`` against the emulated sensor with every fault injected at random, for a
given time, and what came out of it (issue 17).

    python scripts/soak.py --minutes 60 --out soak-out [--busy 2] [--model M.npz --site S.json]

The emulator runs in this process (:class:`~gtsjax.sim.emulator.SensorEmulator`, the one behind
``gtsjax emulate``), so that every frame it formats is known with the scan it holds; ``gtsjax run``
runs as a user starts it, a child process with ``--record``, ``--summary`` and ``--quiet``. The scene
is the lab's UTM-30LX at 40 Hz (default: a static robot put down at five points and lifted away
between them, then the robot walking; served in a loop). Without ``--model``, a lab model is trained
first into the output folder (simulated ``lab-train``, seed 1, as the README's second site).

Faults, all at random from ``--seed``: per data line a corrupted sum (``--line-errors``), per frame
a run of 1–8 bytes lost (``--drop-bytes``), a corrupted sum (``--checksum-errors``), a 0.5 s stall
(``--stalls``), an unplug and re-plug after 0.3 s (``--disconnects``); and, every ``--events-every``
seconds on average, a 2 s stall or an unplug of 1–5 s. ``--busy N`` runs N processes that spin on
the CPU throughout (CPU starvation).

Reported (printed, and in ``OUT/soak.json``):

- frames the emulator sent; frames ``run`` processed; frames lost on the wire by cause (bad sums,
  truncated, malformed), let go by the reader's queue (``dropped``), stale at the start, salvaged;
  reconnects; and the frames no counter accounts for (sent − processed − counted), which should be
  only the few in flight when the run stopped;
- the child's resident memory after its first minute and over its last minute;
- latency over the whole run (median, p99, p99.9, max) and frames later than one scan period;
- against the scene's truth: of the frames sent while a robot had been in view (inside the site's
  bounds) for a second, the share that gave a row (``rows_share``) and the share that gave a row
  within 0.3 m of the robot (``recall``); rows matching no robot, per processed frame; position and
  heading RMSE of the matched rows. Each processed frame is identified with the scan the emulator
  served by comparing their ranges beam by beam (the recording holds every processed frame).
"""

import argparse
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gtsjax.core.geometry import wrap
from gtsjax.drivers.evaluation import match_scan
from gtsjax.io import load_log, load_site, save_site
from gtsjax.io.gtd import read_gtd
from gtsjax.io.record import journal_path, recover
from gtsjax.sensors import get_model
from gtsjax.sim import simulate
from gtsjax.sim.emulator import Faults, SensorEmulator, log_source

MATCH_RADIUS_M = 0.3
SETTLE_S = 1.0


def _cli(*args) -> list[str]:
    return [sys.executable, "-m", "gtsjax", *map(str, args)]


def lab_model(out: Path) -> tuple[Path, Path]:
    """The lab model and site (trained once into ``out``, as the README's second site)."""
    model, site = out / "lab-model.npz", out / "lab-site.json"
    if not model.exists():
        train_log = out / "lab-train.npz"
        subprocess.run(_cli("simulate", "lab-train", "--seed", "1", "--out", train_log, "--site", site), check=True)
        subprocess.run(_cli("train", train_log, "--site", site, "--out", model), check=True)
    return model, site


def scene(specs: list[str]):
    """The scenarios ``NAME:SEED`` simulated and joined end to end: the joined log (for the emulator),
    the truth ``[T, objects, 3]`` (NaN: absent), the classes, the site, the period."""
    logs, site = [], None
    for spec in specs:
        name, _, seed = spec.partition(":")
        log, s = simulate(name, seed=int(seed or 0))
        logs.append(log)
        site = site or s
    first = logs[0]
    n_obj = max(log.truth_poses.shape[1] for log in logs)
    truth = np.concatenate([np.pad(log.truth_poses, ((0, 0), (0, n_obj - log.truth_poses.shape[1]), (0, 0)),
                                   constant_values=np.nan) for log in logs])
    classes = [str(c) for c in max((log.truth_classes for log in logs), key=len)]
    period = float(np.median(np.diff(first.stamps)))
    joined = dataclasses.replace(first, ranges=np.concatenate([log.ranges for log in logs]),
                                 intensities=None if first.intensities is None
                                 else np.concatenate([log.intensities for log in logs]),
                                 stamps=np.arange(truth.shape[0]) * period, truth_poses=truth,
                                 truth_classes=np.asarray(classes), extra={})
    return joined, truth, classes, site, period


def settled_presence(truth: np.ndarray, bounds, period: float) -> tuple[np.ndarray, np.ndarray]:
    """Per scan of the looped scene and object: present inside ``bounds``; and present for at least
    :data:`SETTLE_S` (counted across the loop's seam, as the emulator serves it)."""
    x, y = truth[..., 0], truth[..., 1]
    present = ~np.isnan(x)
    if bounds is not None:
        b = np.asarray(bounds)
        xs, ys = np.nan_to_num(x), np.nan_to_num(y)
        present &= (xs >= b[0]) & (ys >= b[1]) & (xs <= b[2]) & (ys <= b[3])
    T = present.shape[0]
    run = np.zeros(present.shape)
    for t in range(2 * T):  # twice round, so that the seam sees the run before it
        k, prev = t % T, (t - 1) % T
        run[k] = np.where(present[k], (run[prev] + period) if t else 0.0, 0.0)
    return present, present & (run >= SETTLE_S)


def rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def identify(rec_stamps, rec_ranges, served_t, served_i, mm, period):
    """The served scan index of each recorded frame: among the scans served around its stamp, the one
    whose ranges equal its valid beams; -1 where none matches at least 90 % of them."""
    order = np.argsort(served_t)
    st, si = np.asarray(served_t)[order], np.asarray(served_i)[order]
    out = np.full(len(rec_stamps), -1)
    T = mm.shape[0]
    for n, (stamp, r) in enumerate(zip(rec_stamps, rec_ranges, strict=True)):
        lo = np.searchsorted(st, stamp - 0.6 * period)
        hi = np.searchsorted(st, stamp + 4 * period)
        got = np.rint(np.nan_to_num(r) * 1000).astype(np.int64)
        ok = got > 0
        if hi <= lo or not ok.any():
            continue
        cand = si[lo:hi]
        eq = (mm[cand % T][:, ok] == got[ok]).mean(axis=1)
        j = int(np.argmax(eq))
        if eq[j] >= 0.9:
            out[n] = cand[j]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("soak-out"))
    ap.add_argument("--model", type=Path, help="model (default: a lab model trained into --out)")
    ap.add_argument("--site", type=Path, help="site file for run (default: the scene's)")
    ap.add_argument("--scenario", action="append", help="NAME:SEED, repeatable (default: lab-eval:3011, "
                                                          "lab-trajectory:3012)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--line-errors", type=float, default=0.02)
    ap.add_argument("--drop-bytes", type=float, default=0.05)
    ap.add_argument("--checksum-errors", type=float, default=0.01)
    ap.add_argument("--stalls", type=float, default=1e-4)
    ap.add_argument("--disconnects", type=float, default=2e-5)
    ap.add_argument("--events-every", type=float, default=300.0, help="mean seconds between long stalls/unplugs")
    ap.add_argument("--busy", type=int, default=0, help="processes spinning on the CPU throughout")
    ap.add_argument("--analyse", action="store_true", help="only analyse the outputs already in --out")
    args = ap.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.model is None:
        model_path, _ = lab_model(out)
    else:
        model_path = args.model
    specs = args.scenario or ["lab-eval:3011", "lab-trajectory:3012"]
    log, truth, classes, site, period = scene(specs)
    site_path = args.site
    if site_path is None:  # the scene's own site: its landmarks surveyed, the sensor pose a rough guess
        site_path = out / "scene-site.json"
        save_site(site, site_path)
    user_site = load_site(site_path)
    sensor = get_model(log.sensor_model)
    T = log.n_scans
    base = log_source(log)
    mm = np.where(log.valid(), np.rint(np.nan_to_num(log.ranges) * 1000), 0).astype(np.int64)
    served: list[tuple[float, int]] = []

    def source(i):
        served.append((time.time(), i))
        return base(i)

    gtd, raw, summary, err = out / "gtd.csv", out / "raw.npz", out / "summary.json", out / "run.stderr"
    if args.analyse:
        saved = json.loads((out / "soak-run.json").read_text())
        res, rss = saved["res"], saved["rss"]
        served = [tuple(x) for x in np.load(out / "served.npy").tolist()]
        return analyse(res, rss, served, out, truth, classes, T, mm, period, user_site, gtd, raw, summary)
    for p in (gtd, raw, summary, journal_path(raw)):
        p.unlink(missing_ok=True)
    seconds = args.minutes * 60.0
    faults = Faults(checksum_p=args.checksum_errors, line_checksum_p=args.line_errors, drop_p=args.drop_bytes,
                    stall_p=args.stalls, disconnect_p=args.disconnects, seed=args.seed)
    rng = np.random.default_rng(args.seed + 1)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    events, rss = [], []
    t_start = time.monotonic()
    print(f"soak: {seconds / 60:g} min of {' + '.join(specs)} ({T} scans looped, {sensor.name} at "
          f"{1 / period:g} Hz), model {model_path}, busy {args.busy}; output in {out}", flush=True)
    with SensorEmulator(sensor, source, faults=faults) as emu:
        with open(err, "w") as ferr:
            child = subprocess.Popen(_cli("run", "--port", emu.path, "--site", site_path, "--model", model_path,
                                          "--out", gtd, "--record", raw, "--summary", summary, "--quiet",
                                          "--seconds", seconds), stdout=subprocess.DEVNULL, stderr=ferr)
        next_event = time.monotonic() + rng.exponential(args.events_every)
        deadline = time.monotonic() + seconds + 300.0
        hung = False
        start_s = None  # when the run was connected and streaming (its --seconds counts from about then)
        while child.poll() is None:
            now = time.monotonic()
            if start_s is None and "connected to" in err.read_text():
                start_s = now - t_start
            if now > deadline:
                hung = True
                child.send_signal(signal.SIGTERM)
                try:
                    child.wait(30)
                except subprocess.TimeoutExpired:
                    child.kill()
                break
            rss.append((now - t_start, rss_kib(child.pid)))
            if now >= next_event:
                if rng.random() < 0.5:
                    emu.inject_stall(2.0)
                    events.append((now - t_start, "stall 2 s"))
                else:
                    s = float(rng.uniform(1.0, 5.0))
                    emu.inject_disconnect(reopen_after_s=s)
                    events.append((now - t_start, f"unplug {s:.1f} s"))
                next_event = now + rng.exponential(args.events_every)
            time.sleep(2.0)
        code = child.wait()
        sent, injected = emu.frames_sent, emu.faults
    for b in busy:
        b.kill()
    res = {"minutes": args.minutes, "scenarios": specs, "busy": args.busy, "exit": code, "hung": hung,
           "faults_injected": {**injected.__dict__, "long_events": [f"{t:.0f} s: {e}" for t, e in events]},
           "frames_sent": sent, "frames_formatted": len(served), "start_s": start_s or 0.0}
    np.save(out / "served.npy", np.asarray(served, float).reshape(-1, 2))
    (out / "soak-run.json").write_text(json.dumps({"res": res, "rss": rss}) + "\n")
    if not summary.exists():
        res["error"] = f"no summary from run (exit {code}); its stderr: {err.read_text()[-2000:]}"
        _report(res, out)
        return 1
    return analyse(res, rss, served, out, truth, classes, T, mm, period, user_site, gtd, raw, summary)


def analyse(res, rss, served, out, truth, classes, T, mm, period, user_site, gtd, raw, summary) -> int:
    """Counters, memory, latency and the rows against the truth, from the run's outputs."""
    code, hung, sent = res["exit"], res["hung"], res["frames_sent"]
    sm = json.loads(summary.read_text())
    res["run"] = sm
    # Every frame sent is received by the link or lost on the wire (counted by cause); every frame
    # received is processed, let go by the full queue, let go as stale at the start, or was in flight
    # when the run stopped. What no counter explains: frames lost at reconnects (cut by the unplugging).
    received = sm.get("received", sm["frames"])
    wire = sm["checksum_errors"] + sm["truncated"] + sm["malformed"]
    res["frames_received"] = received
    res["frames_processed"] = sm["frames"]
    res["frames_lost_on_wire"] = wire
    res["frames_let_go"] = sm["dropped"] + sm.get("stale", 0)
    res["frames_counted_lost"] = wire + res["frames_let_go"]
    res["frames_unaccounted"] = sent - received - wire
    res["frames_in_flight_at_stop"] = received - sm["frames"] - res["frames_let_go"]
    # Memory: after the first minute of streaming, and over the last minute.
    r = np.array([(t, k) for t, k in rss if k is not None], float).reshape(-1, 2)
    if r.size:
        # Streaming: after the first minute until the run's duration (closing the recording after it,
        # with its own memory, is reported as the maximum).
        end = res["minutes"] * 60.0 + float(res.get("start_s", 0.0))
        first = r[(r[:, 0] >= 60) & (r[:, 0] < 120), 1]
        streaming = r[r[:, 0] <= end]
        last = streaming[streaming[:, 0] >= streaming[-1, 0] - 60, 1] if streaming.size else r[-1:, 1]
        first = first if first.size else r[:1, 1]
        res["rss_mib_start"], res["rss_mib_end"] = float(np.median(first) / 1024), float(np.median(last) / 1024)
        res["rss_mib_max_streaming"] = float(streaming[:, 1].max() / 1024) if streaming.size else float("nan")
        res["rss_mib_max"] = float(r[:, 1].max() / 1024)
        res["rss_growth_pct"] = 100 * (res["rss_mib_end"] / res["rss_mib_start"] - 1)
    # Against the truth.
    if not raw.exists() and journal_path(raw).exists():
        recover(journal_path(raw), raw)
    rec = load_log(raw)
    if "received" not in sm:  # a summary from before ``received`` (its ``frames`` was the link's): count the recording
        res["frames_processed"] = int(rec.n_scans)
        res["frames_in_flight_at_stop"] = received - rec.n_scans - res["frames_let_go"]
    sv = np.asarray(served, float).reshape(-1, 2)
    si = sv[:, 1].astype(np.int64)
    idx = identify(rec.stamps, rec.ranges, sv[:, 0], si, mm, period)
    res["frames_unidentified"] = int(np.sum(idx < 0))
    present, settled = settled_presence(truth, user_site.bounds, period)
    rows_by_frame: dict[int, list] = {}
    rec_pos = {round(float(s), 5): n for n, s in enumerate(rec.stamps)}
    orphan_rows = 0
    for row in read_gtd(gtd):
        n = rec_pos.get(round(row.stamp, 5))
        if n is None:
            orphan_rows += 1
            continue
        rows_by_frame.setdefault(n, []).append(row)
    matched_k: dict[int, bool] = {}  # served index -> a row matched its robot (every settled object)
    with_rows: dict[int, bool] = {}
    false_rows, e_pos, e_th = 0, [], []
    for n, i in enumerate(idx):
        rows = rows_by_frame.get(n, [])
        if i < 0:
            false_rows += len(rows)  # a frame that cannot be placed: its rows cannot be credited
            continue
        k = i % T
        txy = np.nan_to_num(truth[k, :, :2])
        rxy = np.array([[r.x, r.y] for r in rows]).reshape(-1, 2)
        hit = np.full(truth.shape[1], -1)
        for c in set(classes):
            sel = np.array([cl == c for cl in classes])
            ok_r = np.array([r.cls == c for r in rows], bool)
            mm_c = match_scan(txy, present[k] & sel, rxy, ok_r, MATCH_RADIUS_M) if rows else np.full(len(sel), -1)
            hit = np.where(sel, mm_c, hit)
        false_rows += len(rows) - int((hit >= 0).sum())
        if settled[k].any():
            matched_k[int(i)] = bool(np.all(hit[settled[k]] >= 0))
            with_rows[int(i)] = bool(rows)
        for m in np.flatnonzero((hit >= 0) & settled[k]):
            r = rows[hit[m]]
            e_pos.append(np.hypot(r.x - truth[k, m, 0], r.y - truth[k, m, 1]))
            e_th.append(wrap(r.theta - truth[k, m, 2]))
    # The frames sent while the run was reading: from its first processed frame to its last (the
    # emulator keeps streaming while a run starts and until it sends QT).
    t_run = (rec.stamps[0] - period, rec.stamps[-1] + period)
    during = (sv[:, 0] >= t_run[0]) & (sv[:, 0] <= t_run[1])
    res["frames_sent_outside_the_run"] = int(np.sum(~during))
    served_settled = [i for i in si[during] if settled[i % T].any()]
    n_settled = len(served_settled)
    res["frames_sent_with_robot"] = n_settled
    res["rows_share"] = sum(with_rows.get(int(i), False) for i in served_settled) / max(n_settled, 1)
    res["recall"] = sum(matched_k.get(int(i), False) for i in served_settled) / max(n_settled, 1)
    res["false_rows"] = false_rows
    res["false_rows_per_frame"] = false_rows / max(len(idx), 1)
    res["rows_unplaced"] = orphan_rows
    e_pos, e_th = np.asarray(e_pos), np.asarray(e_th)
    if e_pos.size:
        res["position_rmse_cm"] = float(100 * np.sqrt(np.mean(e_pos**2)))
        res["heading_rmse_deg"] = float(np.degrees(np.sqrt(np.mean(e_th**2))))
    _report(res, out)
    ok = (code == 0 and not hung and res["recall"] >= 0.95 and res["false_rows_per_frame"] <= 0.005
          and res.get("rss_growth_pct", 0.0) <= 5.0)
    return 0 if ok else 1


def _report(res: dict, out: Path) -> None:
    (out / "soak.json").write_text(json.dumps(res, indent=1, default=str) + "\n")
    sm = res.get("run", {})
    lines = [
        f"exit {res['exit']}{' (hung: stopped by the script)' if res['hung'] else ''}; "
        f"{res['minutes']:g} min, busy {res['busy']}",
        f"frames: sent {res['frames_sent']}, received {res.get('frames_received')}, processed "
        f"{res.get('frames_processed')}; lost on the wire {res.get('frames_lost_on_wire')} (checksum "
        f"{sm.get('checksum_errors')}, truncated {sm.get('truncated')}, malformed {sm.get('malformed')}), let go "
        f"{res.get('frames_let_go')} (full queue {sm.get('dropped')}, stale {sm.get('stale')}), in flight at the "
        f"stop {res.get('frames_in_flight_at_stop')}, unaccounted {res.get('frames_unaccounted')}; salvaged "
        f"{sm.get('salvaged')}; reconnects {sm.get('reconnects')}, timeouts {sm.get('timeouts')}",
        f"faults injected: {res['faults_injected']}",
        f"latency (whole run): median {sm.get('latency_ms_run_median', float('nan')):.2f} ms, p99 "
        f"{sm.get('latency_ms_run_p99', float('nan')):.2f}, p99.9 {sm.get('latency_ms_run_p999', float('nan')):.2f}, "
        f"max {sm.get('latency_ms_max', float('nan')):.1f}; late {sm.get('late')}",
        f"memory: {res.get('rss_mib_start', float('nan')):.1f} MiB after the first minute, "
        f"{res.get('rss_mib_end', float('nan')):.1f} MiB over the last of streaming (growth "
        f"{res.get('rss_growth_pct', float('nan')):+.2f} %), max {res.get('rss_mib_max_streaming', float('nan')):.1f} "
        f"streaming, {res.get('rss_mib_max', float('nan')):.1f} closing the recording",
    ]
    if "recall" in res:
        lines.append(
            f"truth: {res['frames_sent_with_robot']} frames sent with a robot in view; rows for "
            f"{100 * res['rows_share']:.2f} %, recall {100 * res['recall']:.2f} %, false rows "
            f"{res['false_rows']} ({res['false_rows_per_frame']:.4f} per frame); position RMSE "
            f"{res.get('position_rmse_cm', float('nan')):.1f} cm, heading {res.get('heading_rmse_deg', float('nan')):.1f}°;"
            f" frames unidentified {res['frames_unidentified']}, rows unplaced {res['rows_unplaced']}")
    if "error" in res:
        lines.append(res["error"])
    print("\n".join(lines), flush=True)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
