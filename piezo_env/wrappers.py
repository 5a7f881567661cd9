"""The observation a learning agent needs: scaled by the stroke, relative to the deflection.

The raw observation of ``PiezoBender-v0`` is ``[y_t + nu_t, r_t, r_t+1 .. r_t+P]`` in
micrometres inside a proven Box of +-``bound`` (about 42 times the stroke for the PL140): fine
for a controller, poor input for a neural network, whose inputs should be of order one. The
wrappers here (:class:`TrackingObservation` for one env, :class:`TrackingObservationVector`
for the native vector env, identical output sub-env by sub-env) present instead, all float32:

- index 0: y_t / s, the measured deflection in one-sided strokes s;
- index 1 + k, k = 0 .. P: (r_t+k - y_t) / s, the reference relative to the measured
  deflection (k = 1 is the error the action a_t is scored against);
- index 2 + P + j, j < n_inputs: u_t-1-j / U_r, the voltages applied before, newest first;
- index 2 + P + n_inputs + j, j < n_errors: (r_t-1-j - y_t-1-j) / s, the measured errors
  before, newest first;
- index 2 + P + n_inputs + n_errors + j, j < n_deflections: (y_t-1-j - y_t) / s, the measured
  deflections before, relative to the current one, newest first (observation version 2 only);

and take the action in [-1, 1] (volts = action U_r; values outside are clipped, as the
amplifier would). At reset the voltage history holds the reset's voltage (``info["voltage_V"]``)
and the error history the first error r_0 - y_0, the deflection history y_0, as if the bender
had rested so for ever.

**Versions.** Version 1 (``n_deflections = 0``) is the observation of the first policies;
version 2 adds the past measured deflections, so that with the past voltages a policy sees the
input-output history it needs to tell one plant from another (domain randomisation). Version 1
is version 2 with no deflections: the layout of the first entries is the same.

**Bounds (proven).** Every raw entry lies in [-B, B] (B = the env's observation bound, um) and
every applied voltage in [-U_r, U_r]. The normalised entries are computed by
:func:`normalize_observation` with correctly rounded IEEE operations (subtraction and division
in float64, then the cast to float32), each monotone in its operands, so applying the same
operations to the extreme operands gives bounds that hold exactly: ``B / s`` for index 0,
``(B - (-B)) / s`` for the relative, error and past-deflection entries, 1 for the voltages
(:func:`observation_high`). No bound is a guess or a margin.

**Inverse.** :func:`denormalize_observation` recovers the raw observation, the voltages (V) and
the errors (um); each recovered entry x is within ``2**-22 (|x| + |y_t|)`` of the original
(float32 rounding of the normalised entries; voltages exactly up to rounding of U_r).

The controller :class:`controllers.policy.PolicyController` runs the same functions on the raw
observation, so training and deployment cannot drift apart.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from piezo_env.checks import require_int, require_number

__all__ = [
    "ObservationConfig",
    "ObservationHistory",
    "TrackingObservation",
    "TrackingObservationVector",
    "action_to_voltage",
    "denormalize_observation",
    "normalize_observation",
    "observation_high",
    "past_deflections",
]


@dataclass(frozen=True, kw_only=True)
class ObservationConfig:
    """What the normalised observation holds and the scales it uses; validated on construction.

    Attributes
    ----------
    stroke_um : float
        One-sided stroke s (um), the deflection scale.
    u_max : float
        Rated one-sided voltage U_r (V), the voltage and action scale.
    bound_um : float
        The env's proven bound B of every raw observation entry (um).
    preview : int
        Reference samples after r_t in the raw observation (P >= 0).
    n_inputs : int
        Past voltages in the observation (>= 0).
    n_errors : int
        Past measured errors in the observation (>= 0).
    n_deflections : int
        Past measured deflections in the observation (>= 0; > 0 is observation version 2).
    """

    stroke_um: float
    u_max: float
    bound_um: float
    preview: int
    n_inputs: int = 4
    n_errors: int = 4
    n_deflections: int = 0

    def __post_init__(self) -> None:
        for name in ("stroke_um", "u_max", "bound_um"):
            require_number(name, getattr(self, name), low=0.0, low_open=True)
        for name in ("preview", "n_inputs", "n_errors", "n_deflections"):
            require_int(name, getattr(self, name), minimum=0)

    @classmethod
    def from_env(
        cls, env: Any, *, n_inputs: int = 4, n_errors: int = 4, n_deflections: int = 0
    ) -> ObservationConfig:
        """The config of a ``PiezoBender-v0`` env (single or vector, wrapped or not).

        Read from the env's task, not from its current plant: with domain randomisation the
        plant of the episode changes at every reset, the scales of the observation do not.

        Raises ValueError if the env has no reference in its observation.
        """
        base = env.unwrapped
        space = getattr(base, "single_observation_space", base.observation_space)
        if space.shape is None or len(space.shape) != 1 or space.shape[0] < 2:
            raise ValueError(
                "the env's observation holds no reference (made with reference=None?); "
                "make it with a reference, e.g. gym.make('piezo_env:PiezoBender-v0', preview=10)"
            )
        return cls(
            stroke_um=float(base.task.stroke_um),
            u_max=float(base.task.model.rated_voltage),
            bound_um=float(base.task.bound),
            preview=int(space.shape[0]) - 2,
            n_inputs=n_inputs,
            n_errors=n_errors,
            n_deflections=n_deflections,
        )

    @property
    def version(self) -> int:
        """Observation version: 1 without past deflections, 2 with them."""
        return 2 if self.n_deflections else 1

    @property
    def raw_size(self) -> int:
        """Entries of the raw observation: y_t, r_t .. r_t+P."""
        return 2 + self.preview

    @property
    def size(self) -> int:
        """Entries of the normalised observation."""
        return 2 + self.preview + self.n_inputs + self.n_errors + self.n_deflections

    @property
    def _errors_start(self) -> int:
        return self.raw_size + self.n_inputs

    @property
    def _deflections_start(self) -> int:
        return self.raw_size + self.n_inputs + self.n_errors

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe fields; a version 1 config leaves out ``n_deflections`` (it is 0)."""
        fields = asdict(self)
        if not self.n_deflections:
            del fields["n_deflections"]
        return fields


