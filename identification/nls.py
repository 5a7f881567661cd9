"""Neural static-nonlinearity block (NLS) of the Hammerstein model: voltage u (V) -> hidden z.

The NLS maps the drive voltage ``u`` (V) to the hidden signal ``z`` (equivalent volts, i.e. the
voltage a linear, hysteresis-free actuator would need for the same deflection) that feeds the
linear ARX block. The paper (section 3.4, step e) fits it as a multilayer perceptron with three
hidden tanh layers. A static map ``u -> z`` cannot draw a hysteresis loop, so the network takes
*memory features* of the input:

Three feature sets are defined in :mod:`identification.features`: ``"play"``
(Prandtl-Ishlinskii play operators), ``"past-inputs"`` (the paper's nlarx regressors) and
``"bouc-wen"`` (normalized Bouc-Wen operators).

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
MLP step costs ~10 us), exports to a pure-numpy evaluator (:meth:`NLS.to_numpy`) and to casadi
(:meth:`NLS.to_casadi`, :meth:`NLS.to_casadi_step`), and builds a torch module only for training
(:meth:`NLS.to_torch`). Nothing here needs torch at run time except :func:`fit_nls`.

Inverse
-------
:meth:`NLS.solve_inverse` gives the voltage that produces a desired ``z`` given the current
memory state (for controllers that plan in ``z``), with the reachable range and a status, as an
:class:`piezo_env.inverse.InverseResult` ``(u, z, status, state)``: the same type as the plant
hysteresis' inverse. It is :func:`piezo_env.inverse.solve_increasing`: one batched network pass
over a coarse grid (reachable range, monotonicity at the nodes, bracket), then safeguarded Newton
with a finite-difference slope, typically two passes in all; exact to ~1e-7 V. When ``z`` is
not reachable on the range the range end is returned (``"out-of-range"``); when the map is
found not monotone (several roots) the root nearest a reference voltage is returned
(``"non-monotone"``) and :meth:`NLS.inverse` warns with :class:`NLSInverseWarning`.
"""

from __future__ import annotations

import itertools
import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.features import (
    FEATURE_SETS,
    BoucWenFeatures,
    FeatureMap,
    PastInputFeatures,
    PlayFeatures,
    _as_range,
    _as_scalar,
    _as_signal,
    default_bouc_wen_levels,
    default_play_radii,
    feature_map_from_dict,
)
from piezo_env.inverse import InverseResult, solve_increasing

__all__ = ["NLS", "NLSInverse", "NLSInverseWarning", "NumpyMLP", "fit_nls"]


NLS_FORMAT = "piezo-nls"
NLS_FORMAT_VERSION = 1


class NLSInverseWarning(RuntimeWarning):
    """The NLS inverse found several voltages for one target (map not monotone on the range)."""


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


# ---------------------------------------------------------------------------------------------
# the NLS


NLSInverse = InverseResult
"""Result of one NLS inversion: :class:`piezo_env.inverse.InverseResult` (u, z, status, state),
the same type the plant's hysteresis inverse returns."""


_ARRAY_NAMES = (
    "feature_mean",
    "feature_scale",
    "z_mean",
    "z_scale",
    "skip_weight",
    "skip_bias",
    "out_weight",
    "out_bias",
)


