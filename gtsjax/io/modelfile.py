"""Model files: one versioned ``.npz`` holding the configuration, the hyperparameters and everything
prediction needs.

Layout: a key ``gtsjax_model`` with a JSON header (format name, version, sensor model, classes, a
training summary, and a schema of the model's pytree), and one array per leaf (``leaf00000``, …).
The schema names each node's type from a fixed registry, so loading never unpickles anything and a
file cannot make gtsjax build an object it does not know. Arrays keep their dtype (the step's
float32 copies of the GPs).

Loading checks the file against the model its header describes before building anything, as
equinox's ``tree_deserialise_leaves`` checks leaves against a ``like`` tree: every node is of a type
its field allows, every field without a default is there, and every leaf has the shape and dtype of
its field's jaxtyping annotation. Dimension names bind to the model's configuration where it fixes
them (``classes``: the class list; ``features``/``inputs``: the GP inputs, ``gp_columns``) and
otherwise to the size most leaves of the same node agree on (``points``, ``inducing``, ``bins``, …),
so a leaf that differs is named: ``leaf classifier.gps[1].z has shape (5, 21), expected (5, 22)``.
Fields added after version 3 came out (a pose regressor's ``heading_var_max`` and ``turns``) have defaults,
and a file without them loads.
"""

import dataclasses
import json
import math
import os
import types
import typing
import zipfile
from collections import Counter
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import AbstractArray

from ..core.c_filters import Envelope
from ..core.d_classify import Classifier, Support
from ..core.e_pose import PoseRegressor
from ..core.e_refine import Outline
from ..core.e_tags import TagReader
from ..core.frontend import FrontEndConfig
from ..core.g_track import TrackerParams
from ..core.model import Model, SiteArrays
from ..errors import InputError
from ..gp import GP, Hyperparameters, SharedSparseGP, SparseGP
from ..sensors import with_scanner
from .atomic import atomic_write
from .kinds import not_expected
from .npz import check_npz

FORMAT = "gtsjax-model"
VERSION = 3  # 3: scanner geometry, open-set supports, shape envelopes, per-class motion limits (and, optional, the pose regressors' heading_var_max and turns)
_HEADER_KEY = "gtsjax_model"
_TYPES = {
    c.__name__: c
    for c in (
        Model,
        FrontEndConfig,
        Classifier,
        Support,
        Envelope,
        PoseRegressor,
        Outline,
        TagReader,
        TrackerParams,
        SparseGP,
        SharedSparseGP,
        GP,
        Hyperparameters,
        SiteArrays,
    )
}
# Header keys and their JSON types (``summary`` may be absent).
_HEADER = {"format": str, "version": int, "sensor_model": str, "n_beams": int, "classes": list, "schema": dict}
# Fields made from the others when a model is loaded (``PoseRegressor.with_common_inputs``), never written.
_DERIVED = {(PoseRegressor, "common")}
# Fields the loader fills in from the sensor table (``sensors.with_scanner``), never written nor read.
_FILLED = {(Model, "scan_period"), (Model, "sensor_beams")}
# Tuples with one entry per class.
_PER_CLASS = {(Classifier, "gps"), (Model, "pose")}
# The shape-fixing settings a model file carries, and the ranges within which the step can run on
# them: outside, a file is damaged or edited by hand, and is refused before anything runs.
_RANGES = {
    (Model, "max_tracks"): (1, 1024), (Model, "max_objects"): (1, 1024), (Model, "n_beams"): (1, 1_000_000),
    (FrontEndConfig, "max_candidates"): (1, 4096), (FrontEndConfig, "window"): (2, 65536),
    (FrontEndConfig, "n_dist"): (1, 1024), (FrontEndConfig, "n_intensity"): (0, 1024),
}
# The leaves where ±inf is a value (no bound: an envelope open on one side, a class without an
# open-set threshold); anywhere else it is damage, which the step would turn into NaN and no rows.
_UNBOUNDED = {(Envelope, "lo"), (Envelope, "hi"), (Support, "threshold")}
# The dtype the float32 step expects of each jaxtyping kind.
_DTYPES = ("float32", "int32", "bool")


