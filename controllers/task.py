"""What a controller knows about the task: read once from the environment, never in the loop.

The observation of ``PiezoBender-v0`` at step t is ``[y_t + nu_t, r_t, r_t+1 .. r_t+P]`` (um),
and the action a_t is scored against r_t+1. A controller at step t therefore aims at
r_t+1 .. r_t+N: :meth:`ControlTask.targets` slices them out of the observation (holding the
last previewed sample when the horizon reaches past the preview).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from piezo_env.checks import require_int, require_number

__all__ = ["SLEW_MARGIN_V", "ControlTask"]

SLEW_MARGIN_V = 1e-5
"""Margin (V) of a controller's voltage step below the amplifier's S dt (float32 rounding)."""


@dataclass(frozen=True)
class ControlTask:
    """Task facts a controller may use.

    Attributes
    ----------
    dt : float
        Sample time (s).
    u_max : float
        Drive range is [-u_max, u_max] (V).
    stroke_um : float
        One-sided datasheet stroke (um); the full stroke is twice this.
    preview : int
        Future reference samples in the observation after r_t (P >= 1: a controller must see
        r_t+1, the sample its action is scored against).
    noise_bound_um : float
        Sensor noise bound r (um): the datasheet of the sensor, not a secret of the plant.
    slew_limit : float or None
        The amplifier's slew limit S (V/s) when the env models one (``env.unwrapped.
        slew_limit`` = current limit / drive capacitance, :mod:`piezo_env.amplifier`): a
        datasheet value, not an identified one. None: an ideal amplifier. Controllers keep
        |u_t - u_t-1| <= S dt.
    datasheet : piezo_env.BenderDatasheet or None
        The bender's datasheet, and ``damping_ratio`` the first-mode damping ratio of the env's
        nominal plant (the FE model of :mod:`piezo_env` built from that datasheet): what a
        controller may know of the physics before it sees data (the adaptive MPC's
        ``member_set="datasheet"``). None for a task made by hand.
    damping_ratio : float or None
        See ``datasheet``.
    n_elements : int or None
        Beam elements of that FE model (None: not known).
    observation_bound_um : float or None
        The largest |entry| an observation can hold (um): the env's observation bound, a
        proven bound of the deflection the drive can produce plus the sensor noise
        (``env.unwrapped.task.bound``). A measurement beyond it is no deflection of this bender (a
        sensor fault, a unit error) and is refused by :meth:`check_observation`: one such
        sample would otherwise steer the observer's state far off and, through the QP's
        bounds, the loop with it for the rest of the episode. None: not known, not checked.
    """

    dt: float
    u_max: float
    stroke_um: float
    preview: int
    noise_bound_um: float = 1.0
    slew_limit: float | None = None
    datasheet: Any = None
    damping_ratio: float | None = None
    n_elements: int | None = None
    observation_bound_um: float | None = None

    def __post_init__(self) -> None:
        for name in ("dt", "u_max", "stroke_um"):
            require_number(name, getattr(self, name), low=0.0, low_open=True)
        try:
            require_int("preview", self.preview)
        except ValueError as error:
            raise ValueError(
                f"{error}: the action a_t is scored against r_t+1, which the observation shows "
                "from preview=1 on; make the env with preview >= 1, e.g. "
                "gym.make('piezo_env:PiezoBender-v0', preview=20)"
            ) from None
        require_number("noise_bound_um", self.noise_bound_um, low=0.0)
        if self.observation_bound_um is not None:
            require_number(
                "observation_bound_um", self.observation_bound_um, low=0.0, low_open=True
            )
        if self.slew_limit is not None:
            require_number(
                "slew_limit (V/s, or None)",
                self.slew_limit,
                low=2.0 * SLEW_MARGIN_V / self.dt,
                low_open=True,
            )
        # Python floats whatever number type a caller passed (numpy's float64, say): the
        # controllers' arithmetic on them then does not depend on numpy's promotion rules,
        # which changed between numpy 1 and 2 (controllers.mpc.float32_within).
        for name in ("dt", "u_max", "stroke_um", "noise_bound_um", "slew_limit"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, float(value))
        if self.observation_bound_um is not None:
            object.__setattr__(self, "observation_bound_um", float(self.observation_bound_um))

    @property
    def slew_step(self) -> float | None:
        """The largest voltage change per sample a controller commands (V), or None.

        S dt less 1e-5 V: the env receives float32 volts, whose rounding (at most 2e-6 V at
        30 V) must not carry a command past the amplifier's limit.
        """
        if self.slew_limit is None:
            return None
        return self.slew_limit * self.dt - SLEW_MARGIN_V

    @classmethod
    def from_env(cls, env: Any) -> ControlTask:
        """Read the task of a ``PiezoBender-v0`` env (wrapped or not).

        A controller reads the raw observation (um, ``[y_t, r_t, r_t+1 .. r_t+P]``) and acts
        in volts, so the task comes from the env itself (``env.unwrapped``: its spaces and its
        task, the nominal plant), never from an episode's drawn plant nor from a wrapper.
        Wrappers that keep the spaces (``TimeLimit``, ``OrderEnforcing``, the env checker, ...)
        are fine: the controller runs through them. A wrapper that changes the observation or
        the action space (e.g. :class:`piezo_env.wrappers.TrackingObservation`, made for
        learning agents, or ``RescaleAction``) is refused: a controller stepped through it
        would read scaled numbers as micrometres and send volts to a wrapper expecting
        [-1, 1]. Pass the unwrapped env, or a wrapper that keeps the spaces. A wrapper that
        keeps the spaces but changes the values inside them cannot be told apart and is the
        caller's to avoid.

        The amplifier's slew limit (``env.unwrapped.slew_limit``) is read too: it is a datasheet
        value of the amplifier, which a controller may use as a constraint.

        Raises
        ------
        ValueError
            If the env has no reference in its observation (a tracking controller needs one),
            a wrapper changes its observation or action space, or it is a vector env.
        """
        if hasattr(env, "num_envs") and hasattr(env, "single_observation_space"):
            raise ValueError(
                f"{type(env).__name__} is a vector env of {env.num_envs} benders; a controller "
                "acts on one: build it from a single env, e.g. "
                "gym.make('piezo_env:PiezoBender-v0', preview=20) with the same keywords, and "
                "run one controller per bender"
            )
        base = env.unwrapped
        if env.observation_space != base.observation_space or env.action_space != base.action_space:
            raise ValueError(
                f"{type(env).__name__} changes the env's observation or action space; a "
                "controller reads the raw observation (um) and returns volts: pass the env "
                "without that wrapper (e.g. env.unwrapped) or a wrapper that keeps the spaces"
            )
        shape = base.observation_space.shape
        if shape is None or len(shape) != 1 or shape[0] < 2:
            raise ValueError(
                "the env's observation holds no reference (made with reference=None?); make it "
                "with a reference, e.g. gym.make('piezo_env:PiezoBender-v0', preview=20)"
            )
        nominal = base.task  # not base.model: with domain randomisation that is this episode's
        return cls(
            dt=float(nominal.model.dt),
            u_max=float(base.action_space.high[0]),
            stroke_um=float(nominal.stroke_um),
            preview=int(shape[0]) - 2,
            noise_bound_um=float(nominal.noise_bound),
            slew_limit=_slew_limit(base),
            datasheet=nominal.model.params.datasheet,
            damping_ratio=float(base.config.damping_ratio),
            n_elements=int(nominal.model.beam.n_elements),
            observation_bound_um=float(base.observation_space.high[0]),
        )

    @property
    def observation_size(self) -> int:
        """Length of the observation vector: deflection, r_t and the preview."""
        return 2 + self.preview

    def check_observation(self, observation: Any) -> np.ndarray:
        """The observation as float64, or ValueError naming what is wrong with it.

        A float64 array is returned as it is, any other numeric one as a float64 copy.
        Finiteness is told by the sum of the entries, a dot product with ones: a NaN or an
        infinity makes it non-finite, and only then are the entries checked one by one
        (which also clears a sum of finite entries that overflowed). The dot product is one
        BLAS call, cheaper than numpy's ``sum`` (a reduction); this check runs at every step
        of every controller."""
        obs = observation if type(observation) is np.ndarray else np.asarray(observation)
        if obs.dtype.kind not in "fiu":
            raise ValueError(
                f"observation must be a numeric array (um), got dtype {obs.dtype}: {observation!r}"
            )
        obs = obs.astype(np.float64, copy=False)
        if obs.shape != (2 + self.preview,):
            raise ValueError(
                f"observation must have shape ({self.observation_size},) = [y, r_t, r_t+1 .. "
                f"r_t+{self.preview}] (um), got shape {obs.shape}"
            )
        total = obs.dot(self._ones)
        if not math.isfinite(total):
            bad = np.flatnonzero(~np.isfinite(obs))
            if bad.size:
                raise ValueError(f"observation[{bad[0]}] = {obs[bad[0]]} is not finite")
        bound = self.observation_bound_um
        if bound is not None and not abs(obs[0]) <= bound:
            raise ValueError(
                f"observation[0] = {obs[0]:g} um lies beyond any deflection this bender can "
                f"show (the env's observation bound {bound:g} um): a sensor fault or a unit "
                "error; check the measurement before it reaches the controller"
            )
        return obs

    @functools.cached_property
    def _ones(self) -> np.ndarray:
        """Ones, one per observation entry: :meth:`check_observation` sums with them."""
        return np.ones(self.observation_size)

    def targets(self, observation: np.ndarray, horizon: int) -> np.ndarray:
        """r_t+1 .. r_t+horizon (um) from a checked observation; the last preview sample holds."""
        out = np.empty(horizon)
        seen = observation[2 : 2 + horizon]
        out[: seen.size] = seen
        out[seen.size :] = observation[-1]
        return out


def _slew_limit(env: Any) -> float | None:
    """The env's amplifier slew limit (V/s), or None (an ideal amplifier or an older env)."""
    value = getattr(env, "slew_limit", None)
    return None if value is None else float(value)
