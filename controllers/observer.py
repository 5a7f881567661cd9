"""Offset-free state estimation: a steady-state Kalman filter with an output-disturbance state.

The prediction model ``x_t+1 = A x_t + B z_t``, ``y_t = C x_t`` is augmented with a constant
output disturbance d (a random walk)::

    [x; d]_t+1 = [[A, 0], [0, 1]] [x; d]_t + [B; 0] z_t + w_t,   y_meas,t = C x_t + d_t + v_t

d absorbs whatever the model gets wrong at low frequency (gain error, hysteresis mismatch, creep),
and because the controller predicts with the estimated d, a constant model error leaves no
steady-state tracking error (offset-free MPC: Muske & Badgwell 2002, Pannocchia & Rawlings 2003).

Tuning is one trade-off. The disturbance's random-walk standard deviation ``disturbance_std``
(um per sample) against the sensor's ``measurement_std`` (um) sets how fast d follows the
measurement: fast rejects model error quickly (a plant whose hysteresis differs from the
model's) but passes sensor noise into the control (amplified near the model's zeros close to
-1, i.e. near the Nyquist frequency); slow smooths noise but leaves model error uncorrected for
longer. ``process_std`` (equivalent V) is input-referred model noise on x.

The gain is the steady-state one (``scipy.linalg.solve_discrete_are``), so a step is two small
matrix-vector products.

What sets the noise an MPC passes is the input-referred process noise ``process_std``, not
the model's noise structure. A small term keeps the Riccati equation well posed for delay
states; it is scaled to each state's own variance under unit input (the diagonal of the
controllability Gramian), so it means the same for a model whose states are in um
(identified) and one whose states are in m (the plant's modal realization, the oracle). An
identity in the states' units would be a large process noise on every mode of the oracle, whose
error it would then set whatever its settings (``benchmarks/results/design_measurements.md``;
the oracle's error with the scaled term: ``benchmarks/results/identification_precision.md``).

No single pair of noise levels is right: what the model gets wrong differs by reference and
plant, and so does the best trade-off with it (a smaller ``process_std``, which passes less
noise, leaves more of the Prandtl-Ishlinskii plant's error uncorrected:
``benchmarks/results/design_measurements.md``). The default observer of both MPCs is
therefore a bank (:class:`ObserverBank`): the same filter under a grid of noise levels scaled
by the sensor noise, the data choosing among them by the likelihood of their innovations. With
a good model the data choose a slow filter that passes little noise, on a plant the model
misses a fast one. The figures are in ``benchmarks/results/identification_precision.md`` and
the benchmark's tables.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import scipy.linalg

from controllers.native.step_kernels import bind, kernels_for
from controllers.riccati import filter_riccati, scipy_filter
from controllers.settings import measurement_std
from piezo_env.memo import ContentCache

__all__ = [
    "BANKS_KEPT",
    "DISTURBANCE_RATIOS",
    "PROCESS_RATIOS",
    "RUNAWAY_CORRELATION",
    "RUNAWAY_MEMORY",
    "RUNAWAY_NIS",
    "RUNAWAY_PERSISTENCE",
    "DisturbanceObserver",
    "ObserverBank",
    "make_observer",
    "rescale_output_states",
    "rescale_states",
    "state_scale_of",
]


class DisturbanceObserver:
    """Steady-state Kalman filter of ``[x; d]`` (see the module docstring).

    Parameters
    ----------
    a, b, c : numpy.ndarray
        Linear model ``x_t+1 = a x_t + b z_t``, ``y_t = c x_t`` (um).
    measurement_std : float
        Sensor noise standard deviation (um), > 0.
    disturbance_std : float
        Random-walk step of the output disturbance (um per sample), > 0.
    process_std : float
        Input-referred process noise (equivalent V), >= 0.
    slope_std : float
        0 (default): d is a random walk, constant over the prediction. > 0: d drifts with a
        slope s that is itself a random walk with this step (um per sample^2), the estimate is
        ``[x; d; s]`` and predictions extrapolate ``d_t+k = d_t + k s_t``: a disturbance that
        changes at the reference's frequency (hysteresis the model gets wrong) is then
        followed to second order instead of lagging a sample behind.
    state_scale : numpy.ndarray, optional
        Each state's variance under unit input, the units of the Riccati equation's
        well-posedness term (default: from ``a`` and ``b``, see :func:`state_scale_of`; a bank of
        filters of one model passes it once for all).

    Attributes
    ----------
    n_disturbance : int
        1 (``[x; d]``) or 2 (``[x; d; s]``).
    gain : numpy.ndarray
        The steady-state filter gain L.
    innovation_var : float
        Steady-state variance of the innovation ``y - C x^- - d^-`` the filter expects when the
        data follow its noise model (um^2): ``C P C^T + R`` on the predicted covariance P.
    """

    def __init__(
        self,
        a: np.ndarray,
        b: np.ndarray,
        c: np.ndarray,
        *,
        measurement_std: float,
        disturbance_std: float,
        process_std: float = 0.0,
        slope_std: float = 0.0,
        state_scale: np.ndarray | None = None,
        covariance: np.ndarray | None = None,
    ) -> None:
        if not (
            measurement_std > 0 and disturbance_std > 0 and process_std >= 0 and slope_std >= 0
        ):
            raise ValueError(
                "observer needs measurement_std > 0, disturbance_std > 0, process_std >= 0 and "
                f"slope_std >= 0; got {measurement_std}, {disturbance_std}, {process_std}, "
                f"{slope_std}"
            )
        n = a.shape[0]
        self.n = n
        self.n_disturbance = nd = 2 if slope_std > 0 else 1
        aa, ba, ca = augmented(a, b, c, nd)
        r = np.array([[measurement_std**2]])
        if covariance is None:
            scale = state_scale_of(a, b[:, 0]) if state_scale is None else state_scale
            q = noise_covariance(b, scale, process_std, disturbance_std, slope_std)
            covariance = scipy_filter(aa, ca, q, float(r[0, 0]), "the fixed observer")
        p = covariance
        # Filter (current-estimate) gain: L = P C^T (C P C^T + R)^-1 on the predicted P.
        self.innovation_var = float((ca @ p @ ca.T + r).item())
        self.gain = (p @ ca.T / self.innovation_var).ravel()
        self.process_std, self.disturbance_std = float(process_std), float(disturbance_std)
        self.a_aug, self.b_aug, self.c_aug = aa, ba, ca[0]
        self.estimate = np.zeros(n + nd)

    @classmethod
    def for_controller(cls, model: Any, task: Any, settings: Any) -> DisturbanceObserver:
        """The observer a model-based controller's settings describe.

        Parameters
        ----------
        model : controllers.prediction.PredictionModel
            Its linear part ``(a, b, c)`` is the observer's model.
        task : controllers.task.ControlTask
            Gives the sensor noise when ``settings.measurement_std`` is None.
        settings
            Has ``measurement_std``, ``disturbance_std``, ``process_std`` and, optionally,
            ``slope_std`` (0 without it).
        """
        return cls(
            model.a,
            model.b,
            model.c,
            measurement_std=measurement_std(settings.measurement_std, task),
            disturbance_std=settings.disturbance_std,
            process_std=settings.process_std,
            slope_std=getattr(settings, "slope_std", 0.0),
        )

    def reset(self, estimate: np.ndarray | None = None) -> None:
        """Set the prior ``[x; d (; s)]`` (default: rest, no disturbance)."""
        size = self.n + self.n_disturbance
        self.estimate = np.zeros(size) if estimate is None else np.array(estimate, float)

    def correct(self, y_measured: float) -> np.ndarray:
        """Measurement update with y (um); returns the filtered ``[x; d]`` (a view, not a copy)."""
        innovation = y_measured - float(self.c_aug @ self.estimate)
        self.estimate += self.gain * innovation
        return self.estimate

    def predict(self, z: float) -> None:
        """Time update with the hidden input z actually applied (equivalent V)."""
        self.estimate = self.a_aug @ self.estimate + self.b_aug * z

    def rescale_input(self, ratio: float) -> None:
        """The model's input is now ``ratio`` times the old one (a new gain estimate,
        :mod:`controllers.gain`): x scales with it, and d takes the difference so that the
        output estimate C x + d, which the measurements set, stays where it is."""
        rescale_states(self.estimate[None, :], self.c_aug, self.n, ratio)

    def rescale_output(self, ratio: float) -> None:
        """The measurements are now ``ratio`` times the old ones (read over a new gain
        estimate, :class:`controllers.nmpc.NonlinearMPC`): x, driven by the same input, stays,
        and d takes the change of the output estimate C x + d."""
        rescale_output_states(self.estimate[None, :], self.c_aug, self.n, ratio)

    def shift_input(self, dx: np.ndarray) -> None:
        """The model's past inputs are now others (a new drive estimate,
        :mod:`controllers.drive`), whose states differ by ``dx``: x moves by it, and d takes
        the difference so that the output estimate C x + d stays where it is."""
        shift_states(self.estimate[None, :], self.c_aug, self.n, dx)

    def slowest_pole_hz(self, dt: float) -> float:
        """Decay rate of the slowest observer pole, -ln|p| / (2 pi dt) (Hz), for reports.

        Parameters
        ----------
        dt : float
            Sample time (s).
        """
        return _slowest_pole_hz(self.a_aug, self.gain, self.c_aug, dt)


def _slowest_pole_hz(a_aug: np.ndarray, gain: np.ndarray, c_aug: np.ndarray, dt: float) -> float:
    """-ln|p| / (2 pi dt) (Hz) of the slowest pole of the filter ``(a_aug, gain, c_aug)``."""
    closed = a_aug - np.outer(a_aug @ gain, c_aug)
    radius = np.abs(np.linalg.eigvals(closed)).max()
    return float(-np.log(max(radius, 1e-300)) / (2 * np.pi * dt))


PROCESS_RATIOS = (0.0, 0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
"""The bank's input-referred process noise, as its static output effect over the sensor noise:
``process_std = ratio * measurement_std / |G(1)|`` (equivalent V) for the model's DC gain G(1)
(um per equivalent V)."""

DISTURBANCE_RATIOS = (1 / 27, 1 / 9, 1 / 3, 1.0, 3.0, 9.0)
"""The bank's output-disturbance random-walk step over the sensor noise:
``disturbance_std = ratio * measurement_std`` (um per sample)."""

PRIOR_RATIOS = (1.0, 1.0)
"""(process, disturbance) ratio of the filter an episode starts with, until the data choose:
close to the single filter's defaults on the PL140 (1.2 and 1.4)."""