class NLS:
    """Neural static nonlinearity with memory features: voltage u (V) -> hidden z (equiv. V).

    Build it with :func:`fit_nls` or :meth:`from_dict`. Evaluation is numpy only.

    Parameters
    ----------
    feature_map : PlayFeatures, PastInputFeatures or BoucWenFeatures
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
        if not isinstance(feature_map, PlayFeatures | PastInputFeatures | BoucWenFeatures):
            raise ValueError(
                "feature_map must be PlayFeatures, PastInputFeatures or BoucWenFeatures; "
                f"got {type(feature_map)}"
            )
        self.feature_map = feature_map
        self.u_range = _as_range("u_range", u_range)
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
        u = _as_signal("u_seq", u_seq)
        return self.feature_map.features(u, self.feature_map.check_state(state))

    def evaluate(self, u_seq: ArrayLike, state: ArrayLike | None = None) -> np.ndarray:
        """NLS output ``z`` (equivalent V) of an input sequence ``u_seq`` (V) from ``state``."""
        features, _ = self.features(u_seq, state)
        return self._mlp(features)

    __call__ = evaluate

    def step(self, u_t: float, state: ArrayLike | None) -> tuple[float, np.ndarray]:
        """Advance one sample: input ``u_t`` (V) -> ``(z_t, next_state)`` (equivalent V)."""
        u = _as_scalar("u_t", u_t)
        f, new_state = self.feature_map.step(u, self.feature_map.check_state(state))
        return self._mlp.evaluate_one(f), new_state

    # -- inverse -----------------------------------------------------------------------------

    def solve_inverse(
        self,
        z_target: float,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
        u_ref: float | None = None,
        u_guess: float | None = None,
        n_grid: int = 17,
        xtol: float = 1e-7,
    ) -> NLSInverse:
        """Voltage giving ``z_target`` from the memory ``state``, with a status.

        :func:`piezo_env.inverse.solve_increasing`: one batched pass over an ``n_grid``-point
        grid of ``u_range`` (reachable range, monotonicity at the nodes, bracket), then
        safeguarded Newton steps (finite-difference slope, two points per batched pass) from
        the warm start until the estimated error is below ``xtol``. Typically two network passes.

        Parameters
        ----------
        z_target : float
            Desired hidden signal, equivalent V.
        state : array_like, optional
            Feature state before this sample; None for the rest state.
        u_range : (float, float), optional
            Voltage search range, V. Default: the training input range :attr:`u_range`.
        u_ref : float, optional
            Reference voltage, V, used to choose among several roots (the nearest wins).
            Default: the previous input for past-input and Bouc-Wen features (their state holds
            it), else the middle of the range.
        u_guess : float, optional
            Warm start, V (e.g. the previous solution). Default: ``u_ref``.
        n_grid : int, optional
            Grid points of the bracketing pass. A decrease between nodes, or an iterate outside
            its bracket's values, marks the map non-monotone (then all roots on the grid are
            found by Brent's method); a wiggle narrower than the grid spacing that no iterate
            touches goes unnoticed.
        xtol : float, optional
            Estimated voltage error (V) below which the iteration stops.

        Returns
        -------
        NLSInverse
            Voltage, achieved ``z`` (evaluated at that voltage), status (``"ok"``,
            ``"out-of-range"``, ``"non-monotone"``) and the state after applying the voltage.
        """
        target = _as_scalar("z_target", z_target)
        s = self.feature_map.check_state(state)
        low, high = self.u_range if u_range is None else _as_range("u_range", u_range)
        grid = self._grid(low, high, n_grid)
        if u_ref is None:
            if isinstance(self.feature_map, PastInputFeatures | BoucWenFeatures):
                u_ref = float(s[0])
            else:
                u_ref = 0.5 * (low + high)
        candidates, rows = self.feature_map.candidates, self._mlp.evaluate_rows

        def evaluate(u: np.ndarray) -> np.ndarray:
            return rows(candidates(u, s))

        guess = u_ref if u_guess is None else _as_scalar("u_guess", u_guess)
        sol = solve_increasing(evaluate, target, grid, guess, u_ref=u_ref, xtol=xtol)
        _, new_state = self.feature_map.step(sol.u, s)
        return InverseResult(sol.u, sol.z, sol.status, new_state)

    def inverse(
        self,
        z_target: float,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
        u_ref: float | None = None,
    ) -> float:
        """Voltage (V) that gives ``z_target`` (equivalent V) from the memory ``state``.

        A target outside the reachable set gives the closest reachable voltage (saturation).
        When the map is not monotone on the range, several voltages reach the target: the one
        nearest ``u_ref`` is returned and a :class:`NLSInverseWarning` is issued. See
        :meth:`solve_inverse` for the parameters and a status-returning variant.
        """
        result = self.solve_inverse(z_target, state, u_range=u_range, u_ref=u_ref)
        if result.status == "non-monotone":
            warnings.warn(
                f"NLS is not monotone in u on the range for z_target={z_target}: several "
                f"voltages reach it; returned the one nearest the reference ({result.u:.6g} V)",
                NLSInverseWarning,
                stacklevel=2,
            )
        return result.u

    def inverse_sequence(
        self,
        z_seq: ArrayLike,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Voltages that reproduce a hidden-signal sequence, inverting sample by sample.

        Each step inverts from the memory left by the previous voltages; among several roots
        the one nearest the previous voltage is chosen. Unreachable targets saturate silently;
        a non-monotone map gives one :class:`NLSInverseWarning` for the whole sequence.

        Parameters
        ----------
        z_seq : array_like, shape (T,)
            Desired hidden signal, equivalent V.
        state : array_like, optional
            Feature state before the first sample; None for the rest state.
        u_range : (float, float), optional
            Voltage search range, V (default: the training input range).

        Returns
        -------
        u : numpy.ndarray, shape (T,)
            Voltages, V.
        final_state : numpy.ndarray
            Feature state after the last voltage.
        """
        z = _as_signal("z_seq", z_seq)
        s = self.feature_map.check_state(state)
        u = np.empty_like(z)
        u_ref = None
        n_non_monotone = 0
        for t, target in enumerate(z):
            result = self.solve_inverse(target, s, u_range=u_range, u_ref=u_ref)
            u[t] = u_ref = result.u
            s = result.state
            n_non_monotone += result.status == "non-monotone"
        if n_non_monotone:
            warnings.warn(
                f"NLS is not monotone in u on the range at {n_non_monotone} of {z.size} "
                "samples; chose the root nearest the previous voltage there",
                NLSInverseWarning,
                stacklevel=2,
            )
        return u, s

    def _grid(self, low: float, high: float, n_grid: int) -> np.ndarray:
        """Bracketing grid of the inverse, cached for the last range used."""
        key = (low, high, n_grid)
        if self._grid_cache is None or self._grid_cache[0] != key:
            if isinstance(n_grid, bool) or int(n_grid) != n_grid or n_grid < 2:
                raise ValueError(f"n_grid must be an integer >= 2; got {n_grid!r}")
            self._grid_cache = (key, np.linspace(low, high, int(n_grid)))
        return self._grid_cache[1]

    # -- exports -----------------------------------------------------------------------------

    def to_numpy(self) -> NumpyMLP:
        """Pure-numpy evaluator ``features -> z`` (normalization folded into the weights)."""
        return self._mlp

    def to_casadi(self) -> Any:
        """casadi.Function ``nls(F) -> z`` (F: n_features x 1, V; z: equivalent V)."""
        import casadi

        f = casadi.SX.sym("F", self.n_features)
        return casadi.Function("nls", [f], [self._casadi_network(f)], ["F"], ["z"])

    def to_casadi_features(self) -> Any:
        """casadi.Function ``(u, state) -> (F, next_state)``: the feature state update.

        Play operators use the max/min form ``max(u - r, min(u + r, p))``.
        """
        import casadi

        u = casadi.SX.sym("u")
        s = casadi.SX.sym("state", self.n_state)
        f, new = self.feature_map.casadi_step(u, s)
        return casadi.Function(
            "nls_features", [u, s], [f, new], ["u", "state"], ["F", "next_state"]
        )

    def to_casadi_step(self) -> Any:
        """casadi.Function ``(u, state) -> (z, next_state)``: one NLS step for NMPC."""
        import casadi

        u = casadi.SX.sym("u")
        s = casadi.SX.sym("state", self.n_state)
        f, new = self.feature_map.casadi_step(u, s)
        return casadi.Function(
            "nls_step", [u, s], [self._casadi_network(f), new], ["u", "state"], ["z", "next_state"]
        )

    def _casadi_network(self, f: Any) -> Any:
        import casadi

        h = f
        for w, b in zip(self._mlp.weights, self._mlp.biases, strict=True):
            h = casadi.tanh(casadi.mtimes(casadi.DM(w), h) + casadi.DM(b))
        return (
            casadi.dot(casadi.DM(self._mlp.out_weight), h)
            + casadi.dot(casadi.DM(self._mlp.skip_weight), f)
            + self._mlp.out_bias
        )

    def to_torch(self) -> Any:
        """torch.nn.Module ``F (T, n_f) -> z (T,)`` in float64 with this network's weights."""
        return _TorchNLS.from_params(self._params)

    # -- serialization -----------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe configuration (format, features, widths, input range, training record)."""
        return {
            "format": NLS_FORMAT,
            "version": NLS_FORMAT_VERSION,
            "features": self.feature_map.to_dict(),
            "hidden": list(self.hidden),
            "u_range": list(self.u_range),
            "training": self.training,
        }

    def arrays(self) -> dict[str, np.ndarray]:
        """Network parameters as a dict of float64 arrays (copies), for ``np.savez``."""
        return {name: value.copy() for name, value in self._params.items()}

    @classmethod
    def from_dict(cls, config: dict[str, Any], arrays: dict[str, np.ndarray]) -> NLS:
        """Rebuild an NLS from :meth:`to_dict` and :meth:`arrays` output.

        Raises
        ------
        ValueError
            If the format or version does not match, a key is missing, or an array has the
            wrong shape for the configuration.
        """
        if not isinstance(config, dict):
            raise ValueError(f"NLS config must be a dict; got {type(config).__name__}")
        if config.get("format") != NLS_FORMAT:
            raise ValueError(
                f"NLS config format is {config.get('format')!r}; expected {NLS_FORMAT!r}"
            )
        if config.get("version") != NLS_FORMAT_VERSION:
            raise ValueError(
                f"NLS config version is {config.get('version')!r}; this code reads version "
                f"{NLS_FORMAT_VERSION}"
            )
        missing = [k for k in ("features", "hidden", "u_range") if k not in config]
        if missing:
            raise ValueError(f"NLS config is missing key(s) {missing}")
        try:
            feature_map = feature_map_from_dict(config["features"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"NLS config 'features' is incomplete: {exc!r}") from None
        nls = cls(
            feature_map,
            dict(arrays),
            u_range=config["u_range"],
            training=config.get("training") or {},
        )
        if list(nls.hidden) != list(config["hidden"]):
            raise ValueError(
                f"NLS weights have hidden widths {list(nls.hidden)} but the config says "
                f"{config['hidden']}"
            )
        return nls


def _check_params(params: dict[str, np.ndarray], n_features: int) -> dict[str, np.ndarray]:
    """Validate the raw parameter arrays and return float64 copies."""
    out: dict[str, np.ndarray] = {}
    layer_names = sorted(
        (k for k in params if k.startswith("layer") and k.endswith("_weight")),
        key=lambda k: int(k[len("layer") : -len("_weight")]),
    )
    if not layer_names:
        raise ValueError("NLS weights have no hidden layer (expected 'layer0_weight', ...)")
    expected = [*(_ARRAY_NAMES)]
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


# ---------------------------------------------------------------------------------------------
# torch network and training


def _torch() -> Any:
    import torch

    return torch


class _TorchNLS:
    """Builders of the torch module (lazy: importing this module does not import torch)."""

    @staticmethod
    def build(n_features: int, hidden: Sequence[int]) -> Any:
        torch = _torch()
        nn = torch.nn

        class TorchNLS(nn.Module):
            """``z = z_m + z_s (w^T x + c + MLP(x))``, ``x = (F - m) / s``; float64."""

            def __init__(self) -> None:
                super().__init__()
                widths = [n_features, *hidden]
                self.layers = nn.ModuleList(
                    nn.Linear(a, b, dtype=torch.float64) for a, b in itertools.pairwise(widths)
                )
                self.out = nn.Linear(widths[-1], 1, dtype=torch.float64)
                self.skip = nn.Linear(n_features, 1, dtype=torch.float64)
                self.register_buffer("feature_mean", torch.zeros(n_features, dtype=torch.float64))
                self.register_buffer("feature_scale", torch.ones(n_features, dtype=torch.float64))
                self.register_buffer("z_mean", torch.zeros((), dtype=torch.float64))
                self.register_buffer("z_scale", torch.ones((), dtype=torch.float64))

            def normalized(self, x: Any) -> Any:
                h = x
                for layer in self.layers:
                    h = torch.tanh(layer(h))
                return (self.out(h) + self.skip(x)).squeeze(-1)

            def forward(self, features: Any) -> Any:
                x = (features - self.feature_mean) / self.feature_scale
                return self.z_mean + self.z_scale * self.normalized(x)

        return TorchNLS()

    @staticmethod
    def from_params(params: dict[str, np.ndarray]) -> Any:
        torch = _torch()
        n_layers = sum(1 for k in params if k.startswith("layer") and k.endswith("_weight"))
        hidden = [params[f"layer{i}_weight"].shape[0] for i in range(n_layers)]
        module = _TorchNLS.build(params["feature_mean"].size, hidden)
        state = {
            "feature_mean": params["feature_mean"],
            "feature_scale": params["feature_scale"],
            "z_mean": params["z_mean"],
            "z_scale": params["z_scale"],
            "out.weight": params["out_weight"][None, :],
            "out.bias": params["out_bias"].reshape(1),
            "skip.weight": params["skip_weight"][None, :],
            "skip.bias": params["skip_bias"].reshape(1),
        }
        for i in range(n_layers):
            state[f"layers.{i}.weight"] = params[f"layer{i}_weight"]
            state[f"layers.{i}.bias"] = params[f"layer{i}_bias"]
        module.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()})
        return module

    @staticmethod
    def to_params(module: Any) -> dict[str, np.ndarray]:
        sd = {k: v.detach().numpy().astype(np.float64) for k, v in module.state_dict().items()}
        params = {
            "feature_mean": sd["feature_mean"],
            "feature_scale": sd["feature_scale"],
            "z_mean": sd["z_mean"].reshape(()),
            "z_scale": sd["z_scale"].reshape(()),
            "out_weight": sd["out.weight"].reshape(-1),
            "out_bias": sd["out.bias"].reshape(()),
            "skip_weight": sd["skip.weight"].reshape(-1),
            "skip_bias": sd["skip.bias"].reshape(()),
        }
        for i in range(len(module.layers)):
            params[f"layer{i}_weight"] = sd[f"layers.{i}.weight"]
            params[f"layer{i}_bias"] = sd[f"layers.{i}.bias"]
        return params


