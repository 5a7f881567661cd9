"""Argument checks and the time axis shared by the signal generators (:mod:`piezo_env.signals`).

Each check returns the value as a plain Python number (or the generator itself) or raises
ValueError naming the argument, built on :mod:`piezo_env.checks`.
"""

from __future__ import annotations

import numpy as np

from piezo_env.checks import require_int, require_number

__all__ = [
    "check_dt",
    "check_finite",
    "check_frequency",
    "check_held",
    "check_n",
    "check_positive_int",
    "check_rng",
    "check_sampled",
    "sample_times",
]


def check_n(n: int) -> int:
    """Number of samples: an integer >= 1."""
    return require_int("n (samples)", n)


def check_positive_int(name: str, value: int) -> int:
    """A count of samples (a hold or clock period, a number of tones): an integer >= 1."""
    return require_int(f"{name} (samples)", value)


def check_finite(name: str, value: float, *, minimum: float | None = None) -> float:
    """A finite real number, >= ``minimum`` if given."""
    return require_number(name, value, low=minimum)


def check_dt(dt: float) -> float:
    """Sampling period (s): a finite number > 0."""
    return require_number("dt (sampling period, s)", dt, low=0.0, low_open=True)


def check_frequency(name: str, frequency: float, dt: float) -> float:
    """A frequency (Hz) from 0 up to the Nyquist frequency 1 / (2 dt) of the checked ``dt``."""
    frequency = check_finite(name, frequency, minimum=0.0)
    nyquist = 0.5 / dt
    if frequency > nyquist:
        raise ValueError(
            f"{name} = {frequency} Hz is above the Nyquist frequency {nyquist} Hz of dt = {dt} s"
        )
    return frequency


def check_rng(rng: np.random.Generator) -> np.random.Generator:
    """The only source of randomness: a :class:`numpy.random.Generator` (TypeError otherwise)."""
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), "
            f"got {type(rng).__name__}"
        )
    return rng


def check_sampled(n: int, dt: float, amplitude: float) -> tuple[int, float, float]:
    """(n, dt, amplitude) of a sampled signal: samples >= 1, period (s) > 0, peak >= 0."""
    return check_n(n), check_dt(dt), check_finite("amplitude", amplitude, minimum=0.0)


def check_held(
    n: int, amplitude: float, name: str, period: int, rng: np.random.Generator
) -> tuple[int, float, int, np.random.Generator]:
    """(n, amplitude, period, rng) of a random signal held for ``period`` samples (``name``)."""
    return (
        check_n(n),
        check_finite("amplitude", amplitude, minimum=0.0),
        check_positive_int(name, period),
        check_rng(rng),
    )


def sample_times(n: int, dt: float) -> np.ndarray:
    """Times k dt (s) of the samples k = 0 .. n - 1."""
    return np.arange(n, dtype=np.float64) * dt
