"""SCIP 2.0 codec: decoding one UTM-30LX ``ME`` frame (1081 beams, range and intensity, 3-character
encoding), the live link's per-scan host cost at 40 Hz; also the streaming decoder on the same frame
and encoding it (what the emulator does per scan). Pure Python and NumPy, no JAX.
"""

import numpy as np

from gtsjax.io import scip
from gtsjax.sensors import UTM_30LX

SECTION = "scip"


def me_frame() -> bytes:
    """One UTM-30LX ``ME`` data block with random ranges and intensities."""
    rng = np.random.default_rng(0)
    n = UTM_30LX.n_beams
    echo = scip.parse_command(scip.me_command(UTM_30LX.amin, UTM_30LX.amax)[:-1]).with_remaining(0)
    return scip.format_md_frame(echo, 1_234_567, rng.integers(0, 30_000, n), rng.integers(0, 10_000, n))


def run(ctx) -> None:
    repeats = 300 if ctx.quick else 5000
    frame = me_frame()
    decoded = scip.parse_reply(frame)
    if not (isinstance(decoded, scip.ScanFrame) and decoded.n_values == UTM_30LX.n_beams
            and decoded.intensities is not None):
        raise RuntimeError("the benchmark frame does not decode to 1081 ranges and intensities")
    dec = scip.StreamDecoder()

    def stream_one(i):
        (out,) = dec.feed(frame)
        return out

    cases = {
        "scip.decode_me_1081": ("SCIP decode, one UTM-30LX ME frame (parse_reply, strict)",
                                lambda i: scip.parse_reply(frame)),
        "scip.stream_me_1081": ("SCIP stream decoder, one ME frame (StreamDecoder.feed)", stream_one),
        "scip.encode_me_1081": ("SCIP encode, one ME frame (format_md_frame)", lambda i: scip.format_md_frame(
            decoded.command, decoded.timestamp_ms, decoded.raw_ranges, decoded.intensities)),
    }
    for name, (label, fn) in cases.items():
        ctx.results.add(name, "us", ctx.time_calls(fn, repeats, warmup=max(50, repeats // 10)), section=SECTION,
                        label=label, frame_bytes=len(frame))
