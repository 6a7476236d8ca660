"""Phantom robots on real scans with no robot (issue 13): replay real logs through a model and count
what it reports. By default the shipped model on the shared real logs kept out of its training
(``scripts/build_demo_model.py``'s ``HELD_OUT``), on the SPL demo site (the laser on the side line at
(3, 4) looking into a 6 × 4 m field) and on the same site without bounds (every detection tracked).

    python scripts/check_background.py [--model M.npz] [--confirm-scans N] [--shared ../shared] [LOG[@TOPIC] ...]

Prints a Markdown table per site: scans, candidates kept by the binary filters, candidates taken for a
mobile class (after the open-set test), candidates dropped as unlike their class's examples or
outside its shape envelope, and the mobile classes' reported rows and tracks (what a user would see
in the GTD CSV). Wider fields of view are cropped to the model's, as ``gtsjax replay --crop-fov`` does.
"""

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from build_demo_model import HELD_OUT, SHARED, load_real  # noqa: E402

from gtsjax.cli.demo import demo_model_path  # noqa: E402
from gtsjax.drivers.batch import process_log  # noqa: E402
from gtsjax.io import to_scans  # noqa: E402
from gtsjax.io.importers import import_log  # noqa: E402
from gtsjax.io.logs import fit_to_model  # noqa: E402
from gtsjax.io.modelfile import load_model  # noqa: E402
from gtsjax.io.site import Landmark, Site  # noqa: E402

SPL_SITE = Site(tuple(Landmark("post", x, y) for x, y in ((0, 1.3), (0, 2.7), (6, 1.3), (6, 2.7))),
                (3.0, 4.0, -np.pi / 2), (0.0, 0.0, 6.0, 4.0))


def count(model, log) -> dict:
    """Replay ``log`` (already fitted to the model) and count per scan and per track."""
    _, out = process_log(model, to_scans(log, model.n_beams))
    mobile = np.asarray(model.tracker.tracked)
    rows = out.track_mask & mobile[out.track_class]
    ids = set(np.asarray(out.track_id)[rows].tolist())
    return {"scans": log.n_scans, "kept": int(np.sum(out.n_kept)),
            "taken": int(np.sum(out.det_mask & mobile[out.det_class])),
            "unlike": int(np.sum(out.unlike)), "off_envelope": int(np.sum(out.off_envelope)),
            "rows": int(np.sum(rows)), "tracks": len(ids)}


def main():
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", help="logs to replay, LOG or LOG@TOPIC (default: the held-out shared logs)")
    ap.add_argument("--model", type=Path, default=demo_model_path())
    ap.add_argument("--shared", type=Path, default=SHARED)
    ap.add_argument("--confirm-scans", type=int, default=None, help="as gtsjax replay's (default: the model's)")
    args = ap.parse_args()
    model = load_model(args.model).with_confirmation(args.confirm_scans)
    if args.logs:
        entries = []
        for item in args.logs:
            path, _, topic = item.partition("@")
            entries.append((path, import_log(path, topic=topic or None)))
    else:
        logs, names = load_real(args.shared, HELD_OUT)
        entries = list(zip(names, logs, strict=True))
    fitted = [(name, fit_to_model(log, model, name, crop=True)) for name, log in entries]
    for title, site in (("SPL demo site (bounds 6 × 4 m)", SPL_SITE), ("same site, no bounds", Site(
            SPL_SITE.landmarks, SPL_SITE.sensor_pose, None))):
        m = model.with_site(site)
        print(f"\n{title}, model {args.model}\n")
        print("| log | scans | candidates kept | taken for a mobile class | unlike their class | outside its "
              "envelope | mobile rows | mobile tracks |")
        print("|---|---|---|---|---|---|---|---|")
        tot = dict.fromkeys(("scans", "kept", "taken", "unlike", "off_envelope", "rows", "tracks"), 0)
        for name, log in fitted:
            c = count(m, log)
            tot = {k: tot[k] + c[k] for k in tot}
            print(f"| {name} | {c['scans']} | {c['kept']} | {c['taken']} | {c['unlike']} | {c['off_envelope']} | "
                  f"{c['rows']} | {c['tracks']} |")
        print(f"| all | {tot['scans']} | {tot['kept']} | {tot['taken']} | {tot['unlike']} | {tot['off_envelope']} | "
              f"{tot['rows']} | {tot['tracks']} |")


if __name__ == "__main__":
    main()
