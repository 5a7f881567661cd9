"""The box-constrained QP both MPCs solve, set up once the way OSQP's MPC pattern asks.

``min 1/2 v' P v + q' v  s.t.  lower <= v <= upper`` (and, with a ``rate``, the rate rows
``|v_k - v_k-1| <= rate`` of a slew limit): P's upper triangle as a sparse matrix (its
pattern fixed, so that later updates of its values need no new set-up), the identity as the
constraint matrix (stacked on the first differences with a rate), and the options every MPC
here uses: no polishing, warm starts on, and the
termination checked every 5 iterations (OSQP's default of 25 wastes most of what a warm start
saves). Each solve updates only what changed (q; the bounds or P's values when they change),
warm-starts, and returns the solution only when OSQP says it is usable.

Both MPCs first try the unconstrained optimum ``-P^-1 q`` (:func:`within`). That is exact, not an
approximation: for a convex QP with box constraints, a point inside the box where the gradient
vanishes meets the KKT conditions with no active constraint. Smooth references rarely touch the
bounds, so most steps cost one linear solve (or one matrix-vector product); OSQP solves the rest.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import osqp
import scipy.sparse

from controllers.settings import USABLE_OSQP_STATUS

__all__ = ["BoxQP", "BoxQPSolution", "within"]


class BoxQPSolution(NamedTuple):
    """One solve of :class:`BoxQP`.

    Attributes
    ----------
    x : numpy.ndarray or None
        The minimiser clipped to the box (OSQP meets the bounds only within its tolerance);
        None when OSQP failed or reached its iteration cap.
    duals : numpy.ndarray or None
        The bounds' multipliers (None with ``x``), for the next warm start.
    status : str
        OSQP's status.
    iterations : int
        OSQP's iterations.
    """

    x: np.ndarray | None
    duals: np.ndarray | None
    status: str
    iterations: int


def within(x: np.ndarray, lower: np.ndarray | float, upper: np.ndarray | float) -> bool:
    """True when every entry of ``x`` lies in ``[lower, upper]`` (False for NaN)."""
    return bool(np.all(x >= lower) and np.all(x <= upper))


class BoxQP:
    """OSQP set up (and factorised) once for the box QP of a dense Hessian.

    Parameters
    ----------
    lower, upper : numpy.ndarray
        Box bounds (n,); :meth:`solve` may replace them.
    hessian : numpy.ndarray, optional
        P (n, n), dense and symmetric, when it stays fixed; None when :meth:`solve` gives P
        every time (OSQP is then set up on the full upper-triangular pattern).
    eps_abs, eps_rel : float
        OSQP tolerances.
    max_iter : int
        OSQP iteration cap.
    rate : float, optional
        Bound of ``|v_k - v_k-1|`` (k >= 1); the multipliers then cover the 2 n - 1 rows.
    """

    def __init__(
        self,
        lower: np.ndarray,
        upper: np.ndarray,
        *,
        hessian: np.ndarray | None = None,
        eps_abs: float,
        eps_rel: float,
        max_iter: int,
        rate: float | None = None,
    ) -> None:
        n = lower.size
        self.lower, self.upper = lower, upper
        self._rate = None if rate is None else np.full(n - 1, rate)
        # Column-major order of the upper triangle: the order of OSQP's CSC P values.
        cols, rows = np.tril_indices(n)
        self._upper_triangle = (rows, cols)
        if hessian is None:  # placeholder values; the diagonal dominant, so P is convex
            pattern = np.ones(rows.size) + (rows == cols)
            sparse = scipy.sparse.csc_matrix((pattern, (rows, cols)), shape=(n, n))
        else:
            sparse = scipy.sparse.csc_matrix(np.triu(hessian))
        matrix = scipy.sparse.identity(n, format="csc")
        if rate is not None:
            difference = scipy.sparse.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], (n - 1, n))
            matrix = scipy.sparse.vstack([matrix, difference], format="csc")
        low, high = self._rows()
        self._solver = osqp.OSQP()
        self._solver.setup(
            P=sparse,
            q=np.zeros(n),
            A=matrix,
            l=low,
            u=high,
            verbose=False,
            eps_abs=eps_abs,
            eps_rel=eps_rel,
            max_iter=max_iter,
            check_termination=5,
            polishing=False,
            warm_starting=True,
        )

    def solve(
        self,
        q: np.ndarray,
        warm_x: np.ndarray,
        warm_duals: np.ndarray,
        *,
        hessian: np.ndarray | None = None,
        bounds: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> BoxQPSolution:
        """Minimise ``1/2 v' P v + q' v`` over the box, warm-started (a usable solution or None).

        Parameters
        ----------
        q : numpy.ndarray
            Linear term (n,).
        warm_x, warm_duals : numpy.ndarray
            Warm start: a point inside the box and the constraints' multipliers (n, or
            2 n - 1 with a rate).
        hessian : numpy.ndarray, optional
            A new dense P (only for a QP set up without one).
        bounds : (numpy.ndarray, numpy.ndarray), optional
            New (lower, upper).
        """
        data = {"q": q}
        if bounds is not None:
            self.lower, self.upper = bounds
            data["l"], data["u"] = self._rows()
        if hessian is not None:
            data["Px"] = hessian[self._upper_triangle]
        self._solver.update(**data)
        self._solver.warm_start(x=warm_x, y=warm_duals)
        result = self._solver.solve(raise_error=False)
        status, iterations = result.info.status, int(result.info.iter)
        if status not in USABLE_OSQP_STATUS or not np.all(np.isfinite(result.x)):
            return BoxQPSolution(None, None, status, iterations)
        x = np.clip(result.x, self.lower, self.upper)
        return BoxQPSolution(x, result.y, status, iterations)

    def set_rate(self, rate: float) -> None:
        """A new rate bound (QP set up with a rate); it takes effect at the next
        :meth:`solve` with ``bounds``."""
        if self._rate is None:
            raise ValueError("this QP was set up without rate rows; pass rate= to BoxQP")
        self._rate[:] = rate

    def _rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the constraint rows: the box, then the rate rows."""
        if self._rate is None:
            return self.lower, self.upper
        return np.r_[self.lower, -self._rate], np.r_[self.upper, self._rate]
