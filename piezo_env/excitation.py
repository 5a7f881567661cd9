"""Random excitation signals: PRBS, held uniform noise (the paper's RAND), multisines and the
decaying multisine (:mod:`piezo_env.signals` names them all). Every draw comes from the ``rng``
argument.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.signal

from piezo_env.signal_checks import (
    check_finite,
    check_frequency,
    check_held,
    check_positive_int,
    check_rng,
    check_sampled,
    sample_times,
)
from piezo_env.waveforms import sums_of_sines

__all__ = ["decaying_multisine", "hold_values", "multisine", "prbs", "random_hold", "scale_to_peak"]


def hold_values(values: np.ndarray, period: int, n: int) -> np.ndarray:
    return np.repeat(values, period)[:n].astype(np.float64, copy=False)


def scale_to_peak(x: np.ndarray, amplitude: float) -> np.ndarray:
    peak = np.max(np.abs(x))
    if peak == 0.0:
        return np.zeros_like(x)
    return x * (amplitude / peak)


def prbs(
    n: int,
    *,
    amplitude: float,
    clock_period: int = 1,
    rng: np.random.Generator,
    kind: str = "telegraph",
) -> np.ndarray:
    """Two-level pseudo-random binary sequence.

    Parameters
    ----------
    n
        Number of samples.
    amplitude
        Level C_P; the signal takes the values +amplitude and -amplitude (signal unit, e.g. V).
    clock_period
        Number of samples each level is held (>= 1). Longer periods move the excitation power
        to lower frequencies (first spectral null at 1 / (clock_period dt)).
    rng
        Random generator; the only source of randomness.
    kind
        ``"telegraph"``: independent fair coin flips per clock period. ``"mls"``: a
        maximum-length sequence (:func:`scipy.signal.max_len_seq`) of the shortest register that
        covers the signal, started from a random nonzero state.

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, amplitude, clock_period, rng = check_held(n, amplitude, "clock_period", clock_period, rng)
    n_clocks = -(-n // clock_period)
    if kind == "telegraph":
        bits = rng.integers(0, 2, size=n_clocks)
    elif kind == "mls":
        nbits = max(2, math.ceil(math.log2(n_clocks + 1)))
        state = np.zeros(nbits, dtype=np.int8)
        while not state.any():
            state = rng.integers(0, 2, size=nbits).astype(np.int8)
        bits, _ = scipy.signal.max_len_seq(nbits, state=state, length=n_clocks)
    else:
        raise ValueError(f"kind must be 'telegraph' or 'mls', got {kind!r}")
    levels = np.where(bits > 0, amplitude, -amplitude)
    return hold_values(levels, clock_period, n)


def random_hold(n: int, *, amplitude: float, hold: int = 1, rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed random signal held piecewise constant (the paper's RAND).

    Parameters
    ----------
    n
        Number of samples.
    amplitude
        C_R; each value is drawn from U(-amplitude, amplitude) (signal unit, e.g. V).
    hold
        Number of samples each value is held (>= 1).
    rng
        Random generator; the only source of randomness.

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, amplitude, hold, rng = check_held(n, amplitude, "hold", hold, rng)
    values = rng.uniform(-amplitude, amplitude, size=-(-n // hold))
    return hold_values(values, hold, n)


def multisine(
    n: int,
    *,
    dt: float,
    amplitude: float,
    f_min: float,
    f_max: float,
    n_tones: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Sum of equal-amplitude tones with random phases, scaled so that ``max |x| == amplitude``.

    Parameters
    ----------
    n
        Number of samples.
    dt
        Sampling period, s.
    amplitude
        Peak value of the signal (signal unit).
    f_min, f_max
        Lowest and highest tone frequency, Hz (0 <= f_min <= f_max <= Nyquist).
    n_tones
        Number of tones, linearly spaced from ``f_min`` to ``f_max`` (one tone at ``f_min`` if 1).
    rng
        Random generator for the phases, uniform in [0, 2 pi).

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, dt, amplitude = check_sampled(n, dt, amplitude)
    f_min = check_frequency("f_min", f_min, dt)
    f_max = check_frequency("f_max", f_max, dt)
    if f_max < f_min:
        raise ValueError(f"f_max ({f_max} Hz) must be >= f_min ({f_min} Hz)")
    n_tones = check_positive_int("n_tones", n_tones)
    rng = check_rng(rng)
    frequencies = np.linspace(f_min, f_max, n_tones)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=n_tones)
    x = sums_of_sines(2.0 * np.pi * dt * frequencies[None, :], phases[None, :], n)[0]
    return scale_to_peak(x, amplitude)


def decaying_multisine(
    n: int,
    *,
    dt: float,
    amplitude: float,
    frequencies: Sequence[float] = (1.0, 3.0, 7.0),
    decay: float | None = None,
) -> np.ndarray:
    """Sum of sines under a decaying exponential envelope, peak scaled to ``amplitude``.

    ``x(t) = c exp(-decay t) sum_k sin(2 pi f_k t)`` with ``c`` such that ``max |x| ==
    amplitude``. Each pass of the slow component reverses at a smaller amplitude, so a hysteretic
    plant traces nested minor loops, which an identification of the hysteresis needs.

    Parameters
    ----------
    n
        Number of samples.
    dt
        Sampling period, s.
    amplitude
        Peak value of the signal (signal unit).
    frequencies
        Tone frequencies, Hz (each at most the Nyquist frequency).
    decay
        Envelope decay rate, 1/s. Default: ``3 / (n dt)``, so the envelope falls to
        exp(-3) = 5 % at the end of the signal.

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n, dt, amplitude = check_sampled(n, dt, amplitude)
    frequencies = np.atleast_1d(np.asarray(frequencies, dtype=np.float64))
    if frequencies.ndim != 1 or frequencies.size == 0:
        raise ValueError("frequencies must be a non-empty sequence of frequencies in Hz")
    for f in frequencies:
        check_frequency("frequencies", f, dt)
    decay = 3.0 / (n * dt) if decay is None else check_finite("decay", decay, minimum=0.0)
    t = sample_times(n, dt)
    x = np.exp(-decay * t) * np.sin(2.0 * np.pi * np.outer(t, frequencies)).sum(axis=1)
    return scale_to_peak(x, amplitude)
