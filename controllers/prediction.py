"""One prediction-model interface for every model-based controller.

A Hammerstein prediction model is an input nonlinearity (voltage u in V -> hidden signal z in
equivalent V, with memory) in series with a discrete linear state space (z -> measured tip
deflection in um)::

    z_t = N(u_t; s_t),   s_t+1 = S(u_t; s_t),   x_t+1 = A x_t + B z_t,   y_t = C x_t

Two sources give one: the identified :class:`identification.HammersteinModel` (NLS + ARX) and,
for an oracle comparison, the true plant :class:`piezo_env.PiezoBenderModel` (hysteresis + exact
ZOH beam, seen through the env's sensor where it has one). A controller sees only this object,
so the same controller code runs on either, and the difference of their results is what
identification costs, and, behind a sensor, what steering the measurement instead of the tip
costs: the oracle knows the sensor and steers the tip (:attr:`PredictionModel.tracked`), an
identified model can only steer what was measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from controllers.native.compiled_inverse import CompiledInverse, InverseMap, nls_content
from piezo_env.inverse import InverseResult
from piezo_env.memo import ContentCache

__all__ = [
    "PLANT_REDUCTION_ERROR",
    "Z_BOUNDS_KEPT",
    "HysteresisMap",
    "IdentifiedNLS",
    "InputNonlinearity",
    "InverseResult",
    "PlantHysteresis",
    "PredictionModel",
]


class InputNonlinearity(Protocol):
    """Memory nonlinearity u (V) -> z (equivalent V); states are float64 vectors."""

    u_range: tuple[float, float]

    def initial_state(self) -> np.ndarray:
        """State at rest under 0 V."""

    def step(self, u: float, state: np.ndarray) -> tuple[float, np.ndarray]:
        """(z, next state) for the voltage u applied from ``state``."""

    def inverse(self, z_target: float, state: np.ndarray) -> InverseResult:
        """Voltage reaching ``z_target`` from ``state`` (clipped to the reachable range)."""

    def reachable(self, state: np.ndarray) -> tuple[float, float]:
        """Range of z reachable in one sample from ``state`` over the drive range."""

    def casadi_step(self) -> Any:
        """casadi.Function ``(u, state) -> (z, next_state)``."""


class IdentifiedNLS:
    """The identified neural nonlinearity (:class:`identification.nls.NLS`) as an input model.

    Parameters
    ----------
    nls : identification.nls.NLS
    u_range : (float, float)
        Drive range (V).
    """

    def __init__(self, nls: Any, u_range: tuple[float, float]) -> None:
        self.nls = nls
        self.u_range = (float(u_range[0]), float(u_range[1]))
        # Unchecked fast paths for the control loop: states come from this object itself.
        self._features = nls.feature_map
        self._network = nls.to_numpy()
        self._inverse = CompiledInverse(nls, self.u_range)

    @property
    def native(self) -> list[Any]:
        """The native builds of the inverse (:class:`controllers.native.codegen.NativeBuild`)."""
        return self._inverse.native

    def content(self) -> list[Any]:
        """What :meth:`step` computes from, for a content key
        (:func:`controllers.native.compiled_inverse.nls_content`)."""
        return nls_content(self.nls)

    def initial_state(self) -> np.ndarray:
        return self.nls.initial_state()

    def step(self, u: float, state: np.ndarray) -> tuple[float, np.ndarray]:
        features, new_state = self._features.step(float(u), state)
        return self._network.evaluate_one(features), new_state

    def inverse(self, z_target: float, state: np.ndarray) -> InverseResult:
        """Voltage reaching ``z_target`` (equivalent V) from ``state``, clipped to the range.

        Generated C (:mod:`controllers.native.compiled_inverse`; its speed and accuracy:
        ``benchmarks/results/inverse_speed.md``); the numpy ``self.nls.solve_inverse`` when no
        compiler works or the map is found non-monotone.
        """
        return self._inverse.solve(z_target, state)

    def reachable(self, state: np.ndarray) -> tuple[float, float]:
        return self._inverse.reachable(state)  # generated C (numpy without a compiler)

    def casadi_step(self) -> Any:
        return self.nls.to_casadi_step()


class PlantHysteresis:
    """The plant's own hysteresis (:mod:`piezo_env.hysteresis`) as an input model (oracle).

    Its inverse runs as generated C (:class:`controllers.native.compiled_inverse.
    CompiledInverse` of :class:`HysteresisMap`, the hysteresis strength an input of the
    generated code, so that every Monte Carlo draw shares one compiled function) for a model
    that has one (:meth:`piezo_env.hysteresis.Hysteresis.inverse_parameters`: Bouc-Wen,
    Prandtl-Ishlinskii); the rate-dependent model's map jumps at the previous input, and its
    exact numpy inverse (which detects the jump) runs. The generated iteration stops at an
    estimated voltage error of 1e-9 V (``tests/test_plant_inverse.py`` holds it to the exact
    inverse), far below the float32 rounding of the voltage the plant receives (about 1e-6 V
    at 30 V).

    Parameters
    ----------
    hysteresis : piezo_env.hysteresis.Hysteresis
    u_range : (float, float)
        Drive range (V).
    """

    def __init__(self, hysteresis: Any, u_range: tuple[float, float]) -> None:
        self.hysteresis = hysteresis
        self.u_range = (float(u_range[0]), float(u_range[1]))
        self._inverse: CompiledInverse | None = None
        if hysteresis.inverse_parameters() is not None:
            self._inverse = CompiledInverse(HysteresisMap(hysteresis), self.u_range)

    @property
    def native(self) -> list[Any]:
        """The native builds of the inverse (:class:`controllers.native.codegen.NativeBuild`;
        empty where the model has no generated inverse)."""
        return [] if self._inverse is None else self._inverse.native

    def content(self) -> list[Any]:
        """What :meth:`step` computes from, for a content key: the hysteresis model (a frozen
        dataclass of numbers; any other is not keyed, :meth:`piezo_env.memo.ContentCache.
        get_or_compute`)."""
        return ["hysteresis", self.hysteresis]

    def initial_state(self) -> np.ndarray:
        return np.asarray(self.hysteresis.initial_state(0.0), dtype=np.float64)

    def step(self, u: float, state: np.ndarray) -> tuple[float, np.ndarray]:
        new, u_eff = self.hysteresis.step(np.asarray(state, dtype=np.float64), float(u))
        return float(u_eff), new

    def inverse(self, z_target: float, state: np.ndarray) -> InverseResult:
        """Voltage reaching ``z_target`` (V) from ``state``; the state is checked as the numpy
        inverse checks it (:meth:`piezo_env.hysteresis.Hysteresis.inverse`)."""
        if self._inverse is None:
            return self.hysteresis.inverse(float(z_target), state, self.u_range)
        s = np.asarray(state, dtype=np.float64)
        if s.shape != (self._inverse.map.n_state,) or not np.isfinite(s).all():
            return self.hysteresis.inverse(float(z_target), s, self.u_range)  # raises
        return self._inverse.solve(float(z_target), s)

    def reachable(self, state: np.ndarray) -> tuple[float, float]:
        if self._inverse is not None:
            return self._inverse.reachable(np.asarray(state, dtype=np.float64))
        low, high = self.step(self.u_range[0], state)[0], self.step(self.u_range[1], state)[0]
        return (low, high) if low <= high else (high, low)

    def casadi_step(self) -> Any:
        import casadi

        u = casadi.SX.sym("u")
        s = casadi.SX.sym("state", self.hysteresis.state_size)
        z, new = self.hysteresis.casadi_step(u, s)
        return casadi.Function(
            "hysteresis_step", [u, s], [z, new], ["u", "state"], ["z", "next_state"]
        )


class HysteresisMap(InverseMap):
    """A plant hysteresis with a generated inverse as a
    :class:`controllers.native.compiled_inverse.InverseMap`: u -> u_eff(u; state), with
    :meth:`piezo_env.hysteresis.Hysteresis.inverse_parameters` as the parameter input; its
    exact numpy inverse is the fallback. :attr:`kinked` is the model's
    :attr:`piezo_env.hysteresis.Hysteresis.kinks_anywhere`.
    """

    def __init__(self, hysteresis: Any) -> None:
        parameters = hysteresis.inverse_parameters()
        if parameters is None:
            raise ValueError(f"the {hysteresis.name} hysteresis has no generated inverse")
        self.hysteresis = hysteresis
        self.n_state = int(hysteresis.state_size)
        self.parameters = np.asarray(parameters, dtype=np.float64)
        self.kinked = bool(hysteresis.kinks_anywhere)

    def casadi_z(self, u: Any, s: Any, p: Any) -> tuple[Any, Any]:
        return self.hysteresis.casadi_step_with(u, s, p)

    def solve_inverse(
        self, z_target: float, state: np.ndarray, u_range: tuple[float, float]
    ) -> InverseResult:
        return self.hysteresis.inverse(z_target, state, u_range)

    def content(self) -> list[Any]:
        """What the generated functions are built from: the hysteresis model (see
        :meth:`PlantHysteresis.content`)."""
        return ["hysteresis", self.hysteresis]

    def ends(self, state: np.ndarray, u_range: tuple[float, float]) -> tuple[float, float]:
        low = self.hysteresis.step(state, u_range[0])[1]
        high = self.hysteresis.step(state, u_range[1])[1]
        return float(low), float(high)


@dataclass(frozen=True)
class SteadyStart:
    """A steady state of the model (:meth:`PredictionModel.steady_start`).

    Attributes
    ----------
    x : numpy.ndarray
        Linear state (n,).
    z : float
        Hidden input holding it (equivalent V).
    u : float
        Voltage reaching z (V).
    memory : numpy.ndarray
        The nonlinearity's memory state after that voltage.
    """

    x: np.ndarray
    z: float
    u: float
    memory: np.ndarray


@dataclass(frozen=True)
class PredictionModel:
    """Input nonlinearity in series with a discrete linear state space (z -> um).

    Attributes
    ----------
    a, b, c : numpy.ndarray
        ``x_t+1 = a x_t + b z_t``, ``y_t = c x_t`` (b: (n, 1), c: (1, n); D = 0).
    dt : float
        Sample time (s).
    nonlinearity : InputNonlinearity
        u (V) -> z (equivalent V) with memory.
    source : str
        ``"identified"`` or ``"plant"`` (oracle).
    z_bounds : (float, float)
        Range of z over the drive range on slow full-stroke triangles from rest: both first
        branches and the major loop (equivalent V). The linear MPC plans within it; a jump
        of the voltage can take an identified model's z beyond it, which the plan does not
        count on.
    tracked : numpy.ndarray or None
        (1, n): the output the controller steers to the reference, where it differs from the
        measured ``c x``: the true deflection of a plant seen through a sensor
        (:meth:`from_plant`), which the reward scores. None: the measured output itself (an
        identified model knows only what was measured).
    error_bound_um : float
        A proven bound of the model's output error against the plant it stands for, for any
        drive within the rails (um): the modes the plant's model leaves out
        (:meth:`from_plant`); 0 where none is known (an identified model), whose error the
        data alone can show (:class:`controllers.gain.GainEstimate`'s exact set).
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    dt: float
    nonlinearity: Any
    source: str
    z_bounds: tuple[float, float] = field(default=(-math.inf, math.inf))
    tracked: np.ndarray | None = None
    error_bound_um: float = 0.0

    def __post_init__(self) -> None:
        if self.tracked is not None and np.shape(self.tracked) != np.shape(self.c):
            raise ValueError(
                f"PredictionModel.tracked must have c's shape {np.shape(self.c)}, got "
                f"{np.shape(self.tracked)}; pass None to track the measured output"
            )

    @property
    def c_tracked(self) -> np.ndarray:
        """(1, n): the output the predictions steer to the reference (:attr:`tracked`, else
        the measured ``c``)."""
        return self.c if self.tracked is None else self.tracked

    @property
    def n_states(self) -> int:
        """Length of the linear state."""
        return int(self.a.shape[0])

    def steady_state_per_z(self) -> np.ndarray:
        """(n,) the linear state a constant z of 1 equivalent V holds: ``(I - A)^-1 B``."""
        return np.linalg.solve(np.eye(self.n_states) - self.a, self.b[:, 0])

    @property
    def dc_gain(self) -> float:
        """The linear part's static gain (um per equivalent V): ``C (I - A)^-1 B``."""
        return float(self.c[0] @ self.steady_state_per_z())

    @property
    def native(self) -> list[Any]:
        """The nonlinearity's native builds (:class:`controllers.native.codegen.NativeBuild`;
        empty where it has no generated code: the rate-dependent plant's hysteresis)."""
        return list(getattr(self.nonlinearity, "native", ()))

    def to_control(self) -> Any:
        """The linear part as a python-control state space with ``dt``."""
        import control

        return control.ss(self.a, self.b, self.c, np.zeros((1, 1)), self.dt)

    @classmethod
    def from_hammerstein(cls, model: Any, u_max: float) -> PredictionModel:
        """From an identified :class:`identification.HammersteinModel` (or a folder holding one)."""
        if isinstance(model, (str, Path)):
            from identification.hammerstein import HammersteinModel

            model = HammersteinModel.load(model)
        a, b, c, _ = model.arx.state_space_matrices()
        nonlinearity = IdentifiedNLS(model.nls, (-u_max, u_max))
        return cls(a, b, c, model.dt, nonlinearity, "identified", _z_bounds(nonlinearity))

    @classmethod
    def from_plant(
        cls, plant: Any, *, sensor: Any = None, reduce: bool = True
    ) -> PredictionModel:
        """From the true plant :class:`piezo_env.PiezoBenderModel` (``env.unwrapped.model``).

        With the env's ``sensor`` (:class:`piezo_env.Sensor`, ``env.unwrapped.config.sensor``)
        the model's measured output ``c`` is the beam in series with the sensor's filter and
        delay (:meth:`piezo_env.Sensor.state_space`), and its :attr:`tracked` output is the
        true deflection, which the reward scores: the oracle estimates through the sensor and
        steers the tip, not the measurement. An identified model can only steer the
        measurement, which lags the tip by the sensor's lag tau (an error of 2 pi f tau of the
        amplitude at f); an oracle blind to the sensor did worse than that
        (``benchmarks/results/design_measurements.md``).

        With ``reduce``, the beam modes whose memory the predictions cannot see are carried
        as their one-step response (:meth:`piezo_env.discrete.DiscreteBender.without_modes`):
        those with the smallest error bound first, as long as the proven bound of the
        deflection error they make together
        (:meth:`~piezo_env.discrete.DiscreteBender.mode_error_bounds`, for any input within
        the model's z bounds) stays within :data:`PLANT_REDUCTION_ERROR` of the full stroke.
        An MPC that learns the plant's gain g plans g z, up to 1.2 times those bounds at the
        datasheet's +-20 %: its error stays within 1.2 times the budget. The env keeps every
        mode that outlives a sample to 1e-10 (:func:`piezo_env.discrete.discretize`); under
        stiffness-proportional damping the overdamped high modes can pass that test with
        radii of 1e-6 (the PL127 at 0.25 ms, or a damping of 0.04), and the plant then carries
        up to 42 states where 8 often predict it to a nanometre: a controller predicting with
        all of them spends most of its step on them (``benchmarks/results/
        design_measurements.md``). ``reduce=False`` keeps the plant's own states.
        """
        u_max = plant.rated_voltage
        nonlinearity = PlantHysteresis(plant.hysteresis, (-u_max, u_max))
        z_bounds = _z_bounds(nonlinearity)
        discrete = plant.discrete
        error_bound_um = 0.0
        if reduce:
            budget_m = PLANT_REDUCTION_ERROR * 2.0 * plant.stroke_um * 1e-6
            z_max = max(abs(z_bounds[0]), abs(z_bounds[1]))
            per_volt = discrete.mode_error_bounds(limit=budget_m / z_max)
            per_mode = per_volt * z_max
            order = np.argsort(per_mode, kind="stable")
            affordable = int(np.searchsorted(np.cumsum(per_mode[order]), budget_m, "right"))
            discrete = discrete.without_modes(order[:affordable])
            # The proven bound for any drive: the hysteresis' largest |u_eff| within the rails
            # (a jump of the voltage reaches beyond the triangles' z bounds).
            u_eff = plant.hysteresis.max_effective_voltage(u_max)
            error_bound_um = float(np.sum(per_volt[order[:affordable]])) * u_eff * 1e6
        a, b, c, _ = discrete.state_space_matrices()
        if sensor is None:
            return cls(
                a, b, c, plant.dt, nonlinearity, "plant", z_bounds, error_bound_um=error_bound_um
            )
        a_s, b_s, c_s, d_s = sensor.state_space(plant.dt)
        n, k = a.shape[0], a_s.shape[0]
        series = np.zeros((n + k, n + k))  # [x; q]: the sensor's input is y = c x
        series[:n, :n], series[n:, :n], series[n:, n:] = a, np.outer(b_s, c[0]), a_s
        measured = np.hstack([d_s * c, c_s[None, :]])
        tip = np.hstack([c, np.zeros((1, k))])
        b = np.vstack([b, np.zeros((k, 1))])
        # The sensor's filter passes a convex combination of the deflections (its weights are
        # >= 0 and sum to 1): the bound holds for the measured output too.
        return cls(
            series, b, measured, plant.dt, nonlinearity, "plant", z_bounds, tip, error_bound_um
        )

    def steady_start(
        self, y0: float, noise_bound_um: float, voltage: float | None = None
    ) -> SteadyStart:
        """The model at rest holding the first measured deflection ``y0`` (um), or under a
        known ``voltage`` (V).

        A controller sees only the observation; after an env reset with ``initial_voltage``
        the first measurement is the only sign that the bender is not at rest at 0 V. Within
        the sensor noise bound, rest at 0 V is the best estimate; beyond it, the steady state
        whose output is y0: z0 = y0 / (DC gain), x0 = (I - A)^-1 B z0, and the voltage that
        reaches z0 from the nonlinearity's initial memory (for rate-independent memory, the
        state a slow approach to that voltage leaves). That voltage is only an estimate (the
        sensor's noise and the model's gain error move it), and a first move planned from it
        can step further than an amplifier's slew limit allows from the true one; a caller that
        knows the voltage passes it, and the start is the model at rest under it (z0 the
        nonlinearity's output for that voltage from its initial memory, x0 holding z0).
        """
        memory = self.nonlinearity.initial_state()
        if voltage is not None:
            z0, memory = self.nonlinearity.step(float(voltage), memory)
            return SteadyStart(self.steady_state_per_z() * z0, float(z0), float(voltage), memory)
        if abs(y0) <= noise_bound_um:
            return SteadyStart(np.zeros(self.n_states), 0.0, 0.0, memory)
        per_z = self.steady_state_per_z()
        z0 = y0 / float(self.c[0] @ per_z)
        held = self.nonlinearity.inverse(z0, memory)
        return SteadyStart(per_z * held.z, held.z, held.u, held.state)

    def simulate(self, u: np.ndarray, *, tracked: bool = False) -> np.ndarray:
        """Measured deflection (um) after each voltage of ``u`` (V), from rest: y[t] follows
        u[t]; with ``tracked``, the steered output (:attr:`c_tracked`) instead."""
        state = self.nonlinearity.initial_state()
        x = np.zeros(self.n_states)
        y = np.empty(len(u))
        out = (self.c_tracked if tracked else self.c)[0]
        for t, v in enumerate(np.asarray(u, dtype=np.float64)):
            z, state = self.nonlinearity.step(float(v), state)
            x = self.a @ x + self.b[:, 0] * z
            y[t] = float(out @ x)
        return y


PLANT_REDUCTION_ERROR = 1e-6
"""Largest deflection error the oracle's model reduction may make (fraction of the full
stroke, :meth:`PredictionModel.from_plant`): a tenth of the resolution of every figure the
benchmark prints (0.001 % of the full stroke), 2 nm on the PL140, a five-hundredth of its
sensor noise."""

Z_BOUNDS_KEPT = 64
"""Nonlinearities' z bounds kept by content (:func:`_z_bounds`), one per nonlinearity and
drive range. A benchmark worker meets up to six identified models and the oracles' plants: 12
plants, 10 random draws and 8 corners: 36 (two numbers each)."""

_z_bounds_kept = ContentCache(Z_BOUNDS_KEPT)


def _z_bounds(nonlinearity: Any) -> tuple[float, float]:
    """Extremes of z on full-stroke triangles from rest: the major loop and both first
    branches (a first rise to the top of the drive range and a first descent to its bottom,
    which a hysteresis whose first branches overshoot its major loop reaches beyond it).

    1200 steps of the nonlinearity: kept by content (:data:`Z_BOUNDS_KEPT`) where the
    nonlinearity says what its steps compute from (its ``content()``), so a model built
    again simulates none."""
    content = getattr(nonlinearity, "content", None)
    return _z_bounds_kept.get_or_compute(
        None if content is None else [*content(), nonlinearity.u_range],
        lambda: _triangle_extremes(nonlinearity),
    )


def _triangle_extremes(nonlinearity: Any) -> tuple[float, float]:
    """:func:`_z_bounds`, computed."""
    low, high = nonlinearity.u_range
    ramp = np.linspace(0.0, 1.0, 121)[1:]
    zs = []
    for first, other in ((high, low), (low, high)):  # from rest: up first, then down first
        away, back = first + (other - first) * ramp, other + (first - other) * ramp
        state = nonlinearity.initial_state()
        for v in np.concatenate([first * ramp, away, back, away, back]):
            z, state = nonlinearity.step(float(v), state)
            zs.append(z)
    return float(min(zs)), float(max(zs))
