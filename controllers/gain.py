"""The bender's static gain, learned from the first sample: a credible set inside the datasheet's.

A bender bought to a datasheet differs from the nominal one mostly by a factor on its gain: the
free deflection (deflection per volt) is specified to +-20 %, and at the frequencies a tracking
reference lives at (well below the first resonance) a stiffer or softer, better or worse damped
bender looks, to first order, like the nominal one times a number. A model-based controller
that predicts with the nominal gain leaves the error ``(g - 1) y_ref`` to its output
disturbance, which follows a reference-shaped error only as fast as its observer, and a faster
observer excites the resonance it inverts. Knowing ``g`` instead makes the same prediction right.

The model. The controller applies the hidden signal z (its nonlinearity's output); the nominal
linear part driven by it from the episode's start gives ``s_t`` (um), and the plant answers::

    y_t = g s_t + e_t,     g in [1 - w, 1 + w]   (w: the datasheet's relative tolerance)

where ``e_t`` holds the sensor noise and what the model gets wrong besides the gain. The
estimate is the Bayesian one for a Gaussian prior on g (uniform over the datasheet interval:
mean 1, variance ``w^2 / 3``) and Gaussian ``e_t`` of unknown variance, which is estimated from
the a-priori residuals ``y_t - g_hat s_t`` (floored at the sensor noise's variance)::

    precision_t = 3 / w^2 + sum s_tau^2 / sigma_t^2
    g_hat_t = (3 / w^2 + sum s_tau y_tau / sigma_t^2) / precision_t

Each sample costs a few multiply-adds (three running sums): the work per step is bounded.

The credible set is ``g_hat +- z_975 / sqrt(precision)`` (95 %) intersected with the datasheet
interval. The controller predicts with the point of that set nearest to the nominal gain 1:
while the data do not contradict the nominal model (1 lies in the set) nothing changes, so a
nominal bender is controlled exactly as before; when they do, the model moves by no more than
the data demand, and as the set shrinks it converges to ``g_hat``. That is what a credible set
is for: acting on what the data establish, not on the noise of an estimate.

How it acts on the controller (:class:`controllers.mpc.LinearMPC`): the model predicts with
``g`` times the nominal linear part. Because the linear part is linear, this is the nominal
model driven by ``g z``: the QP plans ``z' = g z`` with bounds ``g [z_lo, z_hi]`` and the
nonlinearity inverts ``z' / g``. When g changes, the observer's state (in units of z') is
rescaled so that its output estimate stays where the measurements put it
(:meth:`controllers.observer.DisturbanceObserver.rescale_input`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CREDIBLE_Z", "GainEstimate"]

CREDIBLE_Z = 1.959963984540054
"""The 97.5 % quantile of the standard normal distribution: a two-sided 95 % credible set."""


class GainEstimate:
    """Recursive Bayesian estimate of the plant's gain relative to the model (module docstring).

    Parameters
    ----------
    a, b, c : numpy.ndarray
        The nominal linear part ``x_t+1 = a x_t + b z_t``, ``s_t = c x_t`` (um per equivalent V).
    tolerance : float
        Relative half-width w of the datasheet's gain interval (-), in (0, 1).
    noise_std : float
        Standard deviation of the sensor noise (um), > 0: the floor of the residual's.
    """

    def __init__(
        self, a: np.ndarray, b: np.ndarray, c: np.ndarray, *, tolerance: float, noise_std: float
    ) -> None:
        if not 0.0 < tolerance < 1.0:
            raise ValueError(f"tolerance must lie in (0, 1) (relative), got {tolerance!r}")
        if not noise_std > 0.0:
            raise ValueError(f"noise_std must be > 0 um, got {noise_std!r}")
        self._a, self._b, self._c = np.asarray(a), np.asarray(b)[:, 0], np.asarray(c)[0]
        self.low, self.high = 1.0 - tolerance, 1.0 + tolerance
        self._prior_precision = 3.0 / tolerance**2
        self._floor = noise_std**2
        self.reset(np.zeros(self._a.shape[0]))

    def reset(self, x0: np.ndarray) -> None:
        """Start an episode from the nominal model's state ``x0`` (the prior: g = 1)."""
        self._x = np.array(x0, dtype=float)
        self._s_ss = 0.0  # sum s^2
        self._s_sy = 0.0  # sum s y
        self._s_ee = 0.0  # sum of squared a-priori residuals
        self._count = 0
        self.mean = 1.0
        self.std = 1.0 / math.sqrt(self._prior_precision)
        self.value = 1.0
        self.set = (self.low, self.high)

    def update(self, y: float) -> float:
        """Take the measurement y (um) of the present sample; returns the gain to predict with."""
        s = float(self._c @ self._x)
        residual = y - self.mean * s
        self._s_ee += residual * residual
        self._count += 1
        self._s_ss += s * s
        self._s_sy += s * y
        variance = max(self._s_ee / self._count, self._floor)
        precision = self._prior_precision + self._s_ss / variance
        self.mean = (self._prior_precision + self._s_sy / variance) / precision
        self.std = 1.0 / math.sqrt(precision)
        half = CREDIBLE_Z * self.std
        low = min(max(self.mean - half, self.low), self.high)
        high = max(min(self.mean + half, self.high), self.low)
        self.set = (low, high)
        self.value = min(max(1.0, low), high)
        return self.value

    def advance(self, z: float) -> None:
        """Time update with the hidden signal z applied this sample (equivalent V)."""
        self._x = self._a @ self._x + self._b * z
