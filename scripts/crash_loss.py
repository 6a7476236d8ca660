"""Crash loss: ``gtsjax run --record`` killed with SIGKILL at random moments, the journal recovered each
time, and the scans lost per kill (issue 17); then what a full disk does.

    python scripts/crash_loss.py --kills 100 --out crash-out [--seed 0]

The emulator (in this process, the one behind ``gtsjax emulate``) serves the demo's walking robot on
a URG-04LX at 10 Hz; each round starts ``gtsjax run --record --json`` with the shipped model, waits
for its first row (one round in ten is killed during start-up instead, at a random moment of its
first 3 s), lets it run a random 0–6 s, kills it with SIGKILL, and recovers the journal as a user
would (``gtsjax recover``'s function). Per kill:

- ``tail_s``: from the last scan in the recovered log to the kill (the scan time lost at the end;
  the sensor's period bounds it from below);
- ``lost``: scans the emulator served between the first recorded scan and the kill that the recovered
  log lacks (those still in the pipe, the reader's queue and the step when the process died);
- the recovered log's state (torn bytes cut, CRC failures).

Then a full disk: ``run --record`` into a 1 MiB tmpfs (where this user may mount one; otherwise each
file limited to 1 MiB by ``RLIMIT_FSIZE``), its stderr and exit status, and what is kept.

Prints a summary and writes ``OUT/crash.json``.
"""

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gtsjax.cli.demo import DEMO_SCENARIO, DEMO_SEED, demo_model_path
from gtsjax.errors import InputError
from gtsjax.io import save_site
from gtsjax.io.gtd import read_gtd
from gtsjax.io.record import journal_path, read_journal, recover
from gtsjax.sensors import URG_04LX
from gtsjax.sim import simulate
from gtsjax.sim.emulator import SensorEmulator, log_source


def _run_args(port, site, raw, gtd) -> list[str]:
    return [sys.executable, "-m", "gtsjax", "run", "--port", port, "--site", str(site), "--model",
            str(demo_model_path()), "--out", str(gtd), "--record", str(raw), "--json", "--quiet", "--seconds", "600"]


