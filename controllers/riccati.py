"""Steady-state Kalman filters of one model under many noise levels at once: the filter Riccati
equation solved by the structure-preserving doubling algorithm, batched over the noise levels.

The observer bank (:class:`controllers.observer.ObserverBank`) needs, for one linear model, the
steady-state filter under every pair of its noise levels, and the adaptive MPC needs a bank for
each model of its set: hundreds of discrete algebraic Riccati equations that share ``A`` and
``C`` and differ in ``Q`` and ``R``. ``scipy.linalg.solve_discrete_are`` solves one at a time
through a generalised Schur decomposition, at a cost that is mostly per-call overhead
(``benchmarks/results/design_measurements.md``); the doubling algorithm below runs all of them
as one stack of small dense matrix products and solves, and converges quadratically, so that 30
iterations cover a closed loop whose slowest pole is within 1e-9 of the unit circle.

The filter equation ``P = A P A' - A P C' (C P C' + R)^-1 C P A' + Q`` is the control
equation of ``(A', C')``; the doubling algorithm for it (Chu, Fan, Lin and Wang, "Structure-
preserving algorithms for periodic discrete-time algebraic Riccati equations", Int. J. Control
77(8), 2004; Anderson, "Second-order convergent algorithms for the steady-state Riccati
equation", Int. J. Control 28(2), 1978) iterates, from ``A_0 = A'``, ``G_0 = C' R^-1 C``,
``H_0 = Q``::

    W = I + G_k H_k
    A_k+1 = A_k W^-1 A_k
    G_k+1 = G_k + A_k W^-1 G_k A_k'
    H_k+1 = H_k + A_k' H_k W^-1 A_k

and ``H_k`` converges to P when ``(A, C)`` is detectable and ``(A, Q^1/2)`` stabilisable. Each
solution is checked against the equation itself; one that does not satisfy it to
:data:`RESIDUAL_TOLERANCE` is solved again by scipy, and the count of those is returned, so
that nothing falls back silently. An equation neither solves (a model with a pole within about
1e-6 of the unit circle, where scipy's reordering of the Schur form fails with "Reordering of
(A, B) failed") is refused by :func:`scipy_filter` with what was wrong and what to do, not
with the LAPACK wrapper's words.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["MAX_ITERATIONS", "RESIDUAL_TOLERANCE", "filter_riccati", "scipy_filter"]

MAX_ITERATIONS = 60
"""Doubling steps at most: 2^60 steps of the Riccati recursion, far beyond any stable loop."""

RESIDUAL_TOLERANCE = 1e-9
"""Largest residual of the Riccati equation relative to the largest entry of its solution
accepted from the doubling algorithm (a few hundred times float64's rounding on these sizes)."""


def filter_riccati(
    a: np.ndarray, c: np.ndarray, q: np.ndarray, r: np.ndarray
) -> tuple[np.ndarray, int]:
    """Predicted steady-state covariances P of the filters ``(a, c, q_i, r_i)``.

    Parameters
    ----------
    a : numpy.ndarray
        (m, m) state matrix shared by all filters.
    c : numpy.ndarray
        (1, m) output matrix shared by all filters.
    q : numpy.ndarray
        (F, m, m) process noise covariances, symmetric positive semidefinite.
    r : numpy.ndarray
        (F,) measurement noise variances, > 0.

    Returns
    -------
    p : numpy.ndarray
        (F, m, m) the stabilising solutions.
    fallbacks : int
        How many were solved by ``scipy.linalg.solve_discrete_are`` instead (their doubling
        iterate did not satisfy the equation).
    """
    f, m = q.shape[0], a.shape[0]
    eye = np.eye(m)
    a_k = np.broadcast_to(a.T, (f, m, m)).copy()
    g_k = (c.T @ c)[None] / np.asarray(r, dtype=float)[:, None, None]
    h_k = np.array(q, dtype=float)
    for _ in range(MAX_ITERATIONS):
        w = eye + g_k @ h_k
        w_a = np.linalg.solve(w, a_k)
        w_g = np.linalg.solve(w, g_k)
        a_t = np.swapaxes(a_k, 1, 2)
        h_next = h_k + a_t @ h_k @ w_a
        g_k = g_k + a_k @ w_g @ a_t
        a_k = a_k @ w_a
        h_next = 0.5 * (h_next + np.swapaxes(h_next, 1, 2))
        g_k = 0.5 * (g_k + np.swapaxes(g_k, 1, 2))
        change = np.max(np.abs(h_next - h_k), axis=(1, 2))
        h_k = h_next
        if np.all(change <= 1e-15 * np.max(np.abs(h_k), axis=(1, 2))):
            break
    fallbacks = 0
    residuals = _residual(a, c, q, r, h_k)
    for i in np.flatnonzero(residuals > RESIDUAL_TOLERANCE):
        which = f"filter {i + 1} of {f} (doubling's residual {residuals[i]:.1e})"
        h_k[i] = scipy_filter(a, c, q[i], r[i], which)
        fallbacks += 1
    return h_k, fallbacks


def scipy_filter(a: np.ndarray, c: np.ndarray, q: np.ndarray, r: float, which: str) -> np.ndarray:
    """``scipy.linalg.solve_discrete_are`` for one filter ``(a, c, q, r)`` (shapes (m, m),
    (1, m), (m, m), scalar), or a ValueError that says what was wrong and what to do.

    ``which`` names the filter in the message (e.g. "filter 3 of 12").

    Raises
    ------
    ValueError
        If scipy finds no stabilising solution: the message gives the largest pole moduli,
        and the fix.
    """
    try:
        return scipy.linalg.solve_discrete_are(a.T, c.T, q, np.array([[r]]))
    except (ValueError, np.linalg.LinAlgError) as error:
        moduli = np.sort(np.abs(np.linalg.eigvals(a)))[::-1][:4]
        raise ValueError(
            f"the observer's steady-state filter has no solution that the solvers find, "
            f"{which}: scipy.linalg.solve_discrete_are says {str(error)!r}. The largest pole "
            f"moduli of the model with its output disturbance (whose integrator is at 1) are "
            f"{', '.join(f'{m:.12f}' for m in moduli)}: a pole of the model that near the "
            "unit circle makes the filter equation ill-posed. Identify the model again (a "
            "longer record, or a lower order), or move the pole inside the circle."
        ) from error


def _residual(
    a: np.ndarray, c: np.ndarray, q: np.ndarray, r: np.ndarray, p: np.ndarray
) -> np.ndarray:
    """Largest |residual| of each filter equation over the largest |P| entry (F,); inf where
    P is not finite."""
    cp = c @ p  # (F, 1, m)
    innovation = (cp @ c.T)[:, 0, 0] + r
    apc = a @ np.swapaxes(cp, 1, 2)  # (F, m, 1) = A P C'
    rhs = a @ p @ a.T - apc @ np.swapaxes(apc, 1, 2) / innovation[:, None, None] + q
    scale = np.max(np.abs(p), axis=(1, 2))
    residual = np.max(np.abs(rhs - p), axis=(1, 2)) / np.where(scale > 0, scale, 1.0)
    return np.where(np.isfinite(residual), residual, np.inf)
