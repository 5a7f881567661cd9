"""Hammerstein model of the bender: neural static nonlinearity (NLS) followed by an ARX model.

::

    u (V) --[NLS, memory features]--> z (equivalent V) --[ARX: B(q)/A(q)]--> y (um)

The NLS (:class:`identification.nls.NLS`) carries the hysteresis, the ARX model
(:class:`identification.arx.ARXModel`) the linear dynamics; the scale between them is fixed by
the unit small-signal gain of the NLS, so ``z`` is in equivalent volts (paper section 3.4).

Model files
-----------
:meth:`HammersteinModel.save` writes a directory with two plain files, never pickles
(:mod:`identification.model_files`):

``model.json``
    format name and version, the ARX model's dictionary, the NLS configuration, a metadata
    dictionary (the pipeline's report, units, data description) and the SHA-256 of the weights
    file, so a weights file from another model is recognised.
``weights.npz``
    the NLS arrays (``np.savez``, read back with ``np.load(allow_pickle=False)``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.arx import ARXModel
from identification.model_files import (
    HAMMERSTEIN_FORMAT,
    HAMMERSTEIN_FORMAT_VERSION,
    read_model_files,
    write_model_files,
)
from identification.nls import NLS

# HAMMERSTEIN_FORMAT and its version: defined with the files, exported here as well
__all__ = ["HAMMERSTEIN_FORMAT", "HAMMERSTEIN_FORMAT_VERSION", "HammersteinModel"]


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
        return write_model_files(self.to_dict(), self.nls.arrays(), directory)

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
        description, nls_arrays, model_path, weights_path = read_model_files(directory)
        try:
            arx = ARXModel.from_dict(description["arx"])
        except (ValueError, TypeError, AttributeError, KeyError, IndexError) as error:
            raise ValueError(f"{model_path}: 'arx': {error}") from error
        try:
            nls = NLS.from_dict(description["nls"], nls_arrays)
        except (ValueError, TypeError, AttributeError, KeyError, IndexError) as error:
            raise ValueError(f"{model_path} / {weights_path}: 'nls': {error}") from error
        return cls(nls, arx, metadata=description["metadata"])
