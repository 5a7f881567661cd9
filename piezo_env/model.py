"""The bender model: datasheet -> FE beam -> exact discrete dynamics, with input hysteresis.

``PiezoBenderModel`` is the typed physics object the environment holds (``env.unwrapped.model``);
it is stateless and serves the single env, the vector env, tests and model-based users.
``BenderSimulator`` carries the state of one bender and steps it with a few scalar operations
and one small matrix-vector product.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from piezo_env.config import TaskConfig  # the one home of the defaults
from piezo_env.datasheet import BenderDatasheet
from piezo_env.discrete import Creep, DiscreteBender, discretize
from piezo_env.fem import BeamFE, assemble_beam
from piezo_env.hysteresis import BoucWen, Hysteresis, make_hysteresis
from piezo_env.parameters import BenderParameters, bender_parameters
from piezo_env.sampling import default_dt

__all__ = ["BenderSimulator", "DriftingSimulator", "PiezoBenderModel", "SimulationResult"]


class PiezoBenderModel:
    """Finite-element PICMA bender with input hysteresis, discretised exactly at ``dt``.

    Parameters
    ----------
    bender : str or BenderDatasheet
        Catalogue name (``"PL140"``, ``"PL112"``, ...) or a datasheet.
    n_elements : int
        Hermite beam elements (default 10: f1..f3 within 0.03 % of the continuum).
    dt : float or None
        Sample time (s); None (the default): the bender's, :func:`piezo_env.default_dt`.
    hysteresis : {"bouc-wen", "prandtl-ishlinskii", "rate-dependent", None} or Hysteresis
        Input hysteresis model; None for a linear bender.
    creep : bool or Creep
        Add linear creep (True: 1.5 % per decade between 10 ms and 100 s).
    damping_ratio : float
        First-mode damping ratio (-).
    damping : {"rayleigh", "modal"}
        How the higher modes are damped (see piezo_env.fem).
    density : float or {"calibrated", "nominal"}
        Density choice (see piezo_env.parameters.bender_parameters).
    """

    def __init__(
        self,
        bender: str | BenderDatasheet = TaskConfig.bender,
        *,
        n_elements: int = TaskConfig.n_elements,
        dt: float | None = TaskConfig.dt,
        hysteresis: str | Hysteresis | None = TaskConfig.hysteresis,
        creep: bool | Creep = TaskConfig.creep,
        damping_ratio: float = TaskConfig.damping_ratio,
        damping: str = "rayleigh",
        density: float | str = "calibrated",
    ) -> None:
        self.params: BenderParameters = bender_parameters(bender, density=density)
        if dt is None:
            dt = default_dt(self.params.datasheet)
        self.beam: BeamFE = assemble_beam(
            self.params, n_elements, damping_ratio=damping_ratio, damping=damping
        )
        if creep is True:
            creep = Creep()
        elif creep is False or creep is None:
            creep = None
        elif not isinstance(creep, Creep):
            raise ValueError(f"creep must be a bool or a Creep, got {creep!r}")
        self.creep: Creep | None = creep
        self.discrete: DiscreteBender = discretize(self.beam, dt, creep=creep)
        self.hysteresis: Hysteresis = make_hysteresis(hysteresis, self.params.rated_voltage, dt=dt)
        self.dt: float = float(dt)

    @property
    def name(self) -> str:
        """Bender type, e.g. ``"PL140.10"``."""
        return self.params.datasheet.name

    @property
    def rated_voltage(self) -> float:
        """One-sided rated voltage U_r (V); the drive range is [-U_r, U_r]."""
        return self.params.rated_voltage

    @property
    def stroke_um(self) -> float:
        """Datasheet free deflection at U_r (um): the one-sided stroke."""
        return self.params.datasheet.free_deflection * 1e6

    def deflection_bound_um(self) -> float:
        """Proven bound of |true tip deflection| (um) for any drive within [-U_r, U_r] from rest.

        Peak-to-peak gain (L1 norm of the impulse response, u_eff -> y) times the largest
        effective voltage the hysteresis can produce.
        """
        u_eff_max = self.hysteresis.max_effective_voltage(self.rated_voltage)
        return self.discrete.impulse_l1_bound() * u_eff_max * 1e6

    def state_space_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Matrices (A, B, C, D) of the exact ZOH beam from u_eff (V) to tip deflection (um).

        ``x_t+1 = A x_t + B u_eff,t``, ``y_t = C x_t`` with the reduced discrete state of
        :class:`piezo_env.discrete.DiscreteBender` (D = 0: the deflection at the end of a sample
        depends on the voltages held before it). The same units as an identified ARX model.
        """
        return self.discrete.state_space_matrices()

    def state_space(self):
        """Discrete state space (python-control, sampling time ``dt``) of the linear beam.

        Input: the effective voltage u_eff (V) after the hysteresis; output: tip deflection
        (um). See :meth:`state_space_matrices`.
        """
        import control

        return control.ss(*self.state_space_matrices(), self.dt)

    def charge(self, voltage: float | np.ndarray, tip_rotation: float | np.ndarray):
        """Drive charge Q = C_p u + Gamma theta_tip (C) for voltage (V) and tip rotation (rad)."""
        return self.params.capacitance * voltage + self.params.piezo_moment * tip_rotation

    def static_state(self, voltage: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Rest state under a constant voltage (V) approached monotonically from 0 V.

        Returns (discrete LTI state, hysteresis state).
        """
        hyst = self.hysteresis.initial_state(voltage)
        _, u_eff = self.hysteresis.step(hyst, voltage)
        return self.discrete.static_state(float(u_eff)), hyst

    def simulate(self, voltage: np.ndarray, *, initial_voltage: float = 0.0) -> SimulationResult:
        """Noise-free response to a voltage sequence (V), one sample per ``dt``.

        Voltages beyond the drive range are clipped, as the amplifier would.
        """
        sim = BenderSimulator(self)
        sim.reset(initial_voltage)
        u = np.clip(np.asarray(voltage, dtype=float), -self.rated_voltage, self.rated_voltage)
        out = np.empty((len(u), 3))
        for i, v in enumerate(u):
            out[i] = sim.step(float(v))
        return SimulationResult(
            time=np.arange(1, len(u) + 1) * self.dt,
            voltage=u,
            effective_voltage=out[:, 1],
            deflection_um=out[:, 0] * 1e6,
            charge=out[:, 2],
        )


@dataclass(frozen=True)
class SimulationResult:
    """Noise-free simulation record; sample i is the state after applying voltage[i].

    Attributes
    ----------
    time : ndarray
        Time at the end of each sample (s).
    voltage : ndarray
        Applied (clipped) voltage (V).
    effective_voltage : ndarray
        Voltage after hysteresis (V).
    deflection_um : ndarray
        Tip deflection (um).
    charge : ndarray
        Drive charge (C).
    """

    time: np.ndarray
    voltage: np.ndarray
    effective_voltage: np.ndarray
    deflection_um: np.ndarray
    charge: np.ndarray


class BenderSimulator:
    """State of one bender, stepped in place.

    ``step(u)`` applies voltage u (V, already inside the drive range) for one sample and
    returns (tip deflection (m), effective voltage (V), charge (C)) at the end of the sample.
    """

    def __init__(self, model: PiezoBenderModel) -> None:
        self.model = model
        n = model.discrete.n_states
        self._matrix = model.discrete.square_step_matrix()
        self._n = n
        self._v = np.zeros(n + 2)
        self._w = np.zeros(n + 2)
        self._hyst = np.zeros(model.hysteresis.state_size)
        self._bouc_wen = model.hysteresis if isinstance(model.hysteresis, BoucWen) else None
        self._in_place = getattr(model.hysteresis, "step_inplace", None)
        self._c_p = model.params.capacitance
        self._gamma = model.params.piezo_moment
        self.deflection = 0.0
        self.tip_rotation = 0.0

    def reset(self, voltage: float = 0.0) -> None:
        """Put the bender at rest under a constant ``voltage`` (V)."""
        state, hyst = self.model.static_state(voltage)
        self._v[:] = 0.0
        self._v[: self._n] = state
        self._hyst = np.array(hyst, dtype=float)
        out = self.model.discrete.output_matrix @ state
        self.deflection, self.tip_rotation = float(out[0]), float(out[1])

    def step(self, u: float) -> tuple[float, float, float]:
        """Advance one sample under voltage u (V); returns (deflection m, u_eff V, charge C)."""
        if self._bouc_wen is not None:
            h, u_eff = self._bouc_wen.step_scalar(self._hyst[0], self._hyst[1], u)
            self._hyst[0] = u
            self._hyst[1] = h
        elif self._in_place is not None:
            u_eff = self._in_place(self._hyst, u)
        else:
            self._hyst, u_eff = self.model.hysteresis.step(self._hyst, u)
            u_eff = float(u_eff)
        v, w, n = self._v, self._w, self._n
        v[n] = u_eff
        np.dot(self._matrix, v, out=w)
        self.deflection = y = w.item(n)
        self.tip_rotation = theta = w.item(n + 1)
        self._v, self._w = w, v
        return y, u_eff, self._c_p * u + self._gamma * theta

    def charge(self, voltage: float) -> float:
        """Drive charge Q = C_p u + Gamma theta_tip (C) now under ``voltage`` (V)."""
        return self._c_p * voltage + self._gamma * self.tip_rotation

    @property
    def nodal_deflection(self) -> np.ndarray:
        """Nodal deflections (m), root first, from the modes carried as states."""
        return self.model.discrete.nodal_matrix @ self._v[: self._n]

    def get_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Copy of (LTI state, hysteresis state)."""
        return self._v[: self._n].copy(), self._hyst.copy()


class DriftingSimulator(BenderSimulator):
    """A bender whose piezoelectric coefficient and stiffness drift (:mod:`piezo_env.drift`).

    Steps like :class:`BenderSimulator` with the step matrix and Gamma of the current segment
    of ``plan`` (a :class:`piezo_env.drift.DriftPlan` of ``model``); ``reset`` starts the drift
    again at the rest state of its first segment (the ramp at that segment's midpoint).
    """

    def __init__(self, model: PiezoBenderModel, plan) -> None:
        super().__init__(model)
        self.plan = plan
        self._segment_steps = plan.segment_steps
        self._last = plan.n_segments - 1
        self._segment = 0
        self._count = 0

    def _enter(self, segment: int) -> None:
        self._segment = segment
        self._count = 0
        self._matrix = self.plan.square_matrices[segment]
        self._gamma = float(self.plan.piezo_moments[segment])

    def reset(self, voltage: float = 0.0) -> None:
        """At rest under ``voltage`` (V) with the first segment's parameters."""
        self._enter(0)
        hyst = self.model.hysteresis.initial_state(voltage)
        _, u_eff = self.model.hysteresis.step(hyst, voltage)
        m = self._matrix
        n = self._n
        a, b = m[:n, :n], m[:n, n]
        state = scipy.linalg.solve(np.eye(n) - a, b * float(u_eff))
        self._v[:] = 0.0
        self._v[:n] = state
        self._hyst = np.array(hyst, dtype=float)
        out = self.model.discrete.output_matrix @ state
        self.deflection, self.tip_rotation = float(out[0]), float(out[1])

    def step(self, u: float) -> tuple[float, float, float]:
        """Advance one sample under voltage u (V); returns (deflection m, u_eff V, charge C)."""
        result = super().step(u)
        self._count += 1
        if self._count == self._segment_steps and self._segment < self._last:
            self._enter(self._segment + 1)
        return result

    def charge(self, voltage: float) -> float:
        """Drive charge (C) now under ``voltage`` (V), with the current segment's Gamma."""
        return self._c_p * voltage + self._gamma * self.tip_rotation
