"""The box-constrained QP both MPCs solve: a persistent solver workspace set up once.

``min 1/2 v' P v + q' v  s.t.  lower <= v <= upper`` (and, with a ``rate``, the rate rows
``|v_k - v_k-1| <= rate`` of a slew limit). Two solvers, one interface (:func:`box_qp`):

``"daqp"`` (the default), :class:`DAQPBoxQP`
    DAQP, a dual active-set solver for dense QPs (Arnstrom, Bemporad and Axehill, "A dual
    active-set solver for embedded quadratic programming using recursive LDL' updates",
    IEEE TAC 67(8), 2022). The MPCs' QPs are dense and small (N = 20 variables, the box as
    simple bounds, the rate rows as 19 general rows), which is the problem class an active-set
    method is made for: it ends on the exact active set (the solution meets the active bounds
    to rounding, and the KKT conditions to ``primal_tol``), and its work per solve is a few
    rank-one updates of an LDL' factor of the active constraints. The workspace is allocated
    and P factorised once; each solve updates only the vector terms (q, the bounds) and starts
    from the previous solve's active set, which is the warm start that matters for a receding
    horizon (the shifted plan keeps most of its active bounds). The iterations of every solve
    are returned, so that a user sizing a real-time target reads the worst case over the
    episodes (a DAQP iteration adds or removes one constraint, so a solve from a correct active
    set takes one).
``"osqp"``, :class:`OSQPBoxQP`
    OSQP set up the way its MPC pattern asks: P's upper triangle as a sparse matrix (its
    pattern fixed, so that later updates of its values need no new set-up), the identity as the
    constraint matrix (stacked on the first differences with a rate), no polishing, warm starts
    on, and the termination checked every 5 iterations (OSQP's default of 25 wastes most of
    what a warm start saves). Its solution meets the bounds to ``eps_abs``/``eps_rel``, so it
    agrees with DAQP's within those tolerances, not to the bit.

Both solvers return the solution only when it is usable (DAQP's exit flag > 0, OSQP's status in
:data:`controllers.settings.USABLE_OSQP_STATUS`), clipped to the box; otherwise None, and the
MPC falls back to its shifted plan (counted in its stats).

Both MPCs first try the unconstrained optimum ``-P^-1 q`` (:func:`within`). That is exact, not an
approximation: for a convex QP with box constraints, a point inside the box where the gradient
vanishes meets the KKT conditions with no active constraint. Smooth references rarely touch the
bounds, so most steps cost one linear solve (or one matrix-vector product); the QP solver solves
the rest.
"""

from __future__ import annotations

from importlib.metadata import version
from typing import NamedTuple

import daqp
import numpy as np
import osqp
import scipy.sparse

from controllers.native import daqp_box
from controllers.native.daqp_box import NativeDAQP, SetupRefused
from controllers.settings import QP_SOLVERS, USABLE_OSQP_STATUS

__all__ = [
    "DAQP_STATUS",
    "BoxQP",
    "BoxQPSolution",
    "DAQPBoxQP",
    "OSQPBoxQP",
    "box_qp",
    "solver_version",
    "within",
]

DAQP_STATUS = {
    1: "solved",
    2: "solved (soft constraints relaxed)",
    -1: "primal infeasible",
    -2: "cycling",
    -3: "unbounded",
    -4: "iteration limit",
    -5: "nonconvex",
    -6: "initial working set overdetermined",
}
"""DAQP's exit flags by name (its documentation's "exitflag" table); a flag > 0 is usable."""


class BoxQPSolution(NamedTuple):
    """One solve of a :class:`BoxQP`.

    Attributes
    ----------
    x : numpy.ndarray or None
        The minimiser clipped to the box; None when the solver failed or reached its
        iteration cap.
    duals : numpy.ndarray or None
        The constraints' multipliers (None with ``x``), for the next warm start.
    status : str
        The solver's status (``"solved"`` when usable and optimal).
    iterations : int
        The solver's iterations.
    """

    x: np.ndarray | None
    duals: np.ndarray | None
    status: str
    iterations: int


def within(x: np.ndarray, lower: np.ndarray | float, upper: np.ndarray | float) -> bool:
    """True when every entry of ``x`` lies in ``[lower, upper]`` (False for NaN)."""
    # The arrays' own .all(): np.all's dispatch wrapper doubles the cost of this test.
    return bool((x >= lower).all() and (x <= upper).all())