def observation_high(config: ObservationConfig) -> np.ndarray:
    """Upper bounds (float32) of the normalised observation; the lower bounds are their negative.

    The same float64 operations as :func:`normalize_observation` applied to the extreme operands
    (B for a deflection or reference, U_r for a voltage), then cast to float32: by the
    monotonicity of correctly rounded arithmetic no normalised entry can exceed them.
    """
    s, b = np.float64(config.stroke_um), np.float64(config.bound_um)
    high = np.empty(config.size, dtype=np.float32)
    high[0] = np.float32(b / s)
    high[1 : config.raw_size] = np.float32((b - (-b)) / s)
    start = config.raw_size
    high[start : start + config.n_inputs] = np.float32(
        np.float64(config.u_max) / np.float64(config.u_max)
    )
    high[config._errors_start :] = np.float32((b - (-b)) / s)
    return high


def normalize_observation(
    raw: np.ndarray,
    voltages: np.ndarray,
    errors: np.ndarray,
    config: ObservationConfig,
    deflections: np.ndarray | None = None,
) -> np.ndarray:
    """The normalised observation (see the module docstring for the layout).

    Parameters
    ----------
    raw : ndarray, shape (n, 2 + P) or (2 + P,)
        Raw observations [y_t + nu_t, r_t .. r_t+P] (um).
    voltages : ndarray, shape (n, n_inputs) or (n_inputs,)
        u_t-1 .. u_t-n_inputs (V), newest first.
    errors : ndarray, shape (n, n_errors) or (n_errors,)
        r_t-1 - y_t-1 .. (um, measured), newest first.
    config : ObservationConfig
    deflections : ndarray, shape (n, n_deflections) or (n_deflections,), optional
        y_t-1 + nu_t-1 .. (um, measured), newest first; required when
        ``config.n_deflections > 0``.

    Returns
    -------
    ndarray, float32, shape (n, size) or (size,)

    Raises
    ------
    ValueError
        When ``config`` has past deflections and none are given.
    """
    raw64 = np.asarray(raw, dtype=np.float64)
    single = raw64.ndim == 1
    raw64 = np.atleast_2d(raw64)
    s = np.float64(config.stroke_um)
    y = raw64[:, :1]
    out = np.empty((raw64.shape[0], config.size), dtype=np.float32)
    out[:, :1] = y / s
    out[:, 1 : config.raw_size] = (raw64[:, 1:] - y) / s
    start = config.raw_size
    out[:, start : start + config.n_inputs] = np.atleast_2d(
        np.asarray(voltages, dtype=np.float64)
    ) / np.float64(config.u_max)
    out[:, config._errors_start : config._deflections_start] = (
        np.atleast_2d(np.asarray(errors, dtype=np.float64)) / s
    )
    if config.n_deflections:
        if deflections is None:
            raise ValueError(
                f"the observation holds {config.n_deflections} past deflections: pass them "
                "as deflections=(n, n_deflections) um, newest first"
            )
        past = np.atleast_2d(np.asarray(deflections, dtype=np.float64))
        out[:, config._deflections_start :] = (past - y) / s
    return out[0] if single else out


