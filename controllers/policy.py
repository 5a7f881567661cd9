"""A trained RL policy as a controller, evaluated in numpy from plain files (no torch at run time).

A policy folder holds two files:

- ``policy.json``: format and version, the network architecture (layer sizes, activation),
  the observation the policy was trained on (:class:`piezo_env.wrappers.ObservationConfig`),
  the action scaling (action in [-1, 1] times U_r volts), the training configuration and the
  library versions, and the SHA-256 of the weights file;
- ``weights.npz``: the actor network's arrays only, ``layer{i}.weight`` (out x in) and
  ``layer{i}.bias``, float32 or float64. Read with ``allow_pickle=False``: nothing is unpickled.

The controller's action is the deterministic one, the mean of the policy's Gaussian, clipped
to [-1, 1], as ``stable_baselines3`` ``predict(obs, deterministic=True)`` gives it. It
normalises the raw observation with the same functions as the training wrappers
(:mod:`piezo_env.wrappers`), keeping the past voltages and errors itself.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controllers.base import Controller
from controllers.settings import number_at_least
from controllers.task import ControlTask
from piezo_env.wrappers import ObservationConfig

__all__ = [
    "FORMAT",
    "LoadedPolicy",
    "PolicyController",
    "PolicyNetwork",
    "load_policy",
    "make_policy_controller",
    "save_policy",
]

FORMAT = "piezo-testbed/policy"
FORMAT_VERSION = 1
POLICY_FILE = "policy.json"
WEIGHTS_FILE = "weights.npz"
_ACTIVATIONS = {"tanh": np.tanh, "relu": lambda x: np.maximum(x, 0.0)}
_FLOAT64 = np.dtype(np.float64)


@dataclass(frozen=True)
class PolicyNetwork:
    """The actor MLP: hidden layers with one activation, then a linear output (the mean action).

    Attributes
    ----------
    weights : tuple of ndarray
        Layer weights, each (out, in), float64.
    biases : tuple of ndarray
        Layer biases, each (out,), float64.
    activation : str
        ``"tanh"`` or ``"relu"``, applied after every layer but the last.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    activation: str

    def mean(self, x: np.ndarray) -> np.ndarray:
        """Mean action(s) in policy units for observations ``x``, shape (n, in) or (in,)."""
        h = np.asarray(x, dtype=np.float64)
        act = _ACTIVATIONS[self.activation]
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = h @ w.T + b
            if i < last:
                h = act(h)
        return h

    @property
    def layer_sizes(self) -> list[int]:
        """[in, hidden..., out]."""
        return [int(self.weights[0].shape[1])] + [int(w.shape[0]) for w in self.weights]


class _OneObservation:
    """:meth:`PolicyNetwork.mean` of one observation, the first output as a float.

    Every layer writes into a buffer made once, and the bias is added at the buffer's own
    shape (adding a (out,) bias to a (1, out) row broadcasts, which costs several times the
    addition itself). The products keep the call form of :meth:`PolicyNetwork.mean`,
    ``h @ w.T`` on a (1, in) row, so BLAS runs the same kernel; the elementwise additions and
    activations give the same bits in place as into new arrays, and the output bias is added
    in Python floats (IEEE double, as numpy's float64): the result equals
    ``float(network.mean(x)[0, 0])`` to the bit.

    Parameters
    ----------
    network : PolicyNetwork
    """

    def __init__(self, network: PolicyNetwork) -> None:
        *hidden, (w_out, b_out) = zip(network.weights, network.biases, strict=True)
        self._input = np.empty((1, network.layer_sizes[0]))
        self._hidden = tuple(
            (w.T, np.ascontiguousarray(b).reshape(1, -1), np.empty((1, w.shape[0])))
            for w, b in hidden
        )
        self._relu = network.activation == "relu"
        self._w_out = w_out.T
        self._out = np.empty((1, w_out.shape[0]))
        self._b_out = float(b_out[0])

    def __call__(self, x: np.ndarray) -> float:
        """The first mean action (policy units) of the (1, in) observation ``x``."""
        h = self._input
        h[...] = x  # as np.asarray(x, dtype=np.float64)
        matmul, add, relu = np.matmul, np.add, self._relu
        # The third argument of a ufunc is its output (positional: a little cheaper).
        for w_t, b, out in self._hidden:
            matmul(h, w_t, out)
            add(out, b, out)
            if relu:
                np.maximum(out, 0.0, out=out)  # positionally, a third operand is deprecated
            else:
                np.tanh(out, out)
            h = out
        matmul(h, self._w_out, self._out)
        return self._out.item(0) + self._b_out


