"""Multi-step prediction error, and a three-parameter modal correction of an identified ARX.

:func:`multi_step_errors` is the criterion an adaptive controller judges models by: from every
start in a record, the model runs ``horizon`` samples ahead on the measured inputs, from the
measured outputs up to the start (what an MPC does over its horizon). A model can fit the next
sample well and still be wrong over the horizon; this criterion sees it.

:func:`scale_modes` and :func:`fit_modal_correction` correct an identified model the way the
plant differs between benders of one type or over temperature: a stiffer bender has a smaller
gain and a higher resonance, a warmer one the reverse, and damping varies. Three numbers (DC
gain factor ``g``, frequency factor ``alpha`` and damping factor ``beta`` of the first bending
mode) describe that, where a full re-estimation has ``na + nb`` coefficients, most of which a
single sine does not excite: the correction is identifiable from a reference at one frequency
(gain and phase there fix two of the three numbers, the rest of the record the third).

How a mode is scaled. In partial fractions the model is
``G(q) = sum_i rho_i p_i q^-1 / (1 - p_i q^-1)`` (+ direct terms), each mode strictly proper;
:class:`ModalSplit` separates the first mode from the rest once. For the first
bending mode (the complex pair of largest modulus) the continuous pole ``s = ln(p) / dt`` becomes
``s' = alpha (beta Re s + j Im s)``: natural frequency times ``alpha``, damping ratio times
about ``beta``. The residue keeps the mode's static contribution: a continuous mode
``r / (s - s_i)`` discretised with a zero-order hold is
``c q^-1 / (1 - p_i q^-1) = rho (1 / (1 - p_i q^-1) - 1)`` with ``c = r / s_i (p_i - 1)`` and
``rho = c / p_i``, so with ``r / s_i`` fixed, ``rho' = rho (p' - 1) p / ((p - 1) p')``; for a
pure change of stiffness
(``beta = 1``) this is exactly the ZOH image of the frequency-scaled mode ``G(s / alpha)``.
The other poles (fast real poles, modes aliased near the Nyquist frequency) are kept. All
residues are then multiplied by ``g``, and the direct term restores strict properness.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize
import scipy.signal

from identification.arx import ARXModel

__all__ = [
    "ModalCorrection",
    "ModalSplit",
    "first_mode_pole",
    "fit_modal_correction",
    "multi_step_errors",
    "scale_modes",
]


def multi_step_errors(
    model: ARXModel, u: np.ndarray, y: np.ndarray, horizon: int, *, stride: int = 1
) -> np.ndarray:
    """Errors of the model's ``1 .. horizon``-step-ahead predictions over a record.

    Parameters
    ----------
    model : ARXModel
        The model (output unit, input unit).
    u, y : numpy.ndarray
        Input and measured output, same length T; ``y_t`` follows ``u_t-1`` and older.
    horizon : int
        Prediction horizon k (samples).
    stride : int
        Use every ``stride``-th start only.

    Returns
    -------
    numpy.ndarray
        Shape (S, k): row s is ``y_t+j - y_hat_t+j|t`` for j = 1 .. k from the s-th start t
        (starts ``max(na, nb) - 1 .. T - k - 1``: each has a full measured history); empty
        when the record is too short.
    """
    u = np.asarray(u, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    na, nb = model.na, model.nb
    first = max(na, nb, 1) - 1
    starts = np.arange(first, y.size - horizon, stride)
    if starts.size == 0:
        return np.zeros((0, horizon))
    forced = scipy.signal.lfilter(np.concatenate([[0.0], model.b]), 1.0, u)
    history = np.stack([y[starts - i] for i in range(na)], axis=1) if na else None
    errors = np.empty((starts.size, horizon))
    for j in range(1, horizon + 1):
        predicted = forced[starts + j]
        if na:
            predicted = predicted + history @ model.a
            history[:, 1:] = history[:, :-1]
            history[:, 0] = predicted
        errors[:, j - 1] = y[starts + j] - predicted
    return errors


class ModalCorrection:
    """The three factors of :func:`scale_modes`: ``gain``, ``frequency``, ``damping`` (-)."""

    __slots__ = ("damping", "frequency", "gain")

    def __init__(self, gain: float = 1.0, frequency: float = 1.0, damping: float = 1.0) -> None:
        for name, value in (("gain", gain), ("frequency", frequency), ("damping", damping)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} factor must be finite and > 0, got {value}")
        self.gain, self.frequency, self.damping = float(gain), float(frequency), float(damping)

    def __repr__(self) -> str:
        return (
            f"ModalCorrection(gain={self.gain:.4g}, frequency={self.frequency:.4g}, "
            f"damping={self.damping:.4g})"
        )


def first_mode_pole(poles: np.ndarray) -> complex | None:
    """The first bending mode's upper pole: the complex pole of largest modulus (the slowest
    decaying, the first mode on every model identified or built here); None without a
    complex pair."""
    index = _first_mode_index(poles)
    return None if index is None else complex(poles[index])


def _first_mode_index(poles: np.ndarray) -> int | None:
    upper = np.flatnonzero(poles.imag > 1e-9)
    return None if upper.size == 0 else int(upper[np.argmax(np.abs(poles[upper]))])


def _first_mode(poles: np.ndarray) -> int:
    """Index of the first bending mode's upper pole (:func:`first_mode_pole`), or ValueError."""
    index = _first_mode_index(poles)
    if index is None:
        raise ValueError(
            "the model has no complex pole pair: there is no bending mode to correct "
            f"(poles {np.round(poles, 4).tolist()})"
        )
    return index


