"""Linear MPC in the hidden signal z, solved by OSQP, then the nonlinearity's inverse to volts.

The Hammerstein structure splits the problem. The linear part predicts the deflection from the
hidden signal z, so tracking is a convex QP in z over the horizon; the memory nonlinearity is
then inverted for the first move only (z -> volts, exact from the current memory state).

Prediction (x_t, d_t from :class:`controllers.observer.DisturbanceObserver`, offset-free)::

    y_t+k = C A^k x_t + sum_j<k C A^(k-1-j) B z_t+j + d_t = (Phi x_t + Gamma z + d_t 1)_k

QP over z = (z_t .. z_t+N-1), condensed (N variables, no equality constraints)::

    min  sum_k (y_t+k - r_t+k)^2 + lambda (z_t+k - z_t+k-1)^2
    s.t. z_lo(s_t) <= z_t <= z_hi(s_t),   z_min <= z_t+k <= z_max  (k >= 1)

The first move's bounds are exact: the z reachable in one sample from the current memory state
s_t over the drive range; later moves use the range of z over the drive range (the major loop).
The targets r_t+1 .. r_t+N come from the reference preview (the last previewed sample holds).

Implementation follows OSQP's documented MPC pattern: P and the constraint matrix are built and
factorised once in ``setup``; each step updates only q, l and u (one stacked matrix-vector
product gives q from [x; d; r; z_prev]) and warm-starts from the shifted previous plan. A
solver failure never stops the loop: the shifted previous plan (else the last z) is used and
counted in ``stats.fallbacks``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import osqp

from controllers.base import Controller
from controllers.box_qp import setup_box_qp
from controllers.observer import DisturbanceObserver
from controllers.prediction import PredictionModel
from controllers.settings import USABLE_OSQP_STATUS, check_settings
from controllers.task import ControlTask

__all__ = ["LinearMPC", "prediction_matrices"]


def qp_matrices(model: PredictionModel, settings: MPCSettings) -> tuple[np.ndarray, np.ndarray]:
    """Hessian P (N, N) and the matrix G with ``q = G [x; d (; s); r; z_prev]``, scaled.

    Scaled so that the largest Hessian entry is 1: OSQP's absolute tolerances then mean the
    same thing for any bender and unit (the minimiser does not change).
    """
    n_hor, lam = settings.horizon, settings.rate_weight
    phi, gamma = prediction_matrices(model.a, model.b, model.c, n_hor)
    diff = np.eye(n_hor) - np.eye(n_hor, k=-1)
    hessian = gamma.T @ gamma + lam * diff.T @ diff
    previous_move = np.zeros((n_hor, 1))  # the rate penalty's link to z_t-1
    previous_move[0, 0] = -lam
    columns = [gamma.T @ phi, gamma.T.sum(axis=1, keepdims=True)]
    if settings.slope_std > 0:  # d_t+k = d_t + k s_t
        columns.append(gamma.T @ np.arange(1.0, n_hor + 1)[:, None])
    scale = 1.0 / float(np.max(np.diag(hessian)))
    _check_well_posed(hessian * scale, float(gamma[0, 0]), lam)
    return hessian * scale, scale * np.hstack([*columns, -gamma.T, previous_move])


def _check_well_posed(hessian: np.ndarray, cb: float, rate_weight: float) -> None:
    """Raise ValueError when the QP has no unique minimiser (a singular Hessian).

    That happens when some move reaches no predicted output and nothing else weighs it: a
    model with C B = 0 (its output lags the input by two samples or more) and rate_weight = 0
    leaves the last move of the horizon free.
    """
    if np.linalg.cond(hessian) < 1e12:
        return
    raise ValueError(
        f"the MPC's QP is singular (rate_weight = {rate_weight:g}, the model's first Markov "
        f"parameter C B = {cb:.3g}): some moves reach no predicted output; set rate_weight > 0"
    )


def prediction_matrices(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, horizon: int
) -> tuple[np.ndarray, np.ndarray]:
    """Phi (N, n) and Gamma (N, N) with ``y_t+1..t+N = Phi x_t + Gamma z_t..t+N-1``."""
    n = a.shape[0]
    phi = np.empty((horizon, n))
    markov = np.empty(horizon)  # C A^k B, k = 0 .. N-1
    row = c[0].copy()
    for k in range(horizon):
        markov[k] = row @ b[:, 0]
        row = row @ a
        phi[k] = row
    gamma = np.zeros((horizon, horizon))
    for k in range(horizon):
        gamma[k, : k + 1] = markov[k::-1]
    return phi, gamma


@dataclass(frozen=True)
class MPCSettings:
    """Settings of :class:`LinearMPC`.

    Attributes
    ----------
    horizon : int
        Prediction horizon N (samples). Only the first few previewed samples matter for these
        plants; 20 covers the first resonance's period at 1 kHz many times over.
    rate_weight : float
        lambda, penalty of (z_t+k - z_t+k-1)^2 relative to 1 um^2 of tracking error
        ((um / equivalent V)^2). Smooths the input against noise; larger is gentler.
    measurement_std : float or None
        Sensor noise standard deviation (um) the observer assumes; None: noise bound / sqrt 3
        (uniform noise), at least 0.05 um.
    disturbance_std : float
        Random-walk step of the output disturbance (um per sample): the observer's speed (see
        :mod:`controllers.observer`).
    process_std : float
        Input-referred process noise of the observer (equivalent V). Without it the observer
        cannot correct the model's lightly damped resonance (its state would decay at the open
        loop's rate), and model error near the resonance (the 3rd harmonic of a 50 Hz
        reference) goes uncorrected.

    The defaults are one tuning for every plant: on the nominal PL140 every smooth reference
    stays at or below 0.05 % of the stroke, while a faster observer (disturbance_std 1-3) would
    gain on plants whose hysteresis differs from the model (Prandtl-Ishlinskii: 0.12 against
    0.14 % at 10 Hz) at the cost of the nominal 50 Hz sine (0.054-0.083 %), and a slower one
    (0.3) the reverse (0.20 % at 10 Hz on the Prandtl-Ishlinskii plant).
    slope_std : float
        0: the output disturbance is held constant over the horizon. > 0: it is modelled as
        drifting with an estimated slope (random walk of this step, um per sample^2) and
        extrapolated; see :class:`controllers.observer.DisturbanceObserver`.
    eps_abs, eps_rel : float
        OSQP tolerances.
    max_iter : int
        OSQP iteration cap; reaching it is a fallback.
    shortcut : bool
        Skip OSQP when the unconstrained optimum -P^-1 q satisfies every bound. That is exact,
        not an approximation: for a convex QP with box constraints, a point inside the box
        where the gradient vanishes meets the KKT conditions with no active constraint.
        Smooth references rarely touch the bounds, so most steps cost one matrix-vector
        product; OSQP (warm-started) solves the others.
    """

    horizon: int = 20
    rate_weight: float = 1e-2
    measurement_std: float | None = None
    disturbance_std: float = 0.8
    process_std: float = 0.04
    slope_std: float = 0.0
    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    max_iter: int = 1000
    shortcut: bool = True

    def __post_init__(self) -> None:
        check_settings(
            self,
            integers=("horizon", "max_iter"),
            non_negative=("rate_weight", "process_std", "slope_std"),
            positive=("disturbance_std", "eps_abs", "eps_rel"),
        )


class LinearMPC(Controller):
    """Offset-free linear MPC in z (OSQP) with the exact nonlinearity inverse to volts.

    Parameters
    ----------
    model : PredictionModel
        Identified Hammerstein model or the plant (oracle).
    task : ControlTask
        Sample time, drive range, preview layout.
    settings : MPCSettings
    name : str
        Name in reports.
    """

    Settings = MPCSettings

    def __init__(
        self,
        model: PredictionModel,
        task: ControlTask,
        settings: MPCSettings | None = None,
        *,
        name: str = "mpc",
    ) -> None:
        super().__init__(task)
        self.name = name
        self.model = model
        self.settings = settings = settings or MPCSettings()
        self._hessian, self._q_matrix = qp_matrices(model, settings)
        self._unconstrained = -np.linalg.solve(self._hessian, self._q_matrix)
        self._vector = np.zeros(self._q_matrix.shape[1])
        z_min, z_max = model.z_bounds
        self._lower = np.full(settings.horizon, z_min)
        self._upper = np.full(settings.horizon, z_max)
        self.observer = DisturbanceObserver.for_controller(model, task, settings)
        self._reset(None)

    def _setup_solver(self) -> osqp.OSQP:
        """OSQP set up (and factorised) afresh: no adapted step size or duals carry over."""
        s = self.settings
        return setup_box_qp(
            self._hessian,
            self._lower,
            self._upper,
            eps_abs=s.eps_abs,
            eps_rel=s.eps_rel,
            max_iter=s.max_iter,
        )

    def _reset(self, observation: np.ndarray | None) -> None:
        """Start from the steady state that holds the first measurement (rest at 0 V within
        the noise bound: :meth:`PredictionModel.steady_start`)."""
        y0 = 0.0 if observation is None else float(observation[0])
        start = self.model.steady_start(y0, self.task.noise_bound_um)
        self.observer.reset(np.r_[start.x, np.zeros(self.observer.n_disturbance)])
        self._solver = self._setup_solver()
        self._plan = np.full(self.settings.horizon, start.z)
        self._duals: np.ndarray | None = None
        self._z_prev = start.z
        self._memory = start.memory

    def _act(self, observation: np.ndarray) -> float:
        estimate = self.observer.correct(float(observation[0]))
        z_target = self._solve(estimate, self.task.targets(observation, self.settings.horizon))
        inverse = self.model.nonlinearity.inverse(z_target, self._memory)
        self.stats.inverse[inverse.status] += 1
        # The plant gets float32 volts; rounding moves u by at most 1e-6 V (at 30 V), within
        # the inverse's own tolerance, so the memory state and z of the inverse stand.
        u = float(np.float32(inverse.u))
        z, self._memory = inverse.z, inverse.state
        self.observer.predict(z)
        self._z_prev = z
        return u

    def _solve(self, estimate: np.ndarray, targets: np.ndarray) -> float:
        """First move z_t (equivalent V) of the QP for the estimate [x; d] and targets (um)."""
        n = estimate.size
        stacked = self._vector  # [x; d; r_t+1 .. r_t+N; z_t-1]: q = G stacked
        stacked[:n] = estimate
        stacked[n:-1] = targets
        stacked[-1] = self._z_prev
        low, high = self.model.nonlinearity.reachable(self._memory)
        self._lower[0], self._upper[0] = low, high
        if self.settings.shortcut:
            plan = self._unconstrained @ stacked
            if np.all(plan >= self._lower) and np.all(plan <= self._upper):
                self.stats.status["unconstrained"] += 1
                self.stats.iterations.append(0)
                self._plan = plan
                self._duals = None  # no bound is active: the optimal multipliers are zero
                return float(plan[0])
        self._solver.update(q=self._q_matrix @ stacked, l=self._lower, u=self._upper)
        shifted = np.r_[self._plan[1:], self._plan[-1]]
        duals = np.zeros(self.settings.horizon) if self._duals is None else self._duals
        self._solver.warm_start(x=np.clip(shifted, self._lower, self._upper), y=duals)
        result = self._solver.solve(raise_error=False)
        self.stats.iterations.append(int(result.info.iter))
        status = result.info.status
        self.stats.status[status] += 1
        if status in USABLE_OSQP_STATUS and np.all(np.isfinite(result.x)):
            self._plan = np.clip(result.x, self._lower, self._upper)
            self._duals = result.y
        else:
            self.stats.fallbacks += 1
            self._plan = np.clip(shifted, self._lower, self._upper)
        return float(self._plan[0])

    def describe(self) -> dict:
        """Settings, model source and observer speed (JSON-safe)."""
        return {
            "name": self.name,
            "model": self.model.source,
            "settings": asdict(self.settings),
            "z_bounds": list(self.model.z_bounds),
            "observer_slowest_pole_hz": self.observer.slowest_pole_hz(self.model.dt),
            "qp_solver": f"osqp {osqp.__version__}",
            "native": self.native_code(),
        }
