"""Hidden signal of the Hammerstein model from the measured output: the inverse ARX model.

Paper step d (eq. 25). With the ARX model ``A(q) y = B(q) z + nu`` and ``|nu_t| <= r``, the
equation error ``e_t = y_t - sum_i a_i y_{t-i} = sum_j b_j z_{t-j} + nu_t`` is known from the
measured output, and ``z`` follows by running the recursion of ``B`` backwards:

    z_{t-1} = (e_t - sum_{j>=2} b_j z_{t-j}) / b_1.

The recursion filters ``nu`` by ``1/B``: the error of ``z_hat`` is ``(1/B) nu``, not ``nu / b_1``.
Its worst case is ``r ||1/B||_1`` (the L1 norm of the impulse response of ``1/B``) and, for
independent noise uniform on ``[-r, r]``, its RMS is ``r / sqrt(3) ||1/B||_2``
(:func:`inverse_error_bounds`). Both grow without bound as a zero of ``B`` nears the unit circle;
past it the recursion diverges, and :func:`inverse_arx` solves a regularised least-squares
deconvolution instead.

Nothing here imports the environment: the functions take arrays and an :class:`ARXModel`.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.signal
import scipy.sparse
import scipy.sparse.linalg

from identification.arx import ARXModel

__all__ = ["inverse_arx", "inverse_error_bounds", "inverse_impulse_response"]

_TAIL = 1e-12
"""Relative size of the impulse-response tail neglected in the norms of ``1/B``."""


def inverse_impulse_response(b: np.ndarray, *, max_samples: int = 1_000_000) -> np.ndarray:
    """Impulse response of ``1 / (b_1 + b_2 q^-1 + ... + b_nb q^-(nb-1))``, the eq. 25 filter.

    Parameters
    ----------
    b : array_like, shape (nb,)
        Numerator coefficients of the ARX model (output units per input unit, e.g. um/V).
    max_samples : int
        Longest response computed.

    Returns
    -------
    numpy.ndarray
        ``h_0, h_1, ...`` (input units per output unit, e.g. V/um), long enough that the
        neglected tail is below 1e-12 of the L1 norm.

    Raises
    ------
    ValueError
        If ``B`` is not minimum-phase (the response does not decay), or ``b_1 = 0``.
    """
    b = np.asarray(b, dtype=float)
    if b.ndim != 1 or b.size == 0 or b[0] == 0.0 or not np.all(np.isfinite(b)):
        raise ValueError(f"b must be finite with b_1 != 0; got {b!r}")
    rho = float(np.max(np.abs(np.roots(b)))) if b.size > 1 else 0.0
    if rho >= 1.0:
        raise ValueError(
            f"B has a zero of modulus {rho:.4g} >= 1: 1/B is unstable and eq. 25 diverges"
        )
    # |h_k| ~ k^m rho^k: 50 samples past where rho^k reaches the tolerance covers the polynomial
    # factor of repeated zeros.
    n = 50 if rho == 0.0 else math.ceil(math.log(_TAIL) / math.log(rho)) + 50 * b.size
    if n > max_samples:
        raise ValueError(
            f"B has a zero of modulus {rho:.6g}: the impulse response of 1/B needs more than "
            f"{max_samples} samples to decay"
        )
    impulse = np.zeros(n)
    impulse[0] = 1.0
    return scipy.signal.lfilter([1.0], b, impulse)


def inverse_error_bounds(arx: ARXModel) -> dict[str, float | None]:
    """Worst-case and RMS error of the eq. 25 hidden signal caused by the equation error.

    Parameters
    ----------
    arx : ARXModel
        Model with noise bound ``r = arx.noise_bound`` (output units, um).

    Returns
    -------
    dict
        ``z_error_bound_V``: ``r ||1/B||_1``, the largest ``|z_hat - z|`` any equation-error
        sequence with ``|nu_t| <= r`` can cause (input units, equivalent V);
        ``z_error_rms_V``: ``r / sqrt(3) ||1/B||_2``, the RMS error for independent noise
        uniform on ``[-r, r]`` (equivalent V); ``inverse_gain_l1`` and ``inverse_gain_l2``:
        the two norms of ``1/B`` (V/um). All None when ``B`` is not minimum-phase (eq. 25 is
        then not used).
    """
    try:
        h = inverse_impulse_response(arx.b)
    except ValueError:
        return {
            "z_error_bound_V": None,
            "z_error_rms_V": None,
            "inverse_gain_l1": None,
            "inverse_gain_l2": None,
        }
    l1, l2 = float(np.abs(h).sum()), float(np.sqrt(np.sum(h**2)))
    r = float(arx.noise_bound)
    return {
        "z_error_bound_V": r * l1,
        "z_error_rms_V": r / math.sqrt(3.0) * l2,
        "inverse_gain_l1": l1,
        "inverse_gain_l2": l2,
    }


def inverse_arx(
    arx: ARXModel, y: np.ndarray, *, regularization: float = 1e-3
) -> tuple[np.ndarray, str]:
    """Hidden signal z_hat (input units) from the output y by inverting the ARX model.

    With e_t = y_t - sum_i a_i y_{t-i} = sum_j b_j z_{t-j} (outputs and inputs before the record
    at rest), a minimum-phase B polynomial makes the paper's eq. 25 recursion stable:
    ``z_{t-1} = (e_t - sum_{j>=2} b_j z_{t-j}) / b_1``. Otherwise the recursion would blow up,
    and a Tikhonov-regularised least-squares deconvolution
    ``min ||B z - e||^2 + lambda (sum |b_j|)^2 ||z||^2`` over ``z_0 .. z_{T-2}`` is solved
    instead (sparse LSQR). See :func:`inverse_error_bounds` for the error of eq. 25.

    Parameters
    ----------
    arx : ARXModel
        The linear part, input (equivalent V) -> output (um).
    y : array_like, shape (T,)
        Measured output, um, ``y[t]`` before the input ``z[t]`` acts (the :func:`collect`
        alignment of :mod:`identification.pipeline`).
    regularization : float
        ``lambda`` of the deconvolution (relative to ``(sum |b_j|)^2``).

    Returns
    -------
    z_hat : ndarray, shape (T,)
        Hidden signal, input units; the last sample, which no output observes, repeats the one
        before (both methods).
    method : str
        ``"eq25"`` or ``"regularized-deconvolution"``.
    """
    y = np.asarray(y, dtype=float)
    e = scipy.signal.lfilter(np.r_[1.0, -arx.a], [1.0], y)
    if arx.is_minimum_phase():
        z = scipy.signal.lfilter([1.0], arx.b, e[1:])
        return np.r_[z, z[-1]], "eq25"
    n = len(y)
    rows, cols, vals = [], [], []
    for j, bj in enumerate(arx.b, start=1):
        t = np.arange(j, n)
        rows.append(t)
        cols.append(t - j)
        vals.append(np.full(len(t), bj))
    # Unknowns z_0 .. z_{n-2}: z_{n-1} acts on no output of the record.
    matrix = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n - 1)
    )
    damp = math.sqrt(regularization) * float(np.abs(arx.b).sum())
    z = scipy.sparse.linalg.lsqr(matrix, e, damp=damp, atol=1e-12, btol=1e-12)[0]
    return np.r_[z, z[-1]], "regularized-deconvolution"
