"""Many drawn plants stepped as one batch: the common state layout and per-row hysteresis.

With domain randomisation every sub-environment of the vector env has its own plant. Plants of
different damping and resonance keep different modes (the modal reduction is exact per plant),
so each plant's step matrix is placed in one common layout with a slot for every FE mode
(:func:`padded_layout`, :func:`scaled_step_matrix_t`), and their hysteresis maps, scaled copies
of one nominal map, are stepped together (:class:`RowHysteresis`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from piezo_env.hysteresis import (
    BoucWen,
    Hysteresis,
    PrandtlIshlinskii,
    RateDependentPrandtlIshlinskii,
    bouc_wen_rows,
)
from piezo_env.operators import BoucWenBatch, play

if TYPE_CHECKING:
    from piezo_env.discrete import DiscreteBender
    from piezo_env.model import PiezoBenderModel

__all__ = ["RowHysteresis", "padded_layout", "scaled_step_matrix_t"]


def padded_layout(discrete: DiscreteBender, n_modes: int) -> np.ndarray:
    """Where each index of a plant's square step vector goes in the common padded layout.

    The common layout holds every FE mode (``n_modes``), so plants that keep different modes
    share one state size ``n_creep + 2 n_modes + 2``: [creep, (eta_m, eta_m') for m = 0 ..
    n_modes - 1, fast deflection, fast rotation], then u_eff / y and theta. A mode a plant
    drops keeps zeros in its slots.
    """
    nc = discrete.n_creep
    size = nc + 2 * n_modes + 2
    kept = np.asarray(discrete.kept_modes, dtype=np.int64)
    modes = (nc + 2 * kept[:, None] + np.arange(2)).ravel()
    return np.r_[np.arange(nc), modes, size - 2, size - 1, size, size + 1]


def scaled_step_matrix_t(model: PiezoBenderModel, layout: np.ndarray, k: int) -> np.ndarray:
    """Transposed square step matrix of ``model`` placed at ``layout`` in a (k + 2)-square.

    The output columns come out scaled: deflection in um, Gamma theta_tip in uC.
    """
    step_t = np.zeros((k + 2, k + 2))
    step_t[np.ix_(layout, layout)] = model.discrete.square_step_matrix().T
    step_t[:, k] *= 1e6
    step_t[:, k + 1] *= model.params.piezo_moment * 1e6
    return step_t


class RowHysteresis:
    """The hysteresis of N sub-envs, each with its own drawn parameters, stepped at once.

    All rows are scaled copies of one nominal model
    (:func:`piezo_env.randomization.scale_hysteresis`): Bouc-Wen rows differ in k and alpha,
    Prandtl-Ishlinskii rows (rate-dependent ones too) in their weights. ``step(state, u)`` has
    the batched signature of :meth:`piezo_env.hysteresis.Hysteresis.step` (state (N, size)).
    """

    def __init__(self, nominal: Hysteresis, num_envs: int) -> None:
        self.nominal = nominal
        self.state_size = nominal.state_size
        if isinstance(nominal, BoucWen):
            self._k = np.full(num_envs, nominal.k)
            self._ak = np.full(num_envs, nominal.alpha * nominal.k)
        elif isinstance(nominal, (PrandtlIshlinskii, RateDependentPrandtlIshlinskii)):
            self._k = np.full(num_envs, nominal.linear_weight)
            self._w = np.tile(np.asarray(nominal.weights, dtype=float), (num_envs, 1))
            self._r = np.asarray(nominal.radii, dtype=float)
        self._batch: BoucWenBatch | None = None

    def set_row(self, i: int, hysteresis: Hysteresis) -> None:
        """Give row ``i`` the parameters of ``hysteresis`` (a scaled copy of the nominal)."""
        if isinstance(hysteresis, BoucWen):
            self._k[i] = hysteresis.k
            self._ak[i] = hysteresis.alpha * hysteresis.k
            self._batch = None
        elif isinstance(hysteresis, (PrandtlIshlinskii, RateDependentPrandtlIshlinskii)):
            self._k[i] = hysteresis.linear_weight
            self._w[i] = hysteresis.weights

    def step(self, state: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Advance every row over its jump to ``u`` (V); returns (new state, u_eff in V)."""
        nominal = self.nominal
        if isinstance(nominal, BoucWen):
            if self._batch is None:
                self._batch = BoucWenBatch(self._ak, nominal.beta, nominal.gamma)
            return bouc_wen_rows(self._batch, self._k, state, u)
        if isinstance(nominal, PrandtlIshlinskii):
            plays = play(state[:, 1:], u[:, None], self._r)
            new_state = np.concatenate([u[:, None], plays], axis=1)
            return new_state, self._k * u + np.einsum("ij,ij->i", plays, self._w)
        if isinstance(nominal, RateDependentPrandtlIshlinskii):  # the plays move as the nominal's
            new_state, _ = nominal.step(state, u)
            return new_state, self._k * u + np.einsum("ij,ij->i", new_state[:, 2:], self._w)
        return nominal.step(state, u)
