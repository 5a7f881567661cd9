"""Hammerstein model of the bender: neural static nonlinearity (NLS) followed by an ARX model.

::

    u (V) --[NLS, memory features]--> z (equivalent V) --[ARX: B(q)/A(q)]--> y (um)

The NLS (:class:`identification.nls.NLS`) carries the hysteresis, the ARX model
(:class:`identification.arx.ARXModel`) the linear dynamics; the scale between them is fixed by
the unit small-signal gain of the NLS, so ``z`` is in equivalent volts (paper section 3.4).

Model files
-----------
:meth:`HammersteinModel.save` writes a directory with two plain files, never pickles:

``model.json``
    format name and version, the ARX model's dictionary, the NLS configuration, a metadata
    dictionary (the pipeline's report, units, data description) and the SHA-256 of the weights
    file, so a weights file from another model is recognised.
``weights.npz``
    the NLS arrays (``np.savez``, read back with ``np.load(allow_pickle=False)``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.arx import ARXModel
from identification.nls import NLS
from piezo_env.checks import require_int, require_number

__all__ = ["HAMMERSTEIN_FORMAT", "HAMMERSTEIN_FORMAT_VERSION", "HammersteinModel"]

HAMMERSTEIN_FORMAT = "piezo-hammerstein"
HAMMERSTEIN_FORMAT_VERSION = 1
MODEL_FILE = "model.json"
WEIGHTS_FILE = "weights.npz"
_NLS_PREFIX = "nls."


class HammersteinModel:
    """NLS (voltage -> hidden signal z) in series with an ARX model (z -> tip deflection).

    Parameters
    ----------
    nls : NLS
        Static nonlinearity with memory features, V -> equivalent V.
    arx : ARXModel
        Linear dynamics, equivalent V -> um (its ``dt`` is the sampling period, s).
    metadata : mapping, optional
        JSON-safe information stored with the model (units, data, identification report).

    Attributes
    ----------
    nls : NLS
    arx : ARXModel
    metadata : dict
    """

    def __init__(
        self, nls: NLS, arx: ARXModel, *, metadata: Mapping[str, Any] | None = None
    ) -> None:
        if not isinstance(nls, NLS):
            raise ValueError(f"nls must be an identification.nls.NLS; got {type(nls).__name__}")
        if not isinstance(arx, ARXModel):
            raise ValueError(
                f"arx must be an identification.arx.ARXModel; got {type(arx).__name__}"
            )
        if metadata is not None and not isinstance(metadata, Mapping):
            raise ValueError(f"metadata must be a mapping; got {type(metadata).__name__}")
        self.nls = nls
        self.arx = arx
        self.metadata: dict[str, Any] = dict(metadata or {})

    @property
    def dt(self) -> float:
        """Sampling period, s (the ARX model's)."""
        return self.arx.dt

    def __repr__(self) -> str:
        return f"HammersteinModel(nls={self.nls!r}, arx={self.arx!r})"

    # -- evaluation --------------------------------------------------------------------------

    def nls_output(self, u: ArrayLike, state: ArrayLike | None = None) -> np.ndarray:
        """Hidden signal ``z`` (equivalent V) for the voltage sequence ``u`` (V).

        ``state`` is the NLS feature state before ``u[0]`` (None: rest).
        """
        return self.nls.evaluate(u, state)

    def simulate(
        self, u: ArrayLike, *, nls_state: ArrayLike | None = None, y0: ArrayLike | None = None
    ) -> np.ndarray:
        """Free-run (simulation) output: ``z = NLS(u)``, ``y = ARX(z)``.

        Alignment: ``y[t]`` is the deflection *before* ``u[t]`` is applied; it depends on
        ``u[t-1], u[t-2], ...`` only (``y[0]`` is the rest or ``y0`` value). This is the
        convention of :func:`identification.pipeline.collect`, which drives the env and returns
        the observation of ``reset`` as ``y[0]`` and the observation returned by the step that
        applied ``u[t-1]`` as ``y[t]``. If you step the env with ``u`` yourself and keep the
        observations returned by ``step``, those are ``y[1:]``: compare them with
        ``simulate(u)[1:]`` (a one-sample shift costs nearly all of the fit on white input).

        Parameters
        ----------
        u : array_like, shape (T,)
            Drive voltage, V.
        nls_state : array_like, optional
            NLS feature state before ``u[0]`` (None: rest).
        y0 : array_like, optional
            First ``na`` outputs, um, to start the ARX recursion from (None: at rest); see
            :meth:`ARXModel.simulate`.

        Returns
        -------
        numpy.ndarray, shape (T,)
            Simulated tip deflection, um.
        """
        return self.arx.simulate(self.nls_output(u, nls_state), y0=y0)

    def predict(
        self, u: ArrayLike, y: ArrayLike, *, nls_state: ArrayLike | None = None
    ) -> np.ndarray:
        """One-step-ahead prediction of ``y`` (um) from measured ``u`` (V) and ``y`` (um).

        The NLS runs on the measured input; the ARX part predicts from past hidden signals and
        measured outputs (see :meth:`ARXModel.predict`).
        """
        return self.arx.predict(self.nls_output(u, nls_state), y)

    def inverse_nls(
        self,
        z_target: float,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
    ) -> float:
        """Voltage (V) whose NLS output from ``state`` is ``z_target`` (equivalent V).

        Saturates at the closest reachable voltage when the target is out of reach; see
        :meth:`NLS.inverse` (and :meth:`NLS.inverse_sequence` for a whole sequence).
        """
        return self.nls.inverse(z_target, state, u_range=u_range)

    # -- files -------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe description (without the NLS arrays; see :meth:`save`)."""
        return {
            "format": HAMMERSTEIN_FORMAT,
            "version": HAMMERSTEIN_FORMAT_VERSION,
            "arx": self.arx.to_dict(),
            "nls": self.nls.to_dict(),
            "metadata": self.metadata,
            "units": {"u": "V", "z": "equivalent V", "y": "um", "dt": "s"},
        }

    def save(self, directory: str | Path) -> Path:
        """Write ``model.json`` and ``weights.npz`` into ``directory``, atomically.

        Both files are written and checked in a temporary folder beside ``directory``, which
        then replaces ``directory`` by renames (an existing folder is renamed aside first and
        removed last). A refused or interrupted save therefore leaves a model already in
        ``directory`` loadable; the worst case, a crash between the two renames, leaves the old
        model complete in a ``.<name>.old-*`` folder beside it.

        Parameters
        ----------
        directory : str or pathlib.Path
            Model folder (its parent is created if needed). Any other files in an existing
            folder are discarded with it.

        Returns
        -------
        pathlib.Path
            The directory.

        Raises
        ------
        ValueError
            If the metadata is not JSON-serializable (NaN and infinity included), or
            ``directory`` exists and is not a folder.
        """
        directory = Path(directory)
        if directory.exists() and not directory.is_dir():
            raise ValueError(f"{directory} exists and is not a folder; choose another path")
        description = self.to_dict()
        description["weights_file"] = WEIGHTS_FILE
        description["weights_sha256"] = ""
        try:  # refuse before anything touches the disk
            json.dumps(description, allow_nan=False)
        except (TypeError, ValueError) as error:
            raise ValueError(
                f"model description is not JSON-safe (check the metadata): {error}"
            ) from error
        arrays = {_NLS_PREFIX + k: v for k, v in self.nls.arrays().items()}
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

    @classmethod
    def load(cls, directory: str | Path) -> HammersteinModel:
        """Read a model written by :meth:`save`.

        Raises
        ------
        FileNotFoundError
            If ``model.json`` or ``weights.npz`` is missing.
        ValueError
            If a file is truncated or corrupted, a key is missing or has the wrong type, the
            format or version does not match, the weights checksum is missing or does not match
            (the weights file belongs to another model), or an array has the wrong shape; the
            message names the file and the field.
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
        try:
            arx = ARXModel.from_dict(description["arx"])
        except (ValueError, TypeError, AttributeError, KeyError, IndexError) as error:
            raise ValueError(f"{model_path}: 'arx': {error}") from error
        nls_arrays = {
            k[len(_NLS_PREFIX) :]: v for k, v in arrays.items() if k.startswith(_NLS_PREFIX)
        }
        unknown = sorted(k for k in arrays if not k.startswith(_NLS_PREFIX))
        if unknown:
            raise ValueError(f"{weights_path}: unexpected array(s) {unknown}")
        try:
            nls = NLS.from_dict(description["nls"], nls_arrays)
        except (ValueError, TypeError, AttributeError, KeyError, IndexError) as error:
            raise ValueError(f"{model_path} / {weights_path}: 'nls': {error}") from error
        return cls(nls, arx, metadata=description["metadata"])


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