def _positive_int(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def _ridge_skip(x: np.ndarray, t: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted ridge fit ``t ~ x @ coef[:-1] + coef[-1]``; column 0 (u) and the offset free."""
    n, n_f = x.shape
    design = np.column_stack([x, np.ones(n)])
    gram = design.T @ (design * w[:, None])
    rhs = design.T @ (w * t)
    penalty = np.full(n_f + 1, ridge * float(w.sum()))
    penalty[0] = penalty[-1] = 0.0
    return np.linalg.lstsq(gram + np.diag(penalty), rhs, rcond=None)[0]


def fit_nls(
    u: ArrayLike,
    z: ArrayLike,
    *,
    features: str = "play",
    n_play: int = 10,
    radii: ArrayLike | None = None,
    n_past: int = 5,
    n_bouc_wen: int = 8,
    levels: ArrayLike | None = None,
    hidden: Sequence[int] = (32, 32, 32),
    u_range: Sequence[float] | None = None,
    initial_input: float = 0.0,
    seed: int = 0,
    max_epochs: int = 200,
    batch_size: int = 1024,
    learning_rate: float = 1e-2,
    weight_decay: float = 0.0,
    validation_fraction: float = 0.2,
    patience: int = 25,
    lbfgs_iterations: int = 0,
    skip_ridge: float | None = None,
    z_weights: ArrayLike | None = None,
    num_threads: int = 1,
) -> NLS:
    """Fit the NLS network to input/hidden-signal data ``(u_t, z_t)`` (paper section 3.4 e).

    Training minimizes the (weighted) mean squared error of ``z`` on a contiguous training block;
    the last ``validation_fraction`` of the record (a contiguous block, never shuffled across
    time) is held out for early stopping, and the best-validating weights are kept. Adam on
    mini-batches (samples shuffled inside the training block: the features carry the memory), then
    optionally full-batch L-BFGS, kept only if it improves the validation loss. The affine skip
    term starts at the weighted least-squares fit and the MLP output at zero (see the module
    docstring), so a map affine in the features is learnt exactly.

    Deterministic: float64, a seeded ``torch.Generator`` for initialization and batches, and
    ``num_threads`` torch threads during training (the previous setting is restored).

    Parameters
    ----------
    u : array_like, shape (T,)
        Input voltage, V, starting from the rest state (memory at ``initial_input``).
    z : array_like, shape (T,)
        Hidden signal, equivalent V (e.g. estimated by the inverse ARX model).
    features : {"play", "past-inputs", "bouc-wen"}
        Memory feature set.
    n_play : int
        Number of play operators (``features="play"``), radii by :func:`default_play_radii`.
    radii : array_like, optional
        Explicit play radii, V (overrides ``n_play``).
    n_past : int
        Number of past inputs (``features="past-inputs"``).
    n_bouc_wen : int
        Number of Bouc-Wen operators (``features="bouc-wen"``), levels by
        :func:`default_bouc_wen_levels`.
    levels : array_like, optional
        Explicit Bouc-Wen saturation levels, V (overrides ``n_bouc_wen``).
    hidden : sequence of int
        Hidden-layer widths (three tanh layers in the paper).
    u_range : (float, float), optional
        Input range, V, for the play radii and as the inverse's default search range.
        Default: ``(min(u), max(u))``.
    initial_input : float
        Rest input, V: the memory state before ``u[0]``.
    seed : int
        Seed of the torch generator (initialization and batch order).
    max_epochs : int
        Maximum number of Adam epochs.
    batch_size : int
        Adam mini-batch size, samples.
    learning_rate : float
        Adam learning rate.
    weight_decay : float
        L2 penalty on the MLP weights (not on the affine skip), added to the loss.
    validation_fraction : float
        Fraction of samples held out at the end, in [0, 0.9]; 0 trains ``max_epochs`` epochs
        without early stopping.
    patience : int
        Epochs without validation improvement before stopping.
    lbfgs_iterations : int
        Full-batch L-BFGS iterations after Adam (0: none).
    skip_ridge : float, optional
        Ridge penalty (relative, on normalized features) of the memory features' weights in the
        initial affine skip; the weight of ``u`` itself is not penalized, so the identity stays
        exact. It keeps nearly collinear features (past inputs of a slow signal) from getting
        large cancelling weights that extrapolate wildly on faster inputs. Default: 1e-3 for
        play features (rate-independent, safe to extrapolate in rate), 1.0 for past inputs
        (their spread grows with the input's rate, so they get a strong prior towards ``u``).
    z_weights : array_like, shape (T,), optional
        Non-negative per-sample loss weights (e.g. inverse squared uncertainty of ``z``).
    num_threads : int
        Torch threads used during training.

    Returns
    -------
    NLS
        The fitted nonlinearity; ``nls.training`` records epochs, losses and wall time.
    """
    torch = _torch()
    start = time.perf_counter()
    u_arr = _as_signal("u", u)
    z_arr = _as_signal("z", z)
    if u_arr.shape != z_arr.shape:
        raise ValueError(f"u and z must have the same length; got {u_arr.size} and {z_arr.size}")
    if features not in FEATURE_SETS:
        raise ValueError(f"features must be one of {FEATURE_SETS}; got {features!r}")
    hidden_t = tuple(_positive_int("hidden width", h) for h in hidden)
    if not hidden_t:
        raise ValueError("hidden must list at least one layer width")
    max_epochs = _positive_int("max_epochs", max_epochs, 0)
    batch_size = _positive_int("batch_size", batch_size)
    patience = _positive_int("patience", patience)
    lbfgs_iterations = _positive_int("lbfgs_iterations", lbfgs_iterations, 0)
    num_threads = _positive_int("num_threads", num_threads)
    learning_rate = _as_scalar("learning_rate", learning_rate)
    weight_decay = _as_scalar("weight_decay", weight_decay)
    if skip_ridge is None:
        skip_ridge = 1.0 if features == "past-inputs" else 1e-3
    skip_ridge = _as_scalar("skip_ridge", skip_ridge)
    if skip_ridge < 0.0:
        raise ValueError(f"skip_ridge must be >= 0; got {skip_ridge}")
    if learning_rate <= 0.0 or weight_decay < 0.0:
        raise ValueError("learning_rate must be > 0 and weight_decay >= 0")
    validation_fraction = _as_scalar("validation_fraction", validation_fraction)
    if not 0.0 <= validation_fraction <= 0.9:
        raise ValueError(f"validation_fraction must be in [0, 0.9]; got {validation_fraction}")
    n = u_arr.size
    n_val = round(validation_fraction * n)
    n_train = n - n_val
    if n_train < 8 or (validation_fraction > 0.0 and n_val < 2):
        raise ValueError(
            f"too few samples ({n}) for a training block and a validation block "
            f"(validation_fraction={validation_fraction})"
        )
    if z_weights is None:
        weights = np.ones(n)
    else:
        weights = _as_signal("z_weights", z_weights)
        if weights.shape != u_arr.shape or np.any(weights < 0.0):
            raise ValueError("z_weights must be non-negative with the same length as u")
        if weights[:n_train].sum() <= 0.0:
            raise ValueError("z_weights are all zero on the training block")
        weights = weights / weights[:n_train].mean()
    if u_range is None:
        if np.ptp(u_arr) == 0.0:
            raise ValueError("u is constant; give u_range or an input that varies")
        u_range = (float(u_arr.min()), float(u_arr.max()))
    u_range = _as_range("u_range", u_range)
    feature_map: FeatureMap
    if features == "play":
        r = default_play_radii(u_range, n_play) if radii is None else np.asarray(radii, float)
        feature_map = PlayFeatures(radii=tuple(np.sort(r)), initial_input=initial_input)
    elif features == "bouc-wen":
        lv = default_bouc_wen_levels(u_range, n_bouc_wen) if levels is None else levels
        feature_map = BoucWenFeatures(
            levels=tuple(np.sort(np.asarray(lv, float))), initial_input=initial_input
        )
    else:
        feature_map = PastInputFeatures(n_past=n_past, initial_input=initial_input)

    feats, _ = feature_map.features(u_arr, feature_map.initial_state())
    f_train, z_train, w_train = feats[:n_train], z_arr[:n_train], weights[:n_train]
    feature_mean = f_train.mean(axis=0)
    feature_scale = f_train.std(axis=0)
    feature_scale[feature_scale < 1e-12] = 1.0
    z_mean = float(z_train.mean())
    z_scale = float(z_train.std()) or 1.0
    x_all = (feats - feature_mean) / feature_scale
    t_all = (z_arr - z_mean) / z_scale

    coef = _ridge_skip(x_all[:n_train], t_all[:n_train], w_train, skip_ridge)

    previous_threads = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        generator = torch.Generator().manual_seed(int(seed))
        net = _TorchNLS.build(feature_map.n_features, hidden_t)
        with torch.no_grad():
            for layer in net.layers:
                bound = math.sqrt(6.0 / (layer.in_features + layer.out_features))
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.zero_()
            net.out.weight.zero_()
            net.out.bias.zero_()
            net.skip.weight.copy_(torch.from_numpy(coef[:-1][None, :]))
            net.skip.bias.fill_(float(coef[-1]))
            net.feature_mean.copy_(torch.from_numpy(feature_mean))
            net.feature_scale.copy_(torch.from_numpy(feature_scale))
            net.z_mean.fill_(z_mean)
            net.z_scale.fill_(z_scale)
        x = torch.from_numpy(x_all)
        t = torch.from_numpy(t_all)
        w = torch.from_numpy(weights)
        x_tr, t_tr, w_tr = x[:n_train], t[:n_train], w[:n_train]
        x_va, t_va, w_va = x[n_train:], t[n_train:], w[n_train:]
        mlp_params = [p for m in (*net.layers, net.out) for p in m.parameters()]

        def data_loss(xb: Any, tb: Any, wb: Any) -> Any:
            return torch.mean(wb * (net.normalized(xb) - tb) ** 2)

        def penalty() -> Any:
            return weight_decay * sum(torch.sum(p**2) for p in mlp_params)

        def validation_loss() -> float:
            with torch.no_grad():
                if n_val == 0:
                    return float(data_loss(x_tr, t_tr, w_tr))
                return float(data_loss(x_va, t_va, w_va))

        optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
        best_loss = validation_loss()
        initial_loss = best_loss
        best_state = {k: v.clone() for k, v in net.state_dict().items()}
        best_epoch = 0
        epochs_run = 0
        for epoch in range(1, max_epochs + 1):
            epochs_run = epoch
            order = torch.randperm(n_train, generator=generator)
            for i in range(0, n_train, batch_size):
                idx = order[i : i + batch_size]
                optimizer.zero_grad()
                loss = data_loss(x_tr[idx], t_tr[idx], w_tr[idx])
                if weight_decay:
                    loss = loss + penalty()
                loss.backward()
                optimizer.step()
            current = validation_loss()
            if current < best_loss:
                best_loss, best_epoch = current, epoch
                best_state = {k: v.clone() for k, v in net.state_dict().items()}
            elif n_val > 0 and epoch - best_epoch >= patience:
                break
        net.load_state_dict(best_state)
        lbfgs_improved = False
        if lbfgs_iterations:
            lbfgs = torch.optim.LBFGS(
                net.parameters(),
                max_iter=lbfgs_iterations,
                history_size=20,
                line_search_fn="strong_wolfe",
            )

            def closure() -> Any:
                lbfgs.zero_grad()
                loss = data_loss(x_tr, t_tr, w_tr)
                if weight_decay:
                    loss = loss + penalty()
                loss.backward()
                return loss

            lbfgs.step(closure)
            current = validation_loss()
            if math.isfinite(current) and current < best_loss:
                best_loss, lbfgs_improved = current, True
            else:
                net.load_state_dict(best_state)
        params = _TorchNLS.to_params(net)
        with torch.no_grad():
            train_loss = float(data_loss(x_tr, t_tr, w_tr))
    finally:
        torch.set_num_threads(previous_threads)

    training = {
        "seed": int(seed),
        "n_train": int(n_train),
        "n_validation": int(n_val),
        "epochs": int(epochs_run),
        "best_epoch": int(best_epoch),
        "lbfgs_improved": lbfgs_improved,
        "affine_validation_mse": initial_loss * z_scale**2,
        "validation_mse": best_loss * z_scale**2,
        "train_mse": train_loss * z_scale**2,
        "wall_time_s": time.perf_counter() - start,
        "mse_unit": "equivalent V^2",
    }
    return NLS(feature_map, params, u_range=u_range, training=training)
