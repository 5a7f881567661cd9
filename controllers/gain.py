"""The bender's static gain, learned from the first sample: a credible set inside the tolerance.

A bender bought to a datasheet differs from the nominal one mostly by a factor on its gain: the
free deflection (deflection per volt) is specified to +-20 %, and the hysteresis strength's
+-30 % moves the gain a linear model sees by up to 9 % more (+-31 % together:
:data:`controllers.settings.LEARNED_GAIN_TOLERANCE`). At the frequencies a tracking reference
lives at (well below the first resonance) a stiffer or softer, better or worse damped
bender looks, to first order, like the nominal one times a number. A model-based controller
that predicts with the nominal gain leaves the error ``(g - 1) y_ref`` to its output
disturbance, which follows a reference-shaped error only as fast as its observer, and a faster
observer excites the resonance it inverts. Knowing ``g`` instead makes the same prediction right.

The model. The controller applies the hidden signal z (its nonlinearity's output); the nominal
linear part driven by it from the episode's start gives ``s_t`` (um), and the plant answers::

    y_t = g s_t + e_t,     g in [1 - w, 1 + w]   (w: the relative tolerance)

where ``e_t`` holds the sensor noise and what the model gets wrong besides the gain. The
estimate is the Bayesian one for a Gaussian prior on g (uniform over ``[1 - w, 1 + w]``:
mean 1, variance ``w^2 / 3``) and Gaussian ``e_t`` of unknown variance, which is estimated from
the a-priori residuals ``y_t - g_hat s_t`` (floored at the sensor noise's variance)::

    precision_t = 3 / w^2 + sum s_tau^2 / sigma_t^2
    g_hat_t = (3 / w^2 + sum s_tau y_tau / sigma_t^2) / precision_t

Each sample costs a few multiply-adds (three running sums): the work per step is bounded.

The credible set is ``g_hat +- z_975 / sqrt(precision)`` (95 %) intersected with
``[1 - w, 1 + w]``. The controller predicts with the point of that set nearest to the nominal
gain 1: while the data do not contradict the nominal model (1 lies in the set) nothing changes,
so a nominal bender is controlled as with the nominal gain while its data agree with it (early
in an episode the set can leave 1 for a few samples, by an amount the prior's width moves);
when they do, the model moves by no more than the data demand, and as the set shrinks it
converges to ``g_hat``. That is what a credible set is for: acting on what the data establish,
not on the noise of an estimate.

Beside it, the exact set. With the sensor noise bounded, ``|e_t| <= r`` (the env's sensor noise
is uniform on ``[-r, r]``), the gains that explain every sample so far are an interval, the
support of the paper's uniform-noise posterior for this one parameter (uniform prior over
``[1 - w, 1 + w]``)::

    G_t = [1 - w, 1 + w]  intersected with  {g : |y_tau - g s_tau| <= r_tau, tau <= t}

kept by two running extremes (a maximum of lower ends, a minimum of upper ends): O(1) per
sample. ``r_t`` is the sensor's bound plus a proven bound of the model's own error where one
is known (:attr:`controllers.prediction.PredictionModel.error_bound_um`: the modes a plant's
model leaves out) plus one float32 unit in the last place of ``|y_t|`` (the env's
observations are float32, :data:`OBSERVATION_ROUNDING`), and each finite end is widened by a
relative :data:`EXACT_WIDENING`, so that rounding never makes the set inner. Whenever the
plant is in the model class (the linear part right up to the gain and that error, the noise
within its bound), ``G_t`` contains its gain, for every noise realisation, and it shrinks as
``2 r / max |s|``. It is a model-invalidation test, not the set the controller acts on: an
identified model leaves errors beside the gain (its nonlinearity's, a resonance of the box
that is not the model's), and an exact set with the sensor's bound then becomes empty, the
data having proven that no gain explains them to within the noise
(``benchmarks/results/design_measurements.md`` measures when on the benchmark's plants). A
sound set for such a plant needs a bound of the model's error, which nothing measures; the
credible set above estimates the residual's variance instead, model error included.
:attr:`GainEstimate.emptied_at` records the sample at which each part's exact set became
empty, so the invalidation is reported, not hidden.

How it acts on the controller (:class:`controllers.mpc.LinearMPC`): the model predicts with
``g`` times the nominal linear part. Because the linear part is linear, this is the nominal
model driven by ``g z``: the QP plans ``z' = g z`` with bounds ``g [z_lo, z_hi]`` and the
nonlinearity inverts ``z' / g``. When g changes, the observer's state (in units of z') is
rescaled so that its output estimate stays where the measurements put it
(:meth:`controllers.observer.DisturbanceObserver.rescale_input`). The nonlinear MPC
(:class:`controllers.nmpc.NonlinearMPC`), which plans in volts through the whole model, reads
the measurement and the preview over ``g`` instead, and carries its observer's output estimate
to each new scale (:meth:`controllers.observer.DisturbanceObserver.rescale_output`).
"""

