"""Excitation and reference signals: the one home for every test input of the testbed.

Every generator is a pure function that returns a float64 array of ``n`` samples taken at a
constant sampling period. Amplitudes are in the unit of the signal itself (volts for a drive
voltage, micrometres for a deflection reference); frequencies are in Hz and the sampling period
``dt`` in s. Random signals draw only from the ``rng`` argument (a seeded
:class:`numpy.random.Generator`), so the same seed always gives the same signal.

Signals
-------
prbs
    Two-level pseudo-random binary sequence +-C_P held for ``clock_period`` samples (the paper's
    PRBS, used to identify the ARX part: under a two-level input a static nonlinearity is affine).
random
    The paper's RAND: uniform in [-C_R, C_R], each value held for ``hold`` samples.
sine, triangle, square, step
    Deterministic references.
multisine
    Sum of equal-amplitude tones between two frequencies with random phases.
chirp
    Linear frequency sweep (:func:`scipy.signal.chirp`).
decaying-multisine
    A sum of sines under an exponentially decaying envelope, in the spirit of MATLAB's piezo
    hysteresis identification example: the shrinking amplitude traces nested minor hysteresis
    loops.

:func:`make_signal` builds any of them by name (the names are the keys of :data:`SIGNALS`).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence

import numpy as np
import scipy.signal

from piezo_env.checks import require_int

__all__ = [
    "SIGNALS",
    "SIGNAL_DEFAULTS",
    "chirp",
    "decaying_multisine",
    "make_signal",
    "multisine",
    "prbs",
    "random_hold",
    "sine",
    "square",
    "step",
    "sums_of_sines",
    "triangle",
    "triangle_wave",
]


def _check_n(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise ValueError(f"n must be a positive integer number of samples, got {n!r}")
    if n < 1:
        raise ValueError(f"n must be a positive integer number of samples, got {n}")
    return int(n)


def _check_positive_int(name: str, value: int) -> int:
    return require_int(f"{name} (samples)", value)


def _check_finite(name: str, value: float, *, minimum: float | None = None) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


def _check_dt(dt: float) -> float:
    dt = _check_finite("dt", dt)
    if dt <= 0.0:
        raise ValueError(f"dt (sampling period, s) must be positive, got {dt}")
    return dt


def _check_frequency(name: str, frequency: float, dt: float) -> float:
    frequency = _check_finite(name, frequency, minimum=0.0)
    nyquist = 0.5 / dt
    if frequency > nyquist:
        raise ValueError(
            f"{name} = {frequency} Hz is above the Nyquist frequency {nyquist} Hz of dt = {dt} s"
        )
    return frequency


def _check_rng(rng: np.random.Generator) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), "
            f"got {type(rng).__name__}"
        )
    return rng


def _time(n: int, dt: float) -> np.ndarray:
    return np.arange(n, dtype=np.float64) * dt


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


def _hold(values: np.ndarray, period: int, n: int) -> np.ndarray:
    return np.repeat(values, period)[:n].astype(np.float64, copy=False)


def _scale_to_peak(x: np.ndarray, amplitude: float) -> np.ndarray:
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
    n = _check_n(n)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    clock_period = _check_positive_int("clock_period", clock_period)
    rng = _check_rng(rng)
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
    return _hold(levels, clock_period, n)


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
    n = _check_n(n)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    hold = _check_positive_int("hold", hold)
    rng = _check_rng(rng)
    values = rng.uniform(-amplitude, amplitude, size=-(-n // hold))
    return _hold(values, hold, n)


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
    n = _check_n(n)
    dt = _check_dt(dt)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    frequency = _check_frequency("frequency", frequency, dt)
    phase = _check_finite("phase", phase)
    w = 2.0 * np.pi * frequency * dt
    return amplitude * sums_of_sines(np.array([[w]]), np.array([[phase]]), n)[0]


def triangle(
    n: int, *, dt: float, amplitude: float, frequency: float, phase: float = 0.0
) -> np.ndarray:
    """Symmetric triangle wave in phase with :func:`sine` (0 and rising at t = 0, phase 0).

    Parameters
    ----------
    n
        Number of samples.
    dt
        Sampling period, s.
    amplitude
        Peak value (signal unit).
    frequency
        Frequency, Hz (at most the Nyquist frequency).
    phase
        Phase at t = 0, rad (a phase of pi/2 starts at the peak, as a cosine would).

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.
    """
    n = _check_n(n)
    dt = _check_dt(dt)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    frequency = _check_frequency("frequency", frequency, dt)
    phase = _check_finite("phase", phase)
    cycles = frequency * _time(n, dt) + phase / (2.0 * np.pi)
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
    n = _check_n(n)
    dt = _check_dt(dt)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    frequency = _check_frequency("frequency", frequency, dt)
    return amplitude * scipy.signal.square(2.0 * np.pi * frequency * _time(n, dt))


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
    n = _check_n(n)
    amplitude = _check_finite("amplitude", amplitude)
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or not 0 <= start <= n:
        raise ValueError(f"start must be an integer sample index in [0, n={n}], got {start!r}")
    x = np.zeros(n, dtype=np.float64)
    x[int(start) :] = amplitude
    return x


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
    n = _check_n(n)
    dt = _check_dt(dt)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    f_min = _check_frequency("f_min", f_min, dt)
    f_max = _check_frequency("f_max", f_max, dt)
    if f_max < f_min:
        raise ValueError(f"f_max ({f_max} Hz) must be >= f_min ({f_min} Hz)")
    n_tones = _check_positive_int("n_tones", n_tones)
    rng = _check_rng(rng)
    frequencies = np.linspace(f_min, f_max, n_tones)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=n_tones)
    x = sums_of_sines(2.0 * np.pi * dt * frequencies[None, :], phases[None, :], n)[0]
    return _scale_to_peak(x, amplitude)


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
    n = _check_n(n)
    dt = _check_dt(dt)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    f0 = _check_frequency("f0", f0, dt)
    f1 = _check_frequency("f1", f1, dt)
    t = _time(n, dt)
    t1 = t[-1] if n > 1 else dt
    return amplitude * scipy.signal.chirp(t, f0=f0, t1=t1, f1=f1, method=method)


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
    n = _check_n(n)
    dt = _check_dt(dt)
    amplitude = _check_finite("amplitude", amplitude, minimum=0.0)
    frequencies = np.atleast_1d(np.asarray(frequencies, dtype=np.float64))
    if frequencies.ndim != 1 or frequencies.size == 0:
        raise ValueError("frequencies must be a non-empty sequence of frequencies in Hz")
    for f in frequencies:
        _check_frequency("frequencies", f, dt)
    decay = 3.0 / (n * dt) if decay is None else _check_finite("decay", decay, minimum=0.0)
    t = _time(n, dt)
    x = np.exp(-decay * t) * np.sin(2.0 * np.pi * np.outer(t, frequencies)).sum(axis=1)
    return _scale_to_peak(x, amplitude)


SIGNALS: dict[str, Callable[..., np.ndarray]] = {
    "prbs": prbs,
    "random": random_hold,
    "sine": sine,
    "triangle": triangle,
    "square": square,
    "step": step,
    "multisine": multisine,
    "chirp": chirp,
    "decaying-multisine": decaying_multisine,
}
"""Signal generators by name; :func:`make_signal` dispatches on these keys."""


SIGNAL_DEFAULTS: dict[str, dict[str, float]] = {
    "prbs": {"clock_period": 5},
    "random": {"hold": 20},
    "sine": {"frequency": 1.0},
    "triangle": {"frequency": 1.0},
    "square": {"frequency": 1.0},
    "step": {},
    "multisine": {"f_min": 1.0, "f_max": 40.0, "n_tones": 10},
    "chirp": {"f0": 0.5, "f1": 50.0},
    "decaying-multisine": {},
}
"""Typical parameters of each signal besides its amplitude (Hz, samples), for command lines and
defaults; explicit parameters override them."""


def make_signal(
    name: str,
    n: int,
    *,
    dt: float,
    rng: np.random.Generator | None = None,
    **params: object,
) -> np.ndarray:
    """Build the signal ``name`` with ``n`` samples.

    ``dt`` and ``rng`` are passed only to the generators that take them, so one call site can
    build any signal. All other keyword arguments go to the generator.

    Parameters
    ----------
    name
        A key of :data:`SIGNALS`.
    n
        Number of samples.
    dt
        Sampling period, s.
    rng
        Random generator; required by the random signals (prbs, random, multisine).
    **params
        The generator's own parameters (e.g. ``amplitude``, ``frequency``).

    Returns
    -------
    numpy.ndarray
        float64 array of length ``n``.

    Raises
    ------
    ValueError
        Unknown name, a parameter the generator does not accept, a missing required parameter,
        or a random signal without ``rng``.
    """
    if name not in SIGNALS:
        raise ValueError(f"unknown signal {name!r}; valid names: {', '.join(SIGNALS)}")
    func = SIGNALS[name]
    signature = inspect.signature(func)
    accepted = [p for p in signature.parameters if p not in ("n", "dt", "rng")]
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise ValueError(
            f"signal {name!r} does not accept {', '.join(unknown)}; "
            f"accepted parameters: {', '.join(accepted)}"
        )
    required = [
        p
        for p, spec in signature.parameters.items()
        if p not in ("n", "dt", "rng") and spec.default is inspect.Parameter.empty
    ]
    missing = [p for p in required if p not in params]
    if missing:
        raise ValueError(
            f"signal {name!r} needs {', '.join(missing)}; "
            f"accepted parameters: {', '.join(accepted)}"
        )
    kwargs = dict(params)
    if "dt" in signature.parameters:
        kwargs["dt"] = dt
    if "rng" in signature.parameters:
        if rng is None:
            raise ValueError(f"signal {name!r} is random: pass rng=numpy.random.default_rng(seed)")
        kwargs["rng"] = rng
    return func(n, **kwargs)
