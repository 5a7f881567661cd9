"""Argument checks and the time axis shared by the signal generators (:mod:`piezo_env.signals`).

Each check returns the value as a plain Python number or raises ValueError naming the argument.
"""

from __future__ import annotations

import math

import numpy as np

from piezo_env.checks import require_int

__all__ = [
    "check_dt",
    "check_finite",
    "check_frequency",
    "check_n",
    "check_positive_int",
    "check_rng",
    "sample_times",
]


def check_n(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise ValueError(f"n must be a positive integer number of samples, got {n!r}")
    if n < 1:
        raise ValueError(f"n must be a positive integer number of samples, got {n}")
    return int(n)


def check_positive_int(name: str, value: int) -> int:
    return require_int(f"{name} (samples)", value)


def check_finite(name: str, value: float, *, minimum: float | None = None) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


def check_dt(dt: float) -> float:
    dt = check_finite("dt", dt)
    if dt <= 0.0:
        raise ValueError(f"dt (sampling period, s) must be positive, got {dt}")
    return dt


def check_frequency(name: str, frequency: float, dt: float) -> float:
    frequency = check_finite(name, frequency, minimum=0.0)
    nyquist = 0.5 / dt
    if frequency > nyquist:
        raise ValueError(
            f"{name} = {frequency} Hz is above the Nyquist frequency {nyquist} Hz of dt = {dt} s"
        )
    return frequency


def check_rng(rng: np.random.Generator) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), "
            f"got {type(rng).__name__}"
        )
    return rng


def sample_times(n: int, dt: float) -> np.ndarray:
    return np.arange(n, dtype=np.float64) * dt
