"""Domain randomisation: a plant drawn from the datasheet tolerances at every reset.

With ``randomize=True`` (or a :class:`DomainRandomization`) the env draws, at each reset and
before anything else of the episode, five numbers from its own generator ``np_random`` with one
call ``rng.uniform(low, high)`` in this order (:data:`DRAW_ORDER`):

1. free deflection d_free at U_r (nominal x U(1 - s, 1 + s), s = 0.2): with the blocking force
   it fixes the tip stiffness k = F_b / d_free;
2. blocking force F_b at U_r (nominal x U(1 - s, 1 + s), s = 0.2);
3. first resonance f_1 (nominal x U(1 - s, 1 + s), s = 0.2): the density is calibrated to it;
4. first-mode damping ratio zeta_1 ~ U(0.01, 0.04) (Rayleigh damping, as the nominal plant);
5. hysteresis strength scale s_h ~ U(0.7, 1.3): Bouc-Wen alpha (or the play weights of
   Prandtl-Ishlinskii) times s_h, then the whole map times c = E_nom / E(s_h), where E is the
   effective voltage at +U_r on the major loop, so that the drawn plant still deflects d_free
   at U_r whatever its loop width. A linear bender draws s_h too (the stream does not depend on
   the hysteresis type) and ignores it.

The drawn datasheet gives the beam (:func:`piezo_env.parameters.bender_parameters`), and the
plant is rebuilt (FE, modes, one matrix exponential per mode: about 1-5 ms).

**Observation bound over the whole range** (:func:`randomized_deflection_bound_um`). Each
plant's proven bound is ||h||_1 max|u_eff|, with h the sampled impulse response of the exact
zero-order-hold model. Its samples are integrals of the continuous impulse response g over
one sample, h_k = int_{(k-1)dt}^{k dt} g, so ||h||_1 <= ||g||_1 (the reduced model and the
numerical L1 sum agree with the exact one to ~1e-9, covered by a 1e-6 margin). The beam's
transfer function is (d_free / U_r) H(s / omega_1; zeta_1): Gamma / EI = 3 d_free / (2 L^2 U_r)
does not depend on F_b, the density only moves every frequency by the same factor, and Rayleigh
damping gives zeta_k = zeta_1 omega_k / omega_1. By the triangle inequality over modes and
int_0^inf e^(-a t) |sin b t| dt = b / (a^2 + b^2) coth(pi a / (2 b)),

    ||g||_1 <= (d_free / d_nom) sum_k |s_k| coth(pi zeta_k / (2 sqrt(1 - zeta_k^2)))

(coth -> 1 for an overdamped mode, zeta_k >= 1), with s_k the static tip gain of mode k of the
nominal beam: linear in d_free, independent of F_b and f_1, decreasing in zeta_1. Creep
multiplies it by at most 1 + sum c_i (its impulse response is positive). The effective voltage
of a drawn Bouc-Wen map is c (k U_r + s_h h_nom) with |h| <= s_h h_nom on the major loop, so
E(s_h) >= k U_r - s_h h_nom and max|u_eff| <= E_nom (k U_r + s_h h_nom) / (k U_r - s_h h_nom),
increasing in s_h; a drawn Prandtl-Ishlinskii map peaks at E_nom exactly. The bound is the
product at the worst corner (largest d_free and s_h, smallest zeta_1).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from threadpoolctl import ThreadpoolController

from piezo_env.datasheet import BenderDatasheet
from piezo_env.fem import check_damping_ratio
from piezo_env.hysteresis import BoucWen, Hysteresis, NoHysteresis, PrandtlIshlinskii
from piezo_env.operators import BoucWenBatch, play

if TYPE_CHECKING:
    from piezo_env.discrete import DiscreteBender
    from piezo_env.model import PiezoBenderModel

__all__ = [
    "DRAW_ORDER",
    "DomainRandomization",
    "PlantDraw",
    "RowHysteresis",
    "major_loop_peak",
    "padded_layout",
    "randomized_deflection_bound_um",
    "scale_hysteresis",
    "single_blas_thread",
]

DRAW_ORDER = (
    "free_deflection",
    "blocking_force",
    "resonance",
    "damping_ratio",
    "hysteresis_scale",
)
"""The numbers drawn at each reset, in the order they are taken from the generator."""

_BOUND_MARGIN = 1e-6
"""Relative margin of the range bound over the per-plant bounds (rounding of both)."""


@dataclass(frozen=True, kw_only=True)
class DomainRandomization:
    """Spread of the plant drawn at each reset (all draws uniform and independent).

    Attributes
    ----------
    free_deflection : float
        Relative half-width s (-) of the free deflection at U_r: nominal x U(1 - s, 1 + s).
        With ``blocking_force`` it sets the tip stiffness F_b / d_free. In [0, 1).
    blocking_force : float
        Relative half-width (-) of the blocking force at U_r. In [0, 1).
    resonance : float
        Relative half-width (-) of the first resonance (Hz). In [0, 1).
    damping_ratio : tuple of float
        (low, high) of the first-mode damping ratio zeta_1 (-), each in [1e-4, 1), low <= high.
    hysteresis_strength : float
        Relative half-width (-) of the hysteresis strength (Bouc-Wen alpha, play weights),
        at constant major-loop peak. In [0, 1); the strongest corner must stay inside the
        hysteresis model's accepted (bounded, monotone) parameter domain.
    """

    free_deflection: float = 0.2
    blocking_force: float = 0.2
    resonance: float = 0.2
    damping_ratio: tuple[float, float] = (0.01, 0.04)
    hysteresis_strength: float = 0.3

    def __post_init__(self) -> None:
        for name in ("free_deflection", "blocking_force", "resonance", "hysteresis_strength"):
            value = getattr(self, name)
            if not (
                isinstance(value, numbers.Real)
                and not isinstance(value, bool)
                and 0.0 <= value < 1.0
            ):
                raise ValueError(
                    f"DomainRandomization.{name} is a relative half-width in [0, 1), got {value!r}"
                )
        try:
            low, high = (float(v) for v in self.damping_ratio)
        except (TypeError, ValueError):
            raise ValueError(
                "DomainRandomization.damping_ratio must be a pair (low, high), "
                f"got {self.damping_ratio!r}"
            ) from None
        check_damping_ratio(low)
        check_damping_ratio(high)
        if low > high:
            raise ValueError(
                f"DomainRandomization.damping_ratio needs low <= high, got {(low, high)}"
            )
        object.__setattr__(self, "damping_ratio", (low, high))

    def limits(self, nominal: BenderDatasheet) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the drawn numbers in :data:`DRAW_ORDER` (m, N, Hz, -, -)."""
        centre = np.array([nominal.free_deflection, nominal.blocking_force, nominal.resonance])
        spread = np.array([self.free_deflection, self.blocking_force, self.resonance])
        s_h = self.hysteresis_strength
        low = np.r_[centre * (1.0 - spread), self.damping_ratio[0], 1.0 - s_h]
        high = np.r_[centre * (1.0 + spread), self.damping_ratio[1], 1.0 + s_h]
        return low, high

    def draw(self, rng: np.random.Generator, nominal: BenderDatasheet) -> PlantDraw:
        """One plant: five uniforms from ``rng`` in :data:`DRAW_ORDER` (one generator call)."""
        values = rng.uniform(*self.limits(nominal))
        return PlantDraw(**{name: float(v) for name, v in zip(DRAW_ORDER, values, strict=True)})


