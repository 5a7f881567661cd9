"""Inverse of an input nonlinearity from one memory state: the voltage that gives a target.

Controllers plan in the hidden input (the effective voltage of the plant's hysteresis, or the
identified NLS output z) and need the drive voltage that produces it one step ahead. From a
fixed memory state the map u -> z(u) is a scalar function on the drive range; for the plant's
hysteresis it is strictly increasing (proved in :mod:`piezo_env.hysteresis`), for an identified
network it usually is. :func:`solve_increasing` inverts it:

1. one batched evaluation on a coarse grid of the range (plus the warm start and a
   finite-difference partner): the reachable range [z(lo), z(hi)], a monotonicity check at the
   grid nodes and the grid cell that brackets the target;
2. an initial point by inverse quadratic interpolation on the smooth side of the warm start
   (hysteresis maps kink where the input reverses, i.e. at the previous input);
3. Newton steps with a finite-difference slope, each one batched evaluation of two points,
   safeguarded by the bracket (a step leaving it becomes a secant/bisection step). The last
   Newton step is taken without a further evaluation once its own error,
   |z''| step^2 / (2 z') with the curvature estimated from secants to both bracket ends, is
   below ``xtol`` and the step does not cross the warm start (memory maps kink there). The
   returned ``z`` is then the evaluated output plus slope times that step, within about
   ``slope * xtol`` of the output at ``u``. Typically two batched passes.

What is and is not detected: a decrease between consecutive grid nodes, or an evaluated value
outside its bracket's values, marks the map non-monotone, and then every root on the grid is
found by Brent's method and the one nearest ``u_ref`` is returned with status
``"non-monotone"``. A non-monotone wiggle narrower than the grid spacing that no iterate
touches goes unnoticed (then the result is still an exact root, just maybe not the only one).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize

__all__ = ["InverseResult", "solve_increasing"]

STATUSES = ("ok", "out-of-range", "non-monotone")


@dataclass(frozen=True)
class InverseResult:
    """Result of inverting an input nonlinearity for one sample.

    Unpacks as a tuple: ``u, z, status, state = result``.

    Attributes
    ----------
    u : float
        Drive voltage, V, inside the search range.
    z : float
        Output at ``u`` from the given state (effective voltage in V, or the NLS output in
        equivalent V); equals the target to within the slope times the tolerance when
        ``status == "ok"``.
    status : str
        ``"ok"`` (the root), ``"out-of-range"`` (target not reachable on the range: ``u`` is
        the range end whose output is closest) or ``"non-monotone"`` (several roots: ``u`` is
        the one nearest the reference voltage).
    state : numpy.ndarray
        Memory state after applying ``u``.
    """

    u: float
    z: float
    status: str
    state: np.ndarray

    def __iter__(self):
        return iter((self.u, self.z, self.status, self.state))


@dataclass(frozen=True)
class _Solution:
    u: float
    z: float
    status: str


def solve_increasing(
    evaluate: Callable[[np.ndarray], np.ndarray],
    target: float,
    grid: np.ndarray,
    guess: float,
    *,
    u_ref: float,
    xtol: float = 1e-7,
    max_iter: int = 40,
    extrapolate: bool = True,
) -> _Solution:
    """Invert an (expectedly) increasing scalar map on ``[grid[0], grid[-1]]``.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(u_rows) -> z_rows``: the map at each entry of a 1-D array (V), one batch.
    target : float
        Output wanted.
    grid : numpy.ndarray
        Increasing bracketing grid over the search range, V (its ends are the range).
    guess : float
        Warm start, V (e.g. the previous input); clipped to the range.
    u_ref : float
        Reference voltage choosing among several roots, V.
    xtol : float
        Estimated error (V) of ``u`` below which the iteration stops.
    max_iter : int
        Newton steps before falling back to Brent's method in the bracket.
    extrapolate : bool
        Take the last Newton step without evaluating it (see the module docstring). False
        stops only at an evaluated point whose Newton correction is below ``xtol``: one pass
        more, and ``z`` exactly the output at ``u`` (for maps with many kinks, such as play
        operators, where the curvature estimate cannot see a kink inside the last step).

    Returns
    -------
    _Solution
        ``u`` (V), ``z`` evaluated at ``u``, status.
    """
    nodes = grid.tolist()
    low, high = nodes[0], nodes[-1]
    delta = 1e-7 * (high - low)
    g = min(max(guess, low), high)
    values = evaluate(np.concatenate((grid, (g, g + delta))))
    zg = values[:-2]
    if (zg[1:] <= zg[:-1]).any():
        return _all_roots(evaluate, target, grid, zg, u_ref)
    zl = values.tolist()
    z_guess = zl[-2]
    del zl[-2:]
    if not zl[0] < target < zl[-1]:
        end = -1 if target >= zl[-1] else 0
        # Within rounding of the end's output (batched and single evaluations differ in ulps).
        status = "ok" if abs(target - zl[end]) <= 1e-12 * (1.0 + abs(target)) else "out-of-range"
        return _Solution(nodes[end], zl[end], status)
    j = bisect.bisect_left(zl, target)  # zl[j - 1] < target <= zl[j]
    a, za, b, zb = nodes[j - 1], zl[j - 1], nodes[j], zl[j]
    if a < g < b:
        if not za < z_guess < zb:
            return _all_roots(evaluate, target, grid, zg, u_ref)
        if z_guess < target:
            a, za = g, z_guess
        else:
            b, zb = g, z_guess
    u = _initial_point(nodes, zl, j, a, za, b, zb, target)
    newton = _Newton(evaluate, target, g, delta, xtol, extrapolate)
    solution = newton.solve(u, (a, za, b, zb), max_iter)
    return solution if solution is not None else _all_roots(evaluate, target, grid, zg, u_ref)


def _initial_point(
    grid: list[float], zg: list[float], j: int, a: float, za: float, b: float, zb: float, t: float
) -> float:
    """First iterate in (a, b): inverse quadratic interpolation through (a, b) and the grid node
    beyond the end that is a grid node (the other end may be the warm start, where the map
    kinks), else the secant point."""
    secant = a + (t - za) * (b - a) / (zb - za)
    if b == grid[j] and j + 1 < len(grid):
        c, zc = grid[j + 1], zg[j + 1]
    elif a == grid[j - 1] and j >= 2:
        c, zc = grid[j - 2], zg[j - 2]
    else:
        return secant
    u = (
        a * (t - zb) * (t - zc) / ((za - zb) * (za - zc))
        + b * (t - za) * (t - zc) / ((zb - za) * (zb - zc))
        + c * (t - za) * (t - zb) / ((zc - za) * (zc - zb))
    )
    return u if a < u < b else secant


def _all_roots(
    evaluate: Callable[[np.ndarray], np.ndarray],
    target: float,
    grid: np.ndarray,
    zg: np.ndarray,
    u_ref: float,
) -> _Solution:
    """Every root bracketed by the grid (Brent's method); the one nearest ``u_ref`` wins."""
    residual = zg - target

    def fun(x: float) -> float:
        return float(evaluate(np.array((x,)))[0]) - target

    roots = [float(grid[i]) for i in np.flatnonzero(residual == 0.0)]
    brackets = np.flatnonzero(np.sign(residual[:-1]) * np.sign(residual[1:]) < 0.0)
    roots += [scipy.optimize.brentq(fun, grid[i], grid[i + 1], xtol=1e-12) for i in brackets]
    if not roots:
        i = int(np.argmin(np.abs(residual)))
        return _Solution(float(grid[i]), float(zg[i]), "out-of-range")
    u = min(roots, key=lambda root: abs(root - u_ref))
    status = "non-monotone" if len(roots) > 1 or (np.diff(zg) <= 0).any() else "ok"
    return _Solution(u, fun(u) + target, status)


class _Newton:
    """Safeguarded Newton in a bracket [a, b] of an increasing map (see :func:`solve_increasing`).

    :meth:`solve` returns the solution, or None when an iterate leaves its bracket's values
    (the map is not increasing there): the caller then looks at every root.
    """

    def __init__(
        self,
        evaluate: Callable[[np.ndarray], np.ndarray],
        target: float,
        g: float,
        delta: float,
        xtol: float,
        extrapolate: bool,
    ) -> None:
        self.evaluate, self.target, self.g = evaluate, target, g
        self.delta, self.xtol, self.extrapolate = delta, xtol, extrapolate

    def solve(
        self, u: float, bracket: tuple[float, float, float, float], max_iter: int
    ) -> _Solution | None:
        """From ``u`` inside ``bracket = (a, z(a), b, z(b))``; Brent after ``max_iter`` steps."""
        a, za, b, zb = bracket
        target, g = self.target, self.g
        for _ in range(max_iter):
            zu, zd = self.evaluate(np.array((u, u + self.delta))).tolist()
            if not za <= zu <= zb:
                return None
            slope = (zd - zu) / self.delta
            if zu == target:
                return _Solution(u, zu, "ok")
            step = (target - zu) / slope if slope > 0.0 else math.inf
            if not self.extrapolate and abs(step) <= self.xtol:
                return _Solution(u, zu, "ok")
            inside = abs(step) < 0.5 * (b - a) and (u - g) * (u + step - g) > 0.0
            if self.extrapolate and inside:
                # Error of the final Newton step u + step: |z''| step^2 / (2 z'), with z''/2
                # from the secants to both bracket ends (a kink there only overestimates it).
                # Never across the warm start: memory maps kink where the input reverses.
                half_curvature = max(
                    abs((za - zu) / (a - u) - slope) / (u - a) if u > a else 0.0,
                    abs((zb - zu) / (b - u) - slope) / (b - u) if u < b else 0.0,
                )
                if half_curvature * step * step <= self.xtol * slope:
                    return _Solution(u + step, zu + slope * step, "ok")
            if zu < target:
                a, za = u, zu
            else:
                b, zb = u, zu
            if b - a <= 1e-13 * (1.0 + abs(a)):  # bracketed to rounding (a root at a kink)
                closer_a = target - za <= zb - target
                return _Solution(a, za, "ok") if closer_a else _Solution(b, zb, "ok")
            u_new = u + step
            if not a < u_new < b:
                u_new = a + (target - za) * (b - a) / (zb - za)
                if not a < u_new < b:
                    u_new = 0.5 * (a + b)
            u = u_new
        u = scipy.optimize.brentq(lambda x: float(self.evaluate(np.array((x,)))[0]) - target, a, b)
        return _Solution(u, float(self.evaluate(np.array((u,)))[0]), "ok")
