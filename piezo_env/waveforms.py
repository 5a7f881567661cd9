"""Deterministic waveforms: sine, triangle, square, step and chirp, and the sums of sines
every periodic signal of the testbed is built from (:mod:`piezo_env.signals` names them all).
"""

from __future__ import annotations

import numpy as np
import scipy.signal

from piezo_env.checks import require_int
from piezo_env.signal_checks import (
    check_finite,
    check_frequency,
    check_n,
    check_sampled,
    sample_times,
)

__all__ = ["chirp", "sine", "square", "step", "sums_of_sines", "triangle", "triangle_wave"]

_BLOCK = 64


def sums_of_sines(w: np.ndarray, phases: np.ndarray, n: int) -> np.ndarray:
    """``sum_j sin(w[i, j] k + phases[i, j])`` for k = 0..n-1, one row per i: shape (rows, n).

    ``w`` (rad per sample) and ``phases`` (rad) have shape (rows, tones). With k = 64 a + b,
    sin(w k + phi) = sin(64 w a + phi) cos(w b) + cos(64 w a + phi) sin(w b), so each row is
    one (n / 64 x 2 tones) @ (2 tones x 64) product: n / 32 sines and cosines per tone instead
    of n, exact to rounding. The products are stacked, one per row, so a row's samples do not
    depend on the other rows.
    """
    w = np.asarray(w, dtype=np.float64)
    phases = np.asarray(phases, dtype=np.float64)
    blocks = -(-n // _BLOCK)
    coarse = w[:, :, None] * (np.arange(blocks) * float(_BLOCK)) + phases[:, :, None]
    fine = w[:, :, None] * np.arange(_BLOCK, dtype=np.float64)
    left = np.concatenate([np.sin(coarse), np.cos(coarse)], axis=1).transpose(0, 2, 1)
    right = np.concatenate([np.cos(fine), np.sin(fine)], axis=1)
    return np.matmul(left, right).reshape(len(w), blocks * _BLOCK)[:, :n]


def triangle_wave(cycles: np.ndarray) -> np.ndarray:
    """Unit triangle wave of a phase in cycles (any shape), in place: 0 and rising at 0.

    ``cycles`` is overwritten with the result.
    """
    cycles += 0.75  # so that 0 cycles starts at 0 and rising, like a sine
    cycles %= 1.0
    cycles -= 0.5
    np.abs(cycles, out=cycles)
    cycles *= 4.0
    cycles -= 1.0
    return cycles


def _periodic(
    n: int, dt: float, amplitude: float, frequency: float, phase: float
) -> tuple[int, float, float, float, float]:
    """The checked arguments of a periodic wave (see :func:`sine` for their units)."""
    n, dt, amplitude = check_sampled(n, dt, amplitude)
    return (
        n,
        dt,
        amplitude,
        check_frequency("frequency", frequency, dt),
        check_finite("phase", phase),
    )


def sine(
    n: int, *, dt: float, amplitude: float, frequency: float, phase: float = 0.0
) -> np.ndarray:
    """Sine wave ``amplitude sin(2 pi frequency t + phase)`` sampled at ``t = k dt``.

    Parameters
    ----------
    n
        Number of samples.
    dt
        Sampling period, s.
    amplitude
        Peak value (signal unit).
    frequency
        Frequency, Hz (at most the Nyquist frequency 1 / (2 dt)).
    phase
        Phase at t = 0, rad.

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, dt, amplitude, frequency, phase = _periodic(n, dt, amplitude, frequency, phase)
    w = 2.0 * np.pi * frequency * dt
    return amplitude * sums_of_sines(np.array([[w]]), np.array([[phase]]), n)[0]


def triangle(
    n: int, *, dt: float, amplitude: float, frequency: float, phase: float = 0.0
) -> np.ndarray:
    """Symmetric triangle wave in phase with :func:`sine` (0 and rising at t = 0, phase 0).

    The parameters are :func:`sine`'s; a phase of pi/2 starts at the peak, as a cosine would.
    """
    n, dt, amplitude, frequency, phase = _periodic(n, dt, amplitude, frequency, phase)
    cycles = frequency * sample_times(n, dt) + phase / (2.0 * np.pi)
    return amplitude * triangle_wave(cycles)


def square(n: int, *, dt: float, amplitude: float, frequency: float) -> np.ndarray:
    """Square wave: +amplitude for the first half of each period, -amplitude for the second.

    Parameters
    ----------
    n
        Number of samples.
    dt
        Sampling period, s.
    amplitude
        Level (signal unit).
    frequency
        Frequency, Hz (at most the Nyquist frequency).

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, dt, amplitude = check_sampled(n, dt, amplitude)
    frequency = check_frequency("frequency", frequency, dt)
    return amplitude * scipy.signal.square(2.0 * np.pi * frequency * sample_times(n, dt))


def step(n: int, *, amplitude: float, start: int = 0) -> np.ndarray:
    """Step: 0 before sample ``start``, ``amplitude`` from sample ``start`` on.

    Parameters
    ----------
    n
        Number of samples.
    amplitude
        Final value (signal unit; may be negative).
    start
        Index of the first sample at the final value (0 <= start <= n).

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n = check_n(n)
    amplitude = check_finite("amplitude", amplitude)
    start = require_int("start (sample index)", start, minimum=0)
    if start > n:
        raise ValueError(f"start must be a sample index in [0, n={n}], got {start}")
    x = np.zeros(n, dtype=np.float64)
    x[start:] = amplitude
    return x


def chirp(
    n: int, *, dt: float, amplitude: float, f0: float, f1: float, method: str = "linear"
) -> np.ndarray:
    """Frequency sweep from ``f0`` at t = 0 to ``f1`` at the last sample (cosine, phase 0).

    Parameters
    ----------
    n
        Number of samples.
    dt
        Sampling period, s.
    amplitude
        Peak value (signal unit).
    f0, f1
        Start and end frequency, Hz (at most the Nyquist frequency).
    method
        Sweep law passed to :func:`scipy.signal.chirp` ("linear", "quadratic", "logarithmic",
        "hyperbolic").

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, dt, amplitude = check_sampled(n, dt, amplitude)
    f0 = check_frequency("f0", f0, dt)
    f1 = check_frequency("f1", f1, dt)
    t = sample_times(n, dt)
    t1 = t[-1] if n > 1 else dt
    return amplitude * scipy.signal.chirp(t, f0=f0, t1=t1, f1=f1, method=method)
