"""The NLS network in numpy and the :class:`NLS` class (structure and evaluation).

Network
-------
With ``x = (F - m) / s`` (feature normalization stored in the model)::

    z = z_m + z_s (w^T x + c + MLP(x)),   MLP: tanh, tanh, tanh hidden layers, linear output

The affine skip term ``w^T x + c`` is initialised by weighted least squares and the MLP's output
layer by zeros, so training starts from the best affine map of the features and the MLP learns
the residual. Consequences:

- an identity NLS (``z = u``) and a Prandtl-Ishlinskii hysteresis with the feature radii (``z`` a
  weighted sum of plays) are represented exactly and are the starting point of training;
- outside the training range the tanh units saturate and the map continues along the affine
  part, i.e. it extrapolates linearly, as the bender's small-signal physics does, instead of
  flattening (a pure tanh network) or growing without bound in arbitrary directions.

Run time
--------
After training the numpy arrays are the source of truth: the NLS evaluates in numpy (a 3 x 32
MLP step costs ~10 us, the default 3 x 2 less), exports to a pure-numpy evaluator
(:meth:`NLS.to_numpy`) and to casadi (:meth:`NLS.to_casadi`, :meth:`NLS.to_casadi_step`), and
builds a torch module only for training (:meth:`NLS.to_torch`). Nothing here needs torch at
run time except :func:`fit_nls`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.arguments import as_range, as_scalar, as_signal
from identification.features import (
    BoucWenFeatures,
    FeatureMap,
    PastInputFeatures,
    PlayFeatures,
    RatePlayFeatures,
    sequence_features,
)
from identification.nls.export import ExportMixin
from identification.nls.files import ARRAY_NAMES, FilesMixin
from identification.nls.inverse import InverseMixin

__all__ = ["NLS", "NumpyMLP"]


# ---------------------------------------------------------------------------------------------
# the network in numpy


@dataclass(frozen=True)
class NumpyMLP:
    """Pure-numpy evaluator ``F -> z`` of the NLS network, normalization folded into the weights.

    ``z = c + w^T F + v^T h_L``, ``h_i = tanh(W_i h_i-1 + b_i)``, ``h_0 = F``.

    Attributes
    ----------
    weights : tuple of numpy.ndarray
        Hidden-layer weights ``W_i``, shapes (n_i, n_i-1).
    biases : tuple of numpy.ndarray
        Hidden-layer biases ``b_i``, shapes (n_i,).
    out_weight : numpy.ndarray, shape (n_L,)
        Output weights ``v`` (equivalent V per unit activation).
    skip_weight : numpy.ndarray, shape (n_features,)
        Affine skip weights ``w`` (equivalent V per feature V).
    out_bias : float
        Output offset ``c``, equivalent V.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    out_weight: np.ndarray
    skip_weight: np.ndarray
    out_bias: float

    def __post_init__(self) -> None:
        transposed = tuple(np.ascontiguousarray(w.T) for w in self.weights)
        object.__setattr__(self, "_transposed", transposed)

    @property
    def n_features(self) -> int:
        """Number of input features."""
        return int(self.skip_weight.size)

    def __call__(self, features: ArrayLike) -> np.ndarray | float:
        """Evaluate on features ``(T, n_f)`` -> z ``(T,)``, or ``(n_f,)`` -> float (equiv. V)."""
        f = np.asarray(features, dtype=np.float64)
        if f.ndim == 1:
            return self.evaluate_one(f)
        if f.ndim != 2 or f.shape[1] != self.n_features:
            raise ValueError(f"features must have shape (T, {self.n_features}); got {f.shape}")
        h = f
        for w, b in zip(self.weights, self.biases, strict=True):
            h = np.tanh(h @ w.T + b)
        return h @ self.out_weight + f @ self.skip_weight + self.out_bias

    def evaluate_rows(self, f: np.ndarray) -> np.ndarray:
        """Evaluate feature rows ``(m, n_f)`` -> z ``(m,)`` (equivalent V), without validation."""
        h = f
        for wt, b in zip(self._transposed, self.biases, strict=True):
            h = np.tanh(h @ wt + b)
        return h @ self.out_weight + f @ self.skip_weight + self.out_bias

    def evaluate_one(self, f: np.ndarray) -> float:
        """Evaluate one feature vector ``(n_f,)`` -> z (equivalent V), without validation."""
        h = f
        for w, b in zip(self.weights, self.biases, strict=True):
            h = np.tanh(w @ h + b)
        return float(self.out_weight @ h + self.skip_weight @ f + self.out_bias)