class ModalSplit:
    """An ARX model split into its first bending mode and the rest, in powers of w = q^-1::

        G(w) = B(w) / A(w) = R(w) / A_rest(w) + M(w),   M(w) = 2 Re(rho p w / (1 - p w))

    (the mode in strictly proper form, ``rho`` its residue), so that :meth:`scaled` only
    rebuilds the mode: a few polynomial products, no root finding.

    Parameters
    ----------
    model : ARXModel
        With ``0 < na <= nb`` and a complex pole pair (:func:`scale_modes`).
    pole : complex, optional
        Split off the mode of the model's upper complex pole nearest this one (another mode
        than the first, e.g. to move every mode with a stiffness factor); default: the first
        bending mode.
    """

    def __init__(self, model: ARXModel, pole: complex | None = None) -> None:
        na, nb = model.na, model.nb
        if nb < na or na == 0:
            raise ValueError(
                f"a modal correction needs an ARX model with 0 < na <= nb, got na = {na}, nb = {nb}"
            )
        self.model = model
        num = np.concatenate([[0.0], model.b])  # B(w), lowest power first
        poles = model.poles()
        top = _first_mode(poles)
        if pole is not None:
            upper = np.flatnonzero(poles.imag > 1e-9)
            top = int(upper[np.argmin(np.abs(poles[upper] - pole))])
        p = poles[top]
        others = np.delete(poles, [top, int(np.argmin(np.abs(poles - np.conj(p))))])
        self.rest_den = _real_poly(others)  # A_rest(w) = prod (1 - p_j w)
        # Residue at w = 1 / p: rho = B(1/p) / (A_rest(1/p) (1 - conj(p) / p)).
        w = 1.0 / p
        rho = np.polyval(num[::-1], w) / (
            np.polyval(self.rest_den[::-1], w) * (1.0 - np.conj(p) * w)
        )
        self.p, self.rho = p, rho
        remainder = num - _padded(np.convolve(self._mode_num(p, rho), self.rest_den), num.size)
        # R(w): B - N A_rest = R Q exactly (the division's remainder is rounding only).
        self.rest_num = np.polynomial.polynomial.polydiv(remainder, _real_poly([p, np.conj(p)]))[0]

    @staticmethod
    def _mode_num(p: complex, rho: complex) -> np.ndarray:
        """N(w) with M = N / Q, Q = (1 - p w)(1 - conj(p) w): 2 Re(rho p w (1 - conj(p) w))."""
        return np.real(np.array([0.0, 2.0 * rho * p, -2.0 * rho * p * np.conj(p)]))

    def scaled(self, correction: ModalCorrection) -> ARXModel:
        """The model with the correction applied (see the module docstring)."""
        s = np.log(self.p) / self.model.dt
        s_new = correction.frequency * (correction.damping * s.real + 1j * s.imag)
        return self.moved(np.exp(s_new * self.model.dt), correction.gain)

    def _residue(self, p_old: complex, p_new: complex) -> complex:
        """The residue at ``p_new`` of the mode moved there from its pole ``p_old`` (``p`` or
        its conjugate) with its static contribution ``2 Re(rho p / (1 - p))`` kept."""
        rho = self.rho if p_old == self.p else np.conj(self.rho)
        return rho * (p_new - 1.0) * p_old / ((p_old - 1.0) * p_new)

    def moved(self, p_new: complex, gain: float = 1.0, p_old: complex | None = None) -> ARXModel:
        """The model with the mode's pole ``p_old`` (default: ``p``; or its conjugate) moved to
        ``p_new``, its static contribution kept, and the whole times ``gain``."""
        model = self.model
        p_old = self.p if p_old is None else p_old
        rho_new = self._residue(p_old, p_new)
        if p_new.imag < 0:  # the same pair, written with its upper pole
            p_new, rho_new = np.conj(p_new), np.conj(rho_new)
        gain = float(gain)
        q_new = _real_poly([p_new, np.conj(p_new)])
        size = model.nb + 1
        num = gain * (
            _padded(np.convolve(self.rest_num, q_new), size)
            + _padded(np.convolve(self._mode_num(p_new, rho_new), self.rest_den), size)
        )
        den = np.convolve(self.rest_den, q_new)
        return ARXModel(
            -den[1 : model.na + 1],
            num[1:],
            noise_bound=model.noise_bound,
            dt=model.dt,
            method="modal-correction",
        )


