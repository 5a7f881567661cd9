"""Inverse of the NLS: the voltage that gives a target hidden signal from a memory state.

:meth:`NLS.solve_inverse` gives the voltage that produces a desired ``z`` given the current
memory state (for controllers that plan in ``z``), with the reachable range and a status, as an
:class:`piezo_env.inverse.InverseResult` ``(u, z, status, state)``: the same type as the plant
hysteresis' inverse. It is :func:`piezo_env.inverse.solve_increasing`: one batched network pass
over a coarse grid (reachable range, monotonicity at the nodes, bracket), then safeguarded Newton
with a finite-difference slope, typically two passes in all; exact to ~1e-7 V. When ``z`` is
not reachable on the range the range end is returned (``"out-of-range"``); when the map is
found not monotone (several roots) the root nearest a reference voltage is returned
(``"non-monotone"``) and :meth:`NLS.inverse` warns with :class:`NLSInverseWarning`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.arguments import as_range, as_scalar, as_signal
from identification.features import BoucWenFeatures, PastInputFeatures, RatePlayFeatures
from piezo_env.checks import require_int
from piezo_env.inverse import InverseResult, solve_increasing

__all__ = ["InverseMixin", "NLSInverse", "NLSInverseWarning"]

NLSInverse = InverseResult
"""Result of one NLS inversion: :class:`piezo_env.inverse.InverseResult` (u, z, status, state),
the same type the plant's hysteresis inverse returns."""


class NLSInverseWarning(RuntimeWarning):
    """The NLS inverse found several voltages for one target (map not monotone on the range)."""


