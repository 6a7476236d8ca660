"""Fuzzing at scale (issue 17): damaged SCIP frames by the million through the stream decoder, and
damaged frames through the live loop.

    python scripts/fuzz_decoder.py --frames 1000000 [--workers 2] [--live-frames 3000] [--seed 0]

**Decoder.** Each case is a short stream (a valid scan reply of a random command: MD, MS, ME, GD,
GS, GE, ND, NE, HD, HE, random range, cluster and values, between two intact replies), damaged by
one to three mutations drawn from: bytes flipped, a run of bytes lost, random bytes inserted, a run
duplicated, the reply cut short, a LF or CR inserted, a line made longer than the decoder's limit,
two replies spliced. It goes through :class:`~gtsjax.io.scip.StreamDecoder` in random chunks (which
must never raise) and through the strict :func:`~gtsjax.io.scip.parse_replies` (which may raise only
:class:`~gtsjax.io.scip.ScipError`). Checked per case: no other exception, no case slower than 1 s
(a hang), the intact replies around the damage delivered, and every delivered frame with the damaged
reply's timestamp compared with what was sent on its valid beams. Frames delivered with beams that
differ are counted, not failed: SCIP's 6-bit additive sums cannot see two changes in one line that
cancel (``U``→``E`` and ``C``→``S``), nor a whole line duplicated where a cut removed another
(``unmarked_changed``: no line marked bad; ``marked_wrong``: some lines marked, others wrong). The
decoder also marks a line holding a character outside the encoding, which catches a character moved
by 64 (its sum unchanged).

**Live loop.** The emulator with a hook that damages its data blocks the same ways, ``run_live``
with the shipped model: the loop must neither raise nor stall, and every frame it gets is
processed.

Prints a summary and exits 1 on any finding.
"""

import argparse
import json
import multiprocessing as mp
import sys
import threading
import time
from pathlib import Path

import numpy as np

from gtsjax.io import scip
from gtsjax.sensors import URG_04LX, UTM_30LX

COMMANDS = ("MD", "MS", "ME", "GD", "GS", "GE", "ND", "NE", "HD", "HE")
MAX_LINE = 1024  # StreamDecoder's default


def _reply(rng, code: str) -> tuple[bytes, scip.ScanFrame | None]:
    """A valid scan reply of ``code`` and its strict decoding."""
    model = URG_04LX if code[0] != "N" and code[0] != "H" and rng.random() < 0.5 else UTM_30LX
    start = int(rng.integers(model.amin, model.amax))
    end = int(rng.integers(start, min(start + 400, model.amax) + 1))
    cluster = int(rng.choice([1, 1, 1, 2, 3]))
    build = {"MD": scip.md_command, "MS": scip.ms_command, "ME": scip.me_command}.get(code)
    if build is not None:
        cmd = scip.parse_command(build(start, end, cluster, 0, 0).rstrip(b"\n"))
    else:
        cmd = scip.parse_command(f"{code}{start:04d}{end:04d}{cluster:02d}".encode() +
                                 (b"000" if code[0] == "N" else b""))
    n = cmd.n_values
    top = (1 << (6 * cmd.chars)) - 1
    ranges = rng.integers(0, min(top, 30000), n)
    inten = rng.integers(0, min(top, 5000), n) if cmd.has_intensity else None
    if cmd.is_multiecho and rng.random() < 0.5:
        extra = np.where(rng.random(n) < 0.2, rng.integers(20, min(top, 30000), n), 0)
        ranges = np.stack([ranges, extra], axis=1)
        if inten is not None:
            inten = np.stack([inten, np.where(extra > 0, rng.integers(0, 5000, n), 0)], axis=1)
    stamp = int(rng.integers(0, 1 << 24))
    status = scip.STATUS_DATA if cmd.is_continuous else scip.STATUS_OK
    data = scip.format_scan_frame(cmd, status, stamp, ranges, inten)
    return data, scip.parse_replies(data)[0]


