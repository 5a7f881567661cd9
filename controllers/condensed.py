"""The condensed prediction both MPCs build once: outputs over the horizon as matrices.

With the hidden input z held over each sample, the linear part's outputs over the horizon N are
an affine function of the state and the inputs (no equality constraints, N decision variables)::

    y_t+1..t+N = Phi x_t + Gamma z_t..t+N-1,   Phi_k = C A^(k+1),   Gamma_kj = C A^(k-j) B (j <= k)

and the input-rate penalty ``lambda sum_k (v_t+k - v_t+k-1)^2`` of a plan v (z for the linear
MPC, volts for the nonlinear one) has the Hessian ``lambda D^T D`` with D the first difference.

**Move blocking** (:func:`move_blocks`, :func:`blocking_matrix`). A prediction over Np samples
may be planned with M < Np moves, each held over a block of samples: ``z = T v`` with T (Np, M)
of ones on each block. The prediction becomes ``Gamma T`` (Np, M), and because the plan changes
only at block starts, the rate penalty over the Np samples is the same penalty over the M moves
(``lambda D^T D`` of size M, with the first move linked to v_t-1): :func:`qp_matrices` takes the
blocked Gamma as it is. The first block is one sample, so the first move, the one applied, is
the one an unblocked plan would have at its bounds.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "blocking_matrix",
    "check_well_posed",
    "move_blocks",
    "prediction_matrices",
    "qp_matrices",
    "rate_hessian",
]


def prediction_matrices(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, horizon: int
) -> tuple[np.ndarray, np.ndarray]:
    """Phi (N, n) and Gamma (N, N) with ``y_t+1..t+N = Phi x_t + Gamma z_t..t+N-1``.

    Parameters
    ----------
    a, b, c : numpy.ndarray
        ``x_t+1 = a x_t + b z_t``, ``y_t = c x_t`` (b: (n, 1), c: (1, n); y in um).
    horizon : int
        N (samples).
    """
    n = a.shape[0]
    phi = np.empty((horizon, n))
    markov = np.empty(horizon)  # C A^k B, k = 0 .. N-1
    row = c[0].copy()
    for k in range(horizon):
        markov[k] = row @ b[:, 0]
        row = row @ a
        phi[k] = row
    gamma = np.zeros((horizon, horizon))
    for k in range(horizon):
        gamma[k, : k + 1] = markov[k::-1]
    return phi, gamma


def move_blocks(moves: int, samples: int) -> tuple[int, ...]:
    """Block lengths (samples) of ``moves`` moves over ``samples`` samples: the first half of
    the moves one sample each (the near plan, against which the applied first move is computed,
    as free as an unblocked plan's), the other half sharing the remaining samples as evenly as
    possible, the longer blocks last.

    Raises
    ------
    ValueError
        If ``samples < moves`` or ``moves < 1``, or one move over several samples.
    """
    if not 1 <= moves <= samples:
        raise ValueError(
            f"a plan of {moves} moves needs at least as many prediction samples, got {samples}"
        )
    if samples == moves:
        return (1,) * moves
    if moves < 2:
        raise ValueError(
            f"blocking one move over {samples} samples leaves no single-sample first move; "
            "plan at least 2 moves"
        )
    single = moves // 2
    rest = moves - single
    edges = np.floor(np.linspace(0.0, samples - single, rest + 1) + 0.5).astype(int)
    return (1,) * single + tuple(sorted(int(length) for length in np.diff(edges)))


def blocking_matrix(blocks: tuple[int, ...]) -> np.ndarray:
    """T (sum(blocks), len(blocks)): column j is one over block j's samples (z = T v)."""
    return np.repeat(np.eye(len(blocks)), blocks, axis=0)


def rate_hessian(horizon: int, rate_weight: float) -> np.ndarray:
    """``lambda D^T D`` (N, N): the Hessian of ``lambda sum_k (v_t+k - v_t+k-1)^2`` in v.

    The link of the first move to the previous one (``v_t-1``, known) is a linear term; each
    controller adds it to its own q.
    """
    diff = np.eye(horizon) - np.eye(horizon, k=-1)
    return rate_weight * diff.T @ diff


def qp_matrices(
    phi: np.ndarray, gamma: np.ndarray, rate_weight: float, *, slope: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Hessian P (M, M) and the matrix G with ``q = G [x; d (; s); r; z_prev]``, scaled.

    The QP ``min_v v^T P v / 2 + q^T v`` of the tracking cost ``sum_k (y_t+k - r_t+k)^2 +
    lambda sum_k (v_t+k - v_t+k-1)^2`` with the output disturbance d held over the horizon
    (``slope``: extrapolated as ``d_t+k = d_t + k s_t``). Scaled so that the largest Hessian
    entry is 1: OSQP's absolute tolerances then mean the same thing for any bender and unit
    (the minimiser does not change).

    Parameters
    ----------
    phi, gamma : numpy.ndarray
        The condensed prediction (:func:`prediction_matrices`): Phi (Np, n) and Gamma (Np, M),
        M = Np, or Gamma times a :func:`blocking_matrix` for M blocked moves.
    rate_weight : float
        lambda ((um / unit of v)^2): the rate penalty, ``lambda D^T D`` (:func:`rate_hessian`)
        in P and its link to v_t-1 in G.
    slope : bool
        Whether the estimate holds a disturbance slope s.
    """
    samples, moves = gamma.shape
    hessian = gamma.T @ gamma + rate_hessian(moves, rate_weight)
    previous_move = np.zeros((moves, 1))  # the rate penalty's link to z_t-1
    previous_move[0, 0] = -rate_weight
    columns = [gamma.T @ phi, gamma.T.sum(axis=1, keepdims=True)]
    if slope:  # d_t+k = d_t + k s_t
        columns.append(gamma.T @ np.arange(1.0, samples + 1)[:, None])
    scale = 1.0 / float(np.max(np.diag(hessian)))
    return hessian * scale, scale * np.hstack([*columns, -gamma.T, previous_move])


def check_well_posed(
    gamma: np.ndarray, rate_weight: float, tracking_weight: float = 1.0, *, name: str = "MPC"
) -> None:
    """Raise ValueError when the QP ``w Gamma^T Gamma + lambda D^T D`` has no unique minimiser.

    That happens when some move reaches no predicted output and nothing else weighs it: a
    model with C B = 0 (its output lags the input by two samples or more) and rate_weight = 0
    leaves the last move of the horizon free, and ``numpy.linalg.solve`` would fail later with
    a LinAlgError. For the nonlinear MPC the Hessian also holds the nonlinearity's Jacobian,
    which is lower triangular with a nonzero diagonal (dz/du > 0), so the same test applies.

    Parameters
    ----------
    gamma : numpy.ndarray
        Gamma (Np, M) of :func:`prediction_matrices`, blocked or not (um per equivalent V).
    rate_weight, tracking_weight : float
        lambda and w of the cost.
    name : str
        The controller, for the message.
    """
    hessian = tracking_weight * gamma.T @ gamma + rate_hessian(gamma.shape[1], rate_weight)
    if np.max(np.diag(hessian)) > 0 and np.linalg.cond(hessian) < 1e12:
        return
    raise ValueError(
        f"the {name}'s QP is singular (rate_weight = {rate_weight:g}, the model's first Markov "
        f"parameter C B = {gamma[0, 0]:.3g}): some moves reach no predicted output; set "
        "rate_weight > 0 (the defaults: 0.3 for mpc, 1e-2 for mpc-adaptive)"
    )