RUNAWAY_NIS = 9.0
"""Normalised innovation squared of the most likely filter, averaged over
:data:`RUNAWAY_MEMORY` samples, above which the bank suspects a runaway loop (an RMS innovation
three times the one the filter expects)."""

RUNAWAY_CORRELATION = -0.5
"""Lag-one correlation of those innovations (over their mean square) below which, with
:data:`RUNAWAY_NIS`, the bank suspects a runaway: they alternate in sign, an oscillation above a
third of the sampling rate (a sinusoid at f has the correlation cos(2 pi f dt)). It lies between
the correlation of a stable loop's ringing after a jump and that of the runaways
(``benchmarks/results/design_measurements.md``)."""

RUNAWAY_MEMORY = 35
"""Samples over which the guard averages its two statistics (exponential forgetting 1 - 1/35).
A runaway grows within tens of samples: over the bank's 200-sample memory of likelihoods the
average crosses :data:`RUNAWAY_NIS` when the drive has swung between its limits for tens of
samples already. Chosen on the benchmark's robustness plants, with
:data:`RUNAWAY_PERSISTENCE`, among 25, 35 and 50 samples: the shortest on which the guard fires
on no stable loop (``benchmarks/results/design_measurements.md`` has the figures)."""

RUNAWAY_PERSISTENCE = 3
"""Consecutive samples over which both tests must hold before the guard falls back. Over the
first samples of an abrupt oscillation the lag-one correlation is whatever their phases make
it: a ringing whose steady-state correlation is above :data:`RUNAWAY_CORRELATION` can read
below it for one or two samples, and then trips a single-sample test; three samples in a row
do not trip on it, and cost a runaway those two samples of delay. Measured on a synthetic
ringing (250-330 Hz, 200 times the noise, appearing within a sample) and on the robustness
plants' runaways: ``benchmarks/results/design_measurements.md``."""


