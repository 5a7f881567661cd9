"""Proven bound of the tip deflection over every plant a domain randomisation can draw.

The observation Box of a randomised task must hold every episode's plant, so its bound is
proven for the whole range of :class:`piezo_env.randomization.DomainRandomization`, not for
the plants drawn so far (:func:`randomized_deflection_bound_um`).

Each plant's proven bound is ||h||_1 max|u_eff|, with h the sampled impulse response of the exact
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

from typing import TYPE_CHECKING

import numpy as np

from piezo_env.hysteresis import (
    Hysteresis,
    NoHysteresis,
    PrandtlIshlinskii,
    RateDependentPrandtlIshlinskii,
)
from piezo_env.randomization import DomainRandomization, major_loop_peak, scale_hysteresis

if TYPE_CHECKING:
    from piezo_env.model import PiezoBenderModel

__all__ = ["randomized_deflection_bound_um"]

_BOUND_MARGIN = 1e-6
"""Relative margin of the range bound over the per-plant bounds (rounding of both)."""


def _effective_voltage_sup(hysteresis: Hysteresis, strongest: float, u_max: float) -> float:
    """Upper bound (V) of max|u_eff| over every drawn map with scale <= ``strongest``."""
    if isinstance(hysteresis, NoHysteresis):
        return u_max
    scale_hysteresis(hysteresis, strongest, u_max)  # raises outside the accepted domain
    if isinstance(hysteresis, RateDependentPrandtlIshlinskii):
        # Its bound at every rate is its rate-independent twin's, w_0 u_max + sum w_i
        # (u_max - r_i)+ (RateDependentPrandtlIshlinskii), the twin's major-loop peak, which
        # the drawn maps keep (scale_hysteresis).
        return hysteresis.max_effective_voltage(u_max)
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