def _real_poly(roots: np.ndarray) -> np.ndarray:
    """Coefficients (lowest power first, real) of prod (1 - r w) over the roots."""
    poly = np.ones(1, dtype=np.complex128)
    for r in np.atleast_1d(roots):
        poly = np.convolve(poly, [1.0, -r])
    return np.real(poly)


def _padded(coefficients: np.ndarray, size: int) -> np.ndarray:
    """The first ``size`` coefficients, zero-padded (the degrees here never exceed it)."""
    out = np.zeros(size)
    out[: min(size, coefficients.size)] = coefficients[:size]
    return out


def scale_modes(model: ARXModel, correction: ModalCorrection) -> ARXModel:
    """The model with its first bending mode and gain corrected (see the module docstring).

    Parameters
    ----------
    model : ARXModel
        Identified model with ``0 < na <= nb`` (so that the corrected model has the same
        orders and the same measured-history realization) and a complex pole pair.
    correction : ModalCorrection

    Returns
    -------
    ARXModel
        Same orders, dt and noise bound.
    """
    return ModalSplit(model).scaled(correction)


def fit_modal_correction(
    model: ARXModel,
    u: np.ndarray,
    y: np.ndarray,
    *,
    horizon: int = 20,
    start: ModalCorrection | None = None,
    stride: int = 1,
    max_nfev: int = 30,
) -> tuple[ModalCorrection, ARXModel]:
    """The correction of ``model`` that minimises the multi-step prediction error on a record.

    Least squares (:func:`scipy.optimize.least_squares`, trust region reflective) over the
    logarithms of the three factors, bounded to ``[1/2, 2]``: the datasheet tolerances (+-20 %
    stiffness and resonance) lie well inside, and so do first-mode damping ratios of half to
    twice the identified one. The damping bound matters: a reference at one frequency says
    little about damping, and an unbounded fit drifts along that flat direction.

    Parameters
    ----------
    model : ARXModel
        The model to correct (:func:`scale_modes`'s conditions).
    u, y : numpy.ndarray
        Record (same length); see :func:`multi_step_errors`.
    horizon : int
        Prediction horizon of the criterion (samples).
    start : ModalCorrection, optional
        Starting point (default: no correction).
    stride : int
        Use every ``stride``-th start of the record (cheaper, nearly the same optimum).
    max_nfev : int
        Cap on the criterion's evaluations (besides those of the finite-difference Jacobian).

    Returns
    -------
    (ModalCorrection, ARXModel)
        The factors and the corrected model.
    """
    start = start or ModalCorrection()
    x0 = np.log([start.gain, start.frequency, start.damping])
    lower = np.log([0.5, 0.5, 0.5])
    upper = np.log([2.0, 2.0, 2.0])
    x0 = np.clip(x0, lower + 1e-9, upper - 1e-9)

    split = ModalSplit(model)

    def residuals(x: np.ndarray) -> np.ndarray:
        corrected = split.scaled(ModalCorrection(*np.exp(x)))
        return multi_step_errors(corrected, u, y, horizon, stride=stride).ravel()

    result = scipy.optimize.least_squares(
        residuals, x0, bounds=(lower, upper), x_scale=0.1, diff_step=1e-4, max_nfev=max_nfev
    )
    correction = ModalCorrection(*np.exp(result.x))
    return correction, split.scaled(correction)
