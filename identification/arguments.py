"""Arguments of the identification functions as checked arrays and numbers.

Signals and run-time values (a voltage, a target, a range) come as anything array-like: these
convert them to float64 and raise a ValueError naming the argument when they are not finite.
Settings (counts, rates, bounds) are checked by :mod:`piezo_env.checks` instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["as_range", "as_scalar", "as_signal"]


def as_signal(name: str, values: ArrayLike) -> np.ndarray:
    """Return ``values`` as a finite float64 1-D array or raise a ValueError naming it."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D sequence; got shape {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        index = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} contains a non-finite value at index {index}: {arr[index]}")
    return arr


def as_scalar(name: str, value: float) -> float:
    """Return ``value`` as a finite float or raise a ValueError naming it."""
    try:
        result = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number; got {value!r}") from None
    if not math.isfinite(result):
        raise ValueError(f"{name} must be a finite number; got {value!r}")
    return result


def as_range(name: str, value: Sequence[float]) -> tuple[float, float]:
    """Return ``value`` as a finite ``(low, high)`` pair with ``low < high``."""
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high) of numbers; got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"{name} must be finite with low < high; got {value!r}")
    return low, high