@dataclass(frozen=True)
class PlantDraw:
    """The drawn parameters of one plant (:data:`DRAW_ORDER`).

    Attributes
    ----------
    free_deflection : float
        Free tip deflection at U_r (m).
    blocking_force : float
        Blocking force at U_r (N).
    resonance : float
        First resonance (Hz).
    damping_ratio : float
        First-mode damping ratio (-).
    hysteresis_scale : float
        Hysteresis strength relative to the nominal (-).
    """

    free_deflection: float
    blocking_force: float
    resonance: float
    damping_ratio: float
    hysteresis_scale: float

    def datasheet(self, nominal: BenderDatasheet) -> BenderDatasheet:
        """The nominal datasheet with the drawn deflection, force and resonance."""
        return dataclasses.replace(
            nominal,
            free_deflection=self.free_deflection,
            blocking_force=self.blocking_force,
            resonance=self.resonance,
        )

    def info(self) -> dict[str, float]:
        """``info["plant"]``: the drawn values with their units in the keys."""
        return {
            "free_deflection_um": self.free_deflection * 1e6,
            "blocking_force_N": self.blocking_force,
            "stiffness_N_per_m": self.blocking_force / self.free_deflection,
            "resonance_Hz": self.resonance,
            "damping_ratio": self.damping_ratio,
            "hysteresis_scale": self.hysteresis_scale,
        }


