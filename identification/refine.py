"""Output-error refinement of the linear part (step b', after the Bayesian ARX estimate).

The ARX model ``A(q) y = B(q) z + nu`` fitted by equation error says that the disturbance is
``nu / A``: process noise shaped by the plant's own resonance. The bender's disturbance is the
sensor's, white and on the measured output: ``y = B(q)/F(q) z + v``, an output-error (OE) model
(Ljung 1999, sec. 4.2). Under output noise the equation-error estimate is biased (its regressors
hold past noisy outputs), and the bias lands mostly in the zeros, which the MPC and the inverse
ARX model both invert. The prediction-error estimate of the OE model minimises the free-run
(simulation) error

    V(theta) = sum_t (y_t - y_hat_t(theta))^2,   y_hat = (b_1 q^-1 + .. + b_nb q^-nb) / F(q) z,

``F(q) = 1 - f_1 q^-1 - .. - f_na q^-na``, and is consistent for white output noise of any
distribution (Ljung 1999, thm. 8.2). It is a nonlinear least-squares problem; started from the
ARX estimate (stable, close) and solved by :func:`scipy.optimize.least_squares` with the exact
Jacobian (the sensitivities are the regressors filtered by ``1/F``), it converges in a handful
of Gauss-Newton steps.

The refined model is an :class:`identification.arx.ARXModel` with ``a = f``: the same transfer
function form and state space realization, so every consumer (inverse ARX, MPC, save and load)
takes it unchanged. Its ``noise_bound`` is the largest equation error of the refined
coefficients on the data (what ``r`` means for an ARX model), and :class:`OutputErrorFit`
reports the output error, the noise model of the OE structure: white, its RMS and its bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.signal
import threadpoolctl

from identification.arx import ARXModel, check_io

__all__ = ["OutputErrorFit", "refine_output_error"]


@dataclass(frozen=True)
class OutputErrorFit:
    """Result of :func:`refine_output_error`.

    Attributes
    ----------
    model : ARXModel
        The refined linear part (``a`` holds F's coefficients; method ``"output-error"``).
    initial : ARXModel
        The model it started from.
    output_error_rms, output_error_bound : float
        RMS and largest absolute free-run error of the refined model on the data (output unit):
        the identified output noise (sensor noise plus what the model misses).
    initial_output_error_rms : float
        The same RMS of the starting model.
    iterations : int
        Function evaluations of the solver.
    status : str
        The solver's message.
    """

    model: ARXModel
    initial: ARXModel
    output_error_rms: float
    output_error_bound: float
    initial_output_error_rms: float
    iterations: int
    status: str


def _simulate(f: np.ndarray, b: np.ndarray, z: np.ndarray) -> np.ndarray:
    return scipy.signal.lfilter(np.r_[0.0, b], np.r_[1.0, -f], z)


def _jacobian(f: np.ndarray, b: np.ndarray, z: np.ndarray, y_hat: np.ndarray) -> np.ndarray:
    """d y_hat / d [f, b]: q^-i y_hat / F and q^-j z / F, one column each (output unit)."""
    den = np.r_[1.0, -f]
    filtered_y = scipy.signal.lfilter([1.0], den, y_hat)
    filtered_z = scipy.signal.lfilter([1.0], den, z)
    n = z.size
    columns = np.zeros((n, f.size + b.size))
    for i in range(1, f.size + 1):
        columns[i:, i - 1] = filtered_y[: n - i]
    for j in range(1, b.size + 1):
        columns[j:, f.size + j - 1] = filtered_z[: n - j]
    return columns


def refine_output_error(
    initial: ARXModel,
    z: np.ndarray,
    y: np.ndarray,
    *,
    max_evaluations: int = 100,
) -> OutputErrorFit:
    """Refine a linear model by minimising its free-run error on ``(z, y)`` (output-error PEM).

    Parameters
    ----------
    initial : ARXModel
        Starting point (for example the Bayesian ARX estimate); must be stable.
    z, y : array_like, shape (T,)
        Input (equivalent V) and measured output (um) of a record that starts at rest, in the
        ARX alignment (``y[t]`` depends on ``z[t-1]`` and older).
    max_evaluations : int
        Cap on the solver's function evaluations.

    Returns
    -------
    OutputErrorFit

    Raises
    ------
    ValueError
        If the starting model is unstable (its free run diverges) or has no output terms, or
        if the refined model is unstable.
    """
    z, y = check_io(z, y)
    if initial.na == 0 or initial.nb == 0:
        raise ValueError("output-error refinement needs na >= 1 and nb >= 1")
    if not initial.is_stable():
        raise ValueError(
            "the starting model is unstable, so its free run diverges; start the output-error "
            "refinement from a stable estimate"
        )
    na = initial.na
    y_start = _simulate(initial.a, initial.b, z)
    start_rms = float(np.sqrt(np.mean((y - y_start) ** 2)))
    scale = max(start_rms, 1e-300)

    def split(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return theta[:na], theta[na:]

    def residual(theta: np.ndarray) -> np.ndarray:
        f, b = split(theta)
        if np.max(np.abs(np.roots(np.r_[1.0, -f]))) >= 1.0:
            return np.full(y.size, np.inf)  # rejected by the trust region: it shrinks
        return (_simulate(f, b, z) - y) / scale

    def jacobian(theta: np.ndarray) -> np.ndarray:
        f, b = split(theta)
        return _jacobian(f, b, z, _simulate(f, b, z)) / scale

    # One BLAS thread: the solver's SVDs are of tall, thin (T, 2n) matrices, too small to
    # share among threads, which then only wait for each other (and for a busy core).
    with threadpoolctl.threadpool_limits(1):
        solution = scipy.optimize.least_squares(
            residual,
            initial.theta,
            jac=jacobian,
            method="trf",
            x_scale="jac",
            max_nfev=max_evaluations,
        )
    f, b = split(solution.x)
    error = y - _simulate(f, b, z)
    equation_error = scipy.signal.lfilter(np.r_[1.0, -f], [1.0], y) - _simulate(np.zeros(0), b, z)
    model = ARXModel(
        f,
        b,
        noise_bound=float(np.max(np.abs(equation_error[max(na, b.size) :]))),
        dt=initial.dt,
        method="output-error",
    )
    if not model.is_stable():
        raise ValueError("the output-error refinement ended at an unstable model")
    rms = float(np.sqrt(np.mean(error**2)))
    return OutputErrorFit(
        model=model,
        initial=initial,
        output_error_rms=rms,
        output_error_bound=float(np.max(np.abs(error))),
        initial_output_error_rms=start_rms,
        iterations=int(solution.nfev),
        status=str(solution.message),
    )
