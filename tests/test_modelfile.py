"""Model files are checked against the model their header describes: a leaf of another shape or
dtype, a header field of the wrong type or a missing key is one line naming the leaf or field, from
the API (``InputError``) and from the command line (exit 2, no output left behind). Files written
before later optional fields were added still load. All cases are edits of the shipped demo model."""

import json
from pathlib import Path

import numpy as np
import pytest

from gtsjax import InputError
from gtsjax.cli import main
from gtsjax.io import save_log, save_site
from gtsjax.io.modelfile import is_model_file, load_model, read_header
from gtsjax.sim import simulate

from ._utils import run_cli

DEMO_MODEL = Path(__file__).resolve().parents[1] / "gtsjax" / "data" / "demo-model.npz"


def _read(path):
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    return json.loads(str(arrays.pop("gtsjax_model"))), arrays


def _write(path, header, arrays):
    np.savez(path, gtsjax_model=np.asarray(json.dumps(header)), **arrays)
    return path


def _node(schema, where):
    """The schema entry at ``where`` (``classifier.gps[1].z``)."""
    node = schema
    for part in where.replace("[", ".[").split("."):
        node = node["tuple"][int(part[1:-1])] if part.startswith("[") else node["fields"][part]
    return node


def _edited(tmp_path, name, edit):
    header, arrays = _read(DEMO_MODEL)
    edit(header, arrays)
    return _write(tmp_path / f"{name}.npz", header, arrays)


def _cut_features(h, a):
    key = _node(h["schema"], "classifier.gps[1].z")["array"]
    a[key] = a[key][:, :-1]


# The heading GPs' inducing inputs: of the heading group where the pose GPs share kernels, else of sin.
_HEADER, _ARRAYS = _read(DEMO_MODEL)
_HEADING_Z = ("pose[2].shared[1].z" if _HEADER["schema"]["fields"]["pose"]["tuple"][2]["fields"].get("shared")
              else "pose[2].sin.z")
# Their number in the shipped model (the training set's, which a rebuild may change).
_N_HEADING_Z = int(_ARRAYS[_node(_HEADER["schema"], _HEADING_Z)["array"]].shape[0])


def _cut_inducing(h, a):
    key = _node(h["schema"], _HEADING_Z)["array"]
    a[key] = a[key][:-1]


def _float64(h, a):
    key = _node(h["schema"], "tracker.gate")["array"]
    a[key] = a[key].astype(np.float64)


def _string_beams(h, a):
    h["n_beams"] = str(h["n_beams"])


def _no_sensor_model(h, a):
    del h["sensor_model"]


def _no_support(h, a):
    del _node(h["schema"], "classifier")["fields"]["support"]


def _string_static(h, a):
    _node(h["schema"], "max_tracks")["value"] = "8"


def _short_pose(h, a):
    _node(h["schema"], "pose")["tuple"].pop()


def _other_classes(h, a):
    h["classes"] = ["background", "post"]


CASES = {
    "cut-features": (_cut_features, "leaf classifier.gps[1].z has shape (2048, 12), expected (2048, 13)"),
    "cut-inducing": (_cut_inducing, f"leaf {_HEADING_Z} has shape ({_N_HEADING_Z - 1}, 13), expected ({_N_HEADING_Z}, 13)"),
    "float64": (_float64, "leaf tracker.gate has dtype float64, expected float32"),
    "string-beams": (_string_beams, "model header field 'n_beams' is str '682', expected an integer"),
    "no-sensor-model": (_no_sensor_model, "model header missing required key(s) 'sensor_model'"),
    "no-support": (_no_support, "field classifier.support is missing"),
    "string-static": (_string_static, "field max_tracks is str '8', expected int"),
    "short-pose": (_short_pose, "pose has 2 entries, expected 3 (one per class)"),
    "other-classes": (_other_classes, "model header's classes ['background', 'post'] differs from the model's"),
}


@pytest.mark.parametrize("name", CASES)
def test_a_differing_file_is_one_line_naming_the_leaf(tmp_path, name):
    edit, message = CASES[name]
    path = _edited(tmp_path, name, edit)
    with pytest.raises(InputError) as exc:
        load_model(path)
    text = str(exc.value)
    assert text.startswith(f"{path}: ") and message in text and "\n" not in text, text


def test_replay_refuses_a_differing_model_with_one_line_and_no_output(tmp_path, capsys):
    log, site = simulate("spl-eval", seed=1, n_scans=5)
    save_log(log, tmp_path / "log.npz")
    save_site(site, tmp_path / "site.json")
    for name in ("cut-features", "float64", "string-beams", "no-sensor-model"):
        edit, message = CASES[name]
        model = _edited(tmp_path, name, edit)
        out = tmp_path / f"{name}.csv"
        code = main(
            [
                "replay",
                str(tmp_path / "log.npz"),
                "--site",
                str(tmp_path / "site.json"),
                "--model",
                str(model),
                "--out",
                str(out),
                "--sensor-out",
                str(tmp_path / f"{name}-sensor.csv"),
            ]
        )
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], (name, lines)
        assert not out.exists() and not (tmp_path / f"{name}-sensor.csv").exists()


