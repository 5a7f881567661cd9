"""What the model-based controllers' settings share: checks and defaults written once."""

from __future__ import annotations

import math

from controllers.task import ControlTask

__all__ = ["USABLE_OSQP_STATUS", "measurement_std", "number_at_least"]

USABLE_OSQP_STATUS = ("solved", "solved inaccurate")
"""OSQP statuses whose solution is applied; any other falls back to the shifted plan."""


def number_at_least(value: object, low: float) -> bool:
    """True for a finite real number (not a bool) >= ``low``."""
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value >= low
    )


def measurement_std(setting: float | None, task: ControlTask) -> float:
    """The sensor noise standard deviation (um) an observer assumes.

    ``setting`` if given, else the task's noise bound r as uniform noise, r / sqrt(3), at least
    0.05 um (an observer needs some measurement noise to stay well posed).
    """
    if setting is not None:
        return float(setting)
    return max(task.noise_bound_um / math.sqrt(3.0), 0.05)
