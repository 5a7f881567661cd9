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

The observation bound over the whole range is proven in :mod:`piezo_env.randomized_bound`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from piezo_env.checks import require_number
from piezo_env.datasheet import BenderDatasheet
from piezo_env.fem import check_damping_ratio
from piezo_env.hysteresis import (
    BoucWen,
    Hysteresis,
    NoHysteresis,
    PrandtlIshlinskii,
    RateDependentPrandtlIshlinskii,
)

__all__ = [
    "DRAW_ORDER",
    "GAIN_AMPLITUDES",
    "PLANT_INFO_KEYS",
    "DomainRandomization",
    "PlantDraw",
    "gain_tolerance",
    "major_loop_peak",
    "scale_hysteresis",
    "strength_gain_range",
]

DRAW_ORDER = (
    "free_deflection",
    "blocking_force",
    "resonance",
    "damping_ratio",
    "hysteresis_scale",
)
"""The numbers drawn at each reset, in the order they are taken from the generator."""

PLANT_INFO_KEYS = (
    "free_deflection_um",
    "blocking_force_N",
    "stiffness_N_per_m",
    "resonance_Hz",
    "damping_ratio",
    "hysteresis_scale",
)
"""Keys of ``info["plant"]`` (:meth:`PlantDraw.info`), in its order: each carries its unit."""

GAIN_AMPLITUDES = (1e-3, 1e-2, 0.1, 0.3, 1.0)
"""Amplitudes (fractions of the rated voltage) of the sine cycles on which
:func:`strength_gain_range` compares a scaled map's gain with its own: from the small-signal
limit (every play stuck, the Bouc-Wen state at its reversal slope), where the strength moves
the gain most, to the major loop, where the peak normalisation pins it."""

SINE_SAMPLES = 64
"""Samples per sine cycle in :func:`strength_gain_range` (-): the maps it compares are rate
independent, so only the sequence of voltages matters; a multiple of 4 puts samples exactly on
the cycle's peaks, where it reverses, and 64 keeps the steps between samples under 10 % of the
amplitude (2 sin(pi / 64))."""


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
            # At a half-width of 1 a draw could give a zero deflection, force or resonance.
            require_number(
                f"DomainRandomization.{name} (a relative half-width)",
                getattr(self, name),
                low=0.0,
                high=1.0,
                high_open=True,
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
        values = (
            self.free_deflection * 1e6,
            self.blocking_force,
            self.blocking_force / self.free_deflection,
            self.resonance,
            self.damping_ratio,
            self.hysteresis_scale,
        )
        return dict(zip(PLANT_INFO_KEYS, values, strict=True))


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
    every weight times c. The rate-dependent Prandtl-Ishlinskii map is scaled as its
    rate-independent twin (the same weights and base radii; its quasi-static loop), its rate
    constant kept. ``u_max`` (V) is the rated voltage. Raises ValueError for a type it cannot
    scale or a scaled map outside the accepted domain.
    """
    if isinstance(hysteresis, NoHysteresis):
        return hysteresis
    if isinstance(hysteresis, BoucWen):
        peak = major_loop_peak(hysteresis, u_max)
        raw = dataclasses.replace(hysteresis, alpha=hysteresis.alpha * scale)
        c = peak / major_loop_peak(raw, u_max)
        return dataclasses.replace(raw, k=hysteresis.k * c)
    if isinstance(hysteresis, (PrandtlIshlinskii, RateDependentPrandtlIshlinskii)):
        static = PrandtlIshlinskii(hysteresis.linear_weight, hysteresis.radii, hysteresis.weights)
        weights = tuple(w * scale for w in hysteresis.weights)
        c = major_loop_peak(static, u_max) / major_loop_peak(
            dataclasses.replace(static, weights=weights), u_max
        )
        return dataclasses.replace(
            hysteresis,
            linear_weight=hysteresis.linear_weight * c,
            weights=tuple(w * c for w in weights),
        )
    raise ValueError(
        f"domain randomisation scales Bouc-Wen, Prandtl-Ishlinskii (rate-dependent too) or no "
        f"hysteresis, got {type(hysteresis).__name__}; pass randomize=None"
    )


def strength_gain_range(
    hysteresis: Hysteresis,
    strength: float,
    u_max: float,
    amplitudes: tuple[float, ...] = GAIN_AMPLITUDES,
) -> tuple[float, float]:
    """(low, high) gain (-) of ``hysteresis`` with its strength scaled by ``1 - strength`` and
    ``1 + strength`` (:func:`scale_hysteresis`, the randomisation's extremes), relative to its
    own gain: the least-squares gain of the scaled map's output on the unscaled one's over the
    third of three sine cycles about rest, at each amplitude of ``amplitudes`` (fractions of the
    rated voltage ``u_max``, V).

    Why it matters. The peak normalisation keeps the major loop's end where the datasheet puts
    it, but a weaker loop is steeper and a stronger one flatter inside it: a linear model
    identified on the nominal map sees a bender of another strength as one with another gain,
    most at small signals (Bouc-Wen at +-30 %: x1.063 / x0.927; the three-play
    Prandtl-Ishlinskii: x1.092 / x0.923), and the gain the model's free deflection allows must
    hold that too (:func:`gain_tolerance`). The cycles are about rest and settled (the third):
    the rate-dependent map, scaled as its quasi-static twin, gives the same range on settled
    cycles, and a small cycle started from rest at 100 Hz and 1 ms sampling reaches x1.099 on
    its third cycle before it settles to x1.091.
    """
    require_number("strength", strength, low=0.0, high=1.0, high_open=True)
    phase = np.sin(2.0 * np.pi * np.arange(3 * SINE_SAMPLES) / SINE_SAMPLES)
    extremes = [scale_hysteresis(hysteresis, s, u_max) for s in (1.0 - strength, 1.0 + strength)]
    gains = []
    for amplitude in amplitudes:
        u = amplitude * u_max * phase
        own = _last_cycle(hysteresis, u)
        gains += [float(own @ _last_cycle(m, u) / (own @ own)) for m in extremes]
    return min(gains), max(gains)


def _last_cycle(hysteresis: Hysteresis, u: np.ndarray) -> np.ndarray:
    """The map's output (V) over the last :data:`SINE_SAMPLES` of ``u``, its mean removed."""
    state = hysteresis.initial_state()
    out = np.empty(u.size)
    for i, value in enumerate(u):
        state, u_eff = hysteresis.step(state, float(value))
        out[i] = float(u_eff)
    last = out[-SINE_SAMPLES:]
    return last - last.mean()


def gain_tolerance(
    randomization: DomainRandomization | None = None, rated_voltage: float = 30.0
) -> float:
    """Relative half-width (-) of the static gain that a linear model of the nominal bender
    sees on the benders ``randomization`` draws (default: the datasheet's): the free deflection
    ``1 -+ s`` times each hysteresis family's :func:`strength_gain_range`, as one interval
    ``[1 - w, 1 + w]`` with ``w = max((1 + s) high - 1, 1 - (1 - s) low)`` over Bouc-Wen and
    Prandtl-Ishlinskii. Their default calibrations scale with the rated voltage, and the ratio
    does not depend on it (``rated_voltage``, V, only sets the scale)."""
    spread = randomization or DomainRandomization()
    s = spread.free_deflection
    width = s
    for family in (BoucWen, PrandtlIshlinskii):
        low, high = strength_gain_range(
            family.for_voltage(rated_voltage), spread.hysteresis_strength, rated_voltage
        )
        width = max(width, (1.0 + s) * high - 1.0, 1.0 - (1.0 - s) * low)
    return width