def mutate(rng, data: bytes, other: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        kind = int(rng.integers(0, 9))
        n = len(b)
        if n == 0:
            break
        at = int(rng.integers(0, n))
        if kind == 0:  # bytes flipped
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(0, n))
                b[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:  # a run lost
            del b[at : at + int(rng.integers(1, 9))]
        elif kind == 2:  # random bytes inserted
            b[at:at] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
        elif kind == 3:  # a run duplicated
            k = int(rng.integers(1, 70))
            b[at:at] = b[at : at + k]
        elif kind == 4:  # cut short
            del b[at:]
        elif kind == 5:  # a LF or CR inserted
            b[at:at] = b"\n" if rng.random() < 0.5 else b"\r"
        elif kind == 6:  # a line too long
            b[at:at] = b"0" * (MAX_LINE + int(rng.integers(1, 100)))
        elif kind == 7:  # spliced with another reply
            j = int(rng.integers(0, len(other)))
            b = b[:at] + bytearray(other[j:])
        else:  # a character moved by 64 (keeps the line's sum)
            if 0x30 <= b[at] < 0x40:
                b[at] += 0x40
    return bytes(b)


def fuzz_chunk(args) -> dict:
    try:
        return _fuzz_chunk(*args)
    except Exception as err:  # noqa: BLE001 - reported, not raised (a pool cannot always pickle it)
        return {"cases": 0, "exceptions": [f"chunk {args[0]} outside the decoder: {type(err).__name__}: {err}"]}


def _fuzz_chunk(seed: int, n_cases: int) -> dict:
    rng = np.random.default_rng(seed)
    out = {"cases": 0, "exceptions": [], "slow": [], "lost_neighbours": 0, "delivered": 0, "marked": 0,
           "exact": 0, "unmarked_changed": 0, "marked_wrong": 0, "strict_ok": 0, "max_case_s": 0.0}
    pre, _ = _reply(rng, "GD")
    for k in range(n_cases):
        code = COMMANDS[int(rng.integers(0, len(COMMANDS)))]
        data, sent = _reply(rng, code)
        post, post_sent = _reply(rng, "MD")
        bad = mutate(rng, data, post)
        stream = pre + bad + post
        t0 = time.perf_counter()
        try:
            dec = scip.StreamDecoder()
            got, i = [], 0
            while i < len(stream):
                j = i + int(rng.integers(1, 4096))
                got += dec.feed(stream[i:j])
                i = j
            got += dec.flush()
            try:
                scip.parse_replies(bad)
                out["strict_ok"] += 1
            except scip.ScipError:
                pass
        except Exception as err:  # noqa: BLE001 - the finding
            out["exceptions"].append(f"case {seed}/{k}: {type(err).__name__}: {err}"[:300])
            continue
        dt = time.perf_counter() - t0
        out["max_case_s"] = max(out["max_case_s"], dt)
        if dt > 1.0:
            out["slow"].append(f"case {seed}/{k}: {dt:.2f} s")
        out["cases"] += 1
        frames = [g for g in got if isinstance(g, scip.ScanFrame)]
        if not any(f.timestamp_ms == post_sent.timestamp_ms and f.command == post_sent.command for f in frames):
            out["lost_neighbours"] += 1  # the intact reply after the damage (a splice may swallow it)
        for f in frames:
            if f.timestamp_ms != sent.timestamp_ms or f.command[:2] != code or f.n_values != sent.n_values:
                continue
            out["delivered"] += 1
            same = np.array_equal(f.ranges_mm[f.valid], sent.ranges_mm[f.valid])
            if f.bad_lines:
                out["marked"] += 1
                out["marked_wrong"] += int(not same)  # a marked frame's valid beams must still be as sent
            elif same and np.array_equal(f.valid, sent.valid):
                out["exact"] += 1
            else:
                out["unmarked_changed"] += 1
    return out


def fuzz_decoder(n: int, workers: int, seed: int) -> dict:
    chunk = 20_000
    jobs = [(seed * 1_000_003 + i, min(chunk, n - i * chunk)) for i in range((n + chunk - 1) // chunk)]
    total = {"cases": 0, "exceptions": [], "slow": [], "lost_neighbours": 0, "delivered": 0, "marked": 0, "exact": 0,
             "unmarked_changed": 0, "marked_wrong": 0, "strict_ok": 0, "max_case_s": 0.0}
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(workers) as pool:
        for r in pool.imap_unordered(fuzz_chunk, jobs):
            for key, v in r.items():  # a failed chunk reports only cases and exceptions
                total[key] = max(total[key], v) if key == "max_case_s" else total[key] + v
            print(f"  {total['cases']} cases, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    total["seconds"] = time.perf_counter() - t0
    return total


def fuzz_live(n_frames: int, seed: int) -> dict:
    """Damaged data blocks from the emulator through the link and ``run_live`` with the shipped model."""
    from gtsjax.cli.demo import DEMO_SCENARIO, DEMO_SEED, demo_model_path
    from gtsjax.drivers.live import run_live, warm_up
    from gtsjax.io.modelfile import load_model
    from gtsjax.io.serial import Link
    from gtsjax.sim import simulate
    from gtsjax.sim.emulator import SensorEmulator

    rng = np.random.default_rng(seed)
    log, site = simulate(DEMO_SCENARIO, seed=DEMO_SEED)
    model = load_model(demo_model_path()).with_site(site)
    damaged = {"blocks": 0}

    class Fuzzing(SensorEmulator):
        def _send(self, data: bytes) -> bool:
            if data[:2] in (b"MD", b"ME", b"MS") and data.split(b"\n", 2)[1][:2] == b"99" and rng.random() < 0.5:
                damaged["blocks"] += 1
                data = mutate(rng, data, data)
            return super()._send(data)

    import tempfile

    compiled = warm_up(model, URG_04LX)  # before the link streams: no frame waits for the compiler
    with Fuzzing(URG_04LX, log) as emu, Link(emu.path) as link, tempfile.TemporaryDirectory() as d:
        stop = threading.Event()
        t0 = time.monotonic()
        error = None
        try:
            stats = run_live(link, model, Path(d) / "gtd.csv", max_frames=n_frames, stop=stop, compiled=compiled,
                             duration=n_frames * URG_04LX.period * 4 + 60)
        except Exception as err:  # noqa: BLE001 - the finding
            error, stats = f"{type(err).__name__}: {err}", None
        ls = link.stats
        sent = emu.frames_sent
    res = {"seconds": time.monotonic() - t0, "frames_sent": sent, "blocks_damaged": damaged["blocks"],
           "error": error, "link": {k: v for k, v in ls.__dict__.items() if k != "last_error"}}
    if stats is not None:
        res.update(processed=stats.frames, stale=stats.stale, rows=stats.rows, late=stats.late)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--live-frames", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="also write the summary here (JSON)")
    args = ap.parse_args(argv)
    res = {"decoder": fuzz_decoder(args.frames, args.workers, args.seed) if args.frames else None,
           "live": fuzz_live(args.live_frames, args.seed) if args.live_frames else None}
    text = json.dumps(res, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    d, live = res["decoder"], res["live"]
    bad = (d is not None and (d["exceptions"] or d["slow"])) or (live is not None and live["error"])
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
