"""Build the model shipped inside the package (``gtsjax/data/demo-model.npz``) that ``gtsjax demo``
uses: trained reproducibly on simulated data of the paper's SPL field (three runs of the training grid,
seeds 1, 3 and 4, plus a log with a person walking, so that legs are background) and on real clutter
as background (issue 13): the shared real logs of ``shared/data/logs`` listed in
:data:`BACKGROUND`, with the training defaults of ``gtsjax train``. The real logs in :data:`HELD_OUT`
are kept out of training, to report what the model does on real scans it has never seen
(``scripts/check_background.py``).

    python scripts/build_demo_model.py [--out gtsjax/data/demo-model.npz] [--shared ../shared]
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax

from gtsjax.io.importers import import_log
from gtsjax.io.modelfile import save_model
from gtsjax.sim import simulate
from gtsjax.train import TrainConfig, train

DEMO_CONFIG = dataclasses.replace(TrainConfig(), seed=0)
SHARED = Path(__file__).resolve().parents[2] / "shared"

# Real logs with no robot of ours in view (shared/data/logs/SOURCES.md): (file, ROS topic or None, scans).
# People walking near a scanner on a robot base, indoor clutter with no people, and an office seen by a
# real URG-04LX (its first half; the second half is held out).
BACKGROUND = [
    ("leg_tracker_positive_1.bag", None, None),
    ("leg_tracker_positive_2.bag", None, None),
    ("leg_tracker_positive_3.bag", None, None),
    ("leg_tracker_positive_4.bag", None, None),
    ("leg_tracker_negative_2.bag", "/left_scan", None),
    ("leg_tracker_negative_2.bag", "/right_scan", None),
    ("breezyslam_exp1.dat", None, (0, 378)),
]
# Kept out of training: other recordings of people walking (5: another corridor; 6 and 7: another
# scanner on the robot's back), the clutter seen by the third scanner, and the office's second half.
HELD_OUT = [
    ("leg_tracker_positive_5.bag", None, None),
    ("leg_tracker_positive_6.bag", None, None),
    ("leg_tracker_positive_7.bag", None, None),
    ("leg_tracker_negative_2.bag", "/rear_scan", None),
    ("breezyslam_exp1.dat", None, (378, None)),
]


def load_real(shared: Path, entries):
    """The listed real logs, read as ``gtsjax convert`` reads them, with a name for each."""
    logs, names = [], []
    for name, topic, scans in entries:
        log = import_log(shared / "data" / "logs" / name, topic=topic)
        if scans is not None:
            log = log.slice(*scans) if scans[1] is not None else log.slice(scans[0], log.n_scans)
        logs.append(log)
        names.append(name + (f" {topic}" if topic else "") + (f" scans {scans[0]}:{scans[1] or ''}" if scans else ""))
    return logs, names


def main():
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="gtsjax/data/demo-model.npz")
    ap.add_argument("--shared", type=Path, default=SHARED, help="the shared folder holding data/logs")
    args = ap.parse_args()
    t0 = time.perf_counter()
    # Three runs of the training grid (each draws its own heading in every 45° sector), so that the pose
    # GPs see about 6 000 distinct views of the robot.
    grids = [simulate("spl-train", seed=s) for s in (1, 3, 4)]
    site = grids[0][1]
    legs_log, _ = simulate("spl-legs", seed=2)
    bg, bg_names = load_real(args.shared, BACKGROUND)
    model, report = train([log for log, _ in grids] + [legs_log], site, DEMO_CONFIG,
                          progress=lambda i: print(f"  {i['gp']:<18} n={i['n']:<5} {i['seconds']:6.1f} s", flush=True),
                          background=bg, background_names=bg_names)
    save_model(model, args.out, summary=report)
    print(json.dumps({k: report[k] for k in ("heldout", "heldout_background_logs", "open_set", "envelopes",
                                             "motion_limits", "warnings") if k in report}, indent=1))
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