def _encode(node, leaves: dict[str, np.ndarray]):
    if node is None:
        return None
    if isinstance(node, eqx.Module):
        name = type(node).__name__
        if _TYPES.get(name) is not type(node):
            raise TypeError(f"cannot save a {type(node)!r} in a model file")
        return {
            "type": name,
            "fields": {f.name: _encode(getattr(node, f.name), leaves) for f in dataclasses.fields(node)
                       if (type(node), f.name) not in _DERIVED | _FILLED},
        }
    if isinstance(node, tuple):
        return {"tuple": [_encode(v, leaves) for v in node]}
    if isinstance(node, (bool, int, float, str)):
        return {"value": node}
    arr = np.asarray(node)
    key = f"leaf{len(leaves):05d}"
    leaves[key] = arr
    return {"array": key}


# ------------------------------------------------------------------------------------------ loading


@dataclasses.dataclass(frozen=True)
class _Node:
    """A module read from the file, not built yet: its class, its fields (NumPy leaves, values,
    tuples, nodes) and where it sits in the model (``classifier.gps[1]``)."""

    cls: type
    fields: dict[str, Any]
    where: str


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _alternatives(ann) -> tuple:
    return typing.get_args(ann) if typing.get_origin(ann) in (typing.Union, types.UnionType) else (ann,)


def _is_array(ann) -> bool:
    return isinstance(ann, type) and issubclass(ann, AbstractArray)


def _describe(alts) -> str:
    def one(a):
        if a is type(None):
            return "nothing"
        if _is_array(a):
            return "an array"
        if typing.get_origin(a) is tuple:
            return "a tuple"
        return getattr(a, "__name__", str(a))

    return " or ".join(one(a) for a in alts)


class _Reader:
    """Phase one of loading: the schema read against the classes' fields, leaves as NumPy arrays."""

    def __init__(self, path: Path, npz):
        self.path, self.npz = path, npz

    def fail(self, problem: str) -> InputError:
        return InputError(self.path, problem)

    def read(self, spec, ann, where: str):
        alts = _alternatives(ann)
        if spec is None:
            if type(None) in alts:
                return None
            raise self.fail(f"field {where} is missing (expected {_describe(alts)})")
        if not isinstance(spec, dict):
            raise self.fail(f"damaged model schema at {where or 'the top'}")
        if "array" in spec:
            if not any(_is_array(a) for a in alts):
                raise self.fail(f"field {where} holds an array, expected {_describe(alts)}")
            key = spec["array"]
            if not isinstance(key, str) or key not in self.npz.files:
                raise self.fail(f"truncated or damaged model file (array {key} of {where} missing)")
            arr = self.npz[key]
            if arr.dtype.kind == "f" and np.isnan(arr).any():  # training writes none; a NaN tracks nothing
                raise self.fail(f"field {where} holds NaN: a damaged model file (retrain it)")
            return arr
        if "value" in spec:
            return self.value(spec["value"], alts, where)
        if "tuple" in spec:
            elems = [typing.get_args(a)[0] for a in alts if typing.get_origin(a) is tuple]
            if not elems or not isinstance(spec["tuple"], list):
                raise self.fail(f"field {where} holds a tuple, expected {_describe(alts)}")
            return tuple(self.read(s, elems[0], f"{where}[{i}]") for i, s in enumerate(spec["tuple"]))
        name = spec.get("type")
        cls = _TYPES.get(name) if isinstance(name, str) else None
        if cls is None:
            raise self.fail(f"unknown node type {name!r} at {where or 'the top'} of the model file")
        if cls not in alts:
            raise self.fail(f"{where or 'the top'} is a {name}, expected {_describe(alts)}")
        given = spec.get("fields")
        if not isinstance(given, dict):
            raise self.fail(f"damaged model schema at {where or 'the top'}")
        fields = {f.name: f for f in dataclasses.fields(cls) if f.init and (cls, f.name) not in _FILLED}
        if unknown := sorted(set(given) - set(fields)):
            raise self.fail(f"field {_join(where, unknown[0])} is not one a {name} has (a newer gtsjax's model file?)")
        out = {}
        for f in fields.values():
            if f.name in given:
                out[f.name] = self.read(given[f.name], f.type, _join(where, f.name))
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise self.fail(f"field {_join(where, f.name)} is missing")
        return _Node(cls, out, where)

    def value(self, v, alts, where: str):
        for a in alts:
            if a is bool and isinstance(v, bool) or a is str and isinstance(v, str):
                return v
            if a is int and isinstance(v, int) and not isinstance(v, bool):
                return v
            if a is float and isinstance(v, (int, float)) and not isinstance(v, bool):
                return float(v)
            if typing.get_origin(a) is tuple and isinstance(v, list):
                elem = typing.get_args(a)[0]
                return tuple(self.value(x, (elem,), f"{where}[{i}]") for i, x in enumerate(v))
        raise self.fail(f"field {where} is {type(v).__name__} {_short(v)}, expected {_describe(alts)}")


