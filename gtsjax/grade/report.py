"""A grade written down: the summary table (Markdown, for a person; JSON, for a program) and the
figures' data. Units in the JSON are in each key's name; the Markdown rounds for reading."""

import json
import math
import os
from pathlib import Path

import numpy as np

from .metrics import JUMP_FACTOR, JUMP_M, JUMP_RAD, JUMP_SPEED, JUMP_TURN_RATE, LOST_M, LOST_RAD, SETTLE_S


def _num(v, scale=1.0, fmt="{:.1f}"):
    return "–" if v is None or not math.isfinite(v) else fmt.format(v * scale)


def robot_json(g) -> dict:
    s = g.summary
    return {
        "robot": g.name,
        "source": g.source,
        "frame": {"kind": g.frame_kind, "tx_m": g.frame[0], "ty_m": g.frame[1], "phi_rad": g.frame[2],
                  **({"support_share": g.frame_support} if g.frame_kind == "fit" else {})},
        "clock": {"offset_s": g.clock.offset, "se_s": None if not math.isfinite(g.clock.se) else g.clock.se,
                  "given": g.clock.fixed},
        "bias_in_robot_frame": {"ahead_m": g.clock.bias[0], "left_m": g.clock.bias[1], "heading_rad": g.clock.bias[2]},
        "tracks": [{"track_id": tid, "from_s": a, "to_s": b} for tid, a, b in g.spans],
        "unseen_share": 1.0 - s["seen_share"],
        **{k: v for k, v in s.items() if k != "seen_share"},
        "hint": g.hint or None,
    }


def _clean(x):
    """NaN and infinities as JSON's null (``json.dump`` would write the non-standard ``NaN``)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        return _clean(x.item())
    return x


def write_json(grades, path: str | os.PathLike, meta: dict) -> None:
    Path(path).write_text(json.dumps(_clean({**meta, "robots": [robot_json(g) for g in grades]}), indent=1) + "\n")


def table_rows(grades) -> list[list[str]]:
    """One row per robot: the columns of :data:`COLUMNS`."""
    out = []
    for g in grades:
        s = g.summary
        p, h = s["position_m"], s["heading_rad"]
        clock = f"{g.clock.offset:+.3f}" + ("" if g.clock.fixed else f" ± {_num(g.clock.se, 1000, '{:.0f}')} ms"
                                             if math.isfinite(g.clock.se) else "")
        if not g.clock.fixed and not s["seen_share"] > 0:  # no row to estimate it from: the search's start
            clock = "– (never seen)"
        rec = s["recovery_s"]
        out.append([
            g.name, _frame_text(g), clock, ", ".join(str(t) for t in dict.fromkeys(tid for tid, _, _ in g.spans)) or "–",
            _num(1.0 - s["seen_share"], 100, "{:.0f} %"),
            f"{_num(p['rmse'], 100)} / {_num(p['median'], 100)} / {_num(p['p95'], 100)} / {_num(p['max'], 100)}",
            f"{_num(h['rmse'], 180 / math.pi)} / {_num(h['median'], 180 / math.pi)} / {_num(h['p95'], 180 / math.pi)}"
            f" / {_num(h['max'], 180 / math.pi)}",
            _num(s["within_gt_2sigma_share"], 100, "{:.0f} %"), _num(s["lost_share"], 100, "{:.1f} %"),
            f"{_num(s['rpe']['1s']['trans']['rmse'], 100)} / {_num(s['rpe']['5s']['trans']['rmse'], 100)}",
            f"{sum(1 for j in g.jumps)} ({sum(1 for j in g.jumps if j.lost)} lost; "
            f"{_num(rec['median'], 1, '{:.1f}')} s median)" if g.jumps else "0",
        ])
    return out


COLUMNS = ("robot", "frame", "clock offset [s]", "tracks", "unseen", "position error RMSE / median / p95 / max [cm]",
           "heading error RMSE / median / p95 / max [°]", "within GT 2σ", "lost", "RPE 1 s / 5 s [cm]",
           "jumps (lost; recovery)")


def _frame_text(g) -> str:
    if g.frame_kind == "fit":
        tx, ty, phi = g.frame
        return f"fit: ({tx:.3f}, {ty:.3f}) m, {math.degrees(phi):.2f}°"
    return g.frame_kind


def markdown(grades, meta: dict) -> str:
    t0 = meta["t0"]
    lines = [f"# Grade of {len(grades)} robot{'s' if len(grades) != 1 else ''} against {meta['gtd']}", "",
             f"Times are seconds from the ground truth's first row ({t0!r} on the laptop's clock).", ""]
    lines += ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(r) + " |" for r in table_rows(grades)]
    lines += ["", "Errors are the robot's belief (at its clock offset, in the field's frame) against the ground "
              f"truth's rows of the tracks that were it. *Lost*: error over {LOST_M:g} m or "
              f"{math.degrees(LOST_RAD):.0f}°. *Within GT 2σ*: rows whose position error is inside the ground truth's "
              "own 2-σ uncertainty (not the robot's to answer for). *Jumps*: the belief moving over "
              f"{JUMP_M:g} m faster than {JUMP_SPEED:g} m/s, or turning over {math.degrees(JUMP_RAD):.0f}° faster than "
              f"{JUMP_TURN_RATE:g} rad/s, and {JUMP_FACTOR:g}× faster than about then; recovery, until back within "
              f"the lost limits for {SETTLE_S:g} s.", ""]
    for g in grades:
        s = g.summary
        lines.append(f"## {g.name}")
        lines.append("")
        lines.append(f"- poses: {g.source}")
        lines.append("- tracks: " + ("; ".join(f"{tid} from {a - t0:.2f} to {b - t0:.2f} s" for tid, a, b in g.spans)
                                             or "none"))
        b = g.clock.bias
        lines.append(f"- bias in its own frame: {100 * b[0]:+.1f} cm ahead, {100 * b[1]:+.1f} cm left, "
                     f"{math.degrees(b[2]):+.1f}° (estimated with the clock offset)")
        lines.append(f"- position RMSE net of the ground truth's own variance: "
                     f"{_num(s['position_rmse_net_of_gt_m'], 100)} cm")
        if g.jumps:
            lines.append("- jumps: " + "; ".join(
                f"{j.stamp - t0:.2f} s, {100 * j.size_m:.0f} cm" + (f", lost, back in {_num(j.recovery_s, 1, '{:.2f}')} s"
                                                                   if j.lost else "") for j in g.jumps))
        if g.hint:
            lines.append(f"- **{g.hint}**")
        lines.append("")
    return "\n".join(lines)