def major_loop_peak(hysteresis: Hysteresis, u_max: float) -> float:
    """Effective voltage (V) at +``u_max`` on the major loop (cycling +-u_max from rest)."""
    state = np.zeros(hysteresis.state_size)
    peak = math.nan
    for _ in range(1000):
        state, _ = hysteresis.step(state, -u_max)
        state, u_eff = hysteresis.step(state, u_max)
        if float(u_eff) == peak:
            break
        peak = float(u_eff)
    return peak


def scale_hysteresis(hysteresis: Hysteresis, scale: float, u_max: float) -> Hysteresis:
    """``hysteresis`` with its hysteretic part times ``scale`` and the same major-loop peak.

    Bouc-Wen: alpha times ``scale``, then k times c = E_nom / E (u_eff scales by c exactly when
    k does at fixed alpha, beta, gamma). Prandtl-Ishlinskii: play weights times ``scale``, then
    every weight times c. ``u_max`` (V) is the rated voltage. Raises ValueError for a type it
    cannot scale or a scaled map outside the accepted domain.
    """
    if isinstance(hysteresis, NoHysteresis):
        return hysteresis
    peak = major_loop_peak(hysteresis, u_max)
    if isinstance(hysteresis, BoucWen):
        raw = dataclasses.replace(hysteresis, alpha=hysteresis.alpha * scale)
        c = peak / major_loop_peak(raw, u_max)
        return dataclasses.replace(raw, k=hysteresis.k * c)
    if isinstance(hysteresis, PrandtlIshlinskii):
        weights = tuple(w * scale for w in hysteresis.weights)
        raw = dataclasses.replace(hysteresis, weights=weights)
        c = peak / major_loop_peak(raw, u_max)
        return dataclasses.replace(
            raw, linear_weight=hysteresis.linear_weight * c, weights=tuple(w * c for w in weights)
        )
    raise ValueError(
        f"domain randomisation scales Bouc-Wen, Prandtl-Ishlinskii or no hysteresis, got "
        f"{type(hysteresis).__name__}; pass randomize=None or hysteresis_strength=0"
    )


def single_blas_thread() -> Any:
    """Context manager: one BLAS thread inside (for building tiny models, see drawn_plant)."""
    return _blas_controller().limit(limits=1)


@functools.cache
def _blas_controller() -> ThreadpoolController:
    """One controller per process (creating one scans the loaded libraries, ~1 ms)."""
    return ThreadpoolController()