def _short(v) -> str:
    s = repr(v)
    return s if len(s) <= 40 else s[:37] + "..."


def _expected_dtype(ann) -> str:
    return next(d for d in _DTYPES if d in ann.dtypes)


def _shape(dims) -> str:
    return "(" + ", ".join(map(str, dims)) + ("," if len(dims) == 1 else "") + ")"


def _check(node: _Node, sizes: dict[str, int], path: Path) -> None:
    """Phase two: every leaf of ``node`` and below against its field's annotation (see the module
    docstring); the first that differs is one line."""
    anns = {f.name: f.type for f in dataclasses.fields(node.cls)}
    leaves = {}
    for name, v in node.fields.items():
        if isinstance(v, np.ndarray):
            leaves[name] = (v, next(a for a in _alternatives(anns[name]) if _is_array(a)))
    # Sizes the configuration leaves open, by majority over this node's leaves of the right rank.
    votes: dict[str, Counter] = {}
    for v, ann in leaves.values():
        names = ann.dim_str.split()
        if len(names) == v.ndim:
            for n, size in zip(names, v.shape, strict=True):
                if not n.isdigit() and n not in sizes:
                    votes.setdefault(n, Counter())[size] += 1
    local = {**{n: c.most_common(1)[0][0] for n, c in votes.items()}, **sizes}
    for name, v in node.fields.items():
        where = _join(node.where, name)
        if (node.cls, name) in _RANGES:
            lo, hi = _RANGES[node.cls, name]
            if not lo <= v <= hi:
                raise InputError(path, f"field {where} is {v}, outside the {lo}–{hi} a model can run with (a damaged "
                                       "or edited model file)")
        if (node.cls, name) == (Model, "angle_increment") and not math.isnan(v) and not (math.isfinite(v) and v > 0):
            raise InputError(path, f"field {where} is {v}, expected a positive angle (rad)")
        if (node.cls, name) in _PER_CLASS and len(v) != sizes["classes"]:
            raise InputError(path, f"{where} has {len(v)} entries, expected {sizes['classes']} (one per class)")
        if name in leaves:
            arr, ann = leaves[name]
            want = [int(n) if n.isdigit() else local.get(n, n) for n in ann.dim_str.split()]
            if list(arr.shape) != want:
                raise InputError(path, f"leaf {where} has shape {_shape(arr.shape)}, expected {_shape(want)}")
            if arr.dtype != (dtype := _expected_dtype(ann)):
                raise InputError(path, f"leaf {where} has dtype {arr.dtype}, expected {dtype}")
            if arr.dtype.kind == "f" and (node.cls, name) not in _UNBOUNDED and np.isinf(arr).any():
                raise InputError(path, f"leaf {where} holds an infinite value: a damaged model file (retrain it)")
        for child in v if isinstance(v, tuple) else (v,):
            if isinstance(child, _Node):
                _check(child, sizes, path)


def _build(v):
    """Phase three: the checked tree as modules of JAX arrays."""
    if isinstance(v, _Node):
        return v.cls(**{k: _build(x) for k, x in v.fields.items()})
    if isinstance(v, tuple):
        return tuple(_build(x) for x in v)
    return jnp.asarray(v) if isinstance(v, np.ndarray) else v


def _config_sizes(top: _Node, header: dict, path: Path) -> dict[str, int]:
    """The dimensions the model's configuration fixes, after checking that the header says what the
    model says."""
    f = top.fields
    for key in ("classes", "sensor_model", "n_beams"):
        mine = list(f[key]) if key == "classes" else f[key]
        if header[key] != mine:
            raise InputError(
                path, f"model header's {key} {_short(header[key])} differs from the model's {_short(mine)}"
            )
    columns = f.get("gp_columns", ())
    if not columns:  # all of gp_inputs: the characteristic vector, depth and range
        fe = f["frontend"].fields
        columns = range(FrontEndConfig(**{k: v for k, v in fe.items() if not isinstance(v, np.ndarray)}).n_features + 2)
    return {"classes": len(f["classes"]), "features": len(columns), "inputs": len(columns)}