def solver_version(solver: str) -> str:
    """``"daqp 0.11.0"`` or ``"osqp 1.0.4"``: the solver and its installed version."""
    if solver not in QP_SOLVERS:
        raise ValueError(f"qp_solver must be one of {QP_SOLVERS}, got {solver!r}")
    return f"{solver} {osqp.__version__ if solver == 'osqp' else version('daqp')}"


class BoxQP:
    """What both solvers' workspaces share: the box, the rate rows and the solve interface.

    Parameters
    ----------
    lower, upper : numpy.ndarray
        Box bounds (n,); :meth:`solve` may replace them.
    rate : float, optional
        Bound of ``|v_k - v_k-1|`` (k >= 1); the multipliers then cover the 2 n - 1 rows.
    """

    solver = ""

    def __init__(self, lower: np.ndarray, upper: np.ndarray, rate: float | None) -> None:
        n = lower.size
        self.lower, self.upper = lower, upper
        self._rate = None if rate is None else np.full(n - 1, rate)
        self._failed = False

    @property
    def failed(self) -> bool:
        """Whether the last solve gave no usable solution."""
        return self._failed

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
            2 n - 1 with a rate). DAQP starts from its own last active set and reads them
            only to clear it (all multipliers zero: no constraint active).
        hessian : numpy.ndarray, optional
            A new dense P (only for a QP set up without one).
        bounds : (numpy.ndarray, numpy.ndarray), optional
            New (lower, upper).
        """
        if bounds is not None:
            self.lower, self.upper = bounds
        x, duals, status, iterations = self._solve(q, warm_x, warm_duals, hessian, bounds)
        self._failed = x is None or not np.isfinite(x).all()
        if self._failed:
            return BoxQPSolution(None, None, status, iterations)
        return BoxQPSolution(np.clip(x, self.lower, self.upper), duals, status, iterations)

    def _solve(
        self,
        q: np.ndarray,
        warm_x: np.ndarray,
        warm_duals: np.ndarray,
        hessian: np.ndarray | None,
        bounds: tuple[np.ndarray, np.ndarray] | None,
    ) -> tuple[np.ndarray | None, np.ndarray | None, str, int]:
        """The solver's own step, the box already in :attr:`lower`/:attr:`upper`: (x or None
        when the solver says it is not usable, multipliers, status, iterations)."""
        raise NotImplementedError

    def set_rate(self, rate: float) -> None:
        """A new rate bound (QP set up with a rate); it takes effect at the next
        :meth:`solve` with ``bounds``."""
        if self._rate is None:
            raise ValueError("this QP was set up without rate rows; pass rate= to box_qp")
        self._rate[:] = rate

    def _rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the constraint rows: the box, then the rate rows."""
        if self._rate is None:
            return self.lower, self.upper
        return np.r_[self.lower, -self._rate], np.r_[self.upper, self._rate]

    def _differences(self) -> np.ndarray:
        """The rate rows' matrix D (n - 1, n): first differences (dense)."""
        n = self.lower.size
        return np.eye(n - 1, n, 1) - np.eye(n - 1, n)