class NLS(InverseMixin, ExportMixin, FilesMixin):
    """Neural static nonlinearity with memory features: voltage u (V) -> hidden z (equiv. V).

    Build it with :func:`fit_nls` or :meth:`from_dict`. Evaluation is numpy only.

    Parameters
    ----------
    feature_map : PlayFeatures, RatePlayFeatures, PastInputFeatures or BoucWenFeatures
        Memory features of the input.
    params : dict of numpy.ndarray
        Network parameters in normalized coordinates: ``feature_mean``, ``feature_scale``
        (n_f,), ``z_mean``, ``z_scale`` (scalars, equivalent V), ``layer{i}_weight`` (n_i,
        n_i-1), ``layer{i}_bias`` (n_i,), ``out_weight`` (n_L,), ``out_bias`` (scalar),
        ``skip_weight`` (n_f,), ``skip_bias`` (scalar).
    u_range : (float, float)
        Input range the network was trained on, V; the default search range of the inverse.
    training : dict, optional
        JSON-safe training record (epochs, losses, time).
    """

    def __init__(
        self,
        feature_map: FeatureMap,
        params: dict[str, np.ndarray],
        *,
        u_range: Sequence[float],
        training: dict[str, Any] | None = None,
    ) -> None:
        if not isinstance(
            feature_map, PlayFeatures | RatePlayFeatures | PastInputFeatures | BoucWenFeatures
        ):
            raise ValueError(
                "feature_map must be PlayFeatures, RatePlayFeatures, PastInputFeatures or "
                "BoucWenFeatures; "
                f"got {type(feature_map)}"
            )
        self.feature_map = feature_map
        self.u_range = as_range("u_range", u_range)
        self.training = dict(training or {})
        self._params = _check_params(params, feature_map.n_features)
        self._mlp = _fold(self._params)
        self._grid_cache: tuple[tuple[float, float, int], np.ndarray] | None = None

    # -- structure ---------------------------------------------------------------------------

    @property
    def hidden(self) -> tuple[int, ...]:
        """Hidden-layer widths."""
        return tuple(int(w.shape[0]) for w in self._mlp.weights)

    @property
    def n_features(self) -> int:
        """Number of network input features."""
        return self.feature_map.n_features

    @property
    def n_state(self) -> int:
        """Length of the feature state vector."""
        return self.feature_map.n_state

    @property
    def feature_set(self) -> str:
        """Name of the feature set: ``"play"``, ``"past-inputs"`` or ``"bouc-wen"``."""
        return self.feature_map.name

    def initial_state(self) -> np.ndarray:
        """Feature state at rest (V)."""
        return self.feature_map.initial_state()

    def __repr__(self) -> str:
        return (
            f"NLS(features={self.feature_set!r}, n_features={self.n_features}, "
            f"hidden={self.hidden}, u_range={self.u_range})"
        )

    # -- evaluation --------------------------------------------------------------------------

    def features(
        self, u_seq: ArrayLike, state: ArrayLike | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Memory features of an input sequence.

        Parameters
        ----------
        u_seq : array_like, shape (T,)
            Input voltage, V.
        state : array_like, optional
            Feature state before ``u_seq[0]``; None for the rest state.

        Returns
        -------
        F : numpy.ndarray, shape (T, n_features)
            Features, V.
        final_state : numpy.ndarray, shape (n_state,)
            State after the last sample.
        """
        u = as_signal("u_seq", u_seq)
        return sequence_features(self.feature_map, u, self.feature_map.check_state(state))

    def evaluate(self, u_seq: ArrayLike, state: ArrayLike | None = None) -> np.ndarray:
        """NLS output ``z`` (equivalent V) of an input sequence ``u_seq`` (V) from ``state``."""
        features, _ = self.features(u_seq, state)
        return self._mlp(features)

    __call__ = evaluate

    def step(self, u_t: float, state: ArrayLike | None) -> tuple[float, np.ndarray]:
        """Advance one sample: input ``u_t`` (V) -> ``(z_t, next_state)`` (equivalent V)."""
        u = as_scalar("u_t", u_t)
        f, new_state = self.feature_map.step(u, self.feature_map.check_state(state))
        return self._mlp.evaluate_one(f), new_state


def _check_params(params: dict[str, np.ndarray], n_features: int) -> dict[str, np.ndarray]:
    """Validate the raw parameter arrays and return float64 copies."""
    out: dict[str, np.ndarray] = {}
    layer_names = sorted(
        (k for k in params if k.startswith("layer") and k.endswith("_weight")),
        key=lambda k: int(k[len("layer") : -len("_weight")]),
    )
    if not layer_names:
        raise ValueError("NLS weights have no hidden layer (expected 'layer0_weight', ...)")
    expected = [*ARRAY_NAMES]
    for i in range(len(layer_names)):
        expected += [f"layer{i}_weight", f"layer{i}_bias"]
    missing = [k for k in expected if k not in params]
    if missing:
        raise ValueError(f"NLS weights are missing array(s) {missing}")
    unknown = sorted(set(params) - set(expected))
    if unknown:
        raise ValueError(f"NLS weights have unexpected array(s) {unknown}")
    for key in expected:
        arr = np.array(params[key], dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"NLS weight array {key!r} contains non-finite values")
        out[key] = arr
    shapes: dict[str, tuple[int, ...]] = {
        "feature_mean": (n_features,),
        "feature_scale": (n_features,),
        "z_mean": (),
        "z_scale": (),
        "skip_weight": (n_features,),
        "skip_bias": (),
        "out_bias": (),
    }
    width = n_features
    for i in range(len(layer_names)):
        w = out[f"layer{i}_weight"]
        if w.ndim != 2 or w.shape[1] != width:
            raise ValueError(
                f"NLS weight array 'layer{i}_weight' has shape {w.shape}; expected (n, {width})"
            )
        width = w.shape[0]
        shapes[f"layer{i}_bias"] = (width,)
    shapes["out_weight"] = (width,)
    for key, shape in shapes.items():
        if out[key].shape != shape:
            raise ValueError(
                f"NLS weight array {key!r} has shape {out[key].shape}; expected {shape}"
            )
    if np.any(out["feature_scale"] <= 0.0) or out["z_scale"] <= 0.0:
        raise ValueError("NLS normalization scales must be positive")
    return out


def _fold(p: dict[str, np.ndarray]) -> NumpyMLP:
    """Fold the feature and output normalization into the weights of a :class:`NumpyMLP`."""
    inv_scale = 1.0 / p["feature_scale"]
    shift = p["feature_mean"] * inv_scale
    n_layers = sum(1 for k in p if k.startswith("layer") and k.endswith("_weight"))
    weights = [p[f"layer{i}_weight"].copy() for i in range(n_layers)]
    biases = [p[f"layer{i}_bias"].copy() for i in range(n_layers)]
    biases[0] = biases[0] - weights[0] @ shift
    weights[0] = weights[0] * inv_scale
    z_scale = float(p["z_scale"])
    skip = p["skip_weight"] * inv_scale * z_scale
    bias = float(p["z_mean"]) + z_scale * (
        float(p["out_bias"]) + float(p["skip_bias"]) - float(p["skip_weight"] @ shift)
    )
    for arr in (*weights, *biases):
        arr.setflags(write=False)
    out_weight = p["out_weight"] * z_scale
    for arr in (out_weight, skip):
        arr.setflags(write=False)
    return NumpyMLP(tuple(weights), tuple(biases), out_weight, skip, bias)
