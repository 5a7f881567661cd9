"""Online estimation of an ARX model while it is used: two recursive estimators.

Both run on the regressors a controller already has, ``psi_t = [y_t-1 .. y_t-na, u_t-1 ..
u_t-nb]`` (for the Hammerstein model: measured deflection y in um and the hidden signal z the
controller's nonlinearity model produced, in equivalent V), both start from a prior model (the
offline estimate) and both forget, so that they follow a plant that differs from the prior or
changes while it runs.

:class:`SlidingWindowBayes` -- the paper's estimator on a sliding window
    The uniform-noise posterior of Pavelkova and Karny (2012) (the one
    :class:`identification.bayes_uniform.BayesUniformEstimator` approximates recursively) over the
    last ``window`` samples only: proportional to ``r^-W`` on the polytope
    ``{|y_tau - psi_tau^T theta| <= r, tau in window}``. Forgetting by a window is exact for this
    posterior (a datum older than the window simply stops constraining), where exponential
    forgetting has no exact form for a density with a bounded support. Its mode is the Chebyshev
    (L-infinity) fit over the window, an LP (HiGHS) solved when an estimate is asked for, not
    per sample: a sample costs one row written into a ring buffer. :meth:`contains` says exactly
    whether a model (the offline one, say) is still consistent with the window's data and a
    noise bound, and :meth:`parallelotope` gives the recursive estimator's parallelotope over the
    same window.

:class:`RecursiveLeastSquares` -- the textbook comparison
    RLS with exponential forgetting ``lambda`` (memory about ``1 / (1 - lambda)`` samples), in
    normalised regressor coordinates, with the covariance's trace held at or below its prior
    value so that it does not wind up when the data excite few directions (a single sine). One
    update is a few small matrix-vector products.

Which one a controller uses is its choice (:mod:`controllers.adaptive` measures both).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.optimize

from identification.arx import ARXModel
from piezo_env.checks import require_int

__all__ = ["RecursiveLeastSquares", "SlidingWindowBayes", "regressor_scales"]


def regressor_scales(model: ARXModel, input_scale: float) -> np.ndarray:
    """Typical magnitudes of the regressor entries: ``input_scale`` for inputs, times the
    model's DC gain for outputs (used to normalise; any positive values are valid).

    Parameters
    ----------
    model : ARXModel
        Gives the orders and the DC gain (output unit per input unit).
    input_scale : float
        Typical input magnitude (input unit), e.g. the drive range.
    """
    gain = abs(model.static_gain())
    output_scale = input_scale * (gain if math.isfinite(gain) and gain > 0 else 1.0)
    return np.concatenate([np.full(model.na, output_scale), np.full(model.nb, input_scale)])


class _Regressor:
    """The ARX regressor ``[y_t-1 .. y_t-na, u_t-1 .. u_t-nb]`` kept from the data stream."""

    def __init__(self, na: int, nb: int) -> None:
        self.na, self.nb = na, nb
        self.psi = np.zeros(na + nb)
        self.filled = 0

    @property
    def ready(self) -> bool:
        return self.filled >= max(self.na, self.nb)

    def push(self, u_t: float, y_t: float) -> None:
        """Shift in the sample (u_t, y_t): the regressor of y_t+1."""
        na, nb, psi = self.na, self.nb, self.psi
        if na:
            psi[1:na] = psi[: na - 1]
            psi[0] = y_t
        if nb:
            psi[na + 1 :] = psi[na : na + nb - 1]
            psi[na] = u_t
        self.filled += 1


def _check_sample(u_t: float, y_t: float) -> tuple[float, float]:
    u_t, y_t = float(u_t), float(y_t)
    if not (math.isfinite(u_t) and math.isfinite(y_t)):
        raise ValueError(f"non-finite sample u_t = {u_t}, y_t = {y_t}: pass finite numbers")
    return u_t, y_t


class RecursiveLeastSquares:
    """Recursive least squares with exponential forgetting, started from a prior ARX model.

    Parameters
    ----------
    prior : ARXModel
        Orders, starting estimate and units.
    scales : numpy.ndarray
        Typical magnitude of each regressor entry (:func:`regressor_scales`); the estimator
        works on ``psi / scales`` so that one prior variance fits every entry.
    forgetting : float
        lambda in (0, 1]; the memory is about ``1 / (1 - lambda)`` samples.
    prior_variance : float
        Initial covariance ``prior_variance * I`` of the normalised parameters (their
        confidence in the prior, relative to the output's variance in output unit^2 per
        scaled regressor). The covariance's trace never exceeds its initial value.

    Notes
    -----
    One :meth:`update` costs O(n^2) for n = na + nb parameters (a gain vector and a rank-one
    covariance update); the trace bound is one comparison.
    """

    def __init__(
        self,
        prior: ARXModel,
        scales: np.ndarray,
        *,
        forgetting: float = 0.998,
        prior_variance: float = 1.0,
    ) -> None:
        if not 0.0 < forgetting <= 1.0:
            raise ValueError(f"forgetting must lie in (0, 1], got {forgetting}")
        if not prior_variance > 0.0:
            raise ValueError(f"prior_variance must be > 0, got {prior_variance}")
        self.na, self.nb = prior.na, prior.nb
        self.dt = prior.dt
        self.scales = np.asarray(scales, dtype=np.float64).copy()
        if self.scales.shape != (self.na + self.nb,) or not np.all(self.scales > 0):
            raise ValueError(
                f"scales must be {self.na + self.nb} positive numbers, got {self.scales}"
            )
        self.forgetting = float(forgetting)
        self._theta = prior.theta * self.scales  # normalised parameters
        n = self._theta.size
        self._p = prior_variance * np.eye(n)
        self._trace_max = prior_variance * n
        self._regressor = _Regressor(self.na, self.nb)
        self._phi = np.zeros(n)
        self.nu = 0

    @property
    def theta(self) -> np.ndarray:
        """Current estimate ``[a, b]`` (data units)."""
        return self._theta / self.scales

    def restarted(self, prior: ARXModel) -> RecursiveLeastSquares:
        """A fresh estimator from the prior ``prior`` with this one's settings and its
        regressor (the data stream continues without a gap)."""
        fresh = RecursiveLeastSquares(
            prior,
            self.scales,
            forgetting=self.forgetting,
            prior_variance=self._trace_max / self._theta.size,
        )
        fresh._regressor.psi[:] = self._regressor.psi
        fresh._regressor.filled = self._regressor.filled
        return fresh

    def model(self) -> ARXModel:
        """The current estimate as an :class:`ARXModel` (noise bound 0: RLS estimates none)."""
        theta = self.theta
        return ARXModel(theta[: self.na], theta[self.na :], dt=self.dt, method="rls")

    def update(self, u_t: float, y_t: float) -> None:
        """Absorb the sample (u_t, y_t): y_t is explained by the regressor of earlier samples."""
        u_t, y_t = _check_sample(u_t, y_t)
        regressor = self._regressor
        if regressor.ready:
            phi = np.divide(regressor.psi, self.scales, out=self._phi)
            p_phi = self._p @ phi
            lam = self.forgetting
            gain = p_phi / (lam + phi @ p_phi)
            self._theta += gain * (y_t - phi @ self._theta)
            p = self._p - np.outer(gain, p_phi)
            # Forget only while the covariance stays within its prior size (no wind-up).
            if np.trace(p) / lam <= self._trace_max:
                p /= lam
            self._p = 0.5 * (p + p.T)
            self.nu += 1
        regressor.push(u_t, y_t)


class SlidingWindowBayes:
    """The uniform-noise Bayesian posterior of an ARX model over a sliding window.

    Parameters
    ----------
    na, nb : int
        ARX orders.
    window : int
        Number of most recent data the posterior is built from (>= 2 (na + nb + 1)).
    dt : float
        Sampling period (s), passed on to the models.

    Notes
    -----
    The posterior over the window is ``r^-W`` on the polytope of the window's slabs
    ``-1 <= D_tau^T K <= 1`` with ``K = [theta; 1] / r`` and ``D_tau = [-psi_tau; y_tau]``; its
    mode maximises ``K_n = 1 / r``: the Chebyshev fit of the window (:meth:`estimate`, one
    HiGHS LP with ``2 W`` rows and ``na + nb + 1`` columns). Per sample, :meth:`update` only
    stores the datum.
    """

    def __init__(self, na: int, nb: int, *, window: int = 300, dt: float = 1.0) -> None:
        self.na = require_int("na", na, minimum=0)
        self.nb = require_int("nb", nb)
        self.n = self.na + self.nb + 1
        self.window = require_int("window", window, minimum=2 * self.n)
        self.dt = float(dt)
        self._rows = np.zeros((self.window, self.n))
        self._inputs = np.zeros(self.window)
        self._outputs = np.zeros(self.window)
        self._count = 0
        self._regressor = _Regressor(self.na, self.nb)

    @property
    def full(self) -> bool:
        """True once the window holds ``window`` data."""
        return self._count >= self.window

    @property
    def size(self) -> int:
        """Number of data in the window."""
        return min(self._count, self.window)

    def update(self, u_t: float, y_t: float) -> None:
        """Store the sample (u_t, y_t) (the oldest datum leaves a full window)."""
        u_t, y_t = _check_sample(u_t, y_t)
        regressor = self._regressor
        if regressor.ready:
            row = self._rows[self._count % self.window]
            row[:-1] = -regressor.psi
            row[-1] = y_t
            self._inputs[self._count % self.window] = u_t
            self._outputs[self._count % self.window] = y_t
            self._count += 1
        regressor.push(u_t, y_t)

    def data(self) -> np.ndarray:
        """The window's data vectors ``D = [-psi; y]``, oldest first, shape (size, n)."""
        if self._count < self.window:
            return self._rows[: self._count].copy()
        start = self._count % self.window
        return np.concatenate([self._rows[start:], self._rows[:start]])

    def estimate(self) -> ARXModel | None:
        """The posterior mode over the window (Chebyshev fit), or None before the window is
        full or when the LP finds no bounded mode (data not exciting enough)."""
        if not self.full:
            return None
        rows = self.data()
        scale = np.max(np.abs(rows), axis=0)
        scale[scale == 0.0] = 1.0
        normalised = rows / scale
        objective = np.zeros(self.n)
        objective[-1] = -1.0
        bounds = [(None, None)] * (self.n - 1) + [(0.0, None)]
        result = scipy.optimize.linprog(
            objective,
            A_ub=np.concatenate([normalised, -normalised]),
            b_ub=np.ones(2 * self.window),
            bounds=bounds,
            method="highs",
        )
        if result.status != 0 or not result.x[-1] > 0.0:
            return None
        k = result.x / scale
        theta = k[:-1] / k[-1]
        return ARXModel(
            theta[: self.na],
            theta[self.na :],
            noise_bound=1.0 / k[-1],
            dt=self.dt,
            method="bayes-uniform-window",
        )

    def contains(self, model: ARXModel, noise_bound: float) -> bool:
        """True if ``(theta, r)`` of ``model`` with ``r = noise_bound`` lies in the window's
        exact posterior support: every residual of the window within +-noise_bound."""
        if not self._count:
            return True
        theta = np.concatenate([model.theta, [1.0]])
        return bool(np.max(np.abs(self.data() @ theta)) <= noise_bound)

    def parallelotope(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(V, l, u)`` of the recursive estimator run over the window's data (normalised
        units, see :attr:`identification.bayes_uniform.BayesUniformEstimator.parallelotope`)."""
        from identification.bayes_uniform import BayesUniformEstimator

        if not self.full:
            raise RuntimeError(
                f"the window holds {self._count} of {self.window} data: update it further"
            )
        start = self._count % self.window
        u = np.concatenate([self._inputs[start:], self._inputs[:start]])
        y = np.concatenate([self._outputs[start:], self._outputs[:start]])
        estimator = BayesUniformEstimator(self.na, self.nb, record_history=False, dt=self.dt)
        estimator.update_many(u, y)
        return estimator.parallelotope

    def describe(self) -> dict[str, Any]:
        """Settings (JSON-safe)."""
        return {"estimator": "bayes-uniform-window", "window": self.window}