from __future__ import annotations

import math

import numpy as np

from controllers.native.step_kernels import bind, kernels_for

__all__ = ["CREDIBLE_Z", "EXACT_WIDENING", "OBSERVATION_ROUNDING", "GainEstimate"]

CREDIBLE_Z = 1.959963984540054
"""The 97.5 % quantile of the standard normal distribution: a two-sided 95 % credible set."""

OBSERVATION_ROUNDING = 2.0**-23
"""Relative rounding of a float32 observation (-): one unit in the last place, twice the
half-unit that rounding to nearest makes, so that the bound holds relative to the rounded value
too."""

EXACT_WIDENING = 1e-9
"""Relative widening of each end of the exact set per sample (-): the rounding of
``(y -+ r) / s`` is a few units of float64's 1.1e-16, and of a linear part run by other code
(another summation order) about 1e-13 of the gain; 1e-9 covers both with room, as the outer
bounds of :mod:`identification.bayes_uniform` are widened, and moves the set by less than
1e-9 of the gain after any number of samples that take its extremes."""


class GainEstimate:
    """Recursive Bayesian estimates of the plant's gain relative to each of K linear parts
    (module docstring), run side by side on the same data.

    One linear part (K = 1) is what :class:`controllers.mpc.LinearMPC` learns; the adaptive
    MPC runs one per model of its set (:mod:`controllers.adaptive`), and their misfits tell
    the models apart.

    Parameters
    ----------
    a, b, c : numpy.ndarray
        The linear parts ``x_t+1 = a x_t + b z_t``, ``s_t = c x_t`` (um per equivalent V):
        shapes (n, n), (n, 1) or (n,), (1, n) or (n,) for one; (K, n, n), (K, n), (K, n)
        for K of the same state size.
    tolerance : float
        Relative half-width w of the gain interval (-), in (0, 1): the controllers'
        :data:`controllers.settings.LEARNED_GAIN_TOLERANCE` by default.
    noise_std : float
        Standard deviation of the sensor noise (um), > 0: the floor of the residual's.
    noise_bound : float, optional
        Bound r of the measurement's error beside the gain (um), >= 0, for the exact set
        (module docstring): the sensor noise's, plus a proven bound of the model's error where
        one is known. Default ``sqrt(3) noise_std``: the bound of a uniform noise of that
        standard deviation, as the env's sensor noise is.

    Attributes
    ----------
    mean, std : numpy.ndarray
        (K,) posterior mean and standard deviation of each gain (-).
    low, high : numpy.ndarray
        (K,) each gain's 95 % credible set within ``[1 - w, 1 + w]`` (-).
    value : numpy.ndarray
        (K,) the point of each set nearest 1: the gain a controller predicts with (-).
    misfit : numpy.ndarray
        (K,) mean squared residual ``y - mean s`` over the samples so far (um^2): how well
        each linear part, at its estimated gain, explains the measurements.
    exact_low, exact_high : numpy.ndarray
        (K,) each gain's exact set with the noise bound (module docstring), within
        ``[1 - w, 1 + w]``; empty (``exact_low > exact_high``) once the data invalidate the
        part at that bound (-).
    emptied_at : numpy.ndarray
        (K,) the sample (1 = the first) at which each exact set became empty; 0 while it is
        not.
    count : int
        Samples taken.
    native : list of NativeBuild
        The record of the compiled kernels that run :meth:`update` and :meth:`advance`
        (:mod:`controllers.native.step_kernels`; numpy when they are not compiled).

    The arrays above are views that each :meth:`update` overwrites in place: copy what must
    outlive the next sample.
    """

    def __init__(
        self,
        a: np.ndarray,
        b: np.ndarray,
        c: np.ndarray,
        *,
        tolerance: float,
        noise_std: float,
        noise_bound: float | None = None,
    ) -> None:
        if not 0.0 < tolerance < 1.0:
            raise ValueError(f"tolerance must lie in (0, 1) (relative), got {tolerance!r}")
        if not noise_std > 0.0:
            raise ValueError(f"noise_std must be > 0 um, got {noise_std!r}")
        if noise_bound is None:
            noise_bound = math.sqrt(3.0) * noise_std
        if not (noise_bound >= 0.0 and math.isfinite(noise_bound)):
            raise ValueError(f"noise_bound must be a finite number >= 0 um, got {noise_bound!r}")
        self.noise_bound = float(noise_bound)
        a = np.asarray(a, dtype=float)
        batch = a.ndim == 3
        self._a = a if batch else a[None]
        k, n = self._a.shape[0], self._a.shape[1]
        # C-contiguous float64 copies: the compiled kernels read them through raw pointers.
        self._b = np.ascontiguousarray(np.asarray(b, dtype=float).reshape(k, n))
        self._c = np.ascontiguousarray(np.asarray(c, dtype=float).reshape(k, n))
        self.bounds = (1.0 - tolerance, 1.0 + tolerance)
        self._prior_precision = 3.0 / tolerance**2
        self._floor = noise_std**2
        # Every running quantity lives in one block, updated in place (by numpy or by the
        # compiled kernel, controllers.native.step_kernels): the attributes are views of it.
        self._state = np.zeros(14 * k + 2)
        (
            self._s_ss,  # sum s^2
            self._s_sy,  # sum s y
            self._s_ee,  # sum of squared a-priori residuals
            self._s_lag,  # sum of products of successive a-priori residuals
            self._residual,
            self.mean,
            self.std,
            self.low,
            self.high,
            self.value,
            self.misfit,
        ) = self._state[: 11 * k].reshape(11, k)
        self._sums = self._state[11 * k : 11 * k + 2]  # s_yy, count
        self.exact_low, self.exact_high, self.emptied_at = self._state[11 * k + 2 :].reshape(3, k)
        self._x = np.zeros((k, n))
        self._a = np.ascontiguousarray(self._a)
        self._update_native = self._advance_native = None
        library, build = kernels_for(n)
        self.native = [build]
        if library is not None:
            dims = np.array([k, n], dtype=np.int64)
            par = np.array(
                [
                    self._prior_precision,
                    self._floor,
                    *self.bounds,
                    CREDIBLE_Z,
                    self.noise_bound,
                    EXACT_WIDENING,
                    OBSERVATION_ROUNDING,
                ],
                dtype=float,
            )
            self._kernel_data = (dims, par)  # kept alive: the kernels hold their pointers
            self._update_native = bind(
                library.gain_update, dims, par, self._c, self._x, self._state
            )
            self._advance_native = bind(library.gain_advance, dims, self._a, self._b, self._x)
        self.reset(np.zeros(n))

    @property
    def size(self) -> int:
        """K, the number of linear parts."""
        return self._a.shape[0]

    @property
    def count(self) -> int:
        """Samples taken."""
        return int(self._sums[1])

    def reset(self, x0: np.ndarray) -> None:
        """Start an episode from the state ``x0`` ((n,) shared or (K, n)); the prior: g = 1."""
        self._x[:] = np.broadcast_to(x0, self._b.shape)
        self._state[:] = 0.0
        self.mean[:] = 1.0
        self.std[:] = 1.0 / math.sqrt(self._prior_precision)
        self.low[:], self.high[:] = self.bounds
        self.exact_low[:], self.exact_high[:] = self.bounds
        self.value[:] = 1.0

    def update(self, y: float) -> np.ndarray:
        """Take the measurement y (um) of the present sample; returns :attr:`value` (a
        copy)."""
        if self._update_native is not None:
            self._update_native(y)
            return self.value.copy()
        s = np.einsum("kn,kn->k", self._c, self._x)
        residual = y - self.mean * s
        self._s_ee += residual * residual
        self._s_lag += residual * self._residual
        self._residual[:] = residual
        sums = self._sums
        sums[1] += 1.0
        sums[0] += y * y
        count = sums[1]
        self._s_ss += s * s
        self._s_sy += s * y
        variance = np.maximum(self._s_ee / count, self._floor)
        precision = self._prior_precision + self._s_ss / variance
        mean = (self._prior_precision + self._s_sy / variance) / precision
        self.mean[:] = mean
        self.std[:] = 1.0 / np.sqrt(precision)
        half = CREDIBLE_Z * self.std
        low, high = self.bounds
        # np.minimum/np.maximum, not np.clip: the same numbers at a third of the overhead.
        np.minimum(np.maximum(mean - half, low), high, out=self.low)
        np.minimum(np.maximum(mean + half, low), high, out=self.high)
        np.minimum(np.maximum(1.0, self.low), self.high, out=self.value)
        self.misfit[:] = (sums[0] - 2.0 * mean * self._s_sy + mean * mean * self._s_ss) / count
        self._narrow_exact(s, y)
        return self.value.copy()

    def _narrow_exact(self, s: np.ndarray, y: float) -> None:
        """Intersect the exact sets with ``{g : |y - g s| <= r}`` (numpy's path; the compiled
        kernel computes the same numbers)."""
        r = self.noise_bound + OBSERVATION_ROUNDING * abs(y)
        # s = 0 is replaced below; a subnormal s overflows to an infinite end, which is not
        # widened (inf - inf would be NaN).
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            low = np.where(s > 0.0, y - r, y + r) / s
            high = np.where(s > 0.0, y + r, y - r) / s
            low = np.where(np.isfinite(low), low - EXACT_WIDENING * np.abs(low), low)
            high = np.where(np.isfinite(high), high + EXACT_WIDENING * np.abs(high), high)
        zero = s == 0.0
        if zero.any():  # the sample says nothing of g, or that none fits (NaN: NaN)
            low[zero] = y if y != y else -np.inf if abs(y) <= r else np.inf
            high[zero] = y if y != y else -low[zero]
        np.maximum(self.exact_low, low, out=self.exact_low)
        np.minimum(self.exact_high, high, out=self.exact_high)
        emptied = (self.emptied_at == 0.0) & (self.exact_low > self.exact_high)
        self.emptied_at[emptied] = self._sums[1]

    @property
    def independent_fraction(self) -> np.ndarray:
        """(K,) the fraction of the samples that count as independent in a test on the
        misfits: ``(1 - rho) / (1 + rho)``, rho the lag-one autocorrelation of each part's
        residuals (the variance inflation of a mean of AR(1) errors), rho clipped to [0, 1)."""
        rho = np.clip(self._s_lag / np.maximum(self._s_ee, 1e-300), 0.0, 1.0 - 1e-12)
        return (1.0 - rho) / (1.0 + rho)

    def independent_fraction_of(self, index: int) -> float:
        """:attr:`independent_fraction` of part ``index`` alone (the same number, one part's
        work)."""
        rho = min(max(self._s_lag[index] / max(self._s_ee[index], 1e-300), 0.0), 1.0 - 1e-12)
        return (1.0 - rho) / (1.0 + rho)

    def advance(self, z: float) -> None:
        """Time update with the hidden signal z applied this sample (equivalent V)."""
        if self._advance_native is not None:
            self._advance_native(z)
            return
        self._x[:] = np.einsum("kij,kj->ki", self._a, self._x) + self._b * z
