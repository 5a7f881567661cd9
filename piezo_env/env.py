"""PiezoBender-v0: a PI PICMA piezoelectric bender as a Gymnasium environment.

A clamped-free piezoelectric bimorph bender (PL140 by default, or any bender of the PICMA
family) modelled with Euler-Bernoulli finite elements built from its datasheet, with
rate-independent input hysteresis (Bouc-Wen by default), optional creep and a bounded-noise
displacement sensor; the task is to make the tip deflection track a reference.
:class:`PiezoBenderEnv` documents the spaces, the reward and the timing (``help(env.unwrapped)``).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from piezo_env.disturbance import DisturbanceState
from piezo_env.model import BenderSimulator, DriftingSimulator
from piezo_env.reference import ReferenceStream
from piezo_env.task import (
    NOISE_BLOCK,
    TaskAttributes,
    TaskConfig,
    check_reset_options,
    episode_reference,
)

__all__ = ["PiezoBenderEnv"]

_TRACE = 500


class PiezoBenderEnv(TaskAttributes, gym.Env[np.ndarray, np.ndarray]):
    """Piezoelectric bender tracking task: drive voltage in, tip deflection out.

    ## Description
    A clamped-free PICMA bimorph (PL140 by default) modelled with Euler-Bernoulli finite
    elements from its datasheet, with rate-independent input hysteresis (Bouc-Wen by default),
    optional creep and a bounded-noise displacement sensor. The dynamics are discretised
    exactly (zero-order hold) at ``dt``: the action a_t is held for one sample, and the plant is
    strictly proper, so a_t first shows in the deflection y_{t+1}. The default ``dt`` follows
    the bender (:func:`piezo_env.default_dt`: its highest first resonance within the datasheet
    tolerance at most a quarter of the sampling rate; 1 ms for the PL140, 0.25 ms for the
    PL127). The physics object is ``env.unwrapped.model``
    (:class:`piezo_env.model.PiezoBenderModel`).

    ## Timing
    At step t the agent sees the observation o_t and sends a_t; ``step(a_t)`` returns
    o_{t+1}, the reward of a_t and the info of t+1. Sample t runs from time t*dt; y_t is the true
    tip deflection and r_t the reference at that time.

    ## Action Space
    ``Box(-U_r, U_r, (1,), float32)``: the drive voltage a_t in volts (one-sided; the physical
    drive is 0..60 V around a 30 V bias, so U_r = 30 V for the whole family). A numeric array of
    shape (1,) (or a numpy/Python number); a voltage beyond the range is clipped, as the
    amplifier saturates, and ``info["saturated"]`` is True. NaN, inf, None, strings and other
    shapes raise ValueError.

    ## Observation Space
    float32 vector, all entries in micrometres. With a reference (the default) and
    ``preview = p`` (default 1), o_t has ``2 + p`` entries:

    | index | sample | meaning |
    |---|---|---|
    | 0 | y_t + nu_t | measured tip deflection, nu_t ~ U(-noise_bound, noise_bound) |
    | 1 | r_t | reference now (what index 0 should equal) |
    | 2 | r_{t+1} | the sample the reward of a_t is scored against (p >= 1) |
    | 1 + k | r_{t+k} | reference k samples ahead, k = 1 .. p |

    With ``preview=0`` the observation is [y_t + nu_t, r_t] and does not contain r_{t+1}: the
    reward is then scored against a sample the agent cannot see (only sensible for slow
    references). With ``reference=None`` (regulation to zero) the observation is [y_t + nu_t]
    alone and ``preview`` must be 0.

    The bounds are proven, not guessed: the peak-to-peak gain of the beam (L1 norm of its
    impulse response) times the largest effective voltage the hysteresis can produce, plus the
    noise bound.

    ## Rewards
    The reward of a_t is ``-((y_{t+1} - r_{t+1}) / stroke)^2``: the squared tracking error of
    the true (noise-free) deflection after a_t, normalised by the datasheet stroke
    (``model.stroke_um``). With ``reference=None``, r = 0. It is a Python float in
    [-(2 bound / stroke)^2, 0].

    ## Episode End
    Truncated after ``max_episode_steps`` (``gym.make`` default 2000 steps = 2 s at
    dt = 1 ms, shorter at a finer dt: pass ``max_episode_steps=round(2.0 / dt)`` for 2 s;
    -1 or None for no limit) by TimeLimit. Terminated only if ``deflection_limit``
    (um) is set and |y_{t+1}| exceeds it, as a bender driven into its mechanical stop would be.

    ## Info
    After ``step(a_t)``: ``deflection_um`` = y_{t+1} (true), ``reference_um`` = r_{t+1} (the
    scored sample; only with a reference), ``voltage_V`` (a_t after clipping),
    ``effective_voltage_V`` (after hysteresis), ``charge_uC`` (drive charge at t+1),
    ``saturated`` (a_t was clipped). After ``reset``: the same keys at t = 0 (y_0, r_0, the
    initial voltage).

    ## Domain randomisation
    With ``randomize=True`` (or a :class:`piezo_env.randomization.DomainRandomization`) each
    reset first draws a plant from the datasheet tolerances with ``np_random`` (five uniforms,
    before the reference and the noise; order and spread in :mod:`piezo_env.randomization`)
    and rebuilds the model (about 1-5 ms per reset). ``env.unwrapped.model`` is then the plant
    of the current episode; the nominal one is ``env.unwrapped.task.model``. References and
    the reward keep the nominal stroke, and the observation bound covers every plant the
    spread can draw (proven in :mod:`piezo_env.randomized_bound`). ``info["plant"]`` at reset
    reports the draw: ``free_deflection_um``, ``blocking_force_N``, ``stiffness_N_per_m``,
    ``resonance_Hz``, ``damping_ratio``, ``hysteresis_scale``.

    ## Bench options (amplifier, sensor, rate-dependent hysteresis, drift, disturbance)
    Off by default; each is documented with its physics in its module and in
    :class:`piezo_env.TaskConfig`. With any of ``amplifier``, ``sensor``, ``drift`` or
    ``disturbance`` on, the env steps through a second path chosen at construction (the default
    path is unchanged).

    - ``amplifier`` (:mod:`piezo_env.amplifier`): the action is the amplifier's command; the
      bender gets v_t = v_{t-1} + (1 - p) clip(c_t - v_{t-1}, +-S dt) with the slew limit
      S = I_max / C_p (``env.unwrapped.slew_limit``, V/s; None without an amplifier) from the
      current limit and the drive capacitance of the charge equation Q = C_p u + Gamma theta.
      Info adds ``command_V`` (the clipped command), ``slew_limited`` (the limit was active)
      and ``current_mA`` (dQ/dt over the sample, capacitive plus motional); ``voltage_V`` is the
      voltage on the bender.
    - ``sensor`` (:mod:`piezo_env.sensor`): a delay of 0-2 samples and a first-order bandwidth
      on the observed deflection only; reward and ``info["deflection_um"]`` stay true.
    - ``hysteresis="rate-dependent"`` (:class:`piezo_env.hysteresis.
      RateDependentPrandtlIshlinskii`): play radii that grow with the drive's rate, so the loop
      widens with frequency (needs no second path).
    - ``drift`` (:mod:`piezo_env.drift`): piezoelectric coefficient and stiffness move linearly
      over the episode (restarting at each reset); ``model`` stays the start plant's
      datasheet model. The observation bound is proven for the drifted plant.

    - ``disturbance`` (:mod:`piezo_env.disturbance`): the amplifier's white output voltage
      noise on the voltage the bender gets (held within the rails +-U_r), a band-limited tip
      vibration added to the deflection that the sensor sees and the reward scores, and the
      measured deflection held within a sensor's range and rounded to its ADC's LSB.
      Info adds ``voltage_noise_V`` (the noise that reached the bender) and ``vibration_um``;
      ``deflection_um`` is then bending plus vibration. Its draws come from ``np_random`` after
      the sensor noise's; a disturbance that is off draws nothing.

    Every bound above still holds: the amplifier keeps |v| <= U_r, the sensor's output is a
    convex combination of true deflections, the rate-dependent map has the quasi-static one's
    bound, the drift bound is proven in :mod:`piezo_env.drift`, the voltage noise stays within
    the rails, the bound adds the vibration's proven peak and covers the ADC's range.

    ## Reset options
    ``reference``: an array (um) for this episode; ``initial_voltage``: start at rest under this
    voltage (V) instead of 0 V.

    Parameters
    ----------
    config : TaskConfig, optional
        Task settings; keyword settings below override its fields.
    render_mode : {None, "rgb_array", "human"}
        ``"rgb_array"`` draws the bent beam and the recent deflection trace.
    **settings
        The fields of :class:`piezo_env.TaskConfig`, each documented there with its unit and
        default (``help(piezo_env.TaskConfig)``): ``bender``, ``n_elements``, ``dt``,
        ``hysteresis``, ``creep``, ``noise_bound``, ``reference``, ``reference_band``,
        ``preview``, ``deflection_limit``, ``damping_ratio``, ``randomize``, ``amplifier``,
        ``sensor``, ``drift``, ``disturbance``. An unknown keyword raises TypeError naming the
        valid ones.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["human", "rgb_array"], "render_fps": 30}

    def __init__(
        self,
        *,
        config: TaskConfig | None = None,
        render_mode: str | None = None,
        **settings: Any,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, "
                f"got {render_mode!r}"
            )
        self._adopt_task(config, settings)
        self.render_mode = render_mode
        self._stroke = self.task.stroke_um
        self.observation_space = self.task.observation_space()
        self.action_space = self.task.action_space()
        self.metadata = {**self.metadata, "render_fps": min(30.0, 1.0 / self.config.dt)}

        self._plant = BenderSimulator(self.model)
        self._amplifier = None
        self._sensor = None
        self._disturbance = None
        self._charge = 0.0
        self.slew_limit: float | None = None
        if self.config.bench_options:
            self._set_up_bench()
        self._reference: ReferenceStream | None = None
        self._ref_values = np.zeros(0, dtype=np.float32)
        self._noise = np.zeros(NOISE_BLOCK)
        self._noise_index = 0
        self._t = 0
        self._trace = np.zeros(_TRACE) if render_mode is not None else None
        self._renderer = None

    # -- Gymnasium API -------------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        options = dict(options or {})
        voltage = check_reset_options(options, self._u_max)  # checked before anything changes
        spec = episode_reference(options, self._reference_spec)
        given = None  # an array reference is checked (and made) now, a named one drawn below
        if spec is not None and not isinstance(spec, str):
            given = self.task.reference_stream(spec, None)
        super().reset(seed=seed)
        plant_info = self._draw_plant() if self.task.randomization is not None else None
        self._plant.reset(voltage)
        if given is None and spec is not None:  # a named reference, drawn after the plant
            given = self.task.reference_stream(spec, self.np_random)
        self._reference = given
        self._t = 0
        self._ref_values = self._window_values()
        self._draw_noise()
        if self._trace is not None:
            self._trace[:] = self._plant.deflection * 1e6
        deflection_um = self._plant.deflection * 1e6
        info = self._info(deflection_um, voltage, voltage, 0.0, False)
        info["effective_voltage_V"] = float(
            self.model.hysteresis.step(self._plant.get_state()[1], voltage)[1]
        )
        info["charge_uC"] = self._plant.charge(voltage) * 1e6
        if plant_info is not None:
            info["plant"] = plant_info
        measured_um = deflection_um
        if self.config.bench_options:
            measured_um = self._reset_bench(voltage, deflection_um, info)
        measured_um = measured_um + self._next_noise()
        if self._disturbance is not None:
            measured_um = self._disturbance.quantise(measured_um)
        return self._observe(measured_um), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        voltage, saturated = self._drive_voltage(action)
        deflection, u_eff, charge = self._plant.step(voltage)
        deflection_um, reward, terminated = self._advance(deflection)
        observation = self._observe(deflection_um + self._next_noise())
        info = self._info(deflection_um, voltage, u_eff, charge * 1e6, saturated)
        if self.render_mode == "human":
            self.render()
        return observation, reward, terminated, False, info

    def _step_bench(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """``step`` with an amplifier, a sensor, a drift or a disturbance (chosen at
        construction)."""
        command, saturated = self._drive_voltage(action)
        amplifier = self._amplifier
        if amplifier is None:
            voltage, limited = command, False
        else:
            voltage, limited = amplifier.apply(command)
        disturbance = self._disturbance
        if disturbance is not None:
            voltage, voltage_noise = disturbance.drive(voltage, self.np_random)
        deflection, u_eff, charge = self._plant.step(voltage)
        if disturbance is not None:
            vibration_um = disturbance.next_vibration(self.np_random)
            deflection += vibration_um * 1e-6
        deflection_um, reward, terminated = self._advance(deflection)
        sensor = self._sensor
        measured_um = deflection_um if sensor is None else sensor.measure(deflection_um)
        measured_um += self._next_noise()
        if disturbance is not None:
            measured_um = disturbance.quantise(measured_um)
        observation = self._observe(measured_um)
        info = self._info(deflection_um, voltage, u_eff, charge * 1e6, saturated)
        if disturbance is not None:
            info["voltage_noise_V"] = voltage_noise
            info["vibration_um"] = vibration_um
        info["command_V"] = command
        info["slew_limited"] = limited
        info["current_mA"] = (charge - self._charge) / self.config.dt * 1e3
        self._charge = charge
        if self.render_mode == "human":
            self.render()
        return observation, reward, terminated, False, info

    def _advance(self, deflection: float) -> tuple[float, float, bool]:
        """Move to the next sample after the plant reached ``deflection`` (m): the deflection
        in um, the reward of the action, and whether the bender hit ``deflection_limit``."""
        self._t += 1
        if self._t + self.preview >= len(self._ref_values) and self._reference is not None:
            self._ref_values = self._window_values()
        deflection_um = deflection * 1e6
        error = deflection_um - self._reference_at(self._t)
        reward = -((error / self._stroke) ** 2)
        terminated = (
            self.deflection_limit is not None and abs(deflection_um) > self.deflection_limit
        )
        if self._trace is not None:
            self._trace[self._t % _TRACE] = deflection_um
        return deflection_um, reward, terminated

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn(
                "You are calling render method without specifying any render mode. "
                "You can specify the render_mode at initialization, "
                'e.g. gym.make("piezo_env:PiezoBender-v0", render_mode="rgb_array")'
            )
            return None
        from piezo_env.render import BenderRenderer

        if self._renderer is None:
            # The nominal plant: a drawn one has the same geometry, and the axes stay put.
            self._renderer = BenderRenderer(self.task.model, human=self.render_mode == "human")
        trace = np.roll(self._trace, -(self._t % _TRACE) - 1)
        reference = None if self._reference is None else self._reference_at(self._t)
        frame = self._renderer.draw(
            self._plant.nodal_deflection * 1e6,
            self._plant.deflection * 1e6,
            trace,
            reference,
            self._t,
        )
        return frame if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_renderer"] = None
        state.pop("step", None)  # the bench path, set again from the config
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        if self.config.bench_options:
            self.step = self._step_bench

    # -- helpers -------------------------------------------------------------------------------

    def _set_up_bench(self) -> None:
        """The amplifier, sensor and drift of the config, and the bench stepping path."""
        config = self.config
        if config.drift is not None:
            self._plant = DriftingSimulator(self.model, self.task.drift_plan)
        if config.amplifier is not None:
            capacitance = self.model.params.capacitance
            self._amplifier = config.amplifier.state(capacitance, config.dt)
            self.slew_limit = config.amplifier.slew_limit(capacitance)
        if config.sensor is not None:
            self._sensor = config.sensor.state(config.dt)
        if config.disturbance is not None:
            self._disturbance = DisturbanceState(
                config.disturbance,
                self.task.vibration,
                self._u_max,
                self.task.sensor_range,
                NOISE_BLOCK,
            )
        self.step = self._step_bench  # the default path stays PiezoBenderEnv.step

    def _reset_bench(self, voltage: float, deflection_um: float, info: dict[str, Any]) -> float:
        """Amplifier and sensor at rest, the disturbance's first draws (after the sensor
        noise's); the bench keys of the reset info; the measured um."""
        if self._amplifier is not None:
            self._amplifier.reset(voltage)
        if self._disturbance is not None:
            vibration_um = self._disturbance.reset(self.np_random)
            deflection_um += vibration_um
            info["deflection_um"] = deflection_um
            info["voltage_noise_V"] = 0.0
            info["vibration_um"] = vibration_um
        self._charge = self._plant.charge(voltage)
        info["command_V"] = voltage
        info["slew_limited"] = False
        info["current_mA"] = 0.0
        return deflection_um if self._sensor is None else self._sensor.reset(deflection_um)

    def _draw_plant(self) -> dict[str, float]:
        """Draw this episode's plant from ``np_random`` and step it from now on; its info."""
        self.model, draw = self.task.draw_plant(self.np_random)
        self._plant = BenderSimulator(self.model)
        return draw.info()

    def _drive_voltage(self, action: np.ndarray) -> tuple[float, bool]:
        """Validated, clipped voltage (V) and whether it was clipped."""
        a = np.asarray(action)
        if a.dtype.kind not in "fiu":
            raise ValueError(_not_a_voltage(action))
        if a.shape != (1,) and a.shape != ():
            raise ValueError(
                f"action must have shape (1,) (one voltage in V), got shape {a.shape}: {action!r}"
            )
        u = float(a.item())
        u_max = self._u_max
        if -u_max <= u <= u_max:  # False for NaN
            return u, False
        if not math.isfinite(u):
            raise ValueError(f"action must be a finite voltage in V, got {u!r}")
        return (u_max, True) if u > 0 else (-u_max, True)

    def _window_values(self) -> np.ndarray:
        """Reference samples covering at least the coming preview window."""
        if self._reference is None:
            return np.zeros(0, dtype=np.float32)
        return self._reference.ensure(self._t + self.preview + 1)

    def _reference_at(self, t: int) -> float:
        return 0.0 if self._reference is None else self._ref_values.item(t)

    def _observe(self, measured_um: float) -> np.ndarray:
        """[measured, r_t .. r_t+P] (float32): after the first sample, a copy of the drawn
        reference from r_t-1 on with its first entry replaced (one numpy call fewer than
        filling an empty array; :meth:`_advance` keeps r_t+P drawn)."""
        if self._reference is None:
            return np.array([measured_um], dtype=np.float32)
        t = self._t
        if t:
            obs = self._ref_values[t - 1 : t + self.preview + 1].copy()
        else:
            obs = np.empty(2 + self.preview, dtype=np.float32)
            obs[1:] = self._ref_values[: self.preview + 1]
        obs[0] = measured_um
        return obs

    def _draw_noise(self) -> None:
        r = self.noise_bound
        if r > 0:
            self._noise = self.np_random.uniform(-r, r, NOISE_BLOCK)
        self._noise_index = 0

    def _next_noise(self) -> float:
        if self._noise_index == NOISE_BLOCK:
            self._draw_noise()
        value = self._noise.item(self._noise_index)
        self._noise_index += 1
        return value

    def _info(
        self, deflection_um: float, voltage: float, u_eff: float, charge_uc: float, saturated: bool
    ) -> dict[str, Any]:
        info = {
            "deflection_um": deflection_um,
            "voltage_V": voltage,
            "effective_voltage_V": u_eff,
            "charge_uC": charge_uc,
            "saturated": saturated,
        }
        if self._reference is not None:
            info["reference_um"] = self._reference_at(self._t)
        return info


def _not_a_voltage(action: object) -> str:
    """Why ``action`` (not a real-valued array) is not a voltage."""
    if action is None:
        return "action is None, which is not a voltage: pass a numeric array of shape (1,) in V"
    return (
        "action must be a numeric array of shape (1,) (one voltage in V), "
        f"got {type(action).__name__} {action!r}"
    )
