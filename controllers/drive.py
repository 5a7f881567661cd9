"""The bender's drive, learned from the first sample: its gain and its hysteresis strength.

A bender bought to a datasheet differs from the nominal one by a factor on its gain
(:mod:`controllers.gain`) and by the strength of its hysteresis (+-30 %). Both hysteresis
families of :mod:`piezo_env.hysteresis` scale the same way
(:func:`piezo_env.randomization.scale_hysteresis`): a linear part ``w0 u`` and a hysteretic
part (Bouc-Wen's ``-h``, the play operators' weighted sum), the hysteretic part times rho and
the whole map then times c to keep the major loop's peak. With ``N`` the nominal map::

    N_rho(u) = c (w0 u + rho H(u)) = c (rho N(u) + (1 - rho) w0 u)

exactly, for every input sequence (Bouc-Wen's h is linear in its share alpha). So a bender of
another strength and gain f is driven by::

    f N_rho(u) = theta_z N(u) + theta_u u,   theta_z = f c rho,   theta_u = f c (1 - rho) w0

two numbers, and the identified nonlinearity (``z = N(u)`` in equivalent V: the linear
weight there is kappa = w0 in z's units) stands for every strength once its input is mixed
back in. Measured on the committed PL140 model: the plant's map at strength x0.7 and x1.3 is
``theta_z z + theta_u u`` to at most 4e-4 V rms (out of 7-11 V), where a gain alone leaves
0.23-0.31 V (``benchmarks/results/design_measurements.md``).

The model. The nominal linear part driven by z gives ``s_t``, driven by u gives ``v_t`` (um),
and the plant answers::

    y_t = theta_z s_t + theta_u v_t + e_t

linear in theta: the Bayesian estimate for a Gaussian prior and Gaussian ``e_t`` of unknown
variance (estimated from the a-priori residuals, floored at the sensor noise's), as
:class:`controllers.gain.GainEstimate` does for one parameter, with a 2 x 2 precision::

    P_t = P_0 + S_t / sigma_t^2,    S_t = sum [s; v] [s, v]
    theta_hat_t = P_t^-1 (P_0 theta_0 + sum [s; v] y / sigma_t^2)

The prior: theta_0 = (1, 0), the identified bender; its box from the datasheet, rho in
``[1 - r, 1 + r]`` (r the strength's tolerance) and ``f c`` in ``[1 - w, 1 + w]`` (w the learned
gain's, :data:`controllers.settings.LEARNED_GAIN_TOLERANCE`): theta_z in ``[(1 - w)(1 - r),
(1 + w)(1 + r)]``, ``theta_u / theta_z = (1 - rho) kappa / rho`` in ``[-r kappa / (1 + r),
r kappa / (1 - r)]``. The prior variances are those of uniforms about the nominal value: theta_z's
over the box's wider side, theta_u's over ``|theta_u| <= (1 + w) r kappa``, its physical bound
``|f c (1 - rho) kappa|`` (the box's ratio bound times theta_z's reaches further).

kappa is not known from an identified map (one strength's data do not
separate its two parts), but the map's own slopes bound it (:func:`slope_range`: smallest
z'_min, largest z'_max on the major loop). A Prandtl-Ishlinskii map's slope right after a
reversal, all plays stuck, is its linear weight: kappa = z'_min. A Bouc-Wen map (beta >= gamma,
as accepted) starts each branch at its flattest, ``k (1 - 2 alpha beta / (beta + gamma))``, and
rises towards k as h saturates: ``dh/du`` stays at ``alpha k + (beta - gamma) |h|`` while h has
the sign opposite to the move, then ``k - z'`` decays as ``exp(-(beta + gamma) du)``; on a
full-stroke branch of the env's calibration (``(beta + gamma) 2 u_max = 2.8``) less than a
fifth of the rise is left at its end, so ``kappa - z'_max <= z'_max - z'_min``. The box takes
``kappa <= 2 z'_max - z'_min``, a superset for both families; its slopes are one-sample secants
at 0.25 V (:data:`controllers.predictive.SLOPE_SAMPLES`), within 0.03 % of finer ones on the
identified maps. The gain's w already holds the strength's effect on the gain
(:data:`controllers.settings.LEARNED_GAIN_TOLERANCE`), so the box counts it twice: wider than
needed, never narrower.

What the controller predicts with: the point of the 95 % credible ellipse
``(theta - m)' P (theta - m) <= chi2_2(0.95)`` nearest theta_0 in the posterior's own metric
(on the segment from the mean to theta_0; theta_0 itself while the data do not contradict it,
as the gain's credible set acts), within the box. Each sample costs a fixed number of
multiply-adds per part: the work per step is bounded.

What it is not: a set-membership estimate. The gain's exact interval keeps its role (the
gain estimate runs beside the drive's, :attr:`DriveEstimate.gain`); the exact set of two
parameters is a polygon whose vertices grow with the data, and the credible ellipse is what
acts.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from controllers.gain import GainEstimate
from controllers.native.step_kernels import bind, kernels_for

__all__ = ["CREDIBLE_CHI2_2", "DriveEstimate", "slope_range"]

CREDIBLE_CHI2_2 = -2.0 * math.log(0.05)
"""The 95 % quantile of the chi-square distribution with 2 degrees of freedom (-2 ln 0.05):
the credible ellipse of two parameters."""


def slope_range(nonlinearity: Any, step: float, legs: int = 3) -> tuple[float, float]:
    """Smallest and largest one-sample secant slope dz/du of ``nonlinearity`` at voltage steps
    ``step`` (V), on a full-stroke triangle (0 -> u_max -> u_min -> ..., ``legs`` legs) at
    ``step`` per sample: at every sample the secants to u +- step (within the drive range) from
    the state there, right after each reversal included, where a hysteresis map is flattest,
    and at each branch's end, where a Bouc-Wen map is steepest.

    Raises
    ------
    ValueError
        If a slope is not positive (the map is not increasing).
    """
    u_min, u_max = nonlinearity.u_range
    n = max(1, math.ceil((u_max - u_min) / step))
    path = [np.linspace(0.0, u_max, max(1, math.ceil(u_max / step)) + 1)[1:]]
    for leg in range(legs - 1):
        ends = (u_max, u_min) if leg % 2 == 0 else (u_min, u_max)
        path.append(np.linspace(*ends, n + 1)[1:])
    state = nonlinearity.initial_state()
    low, high = math.inf, -math.inf
    for u in np.concatenate(path):
        z, state = nonlinearity.step(float(u), state)
        for other in (min(u + step, u_max), max(u - step, u_min)):
            if other != u:
                slope = (nonlinearity.step(float(other), state)[0] - z) / (other - u)
                low, high = min(low, slope), max(high, slope)
    if not low > 0:
        raise ValueError(
            f"the nonlinearity's slope dz/du reaches {low:.3g} along a full-stroke triangle: "
            "it is not increasing, so the slew limit has no z rate equivalent"
        )
    return float(low), float(high)


class DriveEstimate:
    """Recursive Bayesian estimates of the plant's drive ``theta_z z + theta_u u`` relative to
    each of K linear parts (module docstring), run side by side on the same data, beside the
    gain estimate of the same parts (:attr:`gain`).

    The gain estimate tells the adaptive MPC's members apart (its misfits, its credible set
    in the report): the drive's two parameters would also fit a wrong member's resonance at a
    sine's frequency (u and z differ in phase by the hysteresis loop, so together they match
    any gain and phase there), and a selection on the drive's misfits kept a member whose
    resonance lay 20 % off for 1.4 s where the gain's swapped within 0.1 s
    (``benchmarks/results/design_measurements.md``). The drive is what the controller
    predicts with (:attr:`theta_z`, :attr:`theta_u`).

    Parameters
    ----------
    a, b, c : numpy.ndarray
        The linear parts, as :class:`controllers.gain.GainEstimate` takes them.
    tolerance : float
        Relative half-width w of the bender's gain (-), in (0, 1).
    strength : float
        Relative half-width r of the hysteresis strength (-), in (0, 1): the datasheet's
        (:attr:`piezo_env.randomization.DomainRandomization.hysteresis_strength`).
    slopes : (float, float)
        The identified map's smallest and largest slope dz/du (equivalent V per V,
        :func:`slope_range`): kappa's bound, and the mixed map's monotonicity.
    noise_std : float
        Standard deviation of the sensor noise (um), > 0: the floor of the residual's.
    noise_bound : float, optional
        The gain estimate's exact set's bound (:class:`controllers.gain.GainEstimate`).

    Attributes
    ----------
    gain : controllers.gain.GainEstimate
        The gain estimate of the same parts; ``value``, ``low``, ``high``, ``mean``, ``std``,
        ``misfit``, ``count``, :meth:`independent_fraction_of` are its.
    theta_z, theta_u : numpy.ndarray
        (K,) the point of each credible ellipse nearest (1, 0), within the box: the drive a
        controller predicts with.
    mean_z, mean_u : numpy.ndarray
        (K,) the posterior means.
    native : list of NativeBuild
        The record of the compiled kernels that run :meth:`update` and :meth:`advance`
        (:mod:`controllers.native.step_kernels`; numpy when they are not compiled).

    The arrays are overwritten in place by each :meth:`update`: copy what must outlive it.
    """

    def __init__(
        self,
        a: np.ndarray,
        b: np.ndarray,
        c: np.ndarray,
        *,
        tolerance: float,
        strength: float,
        slopes: tuple[float, float],
        noise_std: float,
        noise_bound: float | None = None,
    ) -> None:
        if not 0.0 < strength < 1.0:
            raise ValueError(f"strength must lie in (0, 1) (relative), got {strength!r}")
        self.gain = GainEstimate(
            a, b, c, tolerance=tolerance, noise_std=noise_std, noise_bound=noise_bound
        )
        low_slope, high_slope = (float(v) for v in slopes)
        if not 0.0 < low_slope <= high_slope:
            raise ValueError(f"slopes must be (smallest, largest) > 0, got {slopes!r}")
        kappa = 2.0 * high_slope - low_slope  # the linear weight's bound (module docstring)
        # The mixed map's slope theta_z z' + theta_u >= theta_z (z'_min - r kappa / (1 + r))
        # on the box: positive only if z'_min > r kappa / (1 + r).
        if not low_slope > strength * kappa / (1.0 + strength):
            raise ValueError(
                f"the map's slopes ({low_slope:.3g} to {high_slope:.3g} equivalent V per V) "
                f"leave the mixed drive not increasing on the box's edge at strength tolerance "
                f"r = {strength} (it needs z'_min > r (2 z'_max - z'_min) / (1 + r)); lower "
                "strength_tolerance"
            )
        gain = self.gain
        self._a, self._b, self._c = gain._a, gain._b, gain._c
        k, n = self._a.shape[0], self._a.shape[1]
        self.slopes = (low_slope, high_slope)
        w, r = tolerance, strength
        self.theta_z_bounds = ((1.0 - w) * (1.0 - r), (1.0 + w) * (1.0 + r))
        self.ratio_bounds = (-r * kappa / (1.0 + r), r * kappa / (1.0 - r))
        half_z = max(1.0 - self.theta_z_bounds[0], self.theta_z_bounds[1] - 1.0)
        half_u = (1.0 + tolerance) * strength * kappa  # |f c (1 - rho) kappa| on the box
        self._prior = (3.0 / half_z**2, 3.0 / half_u**2)
        self._floor = noise_std**2
        # Every running quantity lives in one block, updated in place (by numpy or by the
        # compiled kernel, controllers.native.step_kernels); the attributes are views of it.
        self._state = np.zeros(10 * k + 2)
        (
            self._s_ss,  # sum s^2
            self._s_sv,  # sum s v
            self._s_vv,  # sum v^2
            self._s_sy,  # sum s y
            self._s_vy,  # sum v y
            self._s_ee,  # sum of squared a-priori residuals
            self.mean_z,
            self.mean_u,
            self.theta_z,
            self.theta_u,
        ) = self._state[: 10 * k].reshape(10, k)
        self._sums = self._state[10 * k :]  # (a spare slot), count
        self._xz = gain._x  # the gain's linear parts, driven by z
        self._xu = np.zeros((k, n))
        self._update_drive = self._advance_u = None
        library, build = kernels_for(n)
        self.native = [build]
        self._kernel_data = (
            np.array([k, n], dtype=np.int64),
            np.array(
                [
                    *self._prior,
                    self._floor,
                    *self.theta_z_bounds,
                    *self.ratio_bounds,
                    CREDIBLE_CHI2_2,
                ]
            ),
        )  # kept alive: the kernels hold their pointers
        if library is not None:
            dims, par = self._kernel_data
            self._update_drive = bind(
                library.drive_update, dims, par, self._c, self._xz, self._xu, self._state
            )
            self._advance_u = bind(library.gain_advance, dims, self._a, self._b, self._xu)
        self.reset(np.zeros(n), 0.0)

    # The gain estimate's, for the adaptive MPC's selection and the report.
    size = property(lambda self: self.gain.size, doc="K, the number of linear parts.")
    count = property(lambda self: self.gain.count, doc="Samples taken.")
    value = property(lambda self: self.gain.value, doc="The gain estimate's value (K,).")
    low = property(lambda self: self.gain.low, doc="The gain's credible set's low ends (K,).")
    high = property(lambda self: self.gain.high, doc="The gain's credible set's high ends.")
    misfit = property(lambda self: self.gain.misfit, doc="The gain estimate's misfits (K,).")

    noise_bound = property(lambda self: self.gain.noise_bound, doc="The exact set's bound (um).")
    exact_low = property(lambda self: self.gain.exact_low, doc="The gain's exact sets' low ends.")
    exact_high = property(lambda self: self.gain.exact_high, doc="Their high ends (K,).")
    emptied_at = property(lambda self: self.gain.emptied_at, doc="When each became empty.")

    def independent_fraction_of(self, index: int) -> float:
        """:meth:`controllers.gain.GainEstimate.independent_fraction_of`."""
        return self.gain.independent_fraction_of(index)

    @property
    def _update_native(self) -> Any:
        """The compiled update where both estimates have one, else None (the MPCs' compiled
        steps check it)."""
        if self.gain._update_native is None or self._update_drive is None:
            return None
        return self._update_drive

    @property
    def theta(self) -> np.ndarray:
        """(K, 2) theta_z and theta_u, the drive each part predicts with (a copy)."""
        return np.stack([self.theta_z, self.theta_u], axis=1)

    def states(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Part ``index``'s states driven by z and by u since the episode's start (views)."""
        return self._xz[index], self._xu[index]

    def reset(self, x0: np.ndarray, u0: float = 0.0) -> None:
        """Start an episode from the state ``x0`` ((n,) shared or (K, n)) of the linear parts
        at rest under the constant z that the voltage ``u0`` (V) holds; the u-driven parts
        start at rest under ``u0``. The prior: theta = (1, 0), the gain 1."""
        self.gain.reset(x0)
        eye = np.eye(self._a.shape[1])
        for k in range(self.size):
            self._xu[k] = np.linalg.solve(eye - self._a[k], self._b[k]) * u0
        self._state[:] = 0.0
        self.mean_z[:] = 1.0
        self.theta_z[:] = 1.0

    def update(self, y: float) -> None:
        """Take the measurement y (um) of the present sample: the gain estimate's update,
        then the drive's (numpy's path does the compiled kernel's operations in its order, so
        both give the same bits)."""
        self.gain.update(y)
        if self._update_drive is not None:
            self._update_drive(y)
            return
        s, v = _rows_dot(self._c, self._xz), _rows_dot(self._c, self._xu)
        self._sums[1] += 1.0
        count = self._sums[1]
        residual = y - (self.mean_z * s + self.mean_u * v)
        self._s_ee += residual * residual
        self._s_ss += s * s
        self._s_sv += s * v
        self._s_vv += v * v
        self._s_sy += s * y
        self._s_vy += v * y
        variance = np.maximum(self._s_ee / count, self._floor)
        p11 = self._prior[0] + self._s_ss / variance
        p12 = self._s_sv / variance
        p22 = self._prior[1] + self._s_vv / variance
        r1 = self._prior[0] + self._s_sy / variance  # P_0 theta_0 with theta_0 = (1, 0)
        r2 = self._s_vy / variance
        det = p11 * p22 - p12 * p12
        m1 = (p22 * r1 - p12 * r2) / det
        m2 = (p11 * r2 - p12 * r1) / det
        self.mean_z[:], self.mean_u[:] = m1, m2
        # The credible ellipse's point nearest (1, 0) in the metric P: on the segment from m.
        d1, d2 = 1.0 - m1, -m2
        q = p11 * d1 * d1 + 2.0 * p12 * d1 * d2 + p22 * d2 * d2
        reach = np.where(q > CREDIBLE_CHI2_2, np.sqrt(CREDIBLE_CHI2_2 / np.maximum(q, 1e-300)), 1.0)
        self.theta_z[:] = m1 + reach * d1
        self.theta_u[:] = m2 + reach * d2
        (z_low, z_high), (r_low, r_high) = self.theta_z_bounds, self.ratio_bounds
        for k in range(self.size):
            t1, t2 = float(self.theta_z[k]), float(self.theta_u[k])
            if not (z_low <= t1 <= z_high and r_low * t1 <= t2 <= r_high * t1):
                self.theta_z[k], self.theta_u[k] = self._project(
                    t1, t2, float(p11[k]), float(p12[k]), float(p22[k])
                )

    def _project(
        self, t1: float, t2: float, p11: float, p12: float, p22: float
    ) -> tuple[float, float]:
        """The point of the box (theta_z within its bounds, theta_u / theta_z within the
        ratio's) nearest (t1, t2) in the metric ``[[p11, p12], [p12, p22]]``: the combination
        of the two parameters the data determine best moves least. The box is a
        quadrilateral; its nearest point is the point itself, a vertex or the nearest point of
        an edge's line that lies on the box (scalar code, the compiled kernel's operations in
        its order)."""
        (z_low, z_high), (r_low, r_high) = self.theta_z_bounds, self.ratio_bounds
        det = p11 * p22 - p12 * p12
        c11, c12, c22 = p22 / det, -p12 / det, p11 / det  # the covariance
        candidates = [(z, r * z) for z in (z_low, z_high) for r in (r_low, r_high)]
        # Edges a . theta = c: theta_z = z_low, theta_z = z_high, theta_u = r theta_z.
        for a0, a1, c in ((1.0, 0.0, z_low), (1.0, 0.0, z_high), (-r_low, 1.0, 0.0),
                          (-r_high, 1.0, 0.0)):  # fmt: skip
            ca0, ca1 = c11 * a0 + c12 * a1, c12 * a0 + c22 * a1
            f = (a0 * t1 + a1 * t2 - c) / (a0 * ca0 + a1 * ca1)
            candidates.append((t1 - ca0 * f, t2 - ca1 * f))
        candidates.append((t1, t2))  # itself, when it lies on the box
        best, best_distance = candidates[0], math.inf
        for z, u in candidates:
            tolerance = 1e-12 * (1.0 + abs(z))
            inside = (
                z_low - tolerance <= z <= z_high + tolerance
                and r_low * z - tolerance <= u <= r_high * z + tolerance
            )
            dz, du = z - t1, u - t2
            distance = dz * (p11 * dz + p12 * du) + du * (p12 * dz + p22 * du)
            if inside and distance < best_distance:
                best, best_distance = (z, u), distance
        return best

    def advance(self, z: float, u: float) -> None:
        """Time update with the hidden signal z (equivalent V) and the voltage u (V) applied
        this sample."""
        self.gain.advance(z)
        if self._advance_u is not None:
            self._advance_u(u)
            return
        # Summed left to right over the state from 0, as the compiled kernel sums.
        x = self._xu
        following = np.zeros_like(x)
        for j in range(x.shape[1]):
            following += self._a[:, :, j] * x[:, None, j]
        x[:] = following + self._b * u


def _rows_dot(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(K,) each row's dot product ``c_k . x_k``, summed left to right (as the kernels do)."""
    total = c[:, 0] * x[:, 0]
    for j in range(1, c.shape[1]):
        total += c[:, j] * x[:, j]
    return total