@dataclass(frozen=True)
class LoadedPolicy:
    """A policy folder read and checked.

    Attributes
    ----------
    network : PolicyNetwork
    observation : ObservationConfig
    metadata : dict
        The whole ``policy.json``.
    folder : pathlib.Path
    """

    network: PolicyNetwork
    observation: ObservationConfig
    metadata: dict[str, Any]
    folder: Path


def save_policy(
    folder: str | Path,
    *,
    layers: list[tuple[np.ndarray, np.ndarray]],
    activation: str,
    observation: ObservationConfig,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``policy.json`` and ``weights.npz`` into ``folder`` (created if needed).

    Parameters
    ----------
    folder : str or Path
    layers : list of (weight (out, in), bias (out,))
        The actor network, input layer first; the last layer's output is the mean action.
    activation : str
        Hidden activation, ``"tanh"`` or ``"relu"``.
    observation : ObservationConfig
        The observation the policy takes.
    extra : dict, optional
        JSON-safe sections added as they are (``training``, ``versions``, ``task`` ...).

    Returns
    -------
    pathlib.Path
        The folder.
    """
    if activation not in _ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {}
    for i, (w, b) in enumerate(layers):
        arrays[f"layer{i}.weight"] = np.asarray(w, dtype=np.float32)
        arrays[f"layer{i}.bias"] = np.asarray(b, dtype=np.float32)
    weights_path = folder / WEIGHTS_FILE
    np.savez(weights_path, **arrays)
    sizes = [int(layers[0][0].shape[1])] + [int(w.shape[0]) for w, _ in layers]
    document = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "architecture": {
            "type": "mlp",
            "layer_sizes": sizes,
            "activation": activation,
            "output": "mean of a diagonal Gaussian; the deterministic action, clipped to [-1, 1]",
        },
        "observation": {
            "wrapper": "piezo_env.wrappers.TrackingObservation",
            "version": observation.version,
            **observation.to_dict(),
        },
        "action": {"low": -1.0, "high": 1.0, "volts_per_unit": observation.u_max},
        "weights": {
            "file": WEIGHTS_FILE,
            "sha256": _sha256(weights_path),
            "arrays": sorted(arrays),
        },
        **(extra or {}),
    }
    (folder / POLICY_FILE).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    return folder


def load_policy(folder: str | Path) -> LoadedPolicy:
    """Read and check a policy folder.

    Raises
    ------
    ValueError
        Naming the file and the field when a file is missing, unreadable, corrupted (the
        weights' SHA-256 differs from the one recorded in policy.json) or inconsistent with the
        architecture. The hash sits in the same folder as the weights, so it detects damage,
        not deliberate tampering: load policies from sources you trust (the files are plain
        JSON and arrays, never unpickled, so a bad file cannot run code).
    """
    folder = Path(folder)
    json_path = folder / POLICY_FILE
    if not json_path.is_file():
        raise ValueError(
            f"{json_path}: missing; a policy folder holds {POLICY_FILE} and "
            f"{WEIGHTS_FILE}, as `piezo train-rl --out FOLDER` writes them"
        )
    try:
        document = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{json_path}: not readable JSON ({error})") from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise ValueError(f"{json_path}: field 'format' must be {FORMAT!r}")
    if document.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{json_path}: field 'format_version' must be {FORMAT_VERSION}, got "
            f"{document.get('format_version')!r}"
        )
    observation = _observation_config(document, json_path)
    network = _network(document, json_path, folder)
    if network.layer_sizes[0] != observation.size or network.layer_sizes[-1] != 1:
        raise ValueError(
            f"{json_path}: field 'architecture.layer_sizes' {network.layer_sizes} does not take "
            f"the observation's {observation.size} entries to one action"
        )
    return LoadedPolicy(network, observation, document, folder)


def _field(document: dict[str, Any], path: str, json_path: Path) -> Any:
    value: Any = document
    for key in path.split("."):
        if not isinstance(value, dict) or key not in value:
            raise ValueError(f"{json_path}: field {path!r} is missing")
        value = value[key]
    return value


def _observation_config(document: dict[str, Any], json_path: Path) -> ObservationConfig:
    """The observation of a policy file; a file without ``observation.version`` is version 1.

    Version 1 (the first policies) has no past deflections; version 2 has
    ``observation.n_deflections`` > 0 (:mod:`piezo_env.wrappers`).
    """
    names = ("stroke_um", "u_max", "bound_um", "preview", "n_inputs", "n_errors")
    values = {name: _field(document, f"observation.{name}", json_path) for name in names}
    version = _field(document, "observation", json_path).get("version", 1)
    if version == 2:
        values["n_deflections"] = _field(document, "observation.n_deflections", json_path)
        if not (isinstance(values["n_deflections"], int) and values["n_deflections"] > 0):
            raise ValueError(
                f"{json_path}: field 'observation.n_deflections' must be a positive integer in "
                f"observation version 2, got {values['n_deflections']!r}"
            )
    elif version == 1:
        if _field(document, "observation", json_path).get("n_deflections", 0) != 0:
            raise ValueError(
                f"{json_path}: field 'observation.n_deflections' needs 'observation.version' 2 "
                "(version 1 has no past deflections)"
            )
    else:
        raise ValueError(
            f"{json_path}: field 'observation.version' must be 1 or 2, got {version!r}"
        )
    try:
        config = ObservationConfig(**values)
    except ValueError as error:
        raise ValueError(f"{json_path}: field 'observation': {error}") from None
    return config


def _network(document: dict[str, Any], json_path: Path, folder: Path) -> PolicyNetwork:
    activation = _field(document, "architecture.activation", json_path)
    if activation not in _ACTIVATIONS:
        raise ValueError(
            f"{json_path}: field 'architecture.activation' must be one of "
            f"{sorted(_ACTIVATIONS)}, got {activation!r}"
        )
    sizes = _field(document, "architecture.layer_sizes", json_path)
    if not (
        isinstance(sizes, list)
        and len(sizes) >= 2
        and all(isinstance(s, int) and s > 0 for s in sizes)
    ):
        raise ValueError(
            f"{json_path}: field 'architecture.layer_sizes' must be a list of "
            f"positive integers, got {sizes!r}"
        )
    name = _field(document, "weights.file", json_path)
    expected = _field(document, "weights.sha256", json_path)
    weights_path = folder / str(name)
    if Path(str(name)).name != name or not weights_path.is_file():
        raise ValueError(f"{weights_path}: missing (field 'weights.file' of {json_path})")
    if _sha256(weights_path) != expected:
        raise ValueError(
            f"{weights_path}: SHA-256 differs from field 'weights.sha256' of "
            f"{json_path}: the file is corrupted or was replaced"
        )
    arrays = _read_arrays(weights_path)
    weights, biases = [], []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        w = arrays.get(f"layer{i}.weight")
        b = arrays.get(f"layer{i}.bias")
        if w is None or b is None or w.shape != (n_out, n_in) or b.shape != (n_out,):
            raise ValueError(
                f"{weights_path}: arrays 'layer{i}.weight' ({n_out}, {n_in}) and "
                f"'layer{i}.bias' ({n_out},) expected by field "
                f"'architecture.layer_sizes' of {json_path}"
            )
        weights.append(w.astype(np.float64))
        biases.append(b.astype(np.float64))
    if len(arrays) != 2 * (len(sizes) - 1):
        raise ValueError(
            f"{weights_path}: holds arrays {sorted(arrays)} beyond the layers of "
            f"field 'architecture.layer_sizes' of {json_path}"
        )
    return PolicyNetwork(tuple(weights), tuple(biases), activation)


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError) as error:
        raise ValueError(f"{path}: not a readable npz archive of arrays ({error})") from None
    for key, value in arrays.items():
        if value.dtype not in (np.float32, np.float64) or not np.isfinite(value).all():
            raise ValueError(
                f"{path}: array {key!r} must be finite float32/float64, got {value.dtype}"
            )
    return arrays


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class PolicyController(Controller):
    """A trained policy (a folder of :func:`save_policy`) as a controller.

    Parameters
    ----------
    model : str or Path
        The policy folder (``policy.json`` + ``weights.npz``).
    task : ControlTask
        The task it runs on; its drive range and stroke must be the policy's, its preview at
        least the policy's (a longer preview is cut to the one the policy was trained on).
    settings : PolicyController.Settings, optional
    name : str
        Name in reports.

    Raises
    ------
    ValueError
        For a missing, corrupted or mismatched policy (naming the file and the field).
    """

    @dataclass(frozen=True)
    class Settings:
        """Settings of the policy controller.

        Attributes
        ----------
        initial_voltage : float
            Voltage (V) the bender rests under at reset, the start of the voltage history
            (the env's ``initial_voltage`` reset option; 0 V by default).
        """

        initial_voltage: float = 0.0

    name = "policy"

    def __init__(
        self,
        model: str | Path,
        task: ControlTask,
        settings: PolicyController.Settings | None = None,
        *,
        name: str = "policy",
    ) -> None:
        super().__init__(task)
        self.settings = settings or self.Settings()
        voltage = self.settings.initial_voltage
        if not (number_at_least(voltage, -math.inf) and abs(voltage) <= task.u_max):
            raise ValueError(
                f"initial_voltage must be a number within +-{task.u_max} V, got {voltage!r}"
            )
        self.policy = load_policy(model)
        self.name = name
        self._check_task(task)
        config = self.policy.observation
        self._stroke, self._u_scale = np.float64(config.stroke_um), np.float64(config.u_max)
        self._x = np.zeros((1, config.size), dtype=np.float32)  # the normalised observation
        self._inputs = slice(config.raw_size, config._errors_start)
        self._errors = slice(config._errors_start, config._deflections_start)
        self._deflections = slice(config._deflections_start, config.size)
        self._past = np.zeros(config.n_deflections)  # past measured deflections (um)
        self._last_error = self._last_measured = 0.0
        self._last_voltage: float | None = None
        self._set_up_step(config)

    _STEP_ATTRIBUTES = (
        "_row",
        "_raw_size",
        "_head",
        "_head_scratch",
        "_history",
        "_input_at",
        "_error_at",
        "_past_x",
        "_past_scratch",
        "_s",
        "_u",
        "_float32",
        "_mean",
    )
    """What :meth:`_set_up_step` makes (left out of a pickle or a deep copy, made again)."""

    def _set_up_step(self, config: ObservationConfig) -> None:
        """Views, scratch buffers and Python-float scales of :meth:`_act`, made once.

        ``_row``, ``_head`` and ``_past_x`` are views into ``_x``: a pickle or a deep copy
        would copy them apart from the copied ``_x``, so :meth:`__getstate__` leaves them out
        and :meth:`__setstate__` makes them again."""
        x = self._row = self._x[0]
        self._raw_size = config.raw_size
        self._head = x[: config.raw_size]  # y_t / s, (r_t+k - y_t) / s
        self._head_scratch = np.empty(config.raw_size)
        # The input and error histories are adjacent: one shift moves both, and each
        # segment's first entry is then written afresh.
        start, stop = self._inputs.start, self._errors.stop
        self._history = (slice(start + 1, stop), slice(start, stop - 1)) if stop > start else None
        self._input_at = self._inputs.start if config.n_inputs else None
        self._error_at = self._errors.start if config.n_errors else None
        self._past_x = x[self._deflections] if config.n_deflections else None
        self._past_scratch = np.empty(config.n_deflections)
        self._s, self._u = float(config.stroke_um), float(config.u_max)
        self._float32 = np.empty(1, dtype=np.float32)  # rounds a float to float32
        self._mean = _OneObservation(self.policy.network)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        for name in self._STEP_ATTRIBUTES:
            del state[name]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._set_up_step(self.policy.observation)

    def _check_task(self, task: ControlTask) -> None:
        config, where = self.policy.observation, self.policy.folder / POLICY_FILE
        if config.preview > task.preview:
            raise ValueError(
                f"{where}: field 'observation.preview' = {config.preview} but the env shows only "
                f"{task.preview} samples ahead; make the env with preview >= {config.preview}"
            )
        trained_dt = self.policy.metadata.get("task", {}).get("dt_s")
        for field, mine, theirs in (
            ("observation.stroke_um", config.stroke_um, task.stroke_um),
            ("observation.u_max", config.u_max, task.u_max),
            ("task.dt_s", trained_dt, task.dt),
        ):
            if mine is not None and not np.isclose(mine, theirs, rtol=1e-9, atol=0.0):
                raise ValueError(
                    f"{where}: field '{field}' = {mine} (what the policy was trained on) but "
                    f"the env has {theirs}; make the env to match"
                )

    def _reset(self, observation: np.ndarray) -> None:
        config = self.policy.observation
        raw = np.asarray(observation[: config.raw_size], dtype=np.float64)
        error = raw[1] - raw[0]
        x = self._x[0]
        x[self._inputs] = np.float64(self.settings.initial_voltage) / self._u_scale
        x[self._errors] = error / self._stroke
        self._past[:] = raw[0]
        self._last_error, self._last_measured = error, raw[0]
        self._last_voltage = None

    def _act(self, observation: np.ndarray) -> float:
        """The policy's mean action for the normalised observation
        (:func:`piezo_env.wrappers.normalize_observation`), as a voltage.

        The normalised observation is kept in one buffer whose history segments shift by
        one entry per step: each entry is the same float64 quotient rounded to float32 as
        :class:`piezo_env.wrappers.ObservationHistory` computes it afresh every step, so the
        two agree to the bit (a test holds them to it) at a third of the numpy calls. The
        scalar arithmetic runs on Python floats (IEEE double, as numpy's float64), the
        vector arithmetic into buffers made once, and a float32 rounding is a store into a
        one-entry float32 array: the same bits as the plain numpy expressions."""
        if type(observation) is not np.ndarray or observation.dtype is not _FLOAT64:
            observation = np.asarray(observation, dtype=np.float64)
        y, s = observation.item(0), self._s
        past = self._past
        if self._last_voltage is not None:  # the history advances by one step
            if self._history is not None:
                x = self._row
                later, earlier = self._history
                x[later] = x[earlier]
                if self._input_at is not None:
                    x[self._input_at] = self._last_voltage / self._u
                if self._error_at is not None:
                    x[self._error_at] = self._last_error / s
            if self._past_x is not None:
                past[1:] = past[:-1]
                past[0] = self._last_measured
        head = self._head_scratch  # the third argument of a ufunc is its output
        np.subtract(observation[: self._raw_size], y, head)
        head[0] = y
        np.divide(head, s, self._head)  # y / s, then (r - y) / s: float64, stored float32
        if self._past_x is not None:
            np.subtract(past, y, self._past_scratch)
            np.divide(self._past_scratch, s, self._past_x)
        self._last_error, self._last_measured = observation.item(1) - y, y
        # float32 first, as SB3 hands the action to the env wrapper in training; then
        # piezo_env.wrappers.action_to_voltage's arithmetic on one number
        rounding = self._float32
        rounding[0] = self._mean(self._x)
        mean = rounding.item(0)
        if not math.isfinite(mean):
            raise ValueError(f"{self.name}: the policy's action is not finite ({mean})")
        rounding[0] = min(max(mean, -1.0), 1.0) * self._u
        voltage = rounding.item(0)
        self._last_voltage = voltage
        return voltage

    def describe(self) -> dict[str, Any]:
        """Policy folder, observation, architecture and training summary."""
        meta = self.policy.metadata
        return {
            "name": self.name,
            "policy": str(self.policy.folder),
            "observation": self.policy.observation.to_dict(),
            "architecture": meta.get("architecture", {}),
            "training": meta.get("training", {}),
        }


def make_policy_controller(path: str | Path, env: Any, **options: Any) -> PolicyController:
    """A :class:`PolicyController` for the policy folder ``path`` on ``env``.

    The same as ``controllers.make("policy", path, env, **options)``.

    Parameters
    ----------
    path : str or Path
        The policy folder.
    env : gymnasium.Env
        A ``PiezoBender-v0`` env (its preview at least the policy's).
    **options
        Fields of :class:`PolicyController.Settings`; unknown ones raise ValueError.
    """
    from controllers.registry import make

    return make("policy", path, env, **options)
