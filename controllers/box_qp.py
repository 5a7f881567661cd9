"""The box-constrained QP both MPCs solve, set up once the way OSQP's MPC pattern asks.

``min 1/2 v' P v + q' v  s.t.  lower <= v <= upper``: P's upper triangle as a sparse matrix (its
pattern fixed, so that later ``update(Px=...)`` calls can change the values), the identity as
the constraint matrix, and the options every MPC here uses: no polishing, warm starts on, and
the termination checked every 5 iterations (OSQP's default of 25 wastes most of what a warm
start saves).
"""

from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse

__all__ = ["setup_box_qp"]


def setup_box_qp(
    hessian: np.ndarray | scipy.sparse.csc_matrix,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    eps_abs: float,
    eps_rel: float,
    max_iter: int,
) -> osqp.OSQP:
    """OSQP set up (and factorised) for the box QP of ``hessian`` (dense or an upper CSC).

    Parameters
    ----------
    hessian : ndarray or scipy.sparse.csc_matrix
        P (n, n): a dense symmetric matrix, or the sparse upper triangle with its pattern.
    lower, upper : ndarray
        Box bounds (n,).
    eps_abs, eps_rel : float
        OSQP tolerances.
    max_iter : int
        OSQP iteration cap.
    """
    n = lower.size
    if not scipy.sparse.issparse(hessian):
        hessian = scipy.sparse.csc_matrix(np.triu(hessian))
    solver = osqp.OSQP()
    solver.setup(
        P=hessian,
        q=np.zeros(n),
        A=scipy.sparse.identity(n, format="csc"),
        l=lower,
        u=upper,
        verbose=False,
        eps_abs=eps_abs,
        eps_rel=eps_rel,
        max_iter=max_iter,
        check_termination=5,
        polishing=False,
        warm_starting=True,
    )
    return solver
