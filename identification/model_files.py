"""The files of a Hammerstein model: ``model.json`` and ``weights.npz``, never pickles.

:func:`write_model_files` writes them atomically, :func:`read_model_files` reads them back and
checks every field before the ARX and NLS constructors see it (a ValueError naming the file and
the field); :class:`identification.hammerstein.HammersteinModel` saves and loads through them.

``model.json``
    format name and version, the ARX model's dictionary, the NLS configuration, a metadata
    dictionary (the pipeline's report, units, data description) and the SHA-256 of the weights
    file, so a weights file from another model is recognised.
``weights.npz``
    the NLS arrays, named ``nls.<name>`` (``np.savez``, read back with
    ``np.load(allow_pickle=False)``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from piezo_env.checks import require_int, require_number

__all__ = [
    "HAMMERSTEIN_FORMAT",
    "HAMMERSTEIN_FORMAT_VERSION",
    "MODEL_FILE",
    "WEIGHTS_FILE",
    "read_model_files",
    "write_model_files",
]

HAMMERSTEIN_FORMAT = "piezo-hammerstein"
HAMMERSTEIN_FORMAT_VERSION = 1
MODEL_FILE = "model.json"
WEIGHTS_FILE = "weights.npz"
_NLS_PREFIX = "nls."


def write_model_files(
    description: dict[str, Any], nls_arrays: dict[str, np.ndarray], directory: str | Path
) -> Path:
    """Write ``description`` as ``model.json`` and the NLS arrays as ``weights.npz``, atomically.

    See :meth:`identification.hammerstein.HammersteinModel.save` (its arguments and errors).
    """
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"{directory} exists and is not a folder; choose another path")
    description = {**description, "weights_file": WEIGHTS_FILE, "weights_sha256": ""}
    try:  # refuse before anything touches the disk
        json.dumps(description, allow_nan=False)
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"model description is not JSON-safe (check the metadata): {error}"
        ) from error
    arrays = {_NLS_PREFIX + k: v for k, v in nls_arrays.items()}
    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}.new-", dir=directory.parent))
    try:
        with (staging / WEIGHTS_FILE).open("wb") as handle:
            np.savez(handle, **arrays)
            handle.flush()
            os.fsync(handle.fileno())
        description["weights_sha256"] = _sha256(staging / WEIGHTS_FILE)
        text = json.dumps(description, indent=2, allow_nan=False)
        with (staging / MODEL_FILE).open("w", encoding="utf-8") as handle:
            handle.write(text + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        _replace_folder(staging, directory)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return directory


def read_model_files(
    directory: str | Path,
) -> tuple[dict[str, Any], dict[str, np.ndarray], Path, Path]:
    """Read and check the two files of a model folder written by :func:`write_model_files`.

    Returns
    -------
    description : dict
        ``model.json``, every field the loader reads checked.
    nls_arrays : dict of numpy.ndarray
        The NLS arrays of ``weights.npz`` (names without the ``nls.`` prefix).
    model_path, weights_path : pathlib.Path
        The two files, for messages.

    Raises
    ------
    FileNotFoundError, ValueError
        As :meth:`identification.hammerstein.HammersteinModel.load`.
    """
    directory = Path(directory)
    model_path = directory / MODEL_FILE
    weights_path = directory / WEIGHTS_FILE
    for path in (model_path, weights_path):
        if not path.is_file():
            raise FileNotFoundError(f"model file {path} does not exist")
    description = _read_description(model_path)
    if description["weights_sha256"] != _sha256(weights_path):
        raise ValueError(
            f"{weights_path}: contents do not match 'weights_sha256' of {model_path} "
            "(SHA-256 differs); the weights file is truncated, corrupted or belongs to "
            "another model"
        )
    arrays = _read_weights(weights_path)
    nls_arrays = {k[len(_NLS_PREFIX) :]: v for k, v in arrays.items() if k.startswith(_NLS_PREFIX)}
    unknown = sorted(k for k in arrays if not k.startswith(_NLS_PREFIX))
    if unknown:
        raise ValueError(f"{weights_path}: unexpected array(s) {unknown}")
    return description, nls_arrays, model_path, weights_path


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _replace_folder(new: Path, target: Path) -> None:
    """Put the folder ``new`` at ``target`` by renames; an old ``target`` is removed last."""
    if not target.exists():
        os.replace(new, target)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
    old.rmdir()
    os.replace(target, old)
    try:
        os.replace(new, target)
    except BaseException:
        os.replace(old, target)  # put the old model back
        raise
    shutil.rmtree(old, ignore_errors=True)


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-standard JSON constant {name} (numbers must be finite)")


def _read_description(path: Path) -> dict[str, Any]:
    """Parse ``model.json`` and check every field the loader reads (ValueError naming it)."""
    try:
        description = json.loads(path.read_text(encoding="utf-8"), parse_constant=_reject_constant)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON (truncated or corrupted?): {error}") from error
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from error
    if not isinstance(description, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(description).__name__}")
    if description.get("format") != HAMMERSTEIN_FORMAT:
        raise ValueError(
            f"{path}: format is {description.get('format')!r}; expected {HAMMERSTEIN_FORMAT!r}"
        )
    version = description.get("version")
    if type(version) is not int or version != HAMMERSTEIN_FORMAT_VERSION:
        raise ValueError(
            f"{path}: format version {description.get('version')!r} is not supported "
            f"(this code reads version {HAMMERSTEIN_FORMAT_VERSION})"
        )
    missing = [k for k in ("arx", "nls", "weights_sha256") if k not in description]
    if missing:
        raise ValueError(
            f"{path}: missing key(s) {missing}"
            + (
                " (the weights checksum is mandatory: save the model again)"
                if "weights_sha256" in missing
                else ""
            )
        )
    digest = description["weights_sha256"]
    if not (isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{64}", digest)):
        raise ValueError(f"{path}: 'weights_sha256' must be 64 hex digits; got {digest!r}")
    if description.get("weights_file", WEIGHTS_FILE) != WEIGHTS_FILE:
        raise ValueError(
            f"{path}: 'weights_file' is {description['weights_file']!r}; expected {WEIGHTS_FILE!r}"
        )
    metadata = description.setdefault("metadata", {})
    if metadata is None:
        description["metadata"] = {}
    elif not isinstance(metadata, dict):
        raise ValueError(f"{path}: 'metadata' must be a JSON object")
    try:
        _check_arx_fields(description["arx"])
        _check_nls_fields(description["nls"])
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    return description


# -- field checks of model.json (before the ARX and NLS constructors see the values) ----------


def _number(value: Any, field: str, *, positive: bool = False) -> None:
    require_number(repr(field), value, low=0.0 if positive else None, low_open=positive)


def _numbers(value: Any, field: str, *, positive: bool = False, min_len: int = 0) -> None:
    if not isinstance(value, list):
        raise ValueError(f"{field!r} must be a list of numbers; got {value!r}")
    if len(value) < min_len:
        raise ValueError(f"{field!r} must have at least {min_len} entries; got {value!r}")
    for i, v in enumerate(value):
        _number(v, f"{field}[{i}]", positive=positive)


def _object(value: Any, field: str, keys: Sequence[str]) -> None:
    if not isinstance(value, dict):
        raise ValueError(f"{field!r} must be a JSON object; got {value!r}")
    missing = [f"{field}.{k}" for k in keys if k not in value]
    if missing:
        raise ValueError(f"missing key(s) {missing}")


def _tag(value: Any, field: str, expected: str | int) -> None:
    """Check a format name or version (``True`` is not the version 1)."""
    if type(value) is not type(expected) or value != expected:
        raise ValueError(f"{field!r} is {value!r}; this code reads {expected!r}")


def _check_arx_fields(arx: Any) -> None:
    _object(arx, "arx", ("format", "version", "a", "b", "noise_bound", "dt"))
    _tag(arx["format"], "arx.format", "piezo-arx")
    _tag(arx["version"], "arx.version", 1)
    _numbers(arx["a"], "arx.a")
    _numbers(arx["b"], "arx.b", min_len=1)
    _number(arx["noise_bound"], "arx.noise_bound")
    _number(arx["dt"], "arx.dt", positive=True)
    if arx.get("method") is not None and not isinstance(arx["method"], str):
        raise ValueError(f"'arx.method' must be a string or null; got {arx['method']!r}")
    history = arx.get("history")
    if history is not None:
        _object(history, "arx.history", ())
        for key, value in history.items():
            if not isinstance(value, list):
                raise ValueError(f"'arx.history.{key}' must be a list; got {value!r}")


_FEATURE_FIELDS = {
    "play": ("radii", "numbers"),
    "rate-play": ("radii", "numbers"),
    "bouc-wen": ("levels", "numbers"),
    "past-inputs": ("n_past", "integer"),
}


def _check_nls_fields(nls: Any) -> None:
    _object(nls, "nls", ("format", "version", "features", "hidden", "u_range"))
    _tag(nls["format"], "nls.format", "piezo-nls")
    _tag(nls["version"], "nls.version", 1)
    features = nls["features"]
    _object(features, "nls.features", ("name", "initial_input"))
    name = features["name"]
    if not isinstance(name, str) or name not in _FEATURE_FIELDS:
        raise ValueError(
            f"'nls.features.name' must be one of {sorted(_FEATURE_FIELDS)}; got {name!r}"
        )
    key, kind = _FEATURE_FIELDS[name]
    if key not in features:
        raise ValueError(f"missing key(s) ['nls.features.{key}'] (feature set {name!r})")
    if kind == "numbers":
        _numbers(features[key], f"nls.features.{key}", positive=True, min_len=1)
    else:
        require_int(repr(f"nls.features.{key}"), features[key], minimum=0)
    _number(features["initial_input"], "nls.features.initial_input")
    if name == "rate-play":
        _rate_play_fields(features)
    hidden = nls["hidden"]
    if not isinstance(hidden, list) or not hidden:
        raise ValueError(f"'nls.hidden' must be a non-empty list of layer widths; got {hidden!r}")
    for i, width in enumerate(hidden):
        require_int(repr(f"nls.hidden[{i}]"), width)
    _numbers(nls["u_range"], "nls.u_range", min_len=2)
    if len(nls["u_range"]) != 2 or not nls["u_range"][0] < nls["u_range"][1]:
        raise ValueError(f"'nls.u_range' must be [low, high], low < high; got {nls['u_range']!r}")
    training = nls.get("training")
    if training is not None and not isinstance(training, dict):
        raise ValueError(f"'nls.training' must be a JSON object or null; got {training!r}")


def _rate_play_fields(features: dict) -> None:
    """The rate constant (s, >= 0) and sample time (s, > 0) of rate-dependent play features."""
    missing = [f"nls.features.{k}" for k in ("rate_time", "dt") if k not in features]
    if missing:
        raise ValueError(f"missing key(s) {missing} (feature set 'rate-play')")
    _number(features["rate_time"], "nls.features.rate_time")
    _number(features["dt"], "nls.features.dt")
    if features["rate_time"] < 0 or features["dt"] <= 0:
        raise ValueError(
            "'nls.features.rate_time' must be >= 0 s and 'nls.features.dt' > 0 s; got "
            f"{features['rate_time']!r} and {features['dt']!r}"
        )


def _read_weights(path: Path) -> dict[str, np.ndarray]:
    """Read every array of ``weights.npz`` without unpickling; float arrays only."""
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single .npy array, not an .npz archive")
        with data:
            arrays = {name: np.array(data[name]) for name in data.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as error:
        raise ValueError(
            f"{path}: cannot read the weights (truncated, corrupted or not an .npz file): {error}"
        ) from error
    for name, value in arrays.items():
        if value.dtype.kind not in "fiu":
            raise ValueError(f"{path}: array {name!r} has dtype {value.dtype}; expected floats")
    return arrays