def augmented(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, n_disturbance: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, B, C)`` of ``[x; d (; s)]``: the model, then d (+= s, s constant) on the output."""
    n, nd = a.shape[0], n_disturbance
    m = n + nd
    aa = np.zeros((m, m))
    aa[:n, :n] = a
    aa[n:, n:] = np.eye(nd) + np.eye(nd, k=1)  # d += s, s constant
    ba = np.zeros(m)
    ba[:n] = b[:, 0]
    ca = np.zeros((1, m))
    ca[0, :n] = c[0]
    ca[0, n] = 1.0
    return aa, ba, ca


def noise_covariance(
    b: np.ndarray,
    scale: np.ndarray,
    process_std: float,
    disturbance_std: float,
    slope_std: float = 0.0,
) -> np.ndarray:
    """Process noise covariance of ``[x; d (; s)]`` (module docstring): input-referred noise
    on x, the random walks of d (and s), and the well-posedness term scaled per state."""
    n = b.shape[0]
    nd = 2 if slope_std > 0 else 1
    q = np.zeros((n + nd, n + nd))
    q[:n, :n] = process_std**2 * np.outer(b[:, 0], b[:, 0])
    q[n, n] = disturbance_std**2
    if nd == 2:
        q[n + 1, n + 1] = slope_std**2
    return q + 1e-12 * np.diag(np.r_[scale, np.ones(nd)])


def state_scale_of(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each state's variance under unit white input (the controllability Gramian's diagonal,
    floored at 1e-12 of its largest): the units of the Riccati equation's well-posedness term.
    An unstable ``a`` (a candidate model the adaptive MPC is about to refuse) has no Gramian,
    and a zero ``b`` a zero one; their states get unit scale (the identity in the states' own
    units)."""
    if np.max(np.abs(np.linalg.eigvals(a)), initial=0.0) >= 1.0:
        return np.ones(a.shape[0])
    variance = np.diag(scipy.linalg.solve_discrete_lyapunov(a, np.outer(b, b)))
    if not variance.max() > 0:  # no input path (b = 0): nothing to scale by
        return np.ones(a.shape[0])
    return np.maximum(variance, 1e-12 * variance.max())


