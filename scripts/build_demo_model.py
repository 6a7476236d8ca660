"""Build the model shipped inside the package (``gtsjax/data/demo-model.npz``) that ``gtsjax demo``
uses: trained reproducibly on simulated data of the paper's SPL field (three runs of the training grid,
seeds 1, 3 and 4, plus a log with a person walking, so that legs are background), with the training
defaults of ``gtsjax train``.

    python scripts/build_demo_model.py [--out gtsjax/data/demo-model.npz]
"""

import argparse
import dataclasses
import json
import time

import jax

from gtsjax.io.modelfile import save_model
from gtsjax.sim import simulate
from gtsjax.training import TrainConfig, train

DEMO_CONFIG = dataclasses.replace(TrainConfig(), seed=0)


def main():
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="gtsjax/data/demo-model.npz")
    args = ap.parse_args()
    t0 = time.perf_counter()
    # Three runs of the training grid (each draws its own heading in every 45° sector), so that the pose
    # GPs see about 6 000 distinct views of the robot.
    grids = [simulate("spl-train", seed=s) for s in (1, 3, 4)]
    site = grids[0][1]
    legs_log, _ = simulate("spl-legs", seed=2)
    model, report = train([log for log, _ in grids] + [legs_log], site, DEMO_CONFIG,
                          progress=lambda i: print(f"  {i['gp']:<18} n={i['n']:<5} {i['seconds']:6.1f} s", flush=True))
    save_model(model, args.out, summary=report)
    print(json.dumps(report["heldout"], indent=1))
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
