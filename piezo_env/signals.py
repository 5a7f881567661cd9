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
from collections.abc import Callable

import numpy as np

from piezo_env.excitation import decaying_multisine, multisine, prbs, random_hold
from piezo_env.waveforms import chirp, sine, square, step, sums_of_sines, triangle, triangle_wave

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