BANKS_KEPT = 256
"""Observer banks' designs kept by content (:func:`_bank_design`), one per linear model, sensor
noise and grid. A benchmark worker meets up to six identified models (three identification
seeds, on the nominal bender and on the bench), each with the adaptive MPC's 34 members (the
fixed MPCs' banks are its first member's): 204, and a group's oracles (10 drawn plants at
most) on top: 256."""

_bank_designs = ContentCache(BANKS_KEPT)


def _bank_design(
    a: np.ndarray,
    b: np.ndarray,
    c: np.ndarray,
    measurement_std: float,
    ratios: list[tuple[float, float]],
    slope_std: float,
) -> dict[str, Any]:
    """What an :class:`ObserverBank` of the model ``(a, b, c)`` fixes when it is built: every
    filter's steady-state gain and innovation variance under the grid's noise levels
    (``ratios``: (process, disturbance) ratio pairs), and the augmented model.

    A pure function of its arguments, and most of a bank's construction (a Riccati equation
    per filter), so the bank keeps it by content (:data:`BANKS_KEPT`,
    :mod:`piezo_env.memo`): the adaptive MPC's set, and the fixed MPCs on the same model,
    solve each bank once per process.

    Raises
    ------
    ValueError
        If the model's DC gain is not finite and nonzero, or a noise level is invalid
        (:class:`DisturbanceObserver`).
    """
    n = a.shape[0]
    dc_gain = abs((c @ np.linalg.solve(np.eye(n) - a, b)).item())
    if not (np.isfinite(dc_gain) and dc_gain > 0):
        raise ValueError(f"the model's DC gain must be finite and nonzero, got {dc_gain}")
    scale = state_scale_of(a, b[:, 0])  # the same for every filter: solved once
    levels = [(rx * measurement_std / dc_gain, rd * measurement_std) for rx, rd in ratios]
    # Every filter's Riccati equation at once (controllers.riccati).
    aa, _, ca = augmented(a, b, c, 2 if slope_std > 0 else 1)
    q = np.array([noise_covariance(b, scale, px, dx, slope_std) for px, dx in levels])
    covariances, fallbacks = filter_riccati(aa, ca, q, np.full(len(levels), measurement_std**2))
    filters = [
        DisturbanceObserver(
            a,
            b,
            c,
            measurement_std=measurement_std,
            disturbance_std=dx,
            process_std=px,
            slope_std=slope_std,
            covariance=p,
        )
        for (px, dx), p in zip(levels, covariances, strict=True)
    ]
    first = filters[0]
    return {
        "a_aug": first.a_aug,
        "b_aug": first.b_aug,
        "c_aug": first.c_aug,
        "riccati_fallbacks": fallbacks,
        "noise_levels": np.array([(f.process_std, f.disturbance_std) for f in filters]),
        "gains": np.array([f.gain for f in filters]),
        "innovation_var": np.array([f.innovation_var for f in filters]),
    }


