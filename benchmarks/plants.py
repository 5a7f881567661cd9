"""The plants of the benchmark: the nominal bender and the robustness plants.

Each plant is a function of the nominal bender's catalogue name that returns
``PiezoBender-v0`` keyword arguments: changes from the nominal bender the model was identified
on, derived from that bender's own datasheet. A controller is always built for the nominal task
and runs unchanged on every plant.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

__all__ = [
    "DEFAULT_BENDER",
    "DT",
    "MONTE_CARLO",
    "MONTE_CARLO_REFERENCES",
    "NOMINAL_STROKE_UM",
    "PLANTS",
]

DEFAULT_BENDER = "PL140"
"""The bender of ``piezo benchmark`` unless ``--bender`` names another."""

NOMINAL_STROKE_UM = 1000.0
"""One-sided stroke of the nominal PL140 (um), the reference amplitudes' scale: the references
of another bender are scaled by its stroke over this."""

DT = 1e-3
"""Sample time of the benchmark's env (s), the default of PiezoBender-v0."""


def _tolerance_sheet(bender: str, scale: float) -> Any:
    """``bender`` whose stiffness and resonance are off by ``scale`` (blocking force as rated)."""
    from piezo_env import get_datasheet

    sheet = get_datasheet(bender)
    return dataclasses.replace(
        sheet,
        name=f"{sheet.name} (stiffness and resonance x{scale:g})",
        free_deflection=sheet.free_deflection / scale,
        resonance=sheet.resonance * scale,
    )


PLANTS: dict[str, Callable[[str], dict[str, Any]]] = {
    "nominal": lambda bender: {"bender": bender},
    "damping-0.01": lambda bender: {"bender": bender, "damping_ratio": 0.01},
    "damping-0.04": lambda bender: {"bender": bender, "damping_ratio": 0.04},
    "prandtl-ishlinskii": lambda bender: {"bender": bender, "hysteresis": "prandtl-ishlinskii"},
    "creep": lambda bender: {"bender": bender, "creep": True},
    "noise-3um": lambda bender: {"bender": bender, "noise_bound": 3.0},
    "stiffness+20%": lambda bender: {"bender": _tolerance_sheet(bender, 1.2)},
    "stiffness-20%": lambda bender: {"bender": _tolerance_sheet(bender, 0.8)},
    "random-plants": lambda bender: {"bender": bender, "randomize": True},
}
"""Plant name -> (nominal bender -> env keyword arguments): changes from the nominal bender.

``random-plants`` is the Monte Carlo table: each of ``BenchmarkConfig.draws`` episodes per
reference draws a new plant from the datasheet tolerances (``piezo_env.DomainRandomization``:
stiffness, blocking force and resonance +-20 %, damping 0.01-0.04, hysteresis +-30 %) with
its own seed; the report gives the distribution of each controller's RMSE over the draws.
"""

MONTE_CARLO = "random-plants"

MONTE_CARLO_REFERENCES = ("sine-10Hz", "sine-50Hz", "multisine")
"""The references run on the random plants (when selected)."""