class InverseMixin:
    """Inverse methods of :class:`identification.nls.NLS` (needs ``feature_map``, ``_mlp``,
    ``u_range`` and ``_grid_cache``)."""

    feature_map: Any
    u_range: tuple[float, float]
    _mlp: Any
    _grid_cache: tuple[tuple[float, float, int], np.ndarray] | None

    def solve_inverse(
        self,
        z_target: float,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
        u_ref: float | None = None,
        u_guess: float | None = None,
        n_grid: int = 17,
        xtol: float = 1e-7,
        mix: tuple[float, float] | None = None,
    ) -> NLSInverse:
        """Voltage giving ``z_target`` from the memory ``state``, with a status.

        :func:`piezo_env.inverse.solve_increasing`: one batched pass over an ``n_grid``-point
        grid of ``u_range`` (reachable range, monotonicity at the nodes, bracket), then
        safeguarded Newton steps (finite-difference slope, two points per batched pass) from
        the warm start until the estimated error is below ``xtol``. Typically two network passes.

        Parameters
        ----------
        z_target : float
            Desired hidden signal, equivalent V.
        state : array_like, optional
            Feature state before this sample; None for the rest state.
        u_range : (float, float), optional
            Voltage search range, V. Default: the training input range :attr:`u_range`.
        u_ref : float, optional
            Reference voltage, V, used to choose among several roots (the nearest wins).
            Default: the previous input for past-input and Bouc-Wen features (their state holds
            it), else the middle of the range.
        u_guess : float, optional
            Warm start, V (e.g. the previous solution). Default: ``u_ref``.
        n_grid : int, optional
            Grid points of the bracketing pass. A decrease between nodes, or an iterate outside
            its bracket's values, marks the map non-monotone (then all roots on the grid are
            found by Brent's method); a wiggle narrower than the grid spacing that no iterate
            touches goes unnoticed.
        xtol : float, optional
            Estimated voltage error (V) below which the iteration stops.
        mix : (float, float), optional
            ``(a, b)``: invert ``a z(u) + b u`` instead of ``z(u)`` (``z_target`` and the
            returned ``z`` are then of the mixed map): the drive of a bender whose hysteresis
            strength differs from the identified one (:mod:`controllers.drive`).

        Returns
        -------
        NLSInverse
            Voltage, achieved ``z`` (evaluated at that voltage), status (``"ok"``,
            ``"out-of-range"``, ``"non-monotone"``) and the state after applying the voltage.
        """
        target = as_scalar("z_target", z_target)
        s = self.feature_map.check_state(state)
        low, high = self.u_range if u_range is None else as_range("u_range", u_range)
        grid = self._grid(low, high, n_grid)
        if u_ref is None:
            u_ref = self._default_u_ref(s, low, high)
        candidates, rows = self.feature_map.candidates, self._mlp.evaluate_rows

        a, b = (1.0, 0.0) if mix is None else (as_scalar("mix", v) for v in mix)

        def evaluate(u: np.ndarray) -> np.ndarray:
            z = rows(candidates(u, s))
            return z if mix is None else a * z + b * u

        guess = u_ref if u_guess is None else as_scalar("u_guess", u_guess)
        sol = solve_increasing(evaluate, target, grid, guess, u_ref=u_ref, xtol=xtol)
        _, new_state = self.feature_map.step(sol.u, s)
        return InverseResult(sol.u, sol.z, sol.status, new_state)

    def inverse(
        self,
        z_target: float,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
        u_ref: float | None = None,
    ) -> float:
        """Voltage (V) that gives ``z_target`` (equivalent V) from the memory ``state``.

        A target outside the reachable set gives the closest reachable voltage (saturation).
        When the map is not monotone on the range, several voltages reach the target: the one
        nearest ``u_ref`` is returned and a :class:`NLSInverseWarning` is issued. See
        :meth:`solve_inverse` for the parameters and a status-returning variant.
        """
        result = self.solve_inverse(z_target, state, u_range=u_range, u_ref=u_ref)
        if result.status == "non-monotone":
            warnings.warn(
                f"NLS is not monotone in u on the range for z_target={z_target}: several "
                f"voltages reach it; returned the one nearest the reference ({result.u:.6g} V)",
                NLSInverseWarning,
                stacklevel=2,
            )
        return result.u

    def inverse_sequence(
        self,
        z_seq: ArrayLike,
        state: ArrayLike | None = None,
        *,
        u_range: Sequence[float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Voltages that reproduce a hidden-signal sequence, inverting sample by sample.

        Each step inverts from the memory left by the previous voltages; among several roots
        the one nearest the previous voltage is chosen. Unreachable targets saturate silently;
        a non-monotone map gives one :class:`NLSInverseWarning` for the whole sequence.

        Parameters
        ----------
        z_seq : array_like, shape (T,)
            Desired hidden signal, equivalent V.
        state : array_like, optional
            Feature state before the first sample; None for the rest state.
        u_range : (float, float), optional
            Voltage search range, V (default: the training input range).

        Returns
        -------
        u : numpy.ndarray, shape (T,)
            Voltages, V.
        final_state : numpy.ndarray
            Feature state after the last voltage.
        """
        z = as_signal("z_seq", z_seq)
        s = self.feature_map.check_state(state)
        u = np.empty_like(z)
        u_ref = None
        n_non_monotone = 0
        for t, target in enumerate(z):
            result = self.solve_inverse(target, s, u_range=u_range, u_ref=u_ref)
            u[t] = u_ref = result.u
            s = result.state
            n_non_monotone += result.status == "non-monotone"
        if n_non_monotone:
            warnings.warn(
                f"NLS is not monotone in u on the range at {n_non_monotone} of {z.size} "
                "samples; chose the root nearest the previous voltage there",
                NLSInverseWarning,
                stacklevel=2,
            )
        return u, s

    def _default_u_ref(self, state: np.ndarray, low: float, high: float) -> float:
        """The previous input where the state holds it (past inputs, Bouc-Wen, rate-dependent
        plays), else mid-range."""
        if isinstance(self.feature_map, PastInputFeatures | BoucWenFeatures | RatePlayFeatures):
            return float(state[0])
        return 0.5 * (low + high)

    def _grid(self, low: float, high: float, n_grid: int) -> np.ndarray:
        """Bracketing grid of the inverse, cached for the last range used."""
        key = (low, high, n_grid)
        if self._grid_cache is None or self._grid_cache[0] != key:
            n_grid = require_int("n_grid", n_grid, minimum=2)
            self._grid_cache = (key, np.linspace(low, high, n_grid))
        return self._grid_cache[1]