class ObserverBank:
    """Steady-state Kalman filters of one model under a grid of noise models; the data choose.

    Multiple-model adaptive estimation (Magill 1965; Maybeck, *Stochastic Models, Estimation
    and Control* vol. 2, ch. 10) over the two unknown noise levels of
    :class:`DisturbanceObserver`: one filter per pair (``process_std``, ``disturbance_std``)
    of the grid :data:`PROCESS_RATIOS` x :data:`DISTURBANCE_RATIOS`, each scaled by the sensor
    noise (the task's noise bound) and the model's DC gain, so that the grid means the same on
    every bender. All filters run on the same z and y. Each filter's innovation log-likelihood
    ``-(log S_k + nu_k^2 / S_k) / 2``, with ``S_k`` its steady-state innovation variance, is
    averaged with exponential forgetting over ``memory`` samples, and the controller uses the
    estimate of the filter with the largest: a windowed maximum-likelihood estimate of the
    noise covariances (as in Mehra 1970's adaptive filtering), made over a grid so that each
    gain is a steady-state one computed once.

    Why: the noise passed into the loop and the model error corrected are one trade-off, and
    its best point depends on what the model gets wrong, which differs by reference and plant
    (see the module docstring). With the identified PL140 model, sensor noise only, the
    likelihood picks almost no process noise and a slow disturbance; at 50 Hz, where the
    nonlinearity's error passes the first resonance as the third harmonic, more process noise;
    on a plant whose hysteresis or stiffness differs from the model's, the fast filters. Against
    the single default filter: ``benchmarks/results/identification_precision.md`` (identified
    models) and ``benchmarks/results/design_measurements.md`` (Prandtl-Ishlinskii plant). Each
    filter is a fixed, stable observer of the same model; only which estimate the controller
    reads changes.

    A runaway guard. The likelihood judges each filter by how well it predicts the data, not by
    whether the loop it closes is stable on the plant at hand, and the two can feed each other: on a
    bender within the datasheet tolerances whose first resonance sits near the Nyquist frequency
    (the PL127's 420 Hz at 1 kHz, moved by +-20 % or damped twice as much), the fast filters' loops
    are unstable, their growing innovations make them still more likely, and the loop runs into the
    drive limits. The bank therefore watches the most likely filter: when its normalised innovation
    squared, averaged over :data:`RUNAWAY_MEMORY` samples, exceeds :data:`RUNAWAY_NIS` while its
    innovations alternate in sign (lag-one correlation below :data:`RUNAWAY_CORRELATION` of their
    mean square: an oscillation above a third of the sampling rate, which the model error at the
    benchmark's references is not), for :data:`RUNAWAY_PERSISTENCE` samples in a row, it falls
    back, for the rest of the episode, to its :attr:`fallback` filter: the least process noise (none
    on the default grid) and the slowest disturbance, the filter that trusts the model's dynamics
    most and corrects only a slow output offset, whose loop has the largest modulus margin of the
    bank on every catalogue bender (tested on all five). The step is kept in :attr:`runaway_at`, and
    the benchmark reports it (``benchmarks/results/tracking*.md``). Both tests are needed: the size
    of the innovations alone also fires where the loop is stable and the model error large; the
    sign alternation separates the
    runaways (near-Nyquist oscillations, correlation close to -1) from the ringing of a stable
    loop after a jump at the drive limit, which settles. A guard on the drive sitting at its
    limits fires only on runaways but late; asking also that the oscillation grow lets the
    fastest runaways swing the drive into saturation first, and over a few samples any abrupt
    onset looks like growth. The thresholds are chosen on the benchmark's robustness plants of
    the PL127 and the PL140 so that no stable row changes; the alternatives measured there, and
    the correlations of the runaways and of that ringing, are in
    ``benchmarks/results/design_measurements.md``.

    Parameters
    ----------
    a, b, c : numpy.ndarray
        Linear model (see :class:`DisturbanceObserver`).
    measurement_std : float
        Sensor noise standard deviation (um), > 0: the innovation model's R and the grid's
        scale.
    memory : int
        Samples over which the likelihoods are averaged (exponential forgetting 1 - 1/memory).
    process_ratios, disturbance_ratios : sequence of float
        The grid (see :data:`PROCESS_RATIOS`, :data:`DISTURBANCE_RATIOS`).
    slope_std : float
        As :class:`DisturbanceObserver`'s, for every filter.

    Attributes
    ----------
    noise_levels : list of (float, float)
        (process_std in equivalent V, disturbance_std in um per sample) of each filter.
    selected : int
        Index of the filter the controller reads.
    selection_counts : numpy.ndarray
        Samples each filter was selected since the last reset.
    fallback : int
        Index of the filter the runaway guard falls back to (the smallest process noise of the
        grid, then the smallest disturbance step).
    runaway_at : int or None
        Sample (from 0, counted from the last reset) at which the guard fell back; None if it
        has not.
    """

    def __init__(
        self,
        a: np.ndarray,
        b: np.ndarray,
        c: np.ndarray,
        *,
        measurement_std: float,
        memory: int = 200,
        process_ratios: tuple[float, ...] = PROCESS_RATIOS,
        disturbance_ratios: tuple[float, ...] = DISTURBANCE_RATIOS,
        slope_std: float = 0.0,
    ) -> None:
        if not (isinstance(memory, int) and memory >= 1):
            raise ValueError(f"memory must be an integer >= 1 sample, got {memory!r}")
        ratios = list(itertools.product(process_ratios, disturbance_ratios))
        design = _bank_designs.get(
            [a, b, c, measurement_std, ratios, slope_std],
            lambda: _bank_design(a, b, c, measurement_std, ratios, slope_std),
        )
        self.n, self.n_disturbance = a.shape[0], 2 if slope_std > 0 else 1
        self.a_aug, self.b_aug, self.c_aug = design["a_aug"], design["b_aug"], design["c_aug"]
        self._a_aug_t = self.a_aug.T.copy()
        self.riccati_fallbacks = design["riccati_fallbacks"]
        self.noise_levels = [(p, d) for p, d in design["noise_levels"].tolist()]
        self._gains = design["gains"]
        variance = design["innovation_var"]
        self._half_inverse_var = 0.5 / variance
        self._half_log_var = 0.5 * np.log(variance)
        self._keep = 1.0 - 1.0 / memory
        self._guard_keep = 1.0 - 1.0 / RUNAWAY_MEMORY
        self.prior = int(np.argmin(_prior_distance(np.array(ratios))))
        self._ratios = ratios
        self.admissible = np.ones(len(ratios), dtype=bool)
        self._allocate(len(ratios))
        self.fallback = int(np.lexsort(np.array(ratios).T[::-1])[0])  # smallest process, then d
        self.reset()

    def _allocate(self, count: int) -> None:
        """The bank's running state in fixed blocks, updated in place (by numpy or by the
        compiled kernels, :mod:`controllers.native.step_kernels`): the attributes are views."""
        size = self.n + self.n_disturbance
        self._state = np.zeros(count * size + 5 * count)
        self._estimates = self._state[: count * size].reshape(count, size)
        (
            self._score,
            self._mean_nis,
            self._mean_lag,
            self._last_innovation,
            self._penalty,  # -inf on the filters the bank may not select
        ) = self._state[count * size :].reshape(5, count)
        # selected, samples, consecutive suspect samples, runaway sample (-1: none)
        self._counters = np.zeros(4, dtype=np.int64)
        self.selection_counts = np.zeros(count, dtype=np.int64)
        # filters, state size, fallback filter, persistence
        self._dims = np.array([count, size, 0, RUNAWAY_PERSISTENCE], dtype=np.int64)
        self._a_aug = np.ascontiguousarray(self.a_aug, dtype=float)
        self._b_aug = np.ascontiguousarray(self.b_aug, dtype=float)
        self._c_aug = np.ascontiguousarray(self.c_aug, dtype=float)
        self._gains = np.ascontiguousarray(self._gains, dtype=float)
        self._parameters = np.array(
            [self._keep, self._guard_keep, RUNAWAY_NIS, RUNAWAY_CORRELATION], dtype=float
        )
        self._correct_native = self._predict_native = None
        library, build = kernels_for(size)
        self.native = [build]
        if library is None:
            return
        self._correct_native = bind(
            library.bank_correct,
            self._dims,
            self._parameters,
            self._c_aug,
            self._gains,
            self._half_log_var,
            self._half_inverse_var,
            self._state,
            self._counters,
            self.selection_counts,
        )
        self._predict_native = bind(
            library.bank_predict, self._dims, self._a_aug, self._b_aug, self._state
        )

    @property
    def gains(self) -> np.ndarray:
        """(F, m) every filter's steady-state gain (read-only: the kernels hold its memory)."""
        return self._gains

    @property
    def selected(self) -> int:
        """Index of the filter the controller reads."""
        return int(self._counters[0])

    @selected.setter
    def selected(self, index: int) -> None:
        self._counters[0] = index

    @property
    def fallback(self) -> int:
        """Index of the filter the runaway guard falls back to."""
        return int(self._dims[2])

    @fallback.setter
    def fallback(self, index: int) -> None:
        self._dims[2] = index

    @property
    def runaway_at(self) -> int | None:
        """Sample (from 0, since the last reset) at which the guard fell back; None if not."""
        at = int(self._counters[3])
        return None if at < 0 else at

    def allow(self, admissible: np.ndarray) -> None:
        """Mid-episode: from now on select only the filters where ``admissible`` is True; the
        estimates and likelihoods carry on (the adaptive MPC narrows or widens the set as its
        data do). If the filter selected is no longer allowed, the most likely allowed one is.

        Raises
        ------
        ValueError
            As :meth:`restrict`.
        """
        mask = self._mask(admissible)
        self.admissible = mask
        self._penalty[:] = np.where(mask, 0.0, -np.inf)
        if not mask[self.selected] and self.runaway_at is None:
            self.selected = int(np.argmax(self._score + self._penalty))

    def _mask(self, admissible: np.ndarray) -> np.ndarray:
        mask = np.asarray(admissible, dtype=bool)
        if mask.shape != (len(self.noise_levels),) or not mask.any():
            raise ValueError(
                f"admissible must be a boolean mask over the {len(self.noise_levels)} filters "
                f"with at least one True, got {mask.tolist()}"
            )
        return mask

    def restrict(self, admissible: np.ndarray) -> None:
        """Let the bank select only the filters where ``admissible`` is True (boolean, one per
        filter); the prior becomes the admissible filter nearest the prior ratios, the fallback
        the admissible one of least process noise, then least disturbance.

        Raises
        ------
        ValueError
            If no filter is admissible, or the mask's length is not the number of filters.
        """
        self.allow(admissible)
        kept = np.flatnonzero(self.admissible)
        ratios = np.array(self._ratios)[kept]
        self.prior = int(kept[np.argmin(_prior_distance(ratios))])
        self.fallback = int(kept[np.lexsort(ratios.T[::-1])[0]])
        self.reset()

    @classmethod
    def for_controller(cls, model: Any, task: Any, settings: Any) -> ObserverBank:
        """The bank of a model-based controller (see :meth:`DisturbanceObserver.for_controller`;
        ``settings.bank_memory`` is the memory)."""
        return cls(
            model.a,
            model.b,
            model.c,
            measurement_std=measurement_std(settings.measurement_std, task),
            memory=settings.bank_memory,
            slope_std=getattr(settings, "slope_std", 0.0),
        )

    @property
    def estimate(self) -> np.ndarray:
        """The selected filter's ``[x; d (; s)]`` (a view)."""
        return self._estimates[self.selected]

    @property
    def gain(self) -> np.ndarray:
        """The selected filter's gain."""
        return self.gains[self.selected]

    @property
    def noise_level(self) -> tuple[float, float]:
        """The selected filter's (process_std in equivalent V, disturbance_std in um)."""
        return self.noise_levels[self.selected]

    def reset(self, estimate: np.ndarray | None = None, *, selected: int | None = None) -> None:
        """Set every filter's prior ``[x; d (; s)]`` (default: rest) and forget the
        likelihoods; start from filter ``selected`` (default: the prior's)."""
        self._estimates[:] = 0.0 if estimate is None else np.asarray(estimate, float)
        for running in (self._score, self._mean_nis, self._mean_lag, self._last_innovation):
            running[:] = 0.0
        self.selection_counts[:] = 0
        self._counters[:] = (self.prior if selected is None else int(selected), 0, 0, -1)

    @property
    def guard_statistics(self) -> tuple[float, float]:
        """What the runaway guard reads for the most likely filter: its normalised innovation
        squared averaged over :data:`RUNAWAY_MEMORY` samples, and the lag-one correlation of its
        innovations over their mean square (dimensionless; 0 and 0 before the first sample)."""
        best = int(np.argmax(self._score + self._penalty))
        nis = float(self._mean_nis[best])
        return nis, float(self._mean_lag[best] / nis) if nis > 0 else 0.0

    def fall_back(self, at: int | None = None) -> None:
        """Read the :attr:`fallback` filter for the rest of the episode, as the runaway guard
        does; ``at`` is the sample recorded in :attr:`runaway_at` (default: the last corrected
        one). The adaptive MPC calls it on a rebuilt bank to keep the guard's decision."""
        samples = int(self._counters[1])
        self._counters[3] = max(samples - 1, 0) if at is None else int(at)
        self.selected = self.fallback

    def correct(self, y_measured: float) -> np.ndarray:
        """Measurement update of every filter with y (um), score them and select; returns the
        selected filter's filtered ``[x; d]`` (a view that the next update overwrites).

        One call of the compiled kernel where it is built
        (:mod:`controllers.native.step_kernels`), else the same operations in numpy."""
        if self._correct_native is not None:
            self._correct_native(y_measured)
            return self._estimates[self._counters[0]]
        innovation = y_measured - self._estimates @ self.c_aug
        self._estimates += self._gains * innovation[:, None]
        log_likelihood = -self._half_log_var - innovation**2 * self._half_inverse_var
        keep, new = self._keep, 1.0 - self._keep
        self._score[:] = keep * self._score + new * log_likelihood
        normalised = 2.0 * self._half_inverse_var * innovation
        keep, new = self._guard_keep, 1.0 - self._guard_keep
        self._mean_nis[:] = keep * self._mean_nis + new * normalised * innovation
        self._mean_lag[:] = keep * self._mean_lag + new * normalised * self._last_innovation
        self._last_innovation[:] = innovation
        counters = self._counters  # selected, samples, suspect run, runaway sample
        counters[1] += 1
        if counters[3] < 0:
            best = int(np.argmax(self._score + self._penalty))
            nis = self._mean_nis[best]
            suspect = (
                best != self.fallback  # reading the fallback already: nothing to fall back to
                and nis > RUNAWAY_NIS
                and self._mean_lag[best] < RUNAWAY_CORRELATION * nis
            )
            counters[2] = counters[2] + 1 if suspect else 0
            if counters[2] >= RUNAWAY_PERSISTENCE:
                self.fall_back()
            else:
                counters[0] = best
        self.selection_counts[counters[0]] += 1
        return self._estimates[counters[0]]

    def predict(self, z: float) -> None:
        """Time update of every filter with the hidden input z actually applied (equivalent V)."""
        if self._predict_native is not None:
            self._predict_native(z)
            return
        self._estimates[:] = self._estimates @ self._a_aug_t + self.b_aug * z

    def rescale_input(self, ratio: float) -> None:
        """Every filter's :meth:`DisturbanceObserver.rescale_input`."""
        rescale_states(self._estimates, self.c_aug, self.n, ratio)

    def rescale_output(self, ratio: float) -> None:
        """Every filter's :meth:`DisturbanceObserver.rescale_output`."""
        rescale_output_states(self._estimates, self.c_aug, self.n, ratio)

    def shift_input(self, dx: np.ndarray) -> None:
        """Every filter's :meth:`DisturbanceObserver.shift_input`."""
        shift_states(self._estimates, self.c_aug, self.n, dx)

    def slowest_pole_hz(self, dt: float) -> float:
        """The prior filter's slowest-pole decay rate (Hz), for reports; see
        :meth:`DisturbanceObserver.slowest_pole_hz`."""
        return _slowest_pole_hz(self.a_aug, self._gains[self.prior].copy(), self.c_aug, dt)

    def selection_summary(self, top: int = 3) -> list[dict[str, float]]:
        """The filters selected most often since the last reset, with their share of the
        samples (JSON-safe)."""
        total = max(int(self.selection_counts.sum()), 1)
        order = np.argsort(-self.selection_counts, kind="stable")[:top]
        return [
            {
                "process_std_V": self.noise_levels[k][0],
                "disturbance_std_um": self.noise_levels[k][1],
                "share": float(self.selection_counts[k] / total),
            }
            for k in order
            if self.selection_counts[k] > 0
        ]


