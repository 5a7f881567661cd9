"""Recursive approximate Bayesian estimation of ARX models with uniform noise.

Pavelkova and Karny (2012). For ``y_t = psi_t^T theta + nu_t`` with ``nu_t ~ U(-r, r)`` and a
flat prior, the posterior of ``(theta, r)`` is proportional to ``r^-t`` on the polytope
``{|y_tau - psi_tau^T theta| <= r, tau <= t}``. With ``K = [theta; 1] / r`` and
``D_t = [-psi_t; y_t]`` each datum is the slab ``-1 <= D_t^T K <= 1``; ``K_n = 1 / r``. The
estimator replaces the polytope by a parallelotope ``{l <= V K <= u}`` (V unit upper triangular,
so the last coordinate is ``K_n`` itself) and reads the point estimates off it (paper, eq. 23)::

    g = max(l_n, 0) / u_n
    r_hat = (nu + 1) / nu * (1 - g^nu) / (1 - g^(nu + 1)) / u_n
    theta_hat = r_hat v_psi^-1 ((l + u) / 2)_{1:n-1} - v_psi^-1 v_y

How the recursion approximates the exact posterior
--------------------------------------------------
Every bound the estimator keeps is an outer bound of the exact support: the parallelotope always
contains the exact polytope (bounds are widened by a relative rounding margin of 1e-9), so the true
``(theta, r)`` is never excluded. The approximation lies in how far outside the exact polytope the
parallelotope reaches. The statistics are

* ``R``, the triangular factor of the QR decomposition of all data vectors so far (the
  information matrix ``sum D D^T = R^T R``, as in recursive least squares). ``V`` is ``R`` with
  its rows scaled to a unit diagonal, so ``V K`` measures ``K`` along the principal directions of
  the accumulated information; orienting the parallelotope by single-datum rotations instead
  gives a poor shape (parameters off by tens of percent on an ARX(3,2)).
* The box ``[l, u]`` in the coordinates ``xi = V K``. A new datum is the two-sided constraint
  ``-1 <= g^T xi <= 1`` with ``g = V^-T D_t``; each coordinate bound of box-plus-one-slab is
  exact and closed form (vectorized over a block of data, each slab against the box at the start
  of the block). Every ``reorient_every`` samples ``R`` absorbs the new data (one QR call) and the
  box is carried to the new orientation ``V'``: each new row ``h`` of ``V' V^-1`` is bounded over
  the old box intersected with each slab of a short window of recent data. That bound is the
  linear program ``max h^T xi s.t. l <= xi <= u, |g^T xi| <= 1``; its dual is a convex
  piecewise-linear function of one scalar, minimized by sorting its breakpoints ``h_j / g_j``
  (``O(n log n)``, no LP solver). The dual value at any multiplier is an upper bound (weak
  duality), so rounding can never make the bound inner.
* The top face ``u_n``, which sets ``r_hat ~ 1 / u_n``. A box cannot follow the polytope's shape
  near its top: the exact support is close to a cone from a wide base (``r -> infinity``) to a
  single vertex (the Chebyshev solution, ``K_n = 1 / r_min``), so one new slab almost never cuts
  the box's top face and box arithmetic alone leaves ``u_n`` too high and ``r_hat`` biased low (by
  -50 % or worse). The estimator therefore also keeps the vertex ``K*`` that maximizes ``K_n`` over
  a subset of the data (the constraints active at ``K*``, a window of the most recent data and the
  current block of data) intersected with the box. That maximum over fewer constraints is itself an
  outer bound of ``max K_n``; a datum changes it only when its residual at ``K*`` exceeds ``1``,
  which is one dot product per datum (vectorized per block), and only then one small LP per block
  (about ``window + reorient_every + n`` slabs plus the box, HiGHS) is solved. Constraints the
  subset has forgotten can make ``u_n`` slightly higher than the exact ``1 / r_Chebyshev``.

Point estimates
---------------
``r_hat`` is eq. 23. For ``theta`` the estimator offers eq. 23 (``theta_estimate="midpoint"``)
and, by default, the parameters at the top vertex ``K*`` (``"vertex"``): the posterior density
``r^-t`` peaks there, so it is the posterior mode over the kept constraints. The midpoint of the
box is a poor summary of this posterior: the box is as wide as the polytope's base
(``r -> infinity``), and an asymmetry of 1-3 % of that width, which the outer-bound updates leave,
moves eq. 23's ``theta`` by several percent.

What it costs
-------------
``benchmarks/studies/arx_estimation.py`` measures it against the exact MAP (Chebyshev) and least
squares (PRBS input, lightly damped poles 0.99 at 50 Hz, 1 kHz sampling; ARX(2,2), ARX(3,2) and
ARX(4,4) with ``r`` = 1 % and 5 % of the peak output and 2,000 or 20,000 samples):
``benchmarks/results/arx_estimation.md`` gives, per case, the errors of ``r_hat`` and of
``theta`` (at the vertex and at eq. 23's midpoint) and the time, and the samples per second of
:meth:`update_many` and of :meth:`update`. One sample at a time, :meth:`update` is Python-bound
(a small LP each time the top vertex is violated); :meth:`update_many` works per block, where
most of the time is the NumPy work of the box update and the reorientation, not the LPs.

Data are normalized internally (inputs and outputs divided by their largest magnitude in the
initialization data), so ``V``, ``l`` and ``u`` are in normalized units; :meth:`contains`
accepts parameters in the data's units.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.sparse
import threadpoolctl

from identification.arx import ARXModel, check_io
from piezo_env.checks import require_int

__all__ = ["BayesUniformEstimator", "slab_upper_bound"]

_MARGIN = 1e-9


def slab_upper_bound(
    h: np.ndarray, g: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> np.ndarray:
    """Upper bound of ``h^T xi`` over a box intersected with one two-sided slab, row-wise.

    Solves ``max h^T xi s.t. lower <= xi <= upper, -1 <= g^T xi <= 1`` through its dual
    ``min_lam  |lam| + sum_j max((h_j - lam g_j) lower_j, (h_j - lam g_j) upper_j)``, a convex
    piecewise-linear function of the scalar ``lam`` whose breakpoints ``h_j / g_j`` are sorted.
    The box must contain ``xi = 0`` (true for the support of ``K``). The returned value is the
    dual objective at the chosen multiplier, hence never below the true maximum.

    Parameters
    ----------
    h, g
        Arrays of shape (m, n) (or broadcastable to it): objective and slab normal per problem.
    lower, upper
        Box bounds, shape (n,).

    Returns
    -------
    numpy.ndarray
        Shape (m,), the maxima.
    """
    h, g = np.broadcast_arrays(np.atleast_2d(h), np.atleast_2d(g))
    width = upper - lower
    nonzero = g != 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        breakpoints = np.where(nonzero, h / np.where(nonzero, g, 1.0), np.inf)
    increments = np.abs(g) * width
    m = h.shape[0]
    breakpoints = np.concatenate([breakpoints, np.zeros((m, 1))], axis=1)
    increments = np.concatenate([increments, np.full((m, 1), 2.0)], axis=1)
    slope_start = -np.maximum(g * lower, g * upper).sum(axis=1) - 1.0
    columns = breakpoints.shape[1]
    order = (np.argsort(breakpoints, axis=1) + columns * np.arange(m)[:, None]).ravel()
    slope = np.cumsum(increments.ravel()[order].reshape(m, columns), axis=1)
    first = np.argmax(slope >= -slope_start[:, None], axis=1)
    lam = breakpoints.ravel()[order[first + columns * np.arange(m)]]
    lam = np.where(np.isfinite(lam), lam, 0.0)
    coefficient = h - lam[:, None] * g
    return np.maximum(coefficient * lower, coefficient * upper).sum(axis=1) + np.abs(lam)


def _outward(lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pad = _MARGIN * (1.0 + np.maximum(np.abs(lower), np.abs(upper)))
    return lower - pad, upper + pad


class BayesUniformEstimator:
    """Recursive approximate Bayesian estimator of an ARX model with uniform noise.

    Parameters
    ----------
    na, nb
        ARX orders (paper eq. 20): past outputs and past inputs in the regressor.
    window
        Number of most recent data the bounds are tightened against (>= 1).
    reorient_every
        Samples between updates of the orientation ``V`` (one QR of the new data each time).
    n_init
        Data vectors collected before the first parallelotope is computed (by LP) from them.
        Default ``max(4 n, window)`` with ``n = na + nb + 1``. If those data do not bound the
        support (not exciting enough), initialization is retried each time their number doubles.
    record_history
        Record the time course of the estimates (the paper's Figs. 5-8) after every update.
    theta_estimate
        ``"vertex"`` (default): theta at the tracked top vertex ``K*``, the posterior mode over
        the kept constraints. ``"midpoint"``: the paper's eq. 23 from the box midpoint.
    dt
        Sampling period of the data, s (passed on to the model).

    Attributes
    ----------
    nu : int
        Number of data vectors absorbed.
    """

    def __init__(
        self,
        na: int,
        nb: int,
        *,
        window: int = 16,
        reorient_every: int = 32,
        n_init: int | None = None,
        record_history: bool = True,
        theta_estimate: str = "vertex",
        dt: float = 1.0,
    ) -> None:
        if theta_estimate not in ("vertex", "midpoint"):
            raise ValueError(
                f"theta_estimate must be 'vertex' or 'midpoint', got {theta_estimate!r}"
            )
        self.theta_estimate = theta_estimate
        self.na = require_int("na", na, minimum=0)
        self.nb = require_int("nb", nb)
        self.n = self.na + self.nb + 1
        self.window = require_int("window", window)
        self.reorient_every = require_int("reorient_every", reorient_every)
        self.n_init = max(4 * self.n, self.window) if n_init is None else int(n_init)
        if self.n_init < self.n:
            raise ValueError(f"n_init must be >= na + nb + 1 = {self.n}, got {n_init}")
        self.record_history = bool(record_history)
        self.dt = float(dt)
        self._p = max(self.na, self.nb)
        self._u_past: list[float] = []
        self._y_past: list[float] = []
        self._raw: list[np.ndarray] = []
        self._next_init = self.n_init
        self._scale: np.ndarray | None = None
        self.nu = 0
        self._history: dict[str, list[Any]] = {"t": [], "theta": [], "noise_bound": []}

    # ----------------------------------------------------------------- public state
    @property
    def initialized(self) -> bool:
        """True once a bounded parallelotope exists (estimates are NaN before)."""
        return self._scale is not None

    @property
    def parallelotope(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(V, l, u)``: the support estimate ``{l <= V K <= u}`` in normalized units."""
        self._require_initialized()
        return self._V.copy(), self._lower.copy(), self._upper.copy()

    @property
    def theta(self) -> np.ndarray:
        """Current ``theta_hat = [a, b]`` (eq. 23), data units; NaN before initialization."""
        if not self.initialized:
            return np.full(self.n - 1, np.nan)
        return self._estimates()[0]

    @property
    def noise_bound(self) -> float:
        """Current ``r_hat`` (eq. 23), output unit; NaN before initialization."""
        if not self.initialized:
            return math.nan
        return self._estimates()[1]

    @property
    def history(self) -> dict[str, np.ndarray]:
        """Time course: ``"t"`` (samples absorbed), ``"theta"`` (T, na+nb), ``"noise_bound"``."""
        return {
            "t": np.asarray(self._history["t"], dtype=np.float64),
            "theta": np.asarray(self._history["theta"], dtype=np.float64).reshape(-1, self.n - 1),
            "noise_bound": np.asarray(self._history["noise_bound"], dtype=np.float64),
        }

    def contains(self, theta: Any, noise_bound: float) -> bool:
        """True if ``(theta, r)`` (data units) lies in the current parallelotope."""
        self._require_initialized()
        theta = np.asarray(theta, dtype=np.float64)
        k = np.concatenate([theta, [1.0]]) / noise_bound
        xi = self._V @ (k / self._scale)
        return bool(np.all(xi >= self._lower) and np.all(xi <= self._upper))

    def model(self, *, dt: float | None = None) -> ARXModel:
        """The current estimate as an :class:`ARXModel` with the recorded history."""
        self._require_initialized()
        theta, r = self._estimates()
        return ARXModel(
            theta[: self.na],
            theta[self.na :],
            noise_bound=r,
            dt=self.dt if dt is None else dt,
            history=self.history if self.record_history else None,
            method="bayes-uniform",
        )

    # ----------------------------------------------------------------- data in
    def update(self, u_t: float, y_t: float) -> None:
        """Absorb one sample: input ``u_t`` and output ``y_t`` at time t.

        The first ``max(na, nb)`` samples only fill the regressor.
        """
        u_t, y_t = float(u_t), float(y_t)
        if not (math.isfinite(u_t) and math.isfinite(y_t)):
            raise ValueError(f"non-finite sample u_t = {u_t}, y_t = {y_t}")
        if len(self._y_past) >= self._p:
            row = self._data_vector(self._u_past, self._y_past, y_t)
            self._absorb(row[None, :])
        self._u_past.append(u_t)
        self._y_past.append(y_t)
        del self._u_past[: -self._p or None], self._y_past[: -self._p or None]

    def update_many(self, u: Any, y: Any) -> None:
        """Absorb a record of samples (same result as :meth:`update` per sample, up to blocking).

        Data are processed in blocks aligned with the reorientation period, which is what makes
        the batch path fast.
        """
        u, y = check_io(u, y)
        # Tiny matrices: a multi-threaded BLAS only adds synchronization stalls here.
        with threadpoolctl.threadpool_limits(1):
            self._update_many(u, y)

    def _update_many(self, u: np.ndarray, y: np.ndarray) -> None:
        uu = np.concatenate([self._u_past, u])
        yy = np.concatenate([self._y_past, y])
        p = self._p
        if yy.size > p:
            columns = [-yy[p - i : yy.size - i] for i in range(1, self.na + 1)]
            columns += [-uu[p - j : uu.size - j] for j in range(1, self.nb + 1)]
            columns.append(yy[p:])
            rows = np.column_stack(columns)
            start = 0
            while start < rows.shape[0]:
                if not self.initialized:
                    stop = start + max(1, self._next_init - len(self._raw))
                else:
                    stop = start + self.reorient_every - self._since_reorient
                self._absorb(rows[start:stop])
                start = stop
        self._u_past = list(uu[max(uu.size - p, 0) :]) if p else []
        self._y_past = list(yy[max(yy.size - p, 0) :]) if p else []

    # ----------------------------------------------------------------- recursion
    def _data_vector(self, u_past: list[float], y_past: list[float], y_t: float) -> np.ndarray:
        ys = [-y_past[-i] for i in range(1, self.na + 1)]
        us = [-u_past[-j] for j in range(1, self.nb + 1)]
        return np.array([*ys, *us, y_t])

    def _require_initialized(self) -> None:
        if not self.initialized:
            raise RuntimeError(
                f"the estimator has no bounded support yet ({len(self._raw)} data vectors "
                f"absorbed, at least {self.n_init} exciting ones needed)"
            )

    def _absorb(self, raw_rows: np.ndarray) -> None:
        if not self.initialized:
            self._raw.extend(raw_rows)
            self.nu += raw_rows.shape[0]
            if len(self._raw) >= self._next_init:
                self._initialize()
            return
        rows = raw_rows * self._scale
        self._process(rows)
        self.nu += rows.shape[0]
        self._record()

    def _initialize(self) -> None:
        raw = np.asarray(self._raw)
        peak_y = np.max(np.abs(raw[:, [*range(self.na), self.n - 1]]))
        peak_u = np.max(np.abs(raw[:, self.na : self.n - 1]))
        if peak_y == 0.0 or peak_u == 0.0:
            self._next_init *= 2
            return
        scale = np.concatenate(
            [np.full(self.na, 1.0 / peak_y), np.full(self.nb, 1.0 / peak_u), [1.0 / peak_y]]
        )
        rows = raw * scale
        r = scipy.linalg.qr(rows, mode="r")[0][: self.n]
        diagonal = np.diag(r)
        if np.any(np.abs(diagonal) <= 1e-10 * np.abs(diagonal).max()):
            self._next_init *= 2
            return
        v = r / diagonal[:, None]
        a_ub = scipy.sparse.vstack([scipy.sparse.csr_array(rows), -scipy.sparse.csr_array(rows)])
        b_ub = np.ones(2 * rows.shape[0])
        bounds = [(None, None)] * (self.n - 1) + [(0.0, None)]
        lower, upper = np.empty(self.n), np.empty(self.n)
        top = None
        for i in range(self.n):
            for sign in (1.0, -1.0):
                res = scipy.optimize.linprog(
                    -sign * v[i], A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs"
                )
                if res.status != 0:
                    self._next_init *= 2
                    return
                if sign > 0:
                    upper[i] = -res.fun
                    if i == self.n - 1:
                        top = res.x
                else:
                    lower[i] = res.fun
        self._scale = scale
        self._R = r * np.sign(diagonal)[:, None]
        self._set_orientation(v)
        self._lower, self._upper = _outward(lower, upper)
        self._lower[-1] = max(self._lower[-1], 0.0)
        self._window_rows = rows[-self.window :]
        self._pending = np.empty((0, self.n))
        self._since_reorient = 0
        self._set_top(top, rows)
        self._raw = []
        self._record()

    def _set_orientation(self, v: np.ndarray) -> None:
        self._V = v
        self._Vinv = np.linalg.inv(v)

    def _set_top(self, k: np.ndarray, rows: np.ndarray) -> None:
        self._top = k
        active = np.abs(rows @ k) >= 1.0 - 1e-7
        self._support = rows[active][: 2 * self.n]

    def _process(self, rows: np.ndarray) -> None:
        self._tighten_box(rows)
        self._track_top(rows)
        self._window_rows = np.concatenate([self._window_rows, rows])[-self.window :]
        self._pending = np.concatenate([self._pending, rows])
        self._since_reorient += rows.shape[0]
        if self._since_reorient >= self.reorient_every:
            self._reorient()

    def _tighten_box(self, rows: np.ndarray) -> None:
        """Exact coordinate bounds of (box intersected with each slab), intersected over slabs."""
        g = rows @ self._Vinv
        low_terms = np.minimum(g * self._lower, g * self._upper)
        high_terms = np.maximum(g * self._lower, g * self._upper)
        others_low = low_terms.sum(axis=1, keepdims=True) - low_terms
        others_high = high_terms.sum(axis=1, keepdims=True) - high_terms
        with np.errstate(divide="ignore", invalid="ignore"):
            bound_a = (1.0 - others_low) / g
            bound_b = (-1.0 - others_high) / g
        positive = g > 0.0
        negative = g < 0.0
        upper = np.where(positive, bound_a, np.where(negative, bound_b, np.inf)).min(axis=0)
        lower = np.where(positive, bound_b, np.where(negative, bound_a, -np.inf)).max(axis=0)
        lower, upper = _outward(lower, upper)
        self._lower = np.maximum(self._lower, lower)
        self._upper = np.minimum(self._upper, upper)

    def _track_top(self, rows: np.ndarray) -> None:
        """Re-solve the top vertex only if some datum of the block lies outside its slab."""
        if np.any(np.abs(rows @ self._top) > 1.0 + 1e-9):
            self._solve_top(np.concatenate([self._support, self._window_rows, rows]))

    def _solve_top(self, rows: np.ndarray) -> None:
        a_ub = np.concatenate([rows, -rows, self._V, -self._V])
        b_ub = np.concatenate([np.ones(2 * rows.shape[0]), self._upper, -self._lower])
        c = np.zeros(self.n)
        c[-1] = -1.0
        res = scipy.optimize.linprog(
            c, A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * self.n, method="highs"
        )
        if res.status != 0:
            return
        self._set_top(res.x, rows)
        top = -res.fun
        self._upper[-1] = min(self._upper[-1], top + _MARGIN * (1.0 + abs(top)))

    def _reorient(self) -> None:
        stacked = np.concatenate([self._R, self._pending])
        r = np.linalg.qr(stacked, mode="r")
        diagonal = np.diag(r)
        self._pending = np.empty((0, self.n))
        self._since_reorient = 0
        if np.any(diagonal == 0.0):
            return
        self._R = r * np.sign(diagonal)[:, None]
        v_new = self._R / np.abs(diagonal)[:, None]
        transform = v_new @ self._Vinv
        g = self._window_rows @ self._Vinv
        objectives = np.concatenate([transform, -transform])
        m = objectives.shape[0]
        h = np.repeat(objectives, g.shape[0], axis=0)
        gg = np.tile(g, (m, 1))
        bounds = slab_upper_bound(h, gg, self._lower, self._upper).reshape(m, g.shape[0])
        interval = np.maximum(objectives * self._lower, objectives * self._upper).sum(axis=1)
        best = np.minimum(bounds.min(axis=1), interval)
        lower, upper = _outward(-best[self.n :], best[: self.n])
        # V' and V share the last row e_n, so the bounds of K_n carry over exactly.
        lower[-1], upper[-1] = self._lower[-1], self._upper[-1]
        self._lower, self._upper = lower, upper
        self._set_orientation(v_new)

    # ----------------------------------------------------------------- estimates
    def _estimates(self) -> tuple[np.ndarray, float]:
        lower, upper = self._lower, self._upper
        nu = max(self.nu, 1)
        ratio = max(lower[-1], 0.0) / upper[-1]
        r_norm = (nu + 1) / nu * (1.0 - ratio**nu) / (1.0 - ratio ** (nu + 1)) / upper[-1]
        mid = 0.5 * (lower[:-1] + upper[:-1])
        if self.theta_estimate == "vertex":
            theta_norm = self._top[:-1] / self._top[-1]
        else:
            # V^-1 = [[v_psi^-1, -v_psi^-1 v_y], [0, 1]] holds both terms of eq. 23.
            theta_norm = self._Vinv[:-1, :-1] @ (r_norm * mid) + self._Vinv[:-1, -1]
        # Undo the normalization: K = [theta; 1] / r in data units is scale * K_norm.
        theta = theta_norm * self._scale[:-1] / self._scale[-1]
        return theta, float(r_norm / self._scale[-1])

    def _record(self) -> None:
        if not self.record_history:
            return
        theta, r = self._estimates()
        self._history["t"].append(self.nu)
        self._history["theta"].append(theta)
        self._history["noise_bound"].append(r)