class DAQPBoxQP(BoxQP):
    """DAQP's persistent workspace for the box QP of a dense Hessian (module docstring).

    Parameters
    ----------
    lower, upper : numpy.ndarray
        Box bounds (n,), DAQP's simple bounds.
    hessian : numpy.ndarray, optional
        P (n, n), dense, symmetric positive definite, when it stays fixed; None when
        :meth:`solve` gives P every time (the workspace is then set up on the identity).
    max_iter : int
        DAQP's iteration cap (a solve that reaches it is not usable).
    rate : float, optional
        Bound of ``|v_k - v_k-1|``: the n - 1 general rows.
    """

    solver = "daqp"

    def __init__(
        self,
        lower: np.ndarray,
        upper: np.ndarray,
        *,
        hessian: np.ndarray | None = None,
        max_iter: int,
        rate: float | None = None,
    ) -> None:
        super().__init__(lower, upper, rate)
        n = lower.size
        rows = self._differences() if rate is not None else np.zeros((0, n))
        low, high = self._rows()
        self.native: NativeDAQP | None = None
        if hessian is not None and daqp_box.library() is not None:
            try:
                self.native = NativeDAQP(hessian, rows, low, high, int(max_iter))
            except SetupRefused as exc:
                raise _refused(exc.flag) from None
            return
        self._model = daqp.Model()
        p = np.eye(n) if hessian is None else np.array(hessian, dtype=float)
        flag, _ = self._model.setup(p, np.zeros(n), rows, high.copy(), low.copy())
        if flag < 0:
            raise _refused(flag)
        self._model.settings = {"iter_limit": int(max_iter)}
        self._no_active_set = np.zeros(low.size, dtype=np.intc)

    @property
    def failed(self) -> bool:
        """Whether the last solve gave no usable solution (the workspace's own record when C
        code solves in it too)."""
        return self._failed if self.native is None else self.native.failed

    def _solve(self, q, warm_x, warm_duals, hessian, bounds):
        native = self.native
        if native is not None:
            if hessian is not None:
                raise ValueError("this DAQP workspace was set up with a fixed Hessian")
            if bounds is not None:
                native.lower[:], native.upper[:] = self._rows()
            flag, iterations = native.solve(q, not warm_duals.any() or native.failed)
            status = DAQP_STATUS.get(flag, f"exit flag {flag}")
            if native.refused:  # data refused at the update (crossed bounds)
                return None, None, status, 0
            usable = not native.failed
            return (native.x.copy() if usable else None), native.lam.copy(), status, iterations
        data: dict[str, np.ndarray] = {"f": q}
        if bounds is not None:
            data["blower"], data["bupper"] = self._rows()
        if hessian is not None:
            data["H"] = hessian
        if not warm_duals.any() or self.failed:  # after a failure: from no active set
            data["sense"] = self._no_active_set
        flag = int(self._model.update(**data))
        if flag < 0:  # data refused (crossed bounds, an indefinite P)
            return None, None, DAQP_STATUS.get(flag, f"exit flag {flag}"), 0
        x, _, flag, info = self._model.solve()
        status = DAQP_STATUS.get(int(flag), f"exit flag {int(flag)}")
        usable = flag > 0
        return (x if usable else None), info["lam"], status, int(info["iterations"])


def _refused(flag: int) -> ValueError | MemoryError:
    """The error of a QP that DAQP refused at set-up (or that found no memory for it)."""
    if flag == daqp_box.OUT_OF_MEMORY:
        return MemoryError("no memory for DAQP's workspace")
    return ValueError(
        f"DAQP refused the QP at set-up (exit flag {flag}: "
        f"{DAQP_STATUS.get(flag, 'unknown')}); its Hessian must be positive definite"
    )


class OSQPBoxQP(BoxQP):
    """OSQP set up (and factorised) once for the box QP of a dense Hessian (module docstring).

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

    solver = "osqp"

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
        super().__init__(lower, upper, rate)
        n = lower.size
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
            difference = scipy.sparse.csc_matrix(self._differences())
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

    def _solve(self, q, warm_x, warm_duals, hessian, bounds):
        data = {"q": q}
        if bounds is not None:
            data["l"], data["u"] = self._rows()
        if hessian is not None:
            data["Px"] = hessian[self._upper_triangle]
        self._solver.update(**data)
        self._solver.warm_start(x=warm_x, y=warm_duals)
        result = self._solver.solve(raise_error=False)
        status = result.info.status
        usable = status in USABLE_OSQP_STATUS
        return (result.x if usable else None), result.y, status, int(result.info.iter)


def box_qp(
    solver: str,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    hessian: np.ndarray | None = None,
    eps_abs: float,
    eps_rel: float,
    max_iter: int,
    rate: float | None = None,
) -> BoxQP:
    """The box QP's workspace for ``solver`` (``"daqp"`` or ``"osqp"``).

    Parameters are :class:`OSQPBoxQP`'s; DAQP, which ends on an exact active set, takes no
    tolerances (``eps_abs``/``eps_rel`` are OSQP's only).

    Raises
    ------
    ValueError
        If ``solver`` is not one of :data:`controllers.settings.QP_SOLVERS`.
    """
    if solver == "daqp":
        return DAQPBoxQP(lower, upper, hessian=hessian, max_iter=max_iter, rate=rate)
    if solver == "osqp":
        return OSQPBoxQP(
            lower,
            upper,
            hessian=hessian,
            eps_abs=eps_abs,
            eps_rel=eps_rel,
            max_iter=max_iter,
            rate=rate,
        )
    raise ValueError(f"qp_solver must be one of {QP_SOLVERS}, got {solver!r}")
