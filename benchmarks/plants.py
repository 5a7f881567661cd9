"""The plants of the benchmark: the nominal PL140 and the robustness plants.

Each plant is a set of ``PiezoBender-v0`` keyword arguments, changes from the nominal bender the
model was identified on; a controller is always built for the nominal task and runs unchanged
on every plant.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

__all__ = [
    "DT",
    "MONTE_CARLO",
    "MONTE_CARLO_REFERENCES",
    "NOMINAL_STROKE_UM",
    "PLANTS",
]

NOMINAL_STROKE_UM = 1000.0
"""One-sided stroke of the nominal PL140 (um): every plant's percentages are of 2 x this."""

DT = 1e-3
"""Sample time of the benchmark's env (s), the default of PiezoBender-v0."""


def _tolerance_sheet(scale: float) -> Any:
    """PL140 whose stiffness and resonance are off by ``scale`` (blocking force as rated)."""
    from piezo_env import get_datasheet

    sheet = get_datasheet("PL140")
    return dataclasses.replace(
        sheet,
        name=f"{sheet.name} (stiffness and resonance x{scale:g})",
        free_deflection=sheet.free_deflection / scale,
        resonance=sheet.resonance * scale,
    )


PLANTS: dict[str, Callable[[], dict[str, Any]]] = {
    "nominal": dict,
    "damping-0.01": lambda: {"damping_ratio": 0.01},
    "damping-0.04": lambda: {"damping_ratio": 0.04},
    "prandtl-ishlinskii": lambda: {"hysteresis": "prandtl-ishlinskii"},
    "creep": lambda: {"creep": True},
    "noise-3um": lambda: {"noise_bound": 3.0},
    "stiffness+20%": lambda: {"bender": _tolerance_sheet(1.2)},
    "stiffness-20%": lambda: {"bender": _tolerance_sheet(0.8)},
    "random-plants": lambda: {"randomize": True},
}
"""Plant name -> env keyword arguments (changes from the nominal PL140 the model came from).

``random-plants`` is the Monte Carlo table: each of ``BenchmarkConfig.draws`` episodes per
reference draws a new plant from the datasheet tolerances (``piezo_env.DomainRandomization``:
stiffness, blocking force and resonance +-20 %, damping 0.01-0.04, hysteresis +-30 %) with
its own seed; the report gives the distribution of each controller's RMSE over the draws.
"""

MONTE_CARLO = "random-plants"

MONTE_CARLO_REFERENCES = ("sine-10Hz", "sine-50Hz", "multisine")
"""The references run on the random plants (when selected)."""
