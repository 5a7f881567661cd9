"""Nonlinear MPC on the whole Hammerstein model: voltage is the decision variable.

Prediction over the horizon N from the observer's ``[x_t; d_t]`` (offset-free, see
:mod:`controllers.observer`) and the nonlinearity's memory state ``s_t``::

    z = Z(u; s_t)                               (nonlinearity unrolled, network inside)
    y_t+1..t+N = Phi x_t + Gamma z + d_t 1      (linear part, prediction matrices)

Cost and constraints over ``u = (u_t .. u_t+N-1)`` (V), targets r_t+1 .. r_t+N (um)::

    min  w sum_k (y_t+k - r_t+k)^2 + lambda sum_k (u_t+k - u_t+k-1)^2,   |u_t+k| <= u_max
                                                      (|u_t+k - u_t+k-1| <= S dt, slew limit)

**The bender's static gain** (``gain_tolerance``, :mod:`controllers.gain`): a bender bought to
the datasheet answers ``g`` times the model's deflection, g within
:data:`controllers.settings.LEARNED_GAIN_TOLERANCE`. The NMPC learns g from
the first sample, as the linear MPC does, and tracks the reference over g (it reads the
measurement and the preview over g: :meth:`NonlinearMPC._learn_gain`); nothing else changes.
Without it, the model's gain error is left to the output-disturbance observer, which follows a
reference-shaped error only as fast as it dares near the resonance
(``benchmarks/results/design_measurements.md`` measures both on the box's corners).

**Amplifier slew limit** (``task.slew_limit`` = S, V/s; :class:`controllers.task.ControlTask`).
The voltage is the decision variable here, so the limit is linear and exact on every move: the
first move's bounds are the window u_t-1 +- S dt within the drive range, and the later moves
get the rate rows |u_t+k - u_t+k-1| <= S dt (2N - 1 rows with the box, as the linear MPC's).
The plan is one the amplifier follows sample by sample, so the nonlinearity's memory, stepped
with the commanded voltage, is stepped with the voltage the plant receives. IPOPT gets the same
rows as constraints. Without a slew limit nothing changes.

Solvers
-------
``"rti"`` (real-time iteration, the default)
    Gauss-Newton SQP warm-started from the shifted previous plan: linearize ``z`` along the
    plan (``z ~ z_bar + J (u - u_bar)``), solve the box-constrained QP in u, repeat
    ``sqp_iterations`` times (stop early once a step moves no voltage by more than
    ``step_tolerance``). Two iterations are the default because one loses accuracy at input
    reversals, where the hysteresis features kink. The Jacobian comes from
    :class:`controllers.native.nmpc_horizon.StructuredHorizon` for the identified NLS (feature
    recursion in generated C called through ctypes, network batched in numpy, far cheaper than
    casadi's Jacobian of the unrolled horizon; :mod:`controllers.native.nmpc_horizon` says
    why) and from casadi's generic
    Jacobian for any other nonlinearity (the plant's hysteresis in the oracle). The QP is
    dense and small (N variables, the box as bounds): its solver's workspace
    (:func:`controllers.box_qp.box_qp`, DAQP by default, OSQP with ``qp_solver="osqp"``) is set
    up once per episode; each iteration updates P and q, after trying the unconstrained
    optimum (one N x N solve, exact when it meets every bound, which it does on smooth
    references). Two iterations are the default (one loses accuracy at input reversals);
    ``benchmarks/results/controller_latency.md`` has the step's cost. For the identified NLS
    with the observer bank the whole step (the estimators' updates, the iterations'
    linearizations, QP matrices and unconstrained optima, the memory step) runs as one
    compiled call (:mod:`controllers.native.nmpc_step`); where an iteration's optimum leaves
    the bounds, the QP solver runs here and a second call ends the step. Without a compiler
    the numpy path above runs, recorded in ``describe()["native"]["nmpc_step"]``.
``"ipopt"`` (the reference)
    The full nonlinear program through ``casadi.nlpsol("ipopt")`` with exact derivatives,
    warm-started from the shifted plan, capped by ``ipopt_max_iter`` and
    ``ipopt_max_cpu_time``.

A QP or NLP that fails or reaches its cap never stops the loop: the shifted previous plan is
applied (at the very first step that is the rest plan, i.e. the last voltage), counted in
``stats.fallbacks`` and ``stats.status``. When a later SQP iteration's QP fails, the last good
iterate is a plan of its own, not a fallback: it is applied and counted as :data:`KEPT`. The
observer, the condensed linear part and the start of an episode are the linear MPC's
(:mod:`controllers.predictive`). The per-step BLAS calls are small matrix products far
below OpenBLAS's threading threshold, so they run single-threaded without a thread limit.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controllers.box_qp import box_qp, solver_version, within
from controllers.mpc import float32_within
from controllers.native import nmpc_step
from controllers.native.codegen import NativeBuild
from controllers.native.nmpc_horizon import GenericHorizon, StructuredHorizon, horizon_function
from controllers.observer import ObserverBank
from controllers.prediction import IdentifiedNLS, PredictionModel, SteadyStart
from controllers.predictive import PredictiveController
from controllers.settings import (
    DISTURBANCE_STD,
    LEARNED_GAIN_TOLERANCE,
    PROCESS_STD,
    check_settings,
)

__all__ = ["KEPT", "NMPCSettings", "NonlinearMPC"]

KEPT = "kept-last-iterate"
"""Status of a step whose later SQP iteration failed: the previous iterate is applied."""

_SOLVERS = ("rti", "ipopt")
_JACOBIANS = ("auto", "structured", "structured-vm", "generic", "generic-vm")


@dataclass(frozen=True)
class NMPCSettings:
    """Settings of :class:`NonlinearMPC` (validated at construction).

    Attributes
    ----------
    horizon : int
        Prediction horizon N (samples).
    solver : str
        ``"rti"`` (SQP real-time iteration, one box QP per iteration) or ``"ipopt"`` (full
        solve, the reference).
    sqp_iterations : int
        Gauss-Newton QPs per step for ``"rti"`` (2: one loses at input reversals).
    step_tolerance : float
        Stop the SQP early when no voltage of the plan moved more than this (V).
    tracking_weight : float
        w, weight of the squared tracking error (1/um^2).
    rate_weight : float
        lambda, weight of the squared voltage rate (1/V^2): 1e-2 makes a 3 V move cost as much
        as 0.3 um of error, so the rate penalty only smooths noise.
    measurement_std : float or None
        Sensor noise standard deviation the observer assumes (um); None: noise bound /
        sqrt(3) (uniform noise), at least 0.05 um.
    observer, bank_memory, robust_bank : str, int, bool
        The observer, as :class:`controllers.mpc.MPCSettings`' (default: the bank, screened
        over the tolerance box with the linearised law).
    disturbance_std : float
        Random-walk step of the output disturbance of the fixed observer (um per sample): its
        speed.
    process_std : float
        Input-referred process noise of the fixed observer (equivalent V); with none the filter
        trusts the model near the resonance too much and a 150 Hz error builds up on a 50 Hz
        sine (``benchmarks/results/design_measurements.md``). The observer defaults are the
        linear MPC's.
    jacobian : str
        ``"auto"`` (structured for the identified NLS, else generic; generated C where a
        compiler works, the structured horizon's built on first use, since the compiled
        iteration does not use it), ``"structured"``, ``"structured-vm"`` (casadi's virtual
        machine, no compiler), ``"generic"``, ``"generic-vm"``.
    qp_solver : str
        ``"daqp"`` (default) or ``"osqp"``: the QP solver of ``"rti"``
        (:mod:`controllers.box_qp`).
    eps_abs, eps_rel : float
        OSQP tolerances (DAQP ends on an exact active set and takes none).
    max_qp_iterations : int
        The QP solver's iteration cap per QP; reaching it is a fallback. 1000, as the linear
        MPC's: chosen with a margin for OSQP on a step beyond the drive range
        (``benchmarks/results/design_measurements.md``); DAQP, one active-set change per
        iteration, needs far fewer (``solver_iterations_max`` in each episode,
        ``benchmarks/results/controller_latency.md``).
    shortcut : bool
        Try the unconstrained optimum of each QP first and skip the QP solver when it meets
        every bound (exact: see :mod:`controllers.box_qp`).
    ipopt_max_iter : int
        IPOPT iteration cap; reaching it is a fallback.
    ipopt_max_cpu_time : float
        IPOPT CPU-time cap per step (s); reaching it is a fallback.
    gain_tolerance : float
        Relative half-width w (-) of the plant's static gain around the model's, as
        :class:`controllers.mpc.MPCSettings`': the NMPC learns the gain inside [1 - w, 1 + w]
        from the first sample and tracks the reference over it (:meth:`NonlinearMPC._learn_gain`).
        0: predict with the model's gain.
    initial_voltage : float or None
        Voltage (V) the bender rests under at each reset, when it is known, as
        :class:`controllers.mpc.MPCSettings`' (None: estimated from the first measurement).
    """

    horizon: int = 20
    solver: str = "rti"
    sqp_iterations: int = 2
    step_tolerance: float = 1e-3
    tracking_weight: float = 1.0
    rate_weight: float = 1e-2
    measurement_std: float | None = None
    observer: str = "bank"
    bank_memory: int = 200
    robust_bank: bool = True
    disturbance_std: float = DISTURBANCE_STD
    process_std: float = PROCESS_STD
    jacobian: str = "auto"
    qp_solver: str = "daqp"
    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    max_qp_iterations: int = 1000
    shortcut: bool = True
    ipopt_max_iter: int = 100
    ipopt_max_cpu_time: float = 1.0
    gain_tolerance: float = LEARNED_GAIN_TOLERANCE
    initial_voltage: float | None = None

    def __post_init__(self) -> None:
        if self.solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {_SOLVERS}, got {self.solver!r}")
        if self.jacobian not in _JACOBIANS:
            raise ValueError(f"jacobian must be one of {_JACOBIANS}, got {self.jacobian!r}")
        check_settings(
            self,
            integers=("horizon", "sqp_iterations", "max_qp_iterations", "ipopt_max_iter"),
            non_negative=("rate_weight", "process_std", "step_tolerance", "gain_tolerance"),
            positive=(
                "tracking_weight",
                "disturbance_std",
                "eps_abs",
                "eps_rel",
                "ipopt_max_cpu_time",
            ),
        )


def make_horizon(
    model: PredictionModel, horizon: int, jacobian: str, *, defer: bool = False
) -> Any:
    """The horizon linearization (z and dz/du along a plan) chosen by ``jacobian``; ``defer``
    leaves the identified NLS's feature recursion uncompiled until its ``compile()``
    (:class:`controllers.native.nmpc_horizon.StructuredHorizon`)."""
    nonlinearity = model.nonlinearity
    structured_ok = isinstance(nonlinearity, IdentifiedNLS)
    if jacobian in ("structured", "structured-vm") and not structured_ok:
        raise ValueError(
            f"jacobian={jacobian!r} needs the identified NLS; this model's nonlinearity is "
            f"{type(nonlinearity).__name__}: use 'auto' or 'generic'"
        )
    compiled = not jacobian.endswith("-vm")
    if jacobian.startswith("structured") or (jacobian == "auto" and structured_ok):
        return StructuredHorizon(nonlinearity.nls, horizon, compiled=compiled, defer=defer)
    return GenericHorizon(nonlinearity, horizon, compiled=compiled)


class NonlinearMPC(PredictiveController):
    """Offset-free nonlinear MPC in the voltage (see the module docstring).

    ``NonlinearMPC(model, task, settings=None, *, name="nmpc")`` with :class:`NMPCSettings`; the
    parameters are :class:`controllers.predictive.PredictiveController`'s.
    """

    Settings = NMPCSettings
    name = "nmpc"

    # -- episode ------------------------------------------------------------------------------

    def _set_up(self) -> None:
        settings = self.settings
        self.horizon = make_horizon(self.model, settings.horizon, settings.jacobian, defer=True)
        if settings.solver == "ipopt":
            self._nlp = self._build_nlp()
        # The bounds live as long as the controller: the compiled iteration reads them.
        self._lower = np.full(settings.horizon, -self._u_max)
        self._upper = np.full(settings.horizon, self._u_max)
        self._kernel, self._kernel_build = self._iteration_kernel()
        self._gain = self._gain_estimate()
        self._reach = static_reach(self.model, self._u_max)
        self._fused_build = self._fused_record()
        if self._kernel is None and settings.solver == "rti":
            # The numpy path's iterations run the horizon: built here, not inside a step.
            # (ipopt builds its own NLP; the horizon then serves only predict_deflection().)
            self.horizon.compile()

    def _iteration_kernel(self) -> tuple[nmpc_step.IterationKernel | None, NativeBuild]:
        """The compiled iteration (:mod:`controllers.native.nmpc_step`) where this NMPC's
        step fits it, else None and the record of why the iterations run in numpy. Checked
        once here, so that the step validates nothing."""
        why = None
        if self.settings.solver != "rti":
            why = f"solver={self.settings.solver!r} (the kernel runs the real-time iteration)"
        elif not isinstance(self.horizon, StructuredHorizon):
            why = f"the horizon is {type(self.horizon).__name__} (the kernel needs the NLS's)"
        elif not self.horizon.compile_requested:
            why = f"jacobian={self.settings.jacobian!r} asks for casadi's virtual machine"
        if why is not None:
            return None, nmpc_step.unavailable(why)
        nls = self.model.nonlinearity.nls
        partials = nmpc_step.partials_function(nls)
        library, build = nmpc_step.compile_kernel(partials)
        if library is None:
            return None, build
        s = self.settings
        kernel = nmpc_step.IterationKernel(
            library,
            partials,
            nls.to_numpy(),
            self._gamma,
            self._rate_hessian,
            self._lower,
            self._upper,
            tracking_weight=s.tracking_weight,
            rate_weight=s.rate_weight,
            slew_step=self.task.slew_step,
            shortcut=s.shortcut,
            iterations=s.sqp_iterations,
            step_tolerance=s.step_tolerance,
            phi=self._phi,
            observation_size=self.task.observation_size,
        )
        return kernel, build

    def _fused_record(self) -> NativeBuild:
        """Whether the whole step runs as one compiled call (``nmpc_step`` of
        :mod:`controllers.native.nmpc_step`: the estimators' updates, the iterations while
        their optima meet the bounds, the memory step) and why not: it needs the compiled
        iteration, the observer bank and the gain estimate run by the compiled kernels.
        Without it the same compiled iteration runs between the estimators' Python calls (the
        same numbers, to the bit: ``tests/test_nmpc_speed.py``; a longer step)."""
        kernel, observer, gain = self._kernel, self.observer, self._gain
        why = None
        if kernel is None:
            why = "the iterations run in numpy (see nmpc_step)"
        elif not isinstance(observer, ObserverBank) or observer._correct_native is None:
            why = "the observer is not a bank run by the compiled kernels"
        elif gain is not None and gain._update_native is None:
            why = "the gain estimate is not run by the compiled kernels"
        if why is not None:
            return nmpc_step.unavailable(why, function="nmpc_fused")
        return dataclasses.replace(self._kernel_build, function="nmpc_fused")

    def _start(self, start: SteadyStart) -> None:
        s = self.settings
        self._slew_step = self.task.slew_step
        self._lower[:] = -self._u_max
        self._upper[:] = self._u_max
        if s.solver == "rti":  # afresh: no active set, step size or duals carry over episodes
            self._qp = box_qp(
                s.qp_solver,
                self._lower,
                self._upper,
                eps_abs=s.eps_abs,
                eps_rel=s.eps_rel,
                max_iter=s.max_qp_iterations,
                rate=self._slew_step,
            )
        self._plan = np.full(s.horizon, start.u)
        self._u_prev = float(np.float32(start.u))
        self._restart_gain(start.x)
        if self._fused_build.compiled:
            self._kernel.bind_estimators(
                self.observer, self._gain, u_max=self._u_max, reach=self._reach
            )

    def act(self, observation: Any) -> np.ndarray:
        """The base class's step (:meth:`controllers.predictive.PredictiveController.act`):
        one compiled call where the step fits it (:meth:`_fused_record`; on the samples whose
        iteration needs the QP, the QP solver runs here between two calls), else Python
        around the compiled iteration."""
        kernel = self._kernel
        if kernel is None or not kernel.fused:
            return super().act(observation)
        return self._act_compiled(observation, kernel.observation, self._runaway)

    def _runaway(self) -> float:
        """The observer bank's runaway sample as the compiled step last read it (< 0: none)."""
        return self._kernel.scalars[nmpc_step.S_RUNAWAY]

    def _act_fused(self, observation: np.ndarray) -> float:
        """:meth:`_act` by the compiled step; Python runs the QP where an iteration needs it."""
        kernel = self._kernel
        self._into_buffers(kernel.plan, kernel.memory)
        scalars = kernel.scalars
        scalars[nmpc_step.S_G], scalars[nmpc_step.S_U_PREV] = self._g, self._u_prev
        try:
            code = kernel.step()
        finally:  # the gain (and the bank's scale) moved before any error the kernel reports
            self._g = float(scalars[nmpc_step.S_G])
        if code == nmpc_step.NON_FINITE:
            self.task.check_observation(observation)  # raises, naming the entry
            raise RuntimeError(f"{self.name}: the compiled step found a non-finite observation")
        stats = self.stats
        if code == nmpc_step.INSIDE:
            stats.iterations.append(0)
            stats.status["unconstrained"] += 1
        else:  # NEED_QP: the iterations from the first that needs it, then the step's end
            shifted = kernel.shifted.copy()
            plan, status, iterations = self._rti_from(code, int(kernel.dims[nmpc_step.D_DONE]))
            stats.iterations.append(iterations)
            stats.status[status] += 1
            if plan is None:
                stats.fallbacks += 1
                plan = shifted
            kernel.plan[:] = plan
            kernel.finish()
        self._u_prev = u = float(scalars[nmpc_step.S_U_APPLIED])
        return u

    def _act(self, observation: np.ndarray) -> float:
        if self._gain is not None:
            observation = self._learn_gain(observation)
        low, high = self._reach
        reference = observation[1:]
        if reference.min() < low or reference.max() > high:  # the drive cannot hold it
            observation = np.concatenate((observation[:1], np.clip(reference, low, high)))
        estimate = self.observer.correct(float(observation[0]))
        if self._kernel is not None:
            low, high = self._slew_window()
            self._lower[0], self._upper[0] = low, high
            plan, status, iterations, shifted = self._solve_compiled(observation, estimate)
        else:
            n = self.model.n_states
            targets = self.task.targets(observation, self.settings.horizon)
            # Predicted error without the z contribution: y - r = offset + Gamma z.
            offset = self._phi @ estimate[:n] + (estimate[n] - targets)
            low, high = self._slew_window()
            self._lower[0], self._upper[0] = low, high
            shifted = self._feasible(np.concatenate((self._plan[1:], self._plan[-1:])))
            if self.settings.solver == "rti":
                plan, status, iterations = self._solve_rti(offset, shifted)
            else:
                plan, status, iterations = self._solve_nlp(estimate, targets, shifted)
        self.stats.iterations.append(iterations)
        self.stats.status[status] += 1
        if plan is None:
            self.stats.fallbacks += 1
            plan = shifted
        self._plan = plan
        # The plant gets float32 volts: step the memory and the observer with exactly those,
        # kept in the window (the QP meets it to rounding; float32 rounding may step out).
        u = float32_within(min(max(plan[0], low), high), low, high)
        if self._kernel is None:
            z, self._memory = self.model.nonlinearity.step(u, self._memory)
        else:  # the memory array is the kernel's, stepped in place
            self._kernel.plan[:] = plan
            z = self._kernel.apply(u)
        self.observer.predict(z)
        if self._gain is not None:
            self._gain.advance(z)
        self._u_prev = u
        return u

    def _learn_gain(self, observation: np.ndarray) -> np.ndarray:
        """Learn the gain g from the measurement and return the observation over g.

        The plant answers ``g G(z)`` where the model says ``G(z)`` (:mod:`controllers.gain`),
        so tracking r on it is tracking r / g on the model: the NMPC reads the measurement and
        the preview over g, and its horizon, its voltage bounds and slew limit, its memory and
        its plan stay as they are (the linear MPC folds g into its input z instead, which its
        QP plans in). When g changes, the observer's output estimate is carried to the new
        scale (:meth:`controllers.observer.ObserverBank.rescale_output`). While the credible
        set holds the model's gain, g is exactly 1 and the step is the one without learning,
        to the bit. The observer keeps the sensor's noise level in um, so over g its noise model
        is off by the factor g (within +-31 %), which the bank's noise levels,
        a grid of factors of 3, do not resolve."""
        gain = self._gain
        gain.update(float(observation[0]))
        g = float(gain.value[0])
        if g != self._g:
            self.observer.rescale_output(self._g / g)
            self._g = g
        return observation if g == 1.0 else observation / g

    def predict_deflection(
        self,
        u: np.ndarray,
        x: np.ndarray | None = None,
        disturbance: float = 0.0,
        state: np.ndarray | None = None,
    ) -> np.ndarray:
        """The model's prediction y_t+1 .. y_t+N (um) for the plan ``u`` (N,) (V), at the model's
        gain (the controller tracks the reference over its learned :attr:`gain`).

        Parameters
        ----------
        u : ndarray, shape (N,)
            Voltages u_t .. u_t+N-1 (V).
        x : ndarray, optional
            Linear state x_t (default: rest).
        disturbance : float
            Output disturbance d_t (um).
        state : ndarray, optional
            Memory state s_t of the nonlinearity (default: rest).
        """
        x = np.zeros(self.model.n_states) if x is None else np.asarray(x, float)
        state = self.model.nonlinearity.initial_state() if state is None else state
        z = self.horizon.evaluate(np.asarray(u, float), state)
        return self._phi @ x + self._gamma @ z + disturbance

    # -- real-time iteration ------------------------------------------------------------------

    def _solve_rti(
        self, offset: np.ndarray, u_bar: np.ndarray
    ) -> tuple[np.ndarray | None, str, int]:
        """Gauss-Newton SQP from ``u_bar``: (plan or None on failure, status, QP iterations).

        A QP that fails after the first iteration leaves the last good iterate as the plan
        (status ``kept-last-iterate``): it is a real SQP iterate, not a fallback.
        """
        s = self.settings
        bounds = (self._lower, self._upper)
        w, total, status = s.tracking_weight, 0, "solved"
        for iteration in range(s.sqp_iterations):
            z, jac_z = self.horizon.linearize(u_bar, self._memory)
            jac_y = self._gamma @ jac_z
            constant = offset + self._gamma @ z - jac_y @ u_bar
            hessian = w * (jac_y.T @ jac_y) + self._rate_hessian
            q = w * (jac_y.T @ constant)
            q[0] -= s.rate_weight * self._u_prev
            u_new, status, total, step = self._qp_iteration(
                hessian, q, u_bar, bounds, iteration, total
            )
            if step is None:
                return u_new, status, total
            u_bar = u_new
            if step <= s.step_tolerance:
                break
        return u_bar, status, total

    def _solve_compiled(
        self, observation: np.ndarray, estimate: np.ndarray
    ) -> tuple[np.ndarray | None, str, int, np.ndarray]:
        """The targets, the offset, the shifted plan and :meth:`_solve_rti` through the
        compiled iteration (:mod:`controllers.native.nmpc_step`): the iterations run in one
        call while their unconstrained optima meet the bounds, and the QP solver runs here
        from the first that needs it; (plan or None, status, QP iterations, shifted plan)."""
        kernel = self._kernel
        if self._memory is not kernel.memory:  # a new episode's memory, or the first step
            kernel.memory[:] = self._memory
            self._memory = kernel.memory
            kernel.plan[:] = self._plan
        kernel.observation[:] = observation
        kernel.estimate[:] = estimate[: kernel.estimate.size]
        kernel.scalars[nmpc_step.S_U_PREV] = self._u_prev
        kernel.prepare()
        shifted = kernel.u.copy()
        plan, status, iterations = self._rti_compiled()
        return plan, status, iterations, shifted

    def _rti_compiled(self) -> tuple[np.ndarray | None, str, int]:
        """:meth:`_solve_rti` on the kernel's offset from the plan in ``kernel.u``."""
        code, first = self._kernel.run()  # the iterations up to the first that needs the QP
        return self._rti_from(code, first)

    def _rti_from(self, code: int, first: int) -> tuple[np.ndarray | None, str, int]:
        """:meth:`_rti_compiled` after the kernel's iterations ended with ``code`` at
        iteration ``first`` (the plan or the iterate in ``kernel.u``)."""
        s, kernel = self.settings, self._kernel
        bounds = (self._lower, self._upper)
        if code == nmpc_step.INSIDE:
            return kernel.u.copy(), "unconstrained", 0
        u_bar = kernel.u.copy()
        total, status = 0, "solved"
        for iteration in range(first, s.sqp_iterations):
            if iteration > first:
                kernel.u[:] = u_bar
                code = kernel.iterate()
            if code == nmpc_step.INSIDE:
                u_new, status = kernel.u_new.copy(), "unconstrained"
                step = kernel.scalars[nmpc_step.S_STEP]
            else:  # copies: the next iteration overwrites the kernel's arrays
                u_new, status, total, step = self._qp_iteration(
                    kernel.hessian.copy(), kernel.q.copy(), u_bar, bounds, iteration, total
                )
                if step is None:
                    return u_new, status, total
            u_bar = u_new
            if step <= s.step_tolerance:
                break
        return u_bar, status, total

    def _qp_iteration(
        self,
        hessian: np.ndarray,
        q: np.ndarray,
        u_bar: np.ndarray,
        bounds: tuple[np.ndarray, np.ndarray],
        iteration: int,
        total: int,
    ) -> tuple[np.ndarray | None, str, int, float | None]:
        """SQP iteration ``iteration`` (from 0) through its QP along ``u_bar``: (new iterate,
        status, ``total`` plus the QP solver's iterations, largest move (V)).

        A failed QP ends the SQP, with the move None: the first iteration's failure is a
        refusal (plan None), a later one keeps ``u_bar`` (status ``kept-last-iterate``).
        """
        u_new, status, iterations = self._solve_qp(hessian, q, u_bar, bounds)
        total += iterations
        if u_new is None:
            return (None, status, total, None) if iteration == 0 else (u_bar, KEPT, total, None)
        return u_new, status, total, float(np.max(np.abs(u_new - u_bar)))

    def _solve_qp(
        self,
        hessian: np.ndarray,
        q: np.ndarray,
        u_bar: np.ndarray,
        bounds: tuple[np.ndarray, np.ndarray],
    ) -> tuple[np.ndarray | None, str, int]:
        """Box-constrained QP (rate rows with a slew limit): (solution or None, status, the
        QP solver's iterations).

        The unconstrained optimum is tried first: where it meets every bound it is the exact
        solution (:mod:`controllers.box_qp`; most steps on smooth references).
        """
        if self.settings.shortcut:
            try:
                u_new = -np.linalg.solve(hessian, q)
            except np.linalg.LinAlgError:  # dz/du = 0 somewhere and no rate weight
                u_new = None
            if u_new is not None and within(u_new, *bounds) and self._rates_within(u_new):
                return u_new, "unconstrained", 0
        # Zero duals: each SQP iteration's QP has a new Hessian, the last active set means
        # little.
        rows = u_bar.size if self._slew_step is None else 2 * u_bar.size - 1
        solution = self._qp.solve(
            q, self._feasible(u_bar), np.zeros(rows), hessian=hessian, bounds=bounds
        )
        return solution.x, solution.status, solution.iterations

    def _rates_within(self, plan: np.ndarray) -> bool:
        """The plan's later moves meet the slew limit (always True without one)."""
        if self._slew_step is None:
            return True
        return bool(np.all(np.abs(np.diff(plan)) <= self._slew_step))

    def _feasible(self, plan: np.ndarray) -> np.ndarray:
        """``plan`` made feasible: clipped to the bounds and, with a slew limit, each move
        limited to S dt from the one before (first move from u_t-1)."""
        plan = np.maximum(plan, self._lower)  # np.clip's values, without its dispatch cost
        np.minimum(plan, self._upper, out=plan)
        if self._slew_step is None:
            return plan
        step, previous = self._slew_step, self._u_prev
        for k in range(plan.size):
            previous = plan[k] = min(max(plan[k], previous - step), previous + step)
        return plan

    # -- IPOPT reference ------------------------------------------------------------------------

    def _build_nlp(self) -> Any:
        """casadi nlpsol('ipopt') of the full problem; parameters [x; d; s; r; u_prev]."""
        import casadi

        s, model = self.settings, self.model
        n_hor, n = s.horizon, model.n_states
        unrolled = horizon_function(model.nonlinearity, n_hor)
        n_mem = unrolled.size1_in(1)
        u = casadi.SX.sym("u", n_hor)
        p = casadi.SX.sym("p", n + 1 + n_mem + n_hor + 1)
        x, d = p[:n], p[n]
        memory, targets, u_prev = p[n + 1 : n + 1 + n_mem], p[n + 1 + n_mem : -1], p[-1]
        y = casadi.mtimes(casadi.DM(self._phi), x) + casadi.mtimes(
            casadi.DM(self._gamma), unrolled(u, memory)
        )
        error = y + d - targets
        rates = u - casadi.vertcat(u_prev, u[:-1])
        cost = s.tracking_weight * casadi.sumsqr(error) + s.rate_weight * casadi.sumsqr(rates)
        problem = {"x": u, "p": p, "f": cost}
        if self.task.slew_step is not None:
            problem["g"] = rates  # bounded by +-S dt in _solve_nlp
        options = {
            "ipopt.max_iter": s.ipopt_max_iter,
            "ipopt.max_cpu_time": s.ipopt_max_cpu_time,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
            "error_on_fail": False,
        }
        return casadi.nlpsol("nmpc_ipopt", "ipopt", problem, options)

    def _solve_nlp(
        self, estimate: np.ndarray, targets: np.ndarray, u_bar: np.ndarray
    ) -> tuple[np.ndarray | None, str, int]:
        """IPOPT from ``u_bar``: (plan or None on failure, status, iterations)."""
        params = np.concatenate([estimate, self._memory, targets, [self._u_prev]])
        limits = {}
        if self._slew_step is not None:
            limits = {"lbg": -self._slew_step, "ubg": self._slew_step}
        try:
            solution = self._nlp(x0=u_bar, p=params, lbx=-self._u_max, ubx=self._u_max, **limits)
        except RuntimeError as exc:  # casadi raises on evaluation errors inside the solver
            return None, f"error: {type(exc).__name__}", 0
        stats = self._nlp.stats()
        plan = np.asarray(solution["x"].full()).ravel()
        status = str(stats.get("return_status", "unknown"))
        iterations = int(stats.get("iter_count", 0))
        if not stats.get("success", False) or not np.all(np.isfinite(plan)):
            return None, status, iterations
        return np.clip(plan, -self._u_max, self._u_max), status, iterations

    # -- reports ------------------------------------------------------------------------------

    def native_code(self) -> dict[str, dict[str, Any]]:
        """The base class's records, ``nmpc_step``: whether the compiled iteration runs
        (:mod:`controllers.native.nmpc_step`), and why not, and ``nmpc_fused``: whether the
        whole step runs as one compiled call (:meth:`_fused_record`), and why not."""
        return {
            **super().native_code(),
            "nmpc_step": self._kernel_build.to_dict(),
            "nmpc_fused": self._fused_build.to_dict(),
        }

    def describe(self) -> dict[str, Any]:
        """Settings, model source, Jacobian path and observer bandwidth (JSON-safe)."""
        rti = self.settings.solver == "rti"
        solver = solver_version(self.settings.qp_solver) if rti else "ipopt (casadi)"
        slew = {}
        if self.task.slew_step is not None:
            slew = {"slew_limit_V_per_s": self.task.slew_limit}
        return {
            **slew,
            "name": self.name,
            "model": self.model.source,
            "settings": asdict(self.settings),
            "jacobian": f"{type(self.horizon).__name__}: {self.horizon.backend}",
            "solver": solver,
            "observer_slowest_pole_hz": self.observer.slowest_pole_hz(self.model.dt),
            "observer": self.observer_description(),
            "native": self.native_code(),
        }


def static_reach(model: Any, u_max: float) -> tuple[float, float]:
    """The deflections (um, the model's) the drive can hold: the linear part's static gain
    times the nonlinearity's output after a ramp from rest to each end of the drive range and
    a hold there (the top and the bottom of the major loop).

    :class:`NonlinearMPC` plans toward a reference clamped to it. Its finite horizon has no
    terminal cost, so a level beyond it, which no input holds, makes a swing through the
    first resonance look cheaper within the horizon than the held limit: unclamped, it switched
    between the drive's ends and rang the mode (``docs/controllers.md``). A reference within
    it is left as it is, to the bit."""
    gain = model.dc_gain
    ends = []
    for end in (-u_max, u_max):
        state = model.nonlinearity.initial_state()
        z = 0.0
        for u in np.r_[np.linspace(0.0, end, REACH_RAMP), np.full(REACH_RAMP, end)]:
            z, state = model.nonlinearity.step(float(u), state)
        ends.append(gain * z)
    return min(ends), max(ends)


REACH_RAMP = 200
"""Samples of :func:`static_reach`'s ramp and of its hold: a slow ramp and a hold long enough
for a memory feature to reach its level at the drive's end (every play and Bouc-Wen state of a
monotone input has, at the latest, when the input stops moving)."""
