"""Models, logs and training examples that several sections use, built once per run.

* URG-04LX: the shipped demo model (``gtsjax/data/demo-model.npz``) on the simulated SPL field.
* UTM-30LX: no model ships for it, so a small one is trained here on the simulated lab
  (``lab-train``), with the classifier and pose GPs at the same 128 inducing points as the demo
  model (the step's cost depends on that count, not on how many examples were fitted). It is cached
  under ``benchmarks/.cache`` (git-ignored), keyed by the training settings and a hash of the
  gtsjax sources that shape a model, so it is retrained whenever those change.
* GP training data: the project's own characteristic vectors (GP inputs) and pose targets, labelled
  from the SPL training grid as ``gtsjax train`` labels them.
"""

import functools
import hashlib
import json
from pathlib import Path

import numpy as np

CACHE = Path(__file__).resolve().parent / ".cache"
_SRC = Path(__file__).resolve().parents[1] / "gtsjax"

#: Training settings of the cached UTM-30LX model (small fits; 128 inducing points like the demo model). A
#: model to time, not to trust: training's tracking check (some 40 % of a small training) is left out.
UTM_TRAIN = {"max_per_class": 50, "max_pose_examples": 130, "n_inducing": 128, "restarts": 1, "check_pipeline": False}
UTM_TRAIN_SCANS = 600
#: The smoke run's (``--quick``): the same shapes of step to time, from a fraction of the fitting.
UTM_TRAIN_QUICK = {"max_per_class": 20, "max_pose_examples": 40, "n_inducing": 32, "restarts": 1,
                   "check_pipeline": False}
UTM_TRAIN_SCANS_QUICK = 200


@functools.cache
def scenario(name: str, seed: int, n_scans: int | None = None, seconds: float | None = None):
    """``(log, site)`` of a simulated scenario (memoised: rendering takes seconds): ``n_scans`` spread
    over the whole of it (a static grid's poses all kept, each seen briefly), or its first ``seconds``."""
    from gtsjax.sim import simulate

    return simulate(name, seed=seed, n_scans=n_scans, seconds=seconds)


def demo_model(site):
    """The shipped URG-04LX model with ``site`` attached."""
    from gtsjax.cli.demo import demo_model_path
    from gtsjax.io.modelfile import load_model

    return load_model(demo_model_path()).with_site(site)


def demo_model_path() -> Path:
    from gtsjax.cli.demo import demo_model_path as p

    return Path(p())


def _source_hash(config: dict, n_scans: int) -> str:
    """Hash of a training setting and the gtsjax sources a trained model depends on (not the CLI, not
    the importers)."""
    h = hashlib.sha256(json.dumps([config, n_scans]).encode())
    files = sorted(p for p in _SRC.rglob("*.py") if p.parent.name not in ("cli",) and
                   not (p.parent.name == "io" and p.name not in ("modelfile.py", "logs.py", "site.py")))
    for p in files:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def utm_model_path(log=print, quick: bool = False) -> Path:
    """The cached UTM-30LX model file, trained first if missing or stale (about a minute; ``quick``: the
    smoke run's smaller one, kept apart)."""
    import time

    import jax

    from gtsjax.io.modelfile import load_model, save_model
    from gtsjax.train import TrainConfig, train

    config, n_scans = (UTM_TRAIN_QUICK, UTM_TRAIN_SCANS_QUICK) if quick else (UTM_TRAIN, UTM_TRAIN_SCANS)
    tag = "utm30lx-quick" if quick else "utm30lx"
    path = CACHE / f"{tag}-{_source_hash(config, n_scans)}.npz"
    if path.exists():
        try:
            load_model(path)
            return path
        except Exception:  # a damaged or outdated cache entry: retrain
            path.unlink()
    CACHE.mkdir(parents=True, exist_ok=True)
    for old in CACHE.glob(f"{tag}-{'[0-9a-f]' * 16}.npz"):
        old.unlink()
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    train_log, site = scenario("lab-train", 1, n_scans)
    model, report = train([train_log], site, TrainConfig(**config))
    save_model(model, path, summary={"benchmark": "UTM-30LX model for timing", **report})
    log(f"trained the UTM-30LX benchmark model in {time.perf_counter() - t0:.0f} s -> {path}")
    return path


def utm_model(site, log=print, quick: bool = False):
    from gtsjax.io.modelfile import load_model

    return load_model(utm_model_path(log, quick)).with_site(site)


@functools.cache
def gp_examples(n_scans: int = 1200):
    """The robot examples of the SPL training grid: GP inputs ``[E, 23]`` and ORS-relative pose
    targets ``[E, 3]`` (x̃, ỹ, θ̃), labelled as ``gtsjax train`` labels them (first pass)."""
    from gtsjax.train import TrainConfig, class_list, label_log, landmark_centres, run_front_end

    log, site = scenario("spl-train", 0, n_scans)
    cfg = TrainConfig()
    classes, _, _ = class_list([log], site)
    fe = run_front_end(log, cfg.frontend, log.n_beams)
    tf, _ = landmark_centres(log, fe, site, cfg)
    ex, _ = label_log(log, fe, tf, site, classes, cfg, 0)
    robot = ex.cls == classes.index("robot")
    return np.asarray(ex.vectors[robot]), np.asarray(ex.target[robot])


def gp_problem(n: int, seed: int = 0):
    """``n`` robot examples (without replacement) and their x̃ targets: the fit problem of the GP
    comparisons. Falls back to sampling with a little input noise if fewer examples exist."""
    x, t = gp_examples()
    rng = np.random.default_rng(seed)
    if n <= len(x):
        idx = rng.choice(len(x), n, replace=False)
        return x[idx], t[idx, 0]
    idx = rng.choice(len(x), n, replace=True)
    return x[idx] * (1 + 1e-3 * rng.standard_normal(x[idx].shape)), t[idx, 0]