def one_kill(emu, served, site, out: Path, k: int, rng) -> dict:
    raw, gtd = out / f"raw-{k}.npz", out / f"gtd-{k}.csv"
    for p in (raw, gtd, journal_path(raw)):
        p.unlink(missing_ok=True)
    during_start = rng.random() < 0.1
    t0 = time.time()
    child = subprocess.Popen(_run_args(emu.path, site, raw, gtd), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    if during_start:
        time.sleep(float(rng.uniform(0.0, 3.0)))
    else:
        line = child.stdout.readline()  # the first processed frame
        if not line:
            return {"kill": k, "error": f"run ended before its first frame (exit {child.wait()})"}
        time.sleep(float(rng.uniform(0.0, 6.0)))
    t_kill = time.time()
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    child.stdout.close()
    res = {"kill": k, "during_start": during_start, "after_s": t_kill - t0}
    j = journal_path(raw)
    if not j.exists():
        res.update(recorded=0, tail_s=None, lost=None, note="no journal yet (killed before the recorder opened)")
        return res
    log, report = read_journal(j)
    res.update(torn_bytes=report.get("torn_bytes", 0), bad_crc=report.get("bad_crc", 0))
    if log.n_scans == 0:
        res.update(recorded=0, tail_s=None, lost=None, note="journal with no scan (killed before the first)")
        j.unlink()
        return res
    rec = recover(j)  # as ``gtsjax recover`` does
    period = URG_04LX.period
    t = np.array([s for s, _ in served if rec.stamps[0] - period / 2 <= s <= t_kill])
    res.update(recorded=int(rec.n_scans), served_since_first=int(t.size), lost=int(max(t.size - rec.n_scans, 0)),
               tail_s=float(t_kill - rec.stamps[-1]))
    rows = read_gtd(gtd)  # the CSV is readable (no torn row)
    res["rows"] = len(rows)
    for p in (raw, gtd, j):
        p.unlink(missing_ok=True)
    return res


def full_disk(emu, site, out: Path) -> dict:
    """``run --record`` onto a small filesystem until it is full."""
    d = out / "small-disk"
    d.mkdir(exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(d)],
                             capture_output=True).returncode == 0
    raw, gtd = d / "raw.npz", d / "gtd.csv"
    args = _run_args(emu.path, site, raw, gtd)
    if mounted:
        how = "a 1 MiB tmpfs"
    else:
        how = "RLIMIT_FSIZE of 1 MiB per file (no tmpfs could be mounted)"
        args = [sys.executable, "-c", "import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_FSIZE, "
                "(1 << 20, 1 << 20)); sys.argv[0] = 'gtsjax'; runpy.run_module('gtsjax', run_name='__main__', "
                "alter_sys=True)", *args[3:]]
    try:
        res = subprocess.run(args, capture_output=True, text=True, timeout=300,
                             env={**os.environ, "GTSJAX_CACHE_DIR": "off"})
        rows = len(read_gtd(gtd)) if gtd.exists() else 0
        kept = {"gtd_rows": rows, "journal_exists": journal_path(raw).exists(), "npz_exists": raw.exists(),
                "part_left": raw.with_name(raw.name + ".part").exists()}
        if journal_path(raw).exists():
            log, report = read_journal(journal_path(raw))
            kept.update(journal_scans=int(log.n_scans), torn_bytes=report.get("torn_bytes", 0))
        return {"how": how, "exit": res.returncode,
                "stderr_gtsjax_lines": [x for x in res.stderr.splitlines() if x.startswith("gtsjax")],
                "stderr_lines": len(res.stderr.strip().splitlines()), **kept}
    finally:
        if mounted:
            subprocess.run(["umount", str(d)], capture_output=True)
        shutil.rmtree(d, ignore_errors=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("crash-out"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-full-disk", action="store_true")
    args = ap.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    log, site_obj = simulate(DEMO_SCENARIO, seed=DEMO_SEED)
    site = out / "site.json"
    save_site(site_obj, site)
    base, served = log_source(log), []

    def source(i):
        served.append((time.time(), i))
        return base(i)

    rng = np.random.default_rng(args.seed)
    kills = []
    with SensorEmulator(URG_04LX, source) as emu:
        for k in range(args.kills):
            try:
                r = one_kill(emu, served, site, out, k, rng)
            except InputError as err:
                r = {"kill": k, "error": str(err)}
            kills.append(r)
            print(json.dumps(r), flush=True)
            del served[: max(len(served) - 2000, 0)]
        disk = None if args.no_full_disk else full_disk(emu, site, out)
    done = [r for r in kills if r.get("tail_s") is not None]
    tails = np.array([r["tail_s"] for r in done])
    lost = np.array([r["lost"] for r in done])
    summary = {
        "kills": len(kills), "with_scans": len(done),
        "killed_during_start": sum(bool(r.get("during_start")) for r in kills),
        "errors": [r for r in kills if "error" in r],
        "tail_s_median": float(np.median(tails)) if tails.size else None,
        "tail_s_max": float(tails.max()) if tails.size else None,
        "lost_scans_median": float(np.median(lost)) if lost.size else None,
        "lost_scans_max": int(lost.max()) if lost.size else None,
        "kills_within_1s": int(np.sum(tails <= 1.0)) + (len(kills) - len(done) - sum("error" in r for r in kills)),
        "torn_records_cut": int(sum(r.get("torn_bytes", 0) > 0 for r in kills)),
        "bad_crc": int(sum(r.get("bad_crc", 0) for r in kills)),
        "full_disk": disk,
    }
    (out / "crash.json").write_text(json.dumps({"summary": summary, "kills": kills}, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0 if not summary["errors"] and summary["kills_within_1s"] == len(kills) else 1


if __name__ == "__main__":
    sys.exit(main())
