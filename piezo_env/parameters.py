"""Material and beam parameters derived from a bender datasheet.

For a clamped-free parallel bimorph with uniform electrodes, with free length L, width W,
thickness T, rated one-sided voltage U_r, blocking force F_b and free deflection d_free
(both at U_r), a uniform piezoelectric bending moment Gamma*u gives the tip deflection
Gamma u L^2 / (2 EI) and the blocking force 3 Gamma u / (2 L). Matching both to the datasheet:

    Gamma = 2 L F_b / (3 U_r)          piezo moment per volt (N m / V)
    k     = F_b / d_free               tip stiffness (N / m)
    EI    = k L^3 / 3                  bending stiffness (N m^2)
    E     = 4 F_b L^3 / (d_free W T^3) Young's modulus, I = W T^3 / 12 (Pa)
    e31   = 4 L F_b / (3 U_r W T)      effective piezoelectric coefficient (C / m^2)
    eps   = C_half (T / 2) / (W L_el)  permittivity from one half's capacitance (F / m)

PICMA benders are multilayer ceramics (layers of tens of micrometres), so e31 and eps are the
*effective* values of the equivalent two-layer bimorph: the number of layers per half inflates
them (about 150 C/m^2 and eps_r ~ 2.6e5 for PL140, against ~10 C/m^2 and ~2000 for bulk PZT).
The beam dynamics only need Gamma and EI, which the datasheet fixes exactly.

The datasheet gives no mass. The density is either a nominal PZT value or, by default,
calibrated so that the continuum first cantilever mode equals the datasheet resonance:

    f_1 = (beta_1 L)^2 / (2 pi) sqrt(EI / (rho A L^4)),  beta_1 L = 1.875104...
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from piezo_env.checks import require_number
from piezo_env.datasheet import BenderDatasheet, get_datasheet

__all__ = [
    "CANTILEVER_BETA_L",
    "NOMINAL_PZT_DENSITY",
    "BenderParameters",
    "bender_parameters",
    "cantilever_frequencies",
]

NOMINAL_PZT_DENSITY = 7800.0
"""Nominal density of PZT ceramic (kg/m^3)."""

CANTILEVER_BETA_L = (1.8751040687, 4.6940911330, 7.8547574382, 10.995540734, 14.137168391)
"""Roots beta_k L of 1 + cos(bL) cosh(bL) = 0 (clamped-free Euler-Bernoulli beam)."""


@dataclass(frozen=True)
class BenderParameters:
    """Beam and electromechanical parameters of one bender (SI units).

    Attributes
    ----------
    datasheet : BenderDatasheet
        The datasheet the parameters were derived from.
    length : float
        Free (cantilever) length L (m).
    width : float
        Width W (m).
    thickness : float
        Total thickness T (m).
    rated_voltage : float
        One-sided rated voltage U_r (V); the drive range is [-U_r, U_r].
    piezo_moment : float
        Gamma, bending moment per volt (N m / V).
    bending_stiffness : float
        EI (N m^2).
    youngs_modulus : float
        E (Pa).
    e31 : float
        Magnitude of the effective piezoelectric coefficient (C / m^2).
    permittivity : float
        Effective permittivity eps_33 (F / m).
    capacitance : float
        Clamped capacitance of the drive (both halves in parallel, F).
    density : float
        Mass density rho (kg / m^3).
    density_source : str
        ``"calibrated to datasheet resonance"`` or ``"nominal PZT"`` or ``"given"``.
    """

    datasheet: BenderDatasheet
    length: float
    width: float
    thickness: float
    rated_voltage: float
    piezo_moment: float
    bending_stiffness: float
    youngs_modulus: float
    e31: float
    permittivity: float
    capacitance: float
    density: float
    density_source: str

    @property
    def area(self) -> float:
        """Cross-section area A = W T (m^2)."""
        return self.width * self.thickness

    @property
    def linear_density(self) -> float:
        """Mass per unit length rho A (kg / m)."""
        return self.density * self.area

    @property
    def tip_stiffness(self) -> float:
        """Static tip stiffness 3 EI / L^3 (N / m)."""
        return 3.0 * self.bending_stiffness / self.length**3

    def static_tip_deflection(self, voltage: float) -> float:
        """Closed-form static tip deflection Gamma u L^2 / (2 EI) (m) at ``voltage`` (V)."""
        return self.piezo_moment * voltage * self.length**2 / (2.0 * self.bending_stiffness)

    def blocking_force(self, voltage: float) -> float:
        """Closed-form blocking force 3 Gamma u / (2 L) (N) at ``voltage`` (V)."""
        return 3.0 * self.piezo_moment * voltage / (2.0 * self.length)


def cantilever_frequencies(params: BenderParameters, count: int = 3) -> list[float]:
    """Continuum Euler-Bernoulli clamped-free natural frequencies (Hz).

    ``f_k = (beta_k L)^2 / (2 pi) * sqrt(EI / (rho A L^4))`` for k = 1..count (count <= 5).
    """
    if not 1 <= count <= len(CANTILEVER_BETA_L):
        raise ValueError(f"count must be in 1..{len(CANTILEVER_BETA_L)}, got {count}")
    scale = math.sqrt(params.bending_stiffness / (params.linear_density * params.length**4))
    return [bl**2 / (2.0 * math.pi) * scale for bl in CANTILEVER_BETA_L[:count]]


def bender_parameters(
    bender: str | BenderDatasheet = "PL140", *, density: float | str = "calibrated"
) -> BenderParameters:
    """Derive the beam parameters of a bender from its datasheet.

    Parameters
    ----------
    bender : str or BenderDatasheet
        Catalogue name (e.g. ``"PL140"``) or a datasheet object.
    density : float or {"calibrated", "nominal"}
        ``"calibrated"`` (default): choose rho so that the first continuum mode equals the
        datasheet resonance. ``"nominal"``: 7800 kg/m^3. A number: that density (kg/m^3).

    Returns
    -------
    BenderParameters
    """
    sheet = get_datasheet(bender)
    length, width, thickness = sheet.free_length, sheet.width, sheet.thickness
    force, deflection, volts = sheet.blocking_force, sheet.free_deflection, sheet.rated_voltage

    gamma = 2.0 * length * force / (3.0 * volts)
    ei = (force / deflection) * length**3 / 3.0
    area = width * thickness
    if density == "calibrated":
        omega = 2.0 * math.pi * sheet.resonance
        rho = ei * (CANTILEVER_BETA_L[0] ** 2 / omega) ** 2 / (area * length**4)
        source = "calibrated to datasheet resonance"
    elif density == "nominal":
        rho, source = NOMINAL_PZT_DENSITY, "nominal PZT"
    elif isinstance(density, str):
        raise ValueError(f"density must be 'calibrated', 'nominal' or a number, got {density!r}")
    else:
        rho = require_number("density (kg/m^3)", density, low=0.0, low_open=True)
        source = "given"
    return BenderParameters(
        datasheet=sheet,
        length=length,
        width=width,
        thickness=thickness,
        rated_voltage=volts,
        piezo_moment=gamma,
        bending_stiffness=ei,
        youngs_modulus=4.0 * force * length**3 / (deflection * width * thickness**3),
        e31=4.0 * length * force / (3.0 * volts * width * thickness),
        permittivity=sheet.capacitance_half * (thickness / 2.0) / (width * sheet.length),
        capacitance=2.0 * sheet.capacitance_half,
        density=rho,
        density_source=source,
    )
