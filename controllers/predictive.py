"""What the linear and the nonlinear MPC share: model, settings, observer, prediction, start.

Both predict the deflection over the horizon with the condensed linear part
(:mod:`controllers.condensed`), estimate ``[x; d]`` with the offset-free observer
(:mod:`controllers.observer`), penalise the rate of their plan (z for
:class:`controllers.mpc.LinearMPC`, volts for :class:`controllers.nmpc.NonlinearMPC`), and
start each episode from the model's steady state that holds the first measurement:

- within the sensor noise bound, rest at 0 V (the measurement is noise);
- beyond it (an env reset with ``initial_voltage``), the linear state holding y_0 and the
  nonlinearity's memory after the voltage that holds it (:meth:`PredictionModel.steady_start`).

A subclass builds its solver in :meth:`PredictiveController._set_up` and sets its plan from the
start in :meth:`PredictiveController._start`.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from controllers.base import Controller
from controllers.condensed import (
    check_well_posed,
    prediction_matrices,
    qp_matrices,
    rate_hessian,
)
from controllers.loop import feedback_law, modulus_margins
from controllers.observer import ObserverBank, make_observer
from controllers.prediction import PredictionModel, SteadyStart
from controllers.task import ControlTask

__all__ = ["PredictiveController"]


class PredictiveController(Controller):
    """Base of the MPCs (see the module docstring).

    Parameters
    ----------
    model : PredictionModel
        Identified Hammerstein model or the plant (oracle).
    task : ControlTask
        Sample time, drive range, preview layout.
    settings
        The subclass's ``Settings`` (default: its defaults). Has ``horizon``, ``rate_weight``
        and the observer's fields; ``tracking_weight`` if the cost weighs the error.
    name : str, optional
        Name in reports (default: the class's).

    Raises
    ------
    ValueError
        When the QP would be singular (:func:`controllers.condensed.check_well_posed`).
    """

    Settings: ClassVar[type]

    def __init__(
        self,
        model: PredictionModel,
        task: ControlTask,
        settings: Any | None = None,
        *,
        name: str | None = None,
    ) -> None:
        super().__init__(task)
        if name is not None:
            self.name = name
        self.model = model
        self.settings = settings = settings or self.Settings()
        n_hor = settings.horizon
        self._phi, self._gamma = prediction_matrices(model.a, model.b, model.c, n_hor)
        self._rate_hessian = rate_hessian(n_hor, settings.rate_weight)
        weight = getattr(settings, "tracking_weight", 1.0)  # the linear MPC weighs error by 1
        check_well_posed(self._gamma, settings.rate_weight, weight, name=self.name)
        self.observer = make_observer(model, task, settings)
        self._set_up()
        self._reset(None)

    def _reset(self, observation: np.ndarray | None) -> None:
        y0 = 0.0 if observation is None else float(observation[0])
        start = self.model.steady_start(y0, self.task.noise_bound_um)
        # d starts at 0 even when y0 lies beyond the model's reach (the voltage holding it
        # clipped): the part left unexplained is then mostly that one sample's noise, and
        # starting d there made the first 50 steps worse, not better (measured on the plant
        # at 30 V: 0.66-1.19 um against 0.52-0.90 um).
        self.observer.reset(np.r_[start.x, np.zeros(self.observer.n_disturbance)])
        self._memory = start.memory
        self._start(start)

    def act(self, observation: Any) -> np.ndarray:
        """The base class's step, and the step at which the observer bank's runaway guard fell
        back, recorded in :attr:`stats` (``observer_fallback_step``)."""
        action = super().act(observation)
        stats = self.stats
        if stats.observer_fallback_step is None:
            if getattr(self.observer, "runaway_at", None) is not None:
                stats.observer_fallback_step = len(stats.compute_s) - 1
        return action

    def feedback_law(self) -> tuple[np.ndarray, float]:
        """``(k_e, k_z)``: the unconstrained first move's gains on the observer's estimate and
        on the previous move (:func:`controllers.loop.feedback_law`).

        For the nonlinear MPC this is its law linearised at unit slope of the nonlinearity
        (dz/du = 1, the network's small-signal gain on the identification data): the tracking
        weight w and the rate penalty in volts then act as the linear MPC's with
        ``rate_weight / w``. Where the slope m differs (along a major loop, or the oracle's
        hysteresis, which has no unit-gain convention) its rate penalty in z is
        ``rate_weight / (w m^2)``, so its reported margin is an approximation.

        Returns
        -------
        k_e : numpy.ndarray
            Gains on ``[x; d (; s)]`` (equivalent V per um; per um/sample for s).
        k_z : float
            Gain on z_t-1 (dimensionless).
        """
        hessian, q_matrix = self._qp_matrices(self._phi, self._gamma)
        return feedback_law(hessian, q_matrix, self.observer.n + self.observer.n_disturbance)

    def _qp_matrices(self, phi: np.ndarray, gamma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The settings' QP (:func:`controllers.condensed.qp_matrices`) on the condensed
        prediction ``(phi, gamma)``: the rate penalty over the tracking weight (1 for the linear
        MPC), and the disturbance slope when ``slope_std`` > 0."""
        s = self.settings
        weight = getattr(s, "tracking_weight", 1.0)
        slope = getattr(s, "slope_std", 0.0) > 0
        return qp_matrices(phi, gamma, s.rate_weight / weight, slope=slope)

    def observer_description(self) -> dict[str, Any]:
        """Modulus margin of the loop this controller closes around its own model, unconstrained
        (:mod:`controllers.loop`): the single filter's, or the bank's range over its filters and
        its prior filter's (JSON-safe; dimensionless, 0 when that loop is unstable)."""
        observer = self.observer
        bank = isinstance(observer, ObserverBank)
        margins = modulus_margins(
            observer.a_aug,
            observer.b_aug,
            observer.c_aug,
            observer.gains if bank else observer.gain,
            *self.feedback_law(),
            n=observer.n,
        )
        if not bank:
            return {"modulus_margin": float(margins[0])}
        return {
            "modulus_margin_range": [float(margins.min()), float(margins.max())],
            "modulus_margin_prior": float(margins[observer.prior]),
            "riccati_fallbacks": int(observer.riccati_fallbacks),
        }

    def _set_up(self) -> None:
        """Build what stays fixed over episodes (called once, before the first reset)."""
        raise NotImplementedError

    def _start(self, start: SteadyStart) -> None:
        """Set the plan and the solver for an episode that starts at ``start``."""
        raise NotImplementedError
