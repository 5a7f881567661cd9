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
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.arx import ARXModel
from identification.nls import NLS

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
        """Write ``model.json`` and ``weights.npz`` into ``directory`` (created if needed).

        Returns
        -------
        pathlib.Path
            The directory.

        Raises
        ------
        ValueError
            If the metadata is not JSON-serializable (NaN and infinity included).
        """
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        weights_path = directory / WEIGHTS_FILE
        arrays = {_NLS_PREFIX + k: v for k, v in self.nls.arrays().items()}
        with weights_path.open("wb") as handle:
            np.savez(handle, **arrays)
        description = self.to_dict()
        description["weights_file"] = WEIGHTS_FILE
        description["weights_sha256"] = _sha256(weights_path)
        try:
            text = json.dumps(description, indent=2, allow_nan=False)
        except (TypeError, ValueError) as error:
            raise ValueError(
                f"model description is not JSON-safe (check the metadata): {error}"
            ) from error
        (directory / MODEL_FILE).write_text(text + "\n", encoding="utf-8")
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> HammersteinModel:
        """Read a model written by :meth:`save`.

        Raises
        ------
        FileNotFoundError
            If ``model.json`` or ``weights.npz`` is missing.
        ValueError
            If a file is truncated or corrupted, a key is missing, the format or version does
            not match, the weights file belongs to another model, or an array has the wrong
            shape; the message names the file and the problem.
        """
        directory = Path(directory)
        model_path = directory / MODEL_FILE
        weights_path = directory / WEIGHTS_FILE
        for path in (model_path, weights_path):
            if not path.is_file():
                raise FileNotFoundError(f"model file {path} does not exist")
        description = _read_description(model_path)
        expected_hash = description.get("weights_sha256")
        if expected_hash is not None and expected_hash != _sha256(weights_path):
            raise ValueError(
                f"{weights_path}: contents do not match {model_path} (SHA-256 differs); the "
                "weights file is truncated, corrupted or belongs to another model"
            )
        arrays = _read_weights(weights_path)
        try:
            arx = ARXModel.from_dict(description["arx"])
        except ValueError as error:
            raise ValueError(f"{model_path}: 'arx': {error}") from error
        nls_arrays = {
            k[len(_NLS_PREFIX) :]: v for k, v in arrays.items() if k.startswith(_NLS_PREFIX)
        }
        try:
            nls = NLS.from_dict(description["nls"], nls_arrays)
        except ValueError as error:
            raise ValueError(f"{model_path} / {weights_path}: NLS: {error}") from error
        return cls(nls, arx, metadata=description.get("metadata") or {})


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _read_description(path: Path) -> dict[str, Any]:
    """Parse and check the top level of ``model.json``."""
    try:
        description = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON (truncated or corrupted?): {error}") from error
    if not isinstance(description, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(description).__name__}")
    if description.get("format") != HAMMERSTEIN_FORMAT:
        raise ValueError(
            f"{path}: format is {description.get('format')!r}; expected {HAMMERSTEIN_FORMAT!r}"
        )
    if description.get("version") != HAMMERSTEIN_FORMAT_VERSION:
        raise ValueError(
            f"{path}: format version {description.get('version')!r} is not supported "
            f"(this code reads version {HAMMERSTEIN_FORMAT_VERSION})"
        )
    missing = [k for k in ("arx", "nls") if k not in description]
    if missing:
        raise ValueError(f"{path}: missing key(s) {missing}")
    metadata = description.get("metadata")
    if metadata is not None and not isinstance(metadata, dict):
        raise ValueError(f"{path}: 'metadata' must be a JSON object")
    return description


def _read_weights(path: Path) -> dict[str, np.ndarray]:
    """Read every array of ``weights.npz`` without unpickling."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: np.array(data[name]) for name in data.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as error:
        raise ValueError(
            f"{path}: cannot read the weights (truncated, corrupted or not an .npz file): {error}"
        ) from error
