"""Command-line paths no other test ran, each run for real on a short simulated log (the first 8 s of spl-eval:1,
the robot put down at one point with two headings) and checked on what it writes: ``replay --view-save``, a site's
``bounds`` with the tracked robot outside them, and ``evaluate --without-outline``."""

import importlib.util
import json

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.cli.demo import demo_model_path
from gtsjax.io import save_log, save_site
from gtsjax.io.gtd import read_gtd
from gtsjax.sim import simulate
from tests._utils import first_scans
from tests.conftest import need

DEMO_MODEL = str(demo_model_path())


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """The log, its site file, and the log's path."""
    d = tmp_path_factory.mktemp("paths")
    log, site = simulate("spl-eval", seed=1)  # 1 s away and 3 s put down, 8 headings at each point
    n = 80
    log = first_scans(log, n)
    save_log(log, d / "log.npz")
    save_site(site, d / "site.json")
    return log, d / "site.json", d / "log.npz"


def _replay(log_path, site_path, out, *extra):
    return main(
        [
            "replay",
            str(log_path),
            "--site",
            str(site_path),
            "--model",
            DEMO_MODEL,
            "--out",
            str(out),
            "--quiet",
            *map(str, extra),
        ]
    )


def test_replay_view_save_holds_a_pose_per_row(field, tmp_path):
    """``replay --view-save FILE.rrd``: Rerun's own reader finds one track entity per track of the CSV,
    each with a pose per row of it, and the field, the scan and the laser."""
    need(
        importlib.util.find_spec("rerun") is not None,
        'the viewer extra is not installed (pip install "gtsjax[viewer]")',
    )
    from rerun.chunk import RrdReader

    log, site, path = field
    rrd = tmp_path / "replay.rrd"
    assert _replay(path, site, tmp_path / "gtd.csv", "--view-save", rrd) == 0
    rows = read_gtd(tmp_path / "gtd.csv")
    assert len(rows) >= 10
    per_entity: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        per_entity[str(chunk.entity_path)] = per_entity.get(str(chunk.entity_path), 0) + chunk.num_rows
    ids = sorted({r.track_id for r in rows})
    tracks = sorted({e.split("/")[3] for e in per_entity if e.startswith("/field/tracks/")})
    assert tracks == sorted(f"robot_{i}" for i in ids)
    for i in ids:
        assert per_entity[f"/field/tracks/robot_{i}/pose"] == sum(r.track_id == i for r in rows), i
    for e in ("/field/scan", "/field/laser", "/field/landmarks"):
        assert per_entity.get(e, 0) > 0, e


def test_a_robot_outside_the_sites_bounds_is_not_reported(field, tmp_path):
    """The site's ``bounds``: with the field's own the robot is reported where it is; with bounds that
    leave its point out (the field's other half) no row, while the posts still place the laser every
    scan."""
    log, site, path = field
    at = {float(s): t for t, s in enumerate(log.stamps)}
    truth = log.truth_poses[:, 0, :2]
    point = np.unique(truth[~np.isnan(truth[:, 0])], axis=0)
    assert len(point) == 1  # one point in these 8 s
    assert _replay(path, site, tmp_path / "in.csv") == 0
    inside = read_gtd(tmp_path / "in.csv")
    assert len(inside) >= 10 and all(np.hypot(*(truth[at[r.stamp]] - (r.x, r.y))) < 0.05 for r in inside)
    text = json.loads(site.read_text())
    x0, y0, x1, y1 = text.get("bounds", [0.0, 0.0, 6.0, 4.0])
    half = (x0 + x1) / 2
    text["bounds"] = [half, y0, x1, y1] if point[0, 0] < half else [x0, y0, half, y1]
    (tmp_path / "far.json").write_text(json.dumps(text))
    assert _replay(path, tmp_path / "far.json", tmp_path / "out.csv", "--sensor-out", tmp_path / "laser.csv") == 0
    assert read_gtd(tmp_path / "out.csv") == []
    laser = np.genfromtxt(tmp_path / "laser.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert len(laser) == log.n_scans and np.all(laser["n_landmarks"] >= 3)


def test_evaluate_without_outline_scores_the_gps_headings(field, tmp_path, capsys):
    """``evaluate LOG --site --without-outline``: says so, and scores other headings than with the
    outline (stage e′ left out: the pose GP's own), the positions the same within a millimetre (the
    refinement keeps the GP's positions)."""
    log, site, path = field
    results = {}
    for flag in ((), ("--without-outline",)):
        out = tmp_path / ("without" if flag else "with")
        assert (
            main(
                [
                    "evaluate",
                    "--model",
                    DEMO_MODEL,
                    str(path),
                    "--site",
                    str(site),
                    "--out-dir",
                    str(out),
                    "--quiet",
                    *flag,
                ]
            )
            == 0
        )
        said = " ".join(capsys.readouterr().out.split())  # the table's title names the model
        assert ("without its outlines" in said) == bool(flag), said
        results[flag] = json.loads((out / "results.json").read_text())[str(path)]
    with_, without = results[()], results[("--without-outline",)]
    assert with_["n_errors"] == without["n_errors"] > 0
    assert with_["heading_rmse_deg"] != without["heading_rmse_deg"], (with_, without)
    assert abs(with_["position_rmse_m"] - without["position_rmse_m"]) < 1e-3


CHECKS_IN_CHILD = """
import jax, jax.numpy as jnp, numpy as np
from gtsjax.core.c_filters import shape_quantities
print(jax.config.jax_numpy_dtype_promotion, jax.config.jax_numpy_rank_promotion)
try:
    shape_quantities(np.ones(3), jnp.ones(3), jnp.ones(3, jnp.int32), jnp.ones(3))  # NumPy where JAX is annotated
    print("accepted")
except Exception as err:
    print(type(err).__name__)
"""


def test_gtsjax_children_run_under_the_tests_checks():
    """A ``gtsjax`` child (``tests._child``, what ``run_cli`` and ``popen_cli`` start) runs with strict
    dtype promotion, rank promotion raising, and the core's annotations checked (an argument of the
    wrong array type refused), as the in-process tests do."""
    import subprocess
    import sys

    from tests._utils import CHILD, cli_env

    boot = "import tests._child as c; c.install_checks()\n"
    res = subprocess.run(
        [sys.executable, "-c", boot + CHECKS_IN_CHILD], capture_output=True, text=True, timeout=120, env=cli_env()
    )
    assert res.returncode == 0, res.stderr
    lines = res.stdout.split()
    assert lines[:2] == ["strict", "raise"] and len(lines) == 3 and lines[2] != "accepted", res.stdout
    assert CHILD[1:] == ("-m", "tests._child")
    version = subprocess.run([*CHILD, "--version"], capture_output=True, text=True, timeout=120, env=cli_env())
    assert version.returncode == 0 and version.stdout.startswith("gtsjax"), version
