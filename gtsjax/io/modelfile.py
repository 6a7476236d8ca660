"""Model files: one versioned ``.npz`` holding the configuration, the hyperparameters and everything
prediction needs.

Layout: a key ``gtsjax_model`` with a JSON header (format name, version, sensor model, classes, a
training summary, and a schema of the model's pytree), and one array per leaf (``leaf00000``, …).
The schema names each node's type from a fixed registry, so loading never unpickles anything and a
file cannot make gtsjax build an object it does not know. Arrays keep their dtype (the step's
float32 copies of the GPs).
"""

import dataclasses
import json
import os
import zipfile
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._classify import Classifier, Support
from .._filters import Envelope
from .._frontend import FrontEndConfig
from .._pose import PoseRegressor
from .._track import TrackerParams
from ..errors import InputError
from ..gp import GP, Hyperparameters, SparseGP
from ..model import Model, SiteArrays

FORMAT = "gtsjax-model"
VERSION = 3  # 3: scanner geometry, open-set supports, shape envelopes, per-class motion limits (and, optional, the pose regressors' heading_var_max)
_HEADER_KEY = "gtsjax_model"
_TYPES = {c.__name__: c for c in (Model, FrontEndConfig, Classifier, Support, Envelope, PoseRegressor, TrackerParams,
                                  SparseGP, GP, Hyperparameters, SiteArrays)}


def _encode(node, leaves: dict[str, np.ndarray]):
    if node is None:
        return None
    if isinstance(node, eqx.Module):
        name = type(node).__name__
        if _TYPES.get(name) is not type(node):
            raise TypeError(f"cannot save a {type(node)!r} in a model file")
        return {"type": name, "fields": {f.name: _encode(getattr(node, f.name), leaves)
                                         for f in dataclasses.fields(node)}}
    if isinstance(node, tuple):
        return {"tuple": [_encode(v, leaves) for v in node]}
    if isinstance(node, (bool, int, float, str)):
        return {"value": node}
    arr = np.asarray(node)
    key = f"leaf{len(leaves):05d}"
    leaves[key] = arr
    return {"array": key}


def _decode(spec, npz, where):
    if spec is None:
        return None
    if "array" in spec:
        key = spec["array"]
        if key not in npz.files:
            raise InputError(where, f"truncated or damaged model file (array {key} missing)")
        return jnp.asarray(npz[key])
    if "value" in spec:
        v = spec["value"]
        return tuple(v) if isinstance(v, list) else v
    if "tuple" in spec:
        return tuple(_decode(v, npz, where) for v in spec["tuple"])
    cls = _TYPES.get(spec.get("type", ""))
    if cls is None:
        raise InputError(where, f"unknown node type {spec.get('type')!r} in the model file")
    fields = {k: _decode(v, npz, where) for k, v in spec["fields"].items()}
    if spec["type"] == "Model":
        for k in ("classes",):
            fields[k] = tuple(fields[k])
    return cls(**fields)


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
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        np.savez(f, **{_HEADER_KEY: np.asarray(json.dumps(header))}, **leaves)
    os.replace(tmp, path)


def read_header(path: str | os.PathLike) -> dict:
    """The JSON header of a model file (format, version, sensor model, classes, training summary)."""
    return _open(Path(path))[0]


def _open(path: Path):
    if not path.exists():
        raise InputError(path, "no such file")
    try:
        npz = np.load(path, allow_pickle=False)
        files = npz.files
    except (zipfile.BadZipFile, ValueError, OSError, EOFError):
        raise InputError(path, "not a gtsjax model file (not an .npz archive)") from None
    if _HEADER_KEY not in files:
        raise InputError(path, "not a gtsjax model file (no model header; is it a scan log?)")
    try:
        header = json.loads(str(npz[_HEADER_KEY]))
    except (ValueError, zipfile.BadZipFile, OSError, EOFError):
        raise InputError(path, "damaged model header") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(path, "not a gtsjax model file (wrong format name)")
    if header.get("version") != VERSION:
        raise InputError(path, f"model format version {header.get('version')!r}; this gtsjax reads version {VERSION} "
                               "(retrain with this version)")
    return header, npz


def load_model(path: str | os.PathLike, *, sensor_model: str | None = None, n_beams: int | None = None) -> Model:
    """Read a model file. With ``sensor_model``/``n_beams`` given (from the log or the live sensor),
    a model trained for another scanner is refused with one line."""
    path = Path(path)
    header, npz = _open(path)
    try:
        if sensor_model is not None and header["sensor_model"] != sensor_model:
            raise InputError(path, f"model trained for sensor {header['sensor_model']}, but the scans come from "
                                   f"{sensor_model}")
        if n_beams is not None and n_beams > header["n_beams"]:
            raise InputError(path, f"model expects at most {header['n_beams']} beams per scan, got {n_beams}")
        try:
            model = _decode(header["schema"], npz, path)
        except (KeyError, TypeError, zipfile.BadZipFile, OSError, EOFError, ValueError) as err:
            if isinstance(err, InputError):
                raise
            raise InputError(path, f"truncated or damaged model file ({type(err).__name__})") from None
    finally:
        npz.close()
    if not isinstance(model, Model):
        raise InputError(path, "damaged model file (top node is not a model)")
    return model