def denormalize_observation(
    normalized: np.ndarray, config: ObservationConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Invert :func:`normalize_observation`.

    Parameters
    ----------
    normalized : ndarray, shape (n, size) or (size,)
    config : ObservationConfig

    Returns
    -------
    raw : ndarray, float32
        [y_t + nu_t, r_t .. r_t+P] (um).
    voltages : ndarray, float64
        Past voltages (V), newest first.
    errors : ndarray, float64
        Past measured errors (um), newest first.
    """
    n = np.asarray(normalized, dtype=np.float64)
    single = n.ndim == 1
    n = np.atleast_2d(n)
    s = np.float64(config.stroke_um)
    y = n[:, :1] * s
    raw = np.empty((n.shape[0], config.raw_size), dtype=np.float32)
    raw[:, :1] = y
    raw[:, 1:] = y + n[:, 1 : config.raw_size] * s
    start = config.raw_size
    voltages = n[:, start : start + config.n_inputs] * np.float64(config.u_max)
    errors = n[:, config._errors_start : config._deflections_start] * s
    if single:
        return raw[0], voltages[0], errors[0]
    return raw, voltages, errors


def past_deflections(normalized: np.ndarray, config: ObservationConfig) -> np.ndarray:
    """The past measured deflections (um, float64, newest first) of a normalised observation.

    The inverse of the version 2 entries of :func:`normalize_observation`, within
    ``2**-22 (|x| + |y_t|)`` of the original x (float32 rounding); shape (n, n_deflections) or
    (n_deflections,).
    """
    n = np.asarray(normalized, dtype=np.float64)
    s = np.float64(config.stroke_um)
    y = n[..., :1] * s
    return y + n[..., config._deflections_start :] * s


def action_to_voltage(action: np.ndarray, u_max: float) -> np.ndarray:
    """Voltages (V, float32) of actions in [-1, 1]; actions outside are clipped first.

    Raises ValueError for a non-finite action.
    """
    a = np.asarray(action, dtype=np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"actions must be finite numbers in [-1, 1], got {action!r}")
    return (np.clip(a, -1.0, 1.0) * np.float64(u_max)).astype(np.float32)


def _action_clipped(action: np.ndarray) -> np.ndarray:
    """Where an action of [-1, 1] lies outside it (its voltage is clipped to the drive range:
    the env's ``info["saturated"]``)."""
    return np.abs(np.asarray(action, dtype=np.float64)) > 1.0


class ObservationHistory:
    """The past voltages (V) and measured errors (um) of n envs, newest first.

    Parameters
    ----------
    n : int
        Number of envs (rows).
    config : ObservationConfig
    """

    def __init__(self, n: int, config: ObservationConfig) -> None:
        self.config = config
        self.voltages = np.zeros((n, config.n_inputs))
        self.errors = np.zeros((n, config.n_errors))
        self.last_error = np.zeros(n)
        self.deflections = np.zeros((n, config.n_deflections))
        self.last_measured = np.zeros(n)

    def start(self, rows: Any, raw: np.ndarray, voltage: Any) -> None:
        """Rest history for ``rows`` from their first raw observations and the voltage (V)."""
        raw = np.atleast_2d(np.asarray(raw, dtype=np.float64))
        error = raw[:, 1] - raw[:, 0]
        self.voltages[rows] = np.asarray(voltage, dtype=np.float64).reshape(-1, 1)
        self.errors[rows] = error[:, None]
        self.last_error[rows] = error
        self.deflections[rows] = raw[:, :1]
        self.last_measured[rows] = raw[:, 0]

    def push(self, rows: Any, raw: np.ndarray, voltage: Any) -> None:
        """Advance ``rows`` by one step: the voltage applied (V) and the new raw observations."""
        raw = np.atleast_2d(np.asarray(raw, dtype=np.float64))
        voltages, errors = self.voltages[rows], self.errors[rows]
        if self.config.n_inputs:
            voltages[:, 1:] = voltages[:, :-1]
            voltages[:, 0] = voltage
        if self.config.n_errors:
            errors[:, 1:] = errors[:, :-1]
            errors[:, 0] = self.last_error[rows]
        self.voltages[rows], self.errors[rows] = voltages, errors
        self.last_error[rows] = raw[:, 1] - raw[:, 0]
        if self.config.n_deflections:
            deflections = self.deflections[rows]
            deflections[:, 1:] = deflections[:, :-1]
            deflections[:, 0] = self.last_measured[rows]
            self.deflections[rows] = deflections
        self.last_measured[rows] = raw[:, 0]

    def observe(self, raw: np.ndarray, rows: Any = slice(None)) -> np.ndarray:
        """Normalised observations of ``rows`` from their raw observations."""
        deflections = self.deflections[rows] if self.config.n_deflections else None
        return normalize_observation(
            raw, self.voltages[rows], self.errors[rows], self.config, deflections
        )


def _spaces(config: ObservationConfig) -> tuple[spaces.Box, spaces.Box]:
    high = observation_high(config)
    observation = spaces.Box(-high, high, dtype=np.float32)
    action = spaces.Box(-1.0, 1.0, (1,), dtype=np.float32)
    return observation, action


class TrackingObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """One ``PiezoBender-v0`` env with the normalised observation and the [-1, 1] action.

    Use it instead of ``RescaleAction``: it rescales the action itself. The reward, flags and
    info are the env's (``info["voltage_V"]`` is the applied voltage).

    Parameters
    ----------
    env : gymnasium.Env
        A ``PiezoBender-v0`` env made with a reference (any preview).
    n_inputs, n_errors, n_deflections : int
        Past voltages, past errors and past deflections in the observation.
    """

    def __init__(
        self, env: gym.Env, *, n_inputs: int = 4, n_errors: int = 4, n_deflections: int = 0
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self, n_inputs=n_inputs, n_errors=n_errors, n_deflections=n_deflections
        )
        gym.Wrapper.__init__(self, env)
        self.config = ObservationConfig.from_env(
            env, n_inputs=n_inputs, n_errors=n_errors, n_deflections=n_deflections
        )
        self.observation_space, self.action_space = _spaces(self.config)
        self._history = ObservationHistory(1, self.config)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        raw, info = self.env.reset(seed=seed, options=options)
        self._history.start(slice(None), raw, info.get("voltage_V", 0.0))
        return self._history.observe(raw[None])[0], info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        voltage = action_to_voltage(action, self.config.u_max)
        if voltage.size != 1:
            raise ValueError(
                f"the action is one number in [-1, 1] (shape (1,) or a scalar), got shape "
                f"{voltage.shape}"
            )
        voltage = voltage.reshape(1)
        raw, reward, terminated, truncated, info = self.env.step(voltage)
        if "saturated" in info:  # the action clipped here is the drive the amplifier clipped
            info["saturated"] = bool(info["saturated"]) or bool(_action_clipped(action).any())
        self._history.push(slice(None), raw, info.get("voltage_V", float(voltage[0])))
        return self._history.observe(raw[None])[0], reward, terminated, truncated, info


class TrackingObservationVector(VectorWrapper):
    """The native vector env with the normalised observation and the [-1, 1] action.

    Sub-env i gives exactly what :class:`TrackingObservation` on a single env reset with
    seed + i gives, including across Gymnasium's next-step autoreset (the step after an
    episode ends starts the history afresh).

    Parameters
    ----------
    env : gymnasium.vector.VectorEnv
        ``gym.make_vec("piezo_env:PiezoBender-v0", num_envs=N,
        vectorization_mode="vector_entry_point")`` made with a reference.
    n_inputs, n_errors, n_deflections : int
        Past voltages, past errors and past deflections in the observation.
    """

    def __init__(
        self, env: VectorEnv, *, n_inputs: int = 4, n_errors: int = 4, n_deflections: int = 0
    ) -> None:
        super().__init__(env)
        self.config = ObservationConfig.from_env(
            env, n_inputs=n_inputs, n_errors=n_errors, n_deflections=n_deflections
        )
        single_obs, single_action = _spaces(self.config)
        self.single_observation_space, self.single_action_space = single_obs, single_action
        self.observation_space = batch_space(single_obs, self.num_envs)
        self.action_space = batch_space(single_action, self.num_envs)
        self._history = ObservationHistory(self.num_envs, self.config)
        self._done = np.zeros(self.num_envs, dtype=bool)

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        raw, info = self.env.reset(seed=seed, options=options)
        voltage = info.get("voltage_V", np.zeros(self.num_envs))
        self._history.start(slice(None), raw, voltage)
        self._done[:] = False
        return self._history.observe(raw), info

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        voltages = action_to_voltage(actions, self.config.u_max).reshape(self.num_envs, 1)
        raw, reward, terminated, truncated, info = self.env.step(voltages)
        if "saturated" in info:  # as the single wrapper: a clipped action saturated the drive
            clipped = _action_clipped(actions).reshape(self.num_envs, -1).any(axis=1)
            info["saturated"] = np.logical_or(info["saturated"], clipped)
        applied = np.asarray(info.get("voltage_V", voltages[:, 0]), dtype=np.float64)
        running = ~self._done
        if running.all():
            self._history.push(slice(None), raw, applied)
        else:  # next-step autoreset: these rows return a reset's observation
            self._history.push(running, raw[running], applied[running])
            self._history.start(self._done, raw[self._done], applied[self._done])
        self._done = np.logical_or(terminated, truncated)
        return self._history.observe(raw), reward, terminated, truncated, info