def save_model(model: Model, path: str | os.PathLike, *, summary: dict | None = None) -> None:
    """Write ``model`` (its site detached: sites are given at run time) atomically to ``path``."""
    path = Path(path)
    model = eqx.tree_at(lambda m: m.site, model, None, is_leaf=lambda x: x is None)
    leaves: dict[str, np.ndarray] = {}
    schema = _encode(model, leaves)
    header = {
        "format": FORMAT,
        "version": VERSION,
        "sensor_model": model.sensor_model,
        "n_beams": model.n_beams,
        "classes": list(model.classes),
        "summary": summary or {},
        "schema": schema,
    }
    with atomic_write(path) as f:
        np.savez(f, **{_HEADER_KEY: np.asarray(json.dumps(header))}, **leaves)


def is_model_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an ``.npz`` archive with a model header (whatever else may be wrong with it)."""
    try:
        with zipfile.ZipFile(path) as z:
            return f"{_HEADER_KEY}.npy" in z.namelist()
    except (OSError, zipfile.BadZipFile, ValueError):
        return False


def read_header(path: str | os.PathLike) -> dict:
    """The JSON header of a model file (format, version, sensor model, classes, training summary)."""
    header, npz = _open(Path(path))
    npz.close()
    return header


def _open(path: Path):
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, "is a directory, not a gtsjax model file")
    check_npz(path)
    try:
        npz = np.load(path, allow_pickle=False)
        files = npz.files
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as err:
        if isinstance(err, OSError) and err.errno is not None:  # no permission, a socket: the file, not its format
            raise InputError(path, f"cannot be read ({err.strerror})") from None
        other = not_expected(path, "a gtsjax model file")
        raise InputError(path, other or "not a gtsjax model file (not an .npz archive)") from None
    try:
        if _HEADER_KEY not in files:
            raise InputError(path, "not a gtsjax model file (no model header; is it a scan log?)")
        try:
            header = json.loads(str(npz[_HEADER_KEY]))
        except (ValueError, zipfile.BadZipFile, OSError, EOFError):
            raise InputError(path, "damaged model header") from None
        except RecursionError:
            raise InputError(path, "damaged model header (JSON nested deeper than Python reads)") from None
        _check_header(header, path)
    except InputError:
        npz.close()
        raise
    return header, npz


def _check_header(header, path: Path) -> None:
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(path, "not a gtsjax model file (wrong format name)")
    if header.get("version") != VERSION:
        raise InputError(
            path,
            f"model format version {_short(header.get('version'))}; this gtsjax reads version "
            f"{VERSION} (retrain with this version)",
        )
    if missing := [k for k in _HEADER if k not in header]:
        raise InputError(path, f"model header missing required key(s) {', '.join(map(repr, missing))}")
    for key, typ in {**_HEADER, "summary": dict}.items():
        v = header.get(key, {})
        if not isinstance(v, typ) or isinstance(v, bool) or (typ is list and not all(isinstance(c, str) for c in v)):
            want = {int: "an integer", str: "a string", list: "a list of names", dict: "an object"}[typ]
            raise InputError(path, f"model header field {key!r} is {type(v).__name__} {_short(v)}, expected {want}")
    if header["n_beams"] < 1:
        raise InputError(path, f"model header field 'n_beams' is {header['n_beams']}, expected at least 1")


def load_model(path: str | os.PathLike) -> Model:
    """Read a model file, checked against the model its header describes (see the module docstring),
    with what the sensor table says of its scanner (:func:`~gtsjax.sensors.with_scanner`). A model
    ready to run (a site, the run's options, checked against a sensor or log) comes from
    :mod:`gtsjax.drivers.setup`."""
    path = Path(path)
    header, npz = _open(path)
    try:
        try:
            top = _Reader(path, npz).read(header["schema"], Model, "")
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as err:
            if isinstance(err, InputError):
                raise
            raise InputError(path, f"truncated or damaged model file ({type(err).__name__})") from None
    finally:
        npz.close()
    _check(top, _config_sizes(top, header, path), path)
    return with_scanner(_build(top).with_common_pose_inputs())
