"""The table of docs/recordings.md: each recording style of the tests (``tests/test_recordings.py``), trained
with the tests' small settings or the defaults, its training time, what training said, and how the model
tracks held-out scenes.

    python scripts/recordings.py [--defaults] [--case SUBSTRING]

Prints a Markdown table (and one line per case as it ends, on stderr).
"""

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from gtsjax.cli import use_compile_cache  # noqa: E402
from gtsjax.drivers.evaluation import evaluate_log  # noqa: E402
from gtsjax.sim import check_scene, recording  # noqa: E402
from gtsjax.train import TrainConfig, train  # noqa: E402
from tests.test_recordings import CASES, SMALL  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--defaults", action="store_true", help="train with gtsjax train's defaults, not the tests' small settings")
    ap.add_argument("--case", default="", help="only the cases whose name holds this")
    args = ap.parse_args()
    use_compile_cache()
    cfg = TrainConfig() if args.defaults else SMALL
    rows = []
    for name, case in CASES.items():
        if args.case not in name:
            continue
        seed, check_seed = case.get("seeds", (1, 2))
        log, site = recording(case["site"], case["style"], seed=seed, rate_hz=case["rate_hz"], clutter=case["clutter"],
                              outline=case["outline"], seconds=case["seconds"])
        t0 = time.perf_counter()
        model, report = train([log], site, dataclasses.replace(case.get("config", cfg)))
        seconds = time.perf_counter() - t0
        scores = {}
        for kind in ("static", "walking"):
            ev, es = check_scene(case["site"], kind, seed=check_seed, rate_hz=case["rate_hz"], outline=case["outline"],
                                 clutter=case["clutter"])
            scores[kind] = evaluate_log(model.with_site(es), ev)
        said = sorted({"unseen sides" if "is seen from" in w else "half-turn symmetric" if "half a turn" in w
                       else "unseen field" if "is labelled in" in w else "implausible value" if "plausible range" in w else "other" for w in report["warnings"]}
                      | {"detected in few scans" for p in report["pipeline_problems"] if "detected in only" in p})
        motion = report["motion_limits"]["robot"]
        row = (f"| {name} | {log.n_scans} | {seconds:.0f} s | {motion['max_speed']:.2f} ({motion['max_speed_from']}) | "
               f"{'; '.join(said) or '–'} | {'pass' if not report['pipeline_problems'] else 'FAIL'} | "
               + " | ".join(f"{100 * s['recall']:.1f} % / {100 * s['position_rmse_m']:.1f} cm / "
                            f"{s['heading_rmse_deg']:.1f}° ({s['heading_median_deg']:.1f}°)"
                            for s in scores.values()) + " |")
        print(row, file=sys.stderr, flush=True)
        rows.append(row)
    print("| recording | scans | training | max speed [m/s] | training warned | tracking check | static: recall / "
          "position RMSE / heading RMSE (median) | walking: same |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
