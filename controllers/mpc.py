"""Linear MPC in the hidden signal z (a dense box QP), then the nonlinearity's inverse to volts.

The Hammerstein structure splits the problem. The linear part predicts the deflection from the
hidden signal z, so tracking is a convex QP in z over the horizon; the memory nonlinearity is
then inverted for the first move only (z -> volts, exact from the current memory state).

Prediction (x_t, d_t from :class:`controllers.observer.DisturbanceObserver`, offset-free)::

    y_t+k = C A^k x_t + sum_j<k C A^(k-1-j) B z_t+j + d_t = (Phi x_t + Gamma z + d_t 1)_k

QP over z = (z_t .. z_t+N-1), condensed (N variables, no equality constraints)::

    min  sum_k (y_t+k - r_t+k)^2 + lambda (z_t+k - z_t+k-1)^2
    s.t. z_lo(s_t) <= z_t <= z_hi(s_t),   z_min <= z_t+k <= z_max  (k >= 1)

The first move's bounds are exact: the z reachable in one sample from the current memory state
s_t over the drive range; later moves use the range of z over the drive range on slow triangles
from rest (the major loop and both first branches, :attr:`PredictionModel.z_bounds`).
The targets r_t+1 .. r_t+N come from the reference preview (the last previewed sample holds).

**Amplifier slew limit** (``task.slew_limit`` = S, V/s, a datasheet value read from the env,
:class:`controllers.task.ControlTask`). The voltage may change by at most S dt per sample
(less 1e-5 V for the float32 action). The first move stays exact: its bounds are the z reachable
from s_t over the voltages [u_t-1 - S dt, u_t-1 + S dt] within the drive range (the map is
increasing, so they are its values at the two ends), and the voltage the inverse returns is
kept in that window. Later moves get rate constraints in z, |z_t+k - z_t+k-1| <= m S dt
(k >= 1), with m the smallest one-sample secant slope dz/du of the nonlinearity found along a
full-stroke triangle driven at the slew limit, right after its reversals included (where a
hysteresis map is flattest). For a rate-independent map, re-applying u_t+k-1 leaves z
unchanged, so a z step of at most m S dt needs a voltage step of at most S dt wherever the
slope is at least m: the constraint is an inner approximation, sound on the states that
triangle visits, and the plan stays one the amplifier can follow. The QP then has 2N - 1
constraint rows ([I; D], D the first differences) instead of the box; without a slew limit
nothing changes (the same box QP, bitwise).

The QP solver's workspace (:func:`controllers.box_qp.box_qp`; DAQP by default, OSQP with
``qp_solver="osqp"``) is set up, P factorised, once per episode; each step updates only q and
the bounds (one stacked matrix-vector product gives q from [x; d; r; z_prev]) and warm-starts
(DAQP from the last active set, OSQP from the shifted previous plan). A solver failure never
stops the loop: the shifted previous plan (else the last z) is used and counted in
``stats.fallbacks``. Phi, Gamma, the rate penalty and the start of an episode (the steady state
holding the first measurement) are the nonlinear MPC's too: :mod:`controllers.predictive`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controllers.box_qp import DAQP_STATUS, BoxQP, box_qp, solver_version, within
from controllers.drive import DriveEstimate, slope_range
from controllers.native import daqp_box, fused_step
from controllers.native.codegen import NativeBuild
from controllers.native.compiled_inverse import STATUS_NAMES, CompiledInverse, MixedMap
from controllers.observer import ObserverBank
from controllers.prediction import SteadyStart
from controllers.predictive import PredictiveController
from controllers.settings import (
    DISTURBANCE_STD,
    LEARNED_GAIN_TOLERANCE,
    PROCESS_STD,
    check_settings,
)
from controllers.tolerance_box import RESONANCE_TOLERANCE
from identification.correction import first_mode_pole
from piezo_env.checks import require_int

__all__ = ["LONGEST_PERIOD_S", "LinearMPC", "MPCSettings", "covering_samples", "smallest_slope"]


@dataclass(frozen=True)
class MPCSettings:
    """Settings of :class:`LinearMPC`.

    Attributes
    ----------
    horizon : int
        Moves M of the plan (the QP's variables). Only the first few previewed samples matter
        for these plants.
    prediction_horizon : int, "resonance" or None
        Samples Np the output is predicted over (>= ``horizon``), the M moves blocked over them
        (:func:`controllers.condensed.move_blocks`). None (the default): Np = M, no blocking.
        ``"resonance"``: :func:`covering_samples`, one period of the slowest first resonance
        the datasheet allows (at least M: 79 samples on the PL140 at 0.1 ms, M on every
        catalogue bender at its default sample time). The targets beyond the preview are held,
        so a prediction longer than the benchmark's 20-sample preview tracks held targets and
        costs the nominal references accuracy; with a preview as long as the prediction, the
        blocked prediction gains on the box's corners but still costs the nominal 100 Hz sine
        (PL140 at 0.1 ms: ``benchmarks/results/design_measurements.md``).
        So the default predicts as far as the benchmark's preview reaches.
    rate_weight : float
        lambda, penalty of (z_t+k - z_t+k-1)^2 relative to 1 um^2 of tracking error
        ((um / equivalent V)^2). Smooths the input against noise; larger is gentler, and
        more robust to a resonance the model misplaces. The default is the choice of the
        tuning procedure over the datasheet's tolerance box (:mod:`benchmarks.tuning`, its
        scores and sweep in ``benchmarks/results/tuning.md``).
    measurement_std : float or None
        Sensor noise standard deviation (um) the observer assumes; None: noise bound / sqrt 3
        (uniform noise), at least 0.05 um.
    observer : str
        ``"bank"`` (default): a bank of steady-state Kalman filters under a grid of noise levels
        scaled by the sensor noise, and the estimate of the one whose innovations are the most
        likely over the last ``bank_memory`` samples
        (:class:`controllers.observer.ObserverBank`); ``disturbance_std`` and ``process_std``
        are then unused. ``"fixed"``: one filter with those two noise levels.
    bank_memory : int
        Samples over which the bank's likelihoods are averaged.
    disturbance_std : float
        Random-walk step of the output disturbance (um per sample) of the fixed observer: its
        speed (see :mod:`controllers.observer`).
    process_std : float
        Input-referred process noise of the fixed observer (equivalent V). Without it the observer
        cannot correct the model's lightly damped resonance (its state would decay at the open
        loop's rate), and model error near the resonance (the 3rd harmonic of a 50 Hz
        reference) goes uncorrected.

    The fixed observer's defaults are one tuning for every plant: a faster observer (a larger
    disturbance_std) gains on plants whose hysteresis differs from the model at the cost of
    the nominal plant's 50 Hz sine, and a slower one the reverse
    (``benchmarks/results/design_measurements.md``). The bank takes each point where the data
    say it pays.
    slope_std : float
        0: the output disturbance is held constant over the horizon. > 0: it is modelled as
        drifting with an estimated slope (random walk of this step, um per sample^2) and
        extrapolated; see :class:`controllers.observer.DisturbanceObserver`.
    qp_solver : str
        ``"daqp"`` (default: dense dual active set, exact active set) or ``"osqp"``
        (:mod:`controllers.box_qp`); their solve times on this QP are in
        ``benchmarks/results/controller_latency.md``.
    eps_abs, eps_rel : float
        OSQP tolerances (DAQP ends on an exact active set and takes none).
    max_iter : int
        The QP solver's iteration cap; reaching it is a fallback.
    shortcut : bool
        Skip the QP solver when the unconstrained optimum -P^-1 q satisfies every bound:
        exact, not an approximation (see :mod:`controllers.box_qp`). Smooth references rarely
        touch the bounds, so most steps cost one matrix-vector product; the QP solver
        (warm-started) solves the others.
    gain_tolerance : float
        Relative half-width w (-) of the plant's static gain around the model's: the MPC
        learns the gain inside [1 - w, 1 + w] from the first sample and predicts with the
        point of its 95 % credible set nearest the model's (:mod:`controllers.gain`). Default:
        :data:`controllers.settings.LEARNED_GAIN_TOLERANCE`, the datasheet's +-20 % on the free
        deflection with what its +-30 % on the hysteresis strength does to the gain. 0:
        predict with the model's gain.
    strength_tolerance : float
        Relative half-width r (-) of the bender's hysteresis strength around the model's, in
        [0, 1). > 0: the MPC learns the drive ``theta_z z + theta_u u`` (the gain and the
        strength, :mod:`controllers.drive`) instead of the gain alone, plans in it and inverts
        the mixed map (identified models only); 0 (the default): the gain alone.
    robust_bank : bool
        Let the observer bank select only the filters whose loop is stable on every vertex of
        the datasheet's tolerance box and within :data:`controllers.settings.MS_MAX` on the
        model (:func:`controllers.predictive.screen_bank`); identified models only (the
        oracle's model is the plant).
    initial_voltage : float or None
        Voltage (V) the bender rests under at each reset, when it is known (an env reset with
        ``initial_voltage``; within the drive range): the episode starts from the model at rest
        under it, so that the first move's slew window is the amplifier's. None (the default):
        estimated from the first measurement (:meth:`controllers.prediction.PredictionModel.
        steady_start`: 0 V within the sensor's noise).
    """

    horizon: int = 20
    prediction_horizon: int | str | None = None
    rate_weight: float = 0.3
    measurement_std: float | None = None
    observer: str = "bank"
    bank_memory: int = 200
    disturbance_std: float = DISTURBANCE_STD
    process_std: float = PROCESS_STD
    slope_std: float = 0.0
    qp_solver: str = "daqp"
    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    max_iter: int = 1000
    shortcut: bool = True
    gain_tolerance: float = LEARNED_GAIN_TOLERANCE
    strength_tolerance: float = 0.0
    robust_bank: bool = True
    initial_voltage: float | None = None

    def __post_init__(self) -> None:
        check_settings(
            self,
            integers=("horizon", "max_iter"),
            non_negative=(
                "rate_weight",
                "process_std",
                "slope_std",
                "gain_tolerance",
                "strength_tolerance",
            ),
            positive=("disturbance_std", "eps_abs", "eps_rel"),
        )
        if not self.strength_tolerance < 1.0:
            raise ValueError(
                f"strength_tolerance must be < 1 (a relative half-width), got "
                f"{self.strength_tolerance!r}"
            )
        if self.strength_tolerance > 0 and self.gain_tolerance == 0:
            raise ValueError(
                "strength_tolerance > 0 learns the drive with its gain: give gain_tolerance "
                "> 0 too, or strength_tolerance=0"
            )
        value = self.prediction_horizon
        if value is not None and value != "resonance":
            require_int("prediction_horizon", value)
            if value < self.horizon:
                raise ValueError(
                    f"prediction_horizon must be at least horizon ({self.horizon} moves), got "
                    f"{value}; or None (= horizon) or 'resonance' (one period of the first "
                    "resonance)"
                )


class LinearMPC(PredictiveController):
    """Offset-free linear MPC in z (a dense box QP) with the exact nonlinearity inverse to volts.

    ``LinearMPC(model, task, settings=None, *, name="mpc")`` with :class:`MPCSettings`; the
    parameters are :class:`controllers.predictive.PredictiveController`'s.
    """

    Settings = MPCSettings
    name = "mpc"
    _selects = False  # whether _select runs between the gain's update and its use

    def _prediction_samples(self, model: Any, settings: MPCSettings) -> int:
        if settings.prediction_horizon is None:
            return settings.horizon
        if settings.prediction_horizon == "resonance":
            return covering_samples(model.a, model.dt, settings.horizon)
        return settings.prediction_horizon

    def _set_up(self) -> None:
        settings = self.settings
        self._hessian, self._q_matrix = self._qp_matrices(self._phi, self._gamma)
        self._unconstrained = unconstrained_law(self._hessian, self._q_matrix)
        self._vector = np.zeros(self._q_matrix.shape[1])
        z_min, z_max = self.model.z_bounds
        self._lower = np.full(settings.horizon, z_min)
        self._upper = np.full(settings.horizon, z_max)
        self._slew_step = self.task.slew_step
        self._n_rows = settings.horizon
        self._gain = self._gain_estimate()
        if self._slew_step is not None:
            self.z_rate = self._slew_step * smallest_slope(self.model.nonlinearity, self._slew_step)
            self._n_rows = 2 * settings.horizon - 1
        self._mix = self._mixed_inverse()
        self._fused, self._fused_build = self._fused_step()

    def _mixed_inverse(self) -> CompiledInverse | None:
        """The inverse of the mixed drive ``theta_z z + theta_u u`` where the strength is
        learned (:class:`controllers.native.compiled_inverse.MixedMap`, generated C; its
        parameters set at each change of the drive), else None."""
        if not isinstance(self._gain, DriveEstimate):
            return None
        nls = getattr(self.model.nonlinearity, "nls", None)
        if nls is None:
            raise ValueError(
                f"{self.name}: strength_tolerance > 0 learns the hysteresis strength of an "
                f"identified model's network; the {self.model.source} model has none (pass "
                "strength_tolerance=0)"
            )
        if self._gain._a.shape[1] != self.observer.n:
            raise RuntimeError(f"{self.name}: the drive's linear parts and the observer differ")
        # The drive's rate g z_rate + b S dt >= g (z_rate + ratio_low S dt) on the box.
        if self._slew_step is not None and not (
            self.z_rate + self._gain.ratio_bounds[0] * self._slew_step > 0
        ):
            raise ValueError(
                f"{self.name}: at the slew step {self._slew_step:.3g} V the map's smallest "
                f"slope ({self.z_rate / self._slew_step:.3g}) leaves the drive's rate bound not "
                "positive on the strength's box; lower strength_tolerance"
            )
        return CompiledInverse(MixedMap(nls), self.model.nonlinearity.u_range)

    def _fused_step(self) -> tuple[fused_step.FusedStep | None, NativeBuild]:
        """The compiled step (:mod:`controllers.native.fused_step`) where this MPC's step fits
        it, else None and the record of why the step runs in numpy and Python. Checked once
        here, so that the step itself validates nothing but the observation."""
        why = None
        observer, gain = self.observer, self._gain
        if not isinstance(observer, ObserverBank) or observer._correct_native is None:
            why = "the observer is not a bank run by the compiled kernels"
        elif gain is not None and gain._update_native is None:
            why = "the gain estimate is not run by the compiled kernels"
        elif getattr(self.model.nonlinearity, "_inverse", None) is None:
            why = f"the nonlinearity ({self.model.source}) has no compiled inverse"
        if why is not None:
            return None, fused_step.unavailable(why)
        # A learned drive inverts the mixed map (its parameters are the drive's).
        compiled = self.model.nonlinearity._inverse if self._mix is None else self._mix
        library, build = fused_step.compile_step(compiled)
        if library is None:
            return None, build
        inverse, reachable = compiled.functions
        m = observer.n + observer.n_disturbance
        sizes = {
            "observation": self.task.observation_size,
            "states": observer.n,
            "estimate": m,
            "moves": self._unconstrained.shape[0],
            "samples": self.prediction_samples,
            "columns": self._vector.size,
            "memory": self.model.nonlinearity.initial_state().size,
            "shortcut": int(self.settings.shortcut),
            "selects": int(self._selects),
            "members": 0 if gain is None else gain.size,
        }
        if sizes["columns"] != m + sizes["samples"] + 1 or sizes["moves"] != self._lower.size:
            raise RuntimeError(f"{self.name}: the QP's sizes do not match the fused step's")
        slew = None if self._slew_step is None else (self._slew_step, self._u_max, self.z_rate)
        fused = fused_step.FusedStep(
            library,
            inverse,
            reachable,
            self.model.nonlinearity.u_range,
            compiled.map.parameters,
            sizes,
            slew,
        )
        return fused, build

    def _bind_fused(self) -> None:
        """Point the compiled step at the gain estimate's arrays and at the model in use
        (:meth:`_bind_fused_model`)."""
        fused = self._fused
        if fused is None:
            return
        fused.bind_gain(self._gain, self._member)
        # Called at an episode's start only (from _start, after _duals is reset): mid-episode
        # the step's own scalar holds the warm start (see _count_qp).
        fused.scalars[fused_step.S_DUALS_ANY] = 0.0 if self._duals is None else self._duals.any()
        self._bind_fused_model()

    def _bind_fused_model(self) -> None:
        """Point the compiled step at the model in use: its observer bank, plan matrix and z
        bounds, and its member of the gain estimate (:meth:`_fused_addresses`)."""
        fused = self._fused
        fused.bind_addresses(self._fused_addresses())
        fused.bind_qp(getattr(self, "_qp", None))
        fused.dims[fused_step.D_MEMBER] = self._member
        scalars = fused.scalars
        scalars[fused_step.S_Z_MIN], scalars[fused_step.S_Z_MAX] = self.model.z_bounds

    def _fused_addresses(self) -> np.ndarray:
        """The compiled step's table entries of the model in use
        (:meth:`controllers.native.fused_step.FusedStep.bank_addresses`)."""
        return self._fused.bank_addresses(
            self.observer,
            self._unconstrained,
            self._vector,
            self._lower,
            self._upper,
            self._q_matrix,
        )

    def _setup_solver(self, hessian: np.ndarray | None = None) -> BoxQP:
        """The QP solver's workspace set up (and P factorised) afresh for ``hessian`` (default:
        the model's in use): no active set, step size or duals carry over."""
        s = self.settings
        return box_qp(
            s.qp_solver,
            self._lower,
            self._upper,
            hessian=self._hessian if hessian is None else hessian,
            eps_abs=s.eps_abs,
            eps_rel=s.eps_rel,
            max_iter=s.max_iter,
            rate=None if self._slew_step is None else self.z_rate,
        )

    def _start(self, start: SteadyStart) -> None:
        self._qp = self._setup_solver()
        self._later_bounds: tuple | None = None
        self._plan = np.full(self.settings.horizon, start.z)
        self._duals: np.ndarray | None = None
        self._z_prev = start.z  # the model's input (g z, equivalent V)
        self._z_applied = start.z  # the nonlinearity's output (equivalent V)
        self._u_prev = float(np.float32(start.u))
        self._u_applied = start.u  # the voltage the nonlinearity's memory last took (V)
        self._restart_gain(start.x, start.u)
        self._b = 0.0  # the drive's theta_u (V^-1 equivalent V; 0 without a drive estimate)
        if self._mix is not None:
            self._mix.set_parameters((1.0, 0.0))
        self._bind_fused()

    def _update_gain(self, y: float) -> None:
        """Learn the gain from the measurement y (um) and predict with its new value."""
        if self._gain is None:
            return
        self._gain.update(y)
        self._select()
        if self._mix is not None:
            gain, member = self._gain, self._member
            self._set_drive(float(gain.theta_z[member]), float(gain.theta_u[member]))
        else:
            self._set_gain(float(self._gain.value[self._member]))

    def _select(self) -> None:
        """Choose the linear part to predict with (one here: see the adaptive MPC)."""

    def _set_gain(self, g: float) -> None:
        """Predict with gain g from now on: carry the plan, the last input and the observer's
        state to the new input scale g z."""
        if g == self._g:
            return
        ratio = g / self._g
        self.observer.rescale_input(ratio)
        self._plan = self._plan * ratio
        self._z_prev *= ratio
        self._g = g
        if self._slew_step is not None:
            self._qp.set_rate(self._rate())

    def _set_drive(self, a: float, b: float) -> None:
        """Predict with the drive ``a z + b u`` from now on (:mod:`controllers.drive`): the
        observer's states move by the change of the model's states for the inputs applied
        since the episode's start (its output estimate kept), the plan scales with a, and the
        last input is the new drive of the last voltage."""
        if a == self._g and b == self._b:
            return
        xz, xu = self._gain.states(self._member)
        self.observer.shift_input((a - self._g) * xz + (b - self._b) * xu)
        self._plan = self._plan * (a / self._g)
        self._g, self._b = a, b
        self._z_prev = a * self._z_applied + b * self._u_applied
        self._mix.set_parameters((a, b))
        if self._slew_step is not None:
            self._qp.set_rate(self._rate())

    def _rate(self) -> float:
        """The change per sample of the model's input that the slew limit allows at least
        (equivalent V; slew limit only): g z_rate, and with a learned drive g z + b u the
        map's smallest slope times g, plus b, times the slew step (b is 0 without one;
        positive on the drive estimate's box, :class:`controllers.drive.DriveEstimate`)."""
        return self._g * self.z_rate + self._b * self._slew_step

    def act(self, observation: Any) -> np.ndarray:
        """The base class's step (:meth:`controllers.base.Controller.act`): one compiled call
        where the step fits it (:mod:`controllers.native.fused_step`, ``describe()["native"]
        ["mpc_step"]`` says whether), else numpy and Python."""
        fused = self._fused
        if fused is None:
            return super().act(observation)
        return self._act_compiled(observation, fused.observation, self._runaway)

    def _runaway(self) -> float:
        """The observer bank's runaway sample as the compiled step last read it (< 0: none)."""
        return self._fused.scalars[fused_step.S_RUNAWAY]

    def _act_fused(self, observation: np.ndarray) -> float:
        """:meth:`_act` by the compiled step; Python runs what leaves it (the QP, the numpy
        inverse)."""
        fused = self._fused
        scalars = fused.scalars
        self._fused_in()
        code = fused.step()
        if code == fused_step.NEED_SELECT:
            self._select()
            self._fused_in()
            code = fused.solve()
        if code == fused_step.NON_FINITE:
            self.task.check_observation(observation)  # raises, naming the entry
            raise RuntimeError(f"{self.name}: the compiled step found a non-finite observation")
        g, b = scalars[fused_step.S_G], scalars[fused_step.S_B]  # b stays 0 without a drive
        if g != self._g or b != self._b:
            self._g, self._b = g, b
            if self._mix is not None:
                self._mix.set_parameters((g, b))
            if self._slew_step is not None:  # the rate rows of a QP run here
                self._qp.set_rate(self._rate())
        self._z_prev = scalars[fused_step.S_Z_PREV]
        stats = self.stats
        if code == fused_step.NEED_QP:
            scalars[fused_step.S_Z_MODEL] = self._solve_constrained(self._vector)
            self._fused_in()
            code = fused.finish()
        elif scalars[fused_step.S_QP_RAN]:  # the compiled step solved the QP
            self._count_qp(scalars)
        elif code != fused_step.ERROR:
            stats.status["unconstrained"] += 1
            stats.iterations.append(0)
            self._duals = None  # no bound is active: the optimal multipliers are zero
        if code == fused_step.DONE:
            stats.inverse[STATUS_NAMES[int(scalars[fused_step.S_INVERSE_STATUS])]] += 1
            self._z_applied = scalars[fused_step.S_Z_APPLIED]
            if self._mix is not None:
                self._u_applied = scalars[fused_step.S_U_APPLIED]
            self._z_prev = scalars[fused_step.S_Z_PREV]
            self._u_prev = scalars[fused_step.S_U_PREV]  # u itself with a slew limit
            return scalars[fused_step.S_U]
        if code == fused_step.NEED_INVERSE:
            return self._convert(scalars[fused_step.S_Z_MODEL])
        raise RuntimeError(f"{self.name}: the compiled step's generated inverse returned an error")

    def _count_qp(self, scalars: Any) -> None:
        """Count a QP the compiled step solved, as :meth:`_solve_constrained` counts its own.

        Its plan stays in the step's buffer (``self._plan`` is it) and its warm start in the
        step's scalars (``S_DUALS_ANY``) and the workspace (whether the last solve failed):
        while a C workspace is bound, ``self._duals`` is not kept, and nothing reads it (only
        :meth:`_solve_constrained`, which does not run then, and :meth:`_bind_fused` at an
        episode's start, where both are reset)."""
        stats = self.stats
        stats.iterations.append(int(scalars[fused_step.S_QP_ITERATIONS]))
        flag = int(scalars[fused_step.S_QP_FLAG])
        stats.status[DAQP_STATUS.get(flag) or f"exit flag {flag}"] += 1
        if scalars[fused_step.S_QP_RAN] == 2.0:
            stats.fallbacks += 1

    def _fused_in(self) -> None:
        """The plan, the memory and the scalars Python may have replaced, into the compiled
        step's buffers (the attributes then are those buffers)."""
        fused = self._fused
        self._into_buffers(fused.plan, fused.memory)
        scalars = fused.scalars
        scalars[fused_step.S_G], scalars[fused_step.S_Z_PREV] = self._g, self._z_prev
        scalars[fused_step.S_U_PREV] = self._u_prev
        scalars[fused_step.S_Z_APPLIED] = self._z_applied
        if self._mix is not None:
            scalars[fused_step.S_B], scalars[fused_step.S_U_APPLIED] = self._b, self._u_applied
            fused.inverse_inputs[5][:] = fused.reach_inputs[3][:] = (self._g, self._b)

    def _act(self, observation: np.ndarray) -> float:
        y = float(observation[0])
        self._update_gain(y)
        estimate = self.observer.correct(y)
        return self._convert(
            self._solve(estimate, self.task.targets(observation, self.prediction_samples))
        )

    def _convert(self, z_model: float) -> float:
        """The first move of the model's input (g z, or with a learned drive g z + b u;
        equivalent V) to volts, kept inside the slew window where there is one, and the time
        updates with the z the nonlinearity produced."""
        if self._mix is None:
            inverse = self.model.nonlinearity.inverse(z_model / self._g, self._memory)
            z = inverse.z
        else:  # the mixed map's inverse; its z less b u over g is the network's own
            inverse = self._mix.solve(z_model, self._memory)
            z = (inverse.z - self._b * inverse.u) / self._g
        self.stats.inverse[inverse.status] += 1
        # The plant gets float32 volts; rounding moves u by at most 1e-6 V (at 30 V), within
        # the inverse's own tolerance, so the memory state and z of the inverse stand.
        u = float(np.float32(inverse.u))
        memory = inverse.state
        if self._slew_step is not None:
            low, high = self._slew_window()
            if not low <= u <= high:  # the inverse's tolerance or float32 rounding at an edge
                u = float32_within(min(max(u, low), high), low, high)
                z, memory = self.model.nonlinearity.step(u, self._memory)
                self.stats.inverse["slew-window"] += 1
            self._u_prev = u
        self._memory = memory
        self._applied(z, u)
        return u

    def _applied(self, z: float, u: float | None = None) -> None:
        """Time updates with the hidden signal z the nonlinearity produced (equivalent V) and,
        with a learned drive, the voltage u (V) that produced it."""
        self._z_applied = z
        if self._mix is not None:
            self._gain.advance(z, u)
            self._u_applied = u
            self._z_prev = self._g * z + self._b * u
        else:
            if self._gain is not None:
                self._gain.advance(z)
            self._z_prev = self._g * z
        self.observer.predict(self._z_prev)

    def _solve(self, estimate: np.ndarray, targets: np.ndarray) -> float:
        """First move of the model's input g z_t (equivalent V) of the QP for the estimate
        [x; d] and targets (um); the bounds are the nonlinearity's times the gain g."""
        n = estimate.size
        stacked = self._vector  # [x; d; r_t+1 .. r_t+N; z_t-1]: q = G stacked
        stacked[:n] = estimate
        stacked[n:-1] = targets
        stacked[-1] = self._z_prev
        g = self._g
        if self._mix is not None:
            self._drive_bounds()
        else:
            if self._slew_step is None:
                low, high = self.model.nonlinearity.reachable(self._memory)
            else:
                low, high = self._reachable_in_window()
            bounds = (g, self.model.z_bounds)
            if bounds != self._later_bounds:  # the later moves' bounds change with g only
                z_min, z_max = bounds[1]
                self._lower[1:], self._upper[1:] = g * z_min, g * z_max
                self._later_bounds = bounds
            self._lower[0], self._upper[0] = g * low, g * high
        if self.settings.shortcut:
            plan = self._unconstrained @ stacked
            if within(plan, self._lower, self._upper) and self._rates_within(plan):
                self.stats.status["unconstrained"] += 1
                self.stats.iterations.append(0)
                self._plan = plan
                self._duals = None  # no bound is active: the optimal multipliers are zero
                return float(plan[0])
        return self._solve_constrained(stacked)

    def _drive_bounds(self) -> None:
        """The QP's bounds with a learned drive ``a z + b u``: the first move's the mixed
        map's reachable range (in the slew window where there is one), the later ones' the
        drive at z's bounds and the drive range's ends (z's bounds are taken at the range's
        ends, on the major loop and the first branches)."""
        g, b = self._g, self._b
        low, high = self._mix.reachable(self._memory, self._slew_window())
        bounds = (g, b, self.model.z_bounds)
        if bounds != self._later_bounds:
            (z_min, z_max), u_max = self.model.z_bounds, self._u_max
            ends = sorted((g * z_min - b * u_max, g * z_max + b * u_max))
            self._lower[1:], self._upper[1:] = ends
            self._later_bounds = bounds
        self._lower[0], self._upper[0] = low, high

    def _solve_constrained(self, stacked: np.ndarray) -> float:
        """The QP's first move g z_t (equivalent V) for the vector ``stacked`` and the bounds
        set by :meth:`_solve`, warm-started from the shifted plan."""
        shifted = np.clip(np.r_[self._plan[1:], self._plan[-1]], self._lower, self._upper)
        duals = np.zeros(self._n_rows) if self._duals is None else self._duals
        solution = self._qp.solve(
            self._q_matrix @ stacked, shifted, duals, bounds=(self._lower, self._upper)
        )
        self.stats.iterations.append(solution.iterations)
        self.stats.status[solution.status] += 1
        if solution.x is None:
            self.stats.fallbacks += 1
            self._plan = shifted
        else:
            self._plan, self._duals = solution.x, solution.duals
        return float(self._plan[0])

    def _reachable_in_window(self) -> tuple[float, float]:
        """z reachable this sample (equivalent V): the map at the slew window's two ends (the
        generated reachable range where the nonlinearity has one: the compiled step's)."""
        low, high = self._slew_window()
        compiled = getattr(self.model.nonlinearity, "_inverse", None)
        if compiled is not None:
            return compiled.reachable(self._memory, (low, high))
        step = self.model.nonlinearity.step
        z_low, z_high = step(low, self._memory)[0], step(high, self._memory)[0]
        return (z_low, z_high) if z_low <= z_high else (z_high, z_low)

    def _rates_within(self, plan: np.ndarray) -> bool:
        """The plan's later moves meet the z rate constraints (always True without a slew
        limit)."""
        if self._slew_step is None:
            return True
        return bool(np.all(np.abs(np.diff(plan)) <= self._rate()))

    def native_code(self) -> dict[str, dict[str, Any]]:
        """The base class's records, ``mpc_step``: whether the compiled step runs
        (:mod:`controllers.native.fused_step`), and why not, and with DAQP ``daqp_box_qp``:
        whether its QP's DAQP workspace is driven from C (:mod:`controllers.native.daqp_box`),
        and why not. Both compiled: the QP is solved inside the step; only the second (a
        fixed observer, say): the C workspace is called from Python, one call per QP."""
        records = {**super().native_code(), "mpc_step": self._fused_build.to_dict()}
        if self._mix is not None:  # the learned drive's inverse (controllers.drive)
            records.update({f"mixed_{b.function}": b.to_dict() for b in self._mix.native})
        if self.settings.qp_solver == "daqp":
            records["daqp_box_qp"] = daqp_box.build_record().to_dict()
        return records

    def describe(self) -> dict:
        """Settings, model source and observer speed (JSON-safe)."""
        slew = {}
        if self._slew_step is not None:
            slew = {"slew_limit_V_per_s": self.task.slew_limit, "z_rate_per_sample": self.z_rate}
        return {
            **slew,
            "name": self.name,
            "model": self.model.source,
            "settings": asdict(self.settings),
            "prediction_samples": self.prediction_samples,
            "move_blocks": list(self.blocks),
            "z_bounds": list(self.model.z_bounds),
            "observer_slowest_pole_hz": self.observer.slowest_pole_hz(self.model.dt),
            "observer": self.observer_description(),
            "qp_solver": solver_version(self.settings.qp_solver),
            "native": self.native_code(),
        }


def unconstrained_law(hessian: np.ndarray, q_matrix: np.ndarray) -> np.ndarray:
    """``-P^-1 G`` (C-contiguous: the compiled step reads it row by row): the unconstrained
    plan is this times the QP's stacked vector."""
    return np.ascontiguousarray(-np.linalg.solve(hessian, q_matrix))


LONGEST_PERIOD_S = 0.1
"""Longest first-mode period :func:`covering_samples` accepts (s): 10 Hz, more than ten times
below the lowest first resonance the catalogue's datasheets allow (the PL140's 160 Hz less its
20 % tolerance, 128 Hz)."""


def covering_samples(a: np.ndarray, dt: float, moves: int) -> int:
    """Samples covering one period of the slowest first resonance the datasheet allows, and at
    least ``moves``.

    The first bending mode is the model's :func:`identification.correction.first_mode_pole`,
    at ``f = |ln p| / (2 pi dt)``; the datasheet allows a bender whose first
    resonance is :data:`controllers.tolerance_box.RESONANCE_TOLERANCE` lower, whose period is
    ``1 / (f (1 - s))``. A prediction that sees one whole period of the ringing it must damp
    is what lets a plan damp it rather than excite it; at the catalogue's default sample times
    (a resonance at most a quarter of the sampling rate) that is fewer than 20 samples, at
    0.1 ms on the PL140 79. Without a complex pole: ``moves``. (What it buys and costs:
    :class:`MPCSettings`' ``prediction_horizon``.)

    Raises
    ------
    ValueError
        If that period exceeds :data:`LONGEST_PERIOD_S`: no catalogue bender's first mode is
        that slow (the slowest, the PL140's, is at 160 Hz), so the pole is not a bending
        mode, and the prediction would be that many samples long.

    Parameters
    ----------
    a : numpy.ndarray
        The linear part's state matrix (n, n).
    dt : float
        Sample time (s).
    moves : int
        The plan's moves M.
    """
    pole = first_mode_pole(np.linalg.eigvals(a))
    if pole is None:
        return moves
    slowest_hz = abs(np.log(pole)) / (2.0 * math.pi * dt) * (1.0 - RESONANCE_TOLERANCE)
    if 1.0 / slowest_hz > LONGEST_PERIOD_S:
        raise ValueError(
            f"the model's slowest complex mode is at {slowest_hz:.3g} Hz (datasheet's low end), "
            f"a period over {LONGEST_PERIOD_S:g} s: not a bending mode; give "
            "prediction_horizon as a number of samples instead of 'resonance'"
        )
    return max(moves, math.ceil(1.0 / (slowest_hz * dt)))


def float32_within(u: float, low: float, high: float) -> float:
    """``u`` (V, inside ``[low, high]``) rounded to the float32 the plant receives, kept inside
    the window: rounding that steps out is replaced by the next float32 towards the inside
    (one float32 step, 2e-6 V at 30 V, within the window whenever it is wider than that).

    The window's ends are compared as float32 too, explicitly: numpy's own promotion of a
    float32 against a Python float differs between numpy 1 (float64) and 2 (float32, NEP 50),
    and the compiled steps compare in float32. So a voltage may pass the window's edge by up
    to half a float32 step (1e-6 V at 30 V), far inside the slew margin
    :data:`controllers.task.SLEW_MARGIN_V`."""
    rounded = np.float32(u)
    if rounded > np.float32(high):
        rounded = np.nextafter(rounded, np.float32(-np.inf))
    elif rounded < np.float32(low):
        rounded = np.nextafter(rounded, np.float32(np.inf))
    return float(rounded)


def smallest_slope(nonlinearity: Any, step: float, legs: int = 3) -> float:
    """Smallest one-sample secant slope dz/du of ``nonlinearity`` at voltage steps ``step`` (V).

    Drives a full-stroke triangle (0 -> u_max -> u_min -> ..., ``legs`` legs) at ``step`` per
    sample and, at every sample, evaluates the secants to u +- step (within the drive range)
    from the state there, right after each reversal included, where a hysteresis map is
    flattest. The MPC's z rate constraint m S dt uses it (module docstring).

    Raises
    ------
    ValueError
        If a slope is not positive (the map is not increasing: no slew constraint in z).
    """
    return slope_range(nonlinearity, step, legs)[0]