def test_older_files_without_later_fields_load(tmp_path):
    """A version-3 file from before the pose regressors' ``heading_var_max`` (and one without any of
    the optional fields) loads, the missing fields at their defaults."""

    def drop(h, a):
        for reg in _node(h["schema"], "pose")["tuple"]:
            if reg is not None:
                for k in ("sin", "cos", "var_scale", "heading_var_max"):
                    reg["fields"].pop(k, None)
        for k in ("max_objects", "angle_min", "angle_increment", "range_min", "range_max"):
            h["schema"]["fields"].pop(k)

    shipped = load_model(DEMO_MODEL)
    assert shipped.pose[2].heading_var_max is not None
    old = load_model(_edited(tmp_path, "old", drop))
    assert all(reg is None or (reg.heading_var_max is None and reg.sin is None) for reg in old.pose)
    assert old.max_objects == 8 and np.isnan(old.angle_min)
    np.testing.assert_array_equal(old.classifier.gps[1].z, shipped.classifier.gps[1].z)


def test_info_describes_a_model_file(tmp_path, capsys):
    assert is_model_file(DEMO_MODEL) and not is_model_file(tmp_path / "none.npz")
    assert main(["info", str(DEMO_MODEL)]) == 0
    out = capsys.readouterr().out
    assert "gtsjax model (format version 3) for URG-04LX, 682 beams" in out and "robot (tracked)" in out
    assert "ranges" not in out
    bad = _edited(tmp_path, "bad", _cut_features)
    res = run_cli("info", bad, timeout=120)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "leaf classifier.gps[1].z" in lines[0], res.stderr


def test_a_model_given_as_a_log_is_named_as_such(tmp_path, capsys):
    site = tmp_path / "site.json"
    save_site(simulate("spl-eval", seed=1, n_scans=2)[1], site)
    code = main(
        ["replay", str(DEMO_MODEL), "--site", str(site), "--model", str(DEMO_MODEL), "--out", str(tmp_path / "o.csv")]
    )
    assert code == 2 and "a gtsjax model file, not a scan log" in capsys.readouterr().err
    assert read_header(DEMO_MODEL)["sensor_model"] == "URG-04LX"


def test_both_pose_layouts_save_and_load_with_their_predictions(tmp_path):
    """A tracked class's pose GPs held one by one (models trained before shared kernels) and in groups
    of one kernel (``PoseRegressor.shared``) both go through a model file unchanged: every leaf
    equal, and the loaded regressor predicts what the saved one did. Separate GPs over one training
    set come back with their inducing inputs held once as well (``PoseRegressor.common``, never
    written), which predicts what they do to float32 rounding."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from gtsjax import gp
    from gtsjax.core.e_pose import PoseRegressor, regress_one_class
    from gtsjax.io.modelfile import save_model

    shipped = load_model(DEMO_MODEL)
    k = shipped.class_index("robot")
    reg = shipped.pose[k]
    d = int(reg.outputs()[0].x_mean.shape[0])
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, d))
    y = np.stack([x[:, 0], x[:, 1], np.sin(x[:, 2]), np.cos(x[:, 2])], 1) + 0.05 * rng.normal(size=(40, 4))
    groups = tuple(gp.SharedSparseGP.build(gp.fit_shared(x, y[:, g], key=jax.random.key(i), restarts=1), 40, 8)
                   .astype(jnp.float32) for i, g in enumerate(((0, 1), (2, 3))))
    layouts = {"separate": PoseRegressor(*reg.outputs(), var_scale=reg.var_scale, heading_var_max=reg.heading_var_max),
               "shared": PoseRegressor(shared=groups, var_scale=reg.var_scale, heading_var_max=reg.heading_var_max)}
    o = reg.outputs()[0]
    probe = jnp.asarray(rng.normal(size=(6, d)) * np.asarray(o.x_scale)[None] + np.asarray(o.x_mean)[None], jnp.float32)
    for name, r in layouts.items():
        model = eqx.tree_at(lambda m, k=k: m.pose[k], shipped, r)
        save_model(model, tmp_path / f"{name}.npz")
        back = load_model(tmp_path / f"{name}.npz").pose[k]
        assert (back.shared is None) == (name == "separate")
        assert (back.common is not None) == (name == "separate")
        stored = eqx.tree_at(lambda p: p.common, back, None, is_leaf=lambda v: v is None)
        for a, b in zip(jax.tree.leaves(r), jax.tree.leaves(stored), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(regress_one_class(r, probe), regress_one_class(stored, probe), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(regress_one_class(r, probe), regress_one_class(back, probe), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name, content, what", [  # (a .csv, or a GTD header, info reads as a ground-truth CSV)
    ("report.txt", b'{"accuracy": 0.99}\n', "a JSON file"),
    ("notes.txt", b"the robot walked twice\n", "a text file"),
    ("table.txt", b"a,b\n1,2\n", "a CSV file"),
    ("plot.png", b"\x89PNG\r\n\x1a\n" + bytes(64), "a PNG image"),
    ("empty.npz", b"", "an empty file"),
])
def test_info_says_what_a_file_is_when_it_is_not_a_log(tmp_path, capsys, name, content, what):
    p = tmp_path / name
    p.write_bytes(content)
    assert main(["info", str(p)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gtsjax: {p}: {what}"), lines
    assert lines[0].endswith("not a scan log, site file or model file"), lines
