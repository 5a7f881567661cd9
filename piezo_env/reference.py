"""Tracking references for the environment, built from piezo_env.signals.

A reference is a deflection trajectory in micrometres, one sample per environment step.
Named references draw their free parameters from the environment's ``np_random``, so each
reset under a seed gives the same reference.

``"random"`` (the default) picks one of the shapes below with random parameters:

- ``"steps"``: random levels held 50..400 samples (RAND of the paper, in um),
- ``"sine"`` / ``"triangle"``: 0.5..20 Hz (log-uniform), random phase,
- ``"multisine"``: 5 tones in 0.5..20 Hz with random phases.

Amplitudes are 20..80 % of the stroke, so every reference is reachable inside the drive range.
"""

from __future__ import annotations

import math

import numpy as np

from piezo_env import signals

__all__ = ["REFERENCE_SHAPES", "make_reference"]

REFERENCE_SHAPES = ("steps", "sine", "triangle", "multisine")
"""Shapes a named reference can take; ``"random"`` draws one of them."""

_F_MIN, _F_MAX = 0.5, 20.0


def make_reference(
    kind: str, n: int, *, dt: float, stroke_um: float, rng: np.random.Generator
) -> np.ndarray:
    """A reference of ``n`` samples (um) of the named ``kind``.

    Parameters
    ----------
    kind : {"random", "steps", "sine", "triangle", "multisine"}
        Shape; ``"random"`` draws one shape per call.
    n : int
        Number of samples.
    dt : float
        Sample time (s).
    stroke_um : float
        One-sided stroke of the bender (um); amplitudes are 20..80 % of it.
    rng : numpy.random.Generator
        Source of every random parameter.
    """
    if kind == "random":
        kind = REFERENCE_SHAPES[int(rng.integers(len(REFERENCE_SHAPES)))]
    if kind not in REFERENCE_SHAPES:
        raise ValueError(
            f"unknown reference {kind!r}; use 'random', one of {REFERENCE_SHAPES}, or an array (um)"
        )
    amplitude = stroke_um * rng.uniform(0.2, 0.8)
    f_max = min(_F_MAX, 0.25 / dt)
    frequency = math.exp(rng.uniform(math.log(_F_MIN), math.log(f_max)))
    if kind == "steps":
        hold = int(rng.integers(50, 401))
        return signals.random_hold(n, amplitude=amplitude, hold=hold, rng=rng)
    if kind == "multisine":
        return signals.multisine(
            n, dt=dt, amplitude=amplitude, f_min=_F_MIN, f_max=f_max, n_tones=5, rng=rng
        )
    phase = rng.uniform(0.0, 2.0 * math.pi)
    shape = signals.sine if kind == "sine" else signals.triangle
    return shape(n, dt=dt, amplitude=amplitude, frequency=frequency, phase=phase)