def _prior_distance(ratios: np.ndarray) -> np.ndarray:
    """Log distance of (process, disturbance) ratio pairs ((F, 2)) from :data:`PRIOR_RATIOS`."""
    return np.abs(np.log((ratios[:, 0] + 1e-3) / (PRIOR_RATIOS[0] + 1e-3))) + np.abs(
        np.log(ratios[:, 1] / PRIOR_RATIOS[1])
    )


def rescale_states(estimates: np.ndarray, c_aug: np.ndarray, n: int, ratio: float) -> None:
    """In place, on rows ``[x; d (; s)]``: x times ``ratio``, d less the change of C x."""
    output = estimates[:, :n] @ c_aug[:n]
    estimates[:, :n] *= ratio
    estimates[:, n] -= (ratio - 1.0) * output


def shift_states(estimates: np.ndarray, c_aug: np.ndarray, n: int, dx: np.ndarray) -> None:
    """In place, on rows ``[x; d (; s)]``: x plus ``dx`` ((n,)), d less C dx (summed left to
    right, as the linear MPC's compiled step sums it, :mod:`controllers.native.fused_step`)."""
    output = 0.0
    for j in range(n):
        output += float(dx[j]) * float(c_aug[j])
    estimates[:, :n] += dx
    estimates[:, n] -= output


def rescale_output_states(estimates: np.ndarray, c_aug: np.ndarray, n: int, ratio: float) -> None:
    """In place, on rows ``[x; d (; s)]``: the output estimate C x + d times ``ratio`` with x
    kept (d takes the change). A slope s of d is scaled with it, which leaves out the change of
    C x between samples that d' now also carries: exact without a slope state (the nonlinear
    MPC's observer, the one caller, has none). C x is summed left to right, as the NMPC's
    compiled step sums it (:mod:`controllers.native.nmpc_step`), so both give the same bits."""
    output = np.zeros(estimates.shape[0])
    for j in range(n):
        output += estimates[:, j] * c_aug[j]
    estimates[:, n] = ratio * (output + estimates[:, n]) - output
    estimates[:, n + 1 :] *= ratio


def make_observer(model: Any, task: Any, settings: Any) -> DisturbanceObserver | ObserverBank:
    """The observer ``settings.observer`` names (``"fixed"`` when the settings have none)."""
    if getattr(settings, "observer", "fixed") == "bank":
        return ObserverBank.for_controller(model, task, settings)
    return DisturbanceObserver.for_controller(model, task, settings)