def _effective_voltage_sup(hysteresis: Hysteresis, strongest: float, u_max: float) -> float:
    """Upper bound (V) of max|u_eff| over every drawn map with scale <= ``strongest``."""
    if isinstance(hysteresis, NoHysteresis):
        return u_max
    scale_hysteresis(hysteresis, strongest, u_max)  # raises outside the accepted domain
    peak = major_loop_peak(hysteresis, u_max)
    if isinstance(hysteresis, PrandtlIshlinskii):
        return peak
    linear = hysteresis.k * u_max
    loop = strongest * hysteresis.h_max
    if not loop < linear:
        raise ValueError(
            f"hysteresis_strength up to x{strongest:g} gives a Bouc-Wen loop h_max = {loop:.4g} V "
            f"not below k U_r = {linear:.4g} V: no finite bound; narrow the spread"
        )
    return peak * (linear + loop) / (linear - loop)


def _beam_l1_factor(model: PiezoBenderModel, zeta_1: float) -> float:
    """sum_k |s_k| coth(pi zeta_k / (2 sqrt(1 - zeta_k^2))) (m/V) at first-mode ratio zeta_1."""
    beam = model.beam
    omega = 2.0 * np.pi * beam.frequencies
    static = beam.modes[-2, :] * (beam.modes.T @ beam.piezo_input) / omega**2
    zeta = zeta_1 * omega / omega[0]
    under = zeta < 1.0
    kappa = np.ones_like(zeta)
    z = zeta[under]
    kappa[under] = 1.0 / np.tanh(np.pi * z / (2.0 * np.sqrt(1.0 - z * z)))
    return float(np.abs(static) @ kappa)


def randomized_deflection_bound_um(nominal: PiezoBenderModel, spread: DomainRandomization) -> float:
    """Proven bound (um) of |tip deflection| of every plant ``spread`` can draw (module doc).

    Each drawn plant's own ``deflection_bound_um()`` is below it. Raises ValueError when the
    hysteresis cannot be randomised as asked.
    """
    low, high = spread.limits(nominal.params.datasheet)
    u_max = nominal.rated_voltage
    gain = high[0] / nominal.params.datasheet.free_deflection
    creep = 1.0 if nominal.creep is None else 1.0 + sum(nominal.creep.weights)
    u_eff = _effective_voltage_sup(nominal.hysteresis, float(high[4]), u_max)
    beam = _beam_l1_factor(nominal, float(low[3]))
    return gain * beam * creep * u_eff * 1e6 * (1.0 + _BOUND_MARGIN)


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


class RowHysteresis:
    """The hysteresis of N sub-envs, each with its own drawn parameters, stepped at once.

    All rows are scaled copies of one nominal model (:func:`scale_hysteresis`): Bouc-Wen rows
    differ in k and alpha, Prandtl-Ishlinskii rows in their weights. ``step(state, u)`` has the
    batched signature of :meth:`piezo_env.hysteresis.Hysteresis.step` (state (N, size)).
    """

    def __init__(self, nominal: Hysteresis, num_envs: int) -> None:
        self.nominal = nominal
        self.state_size = nominal.state_size
        if isinstance(nominal, BoucWen):
            self._k = np.full(num_envs, nominal.k)
            self._ak = np.full(num_envs, nominal.alpha * nominal.k)
        elif isinstance(nominal, PrandtlIshlinskii):
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
        elif isinstance(hysteresis, PrandtlIshlinskii):
            self._k[i] = hysteresis.linear_weight
            self._w[i] = hysteresis.weights

    def step(self, state: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Advance every row over its jump to ``u`` (V); returns (new state, u_eff in V)."""
        nominal = self.nominal
        if isinstance(nominal, BoucWen):
            if self._batch is None:
                self._batch = BoucWenBatch(self._ak, nominal.beta, nominal.gamma)
            h = self._batch(state[:, 1], u - state[:, 0])
            new_state = np.empty_like(state)
            new_state[:, 0] = u
            new_state[:, 1] = h
            return new_state, self._k * u - h
        if isinstance(nominal, PrandtlIshlinskii):
            plays = play(state[:, 1:], u[:, None], self._r)
            new_state = np.concatenate([u[:, None], plays], axis=1)
            return new_state, self._k * u + np.einsum("ij,ij->i", plays, self._w)
        return nominal.step(state, u)
