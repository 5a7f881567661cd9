"""The benchmark's tracking references: one registry, each named and seeded.

Every reference is a deflection trajectory in micrometres, one sample per step, built from the
signal shapes of :mod:`piezo_env.signals`. Sample k is the reference at time k dt; the env
scores the action a_t against sample t + 1. Random-phase signals fade in over 50 ms
(:func:`fade_in`) so that every smooth reference starts at rest. Random references draw from a
generator seeded by the benchmark seed and the reference's name, so a name and a seed always
give the same array. Add your own with :func:`register_reference` (a function of n, dt and a
generator) or pass an array straight to :func:`controllers.run_episode`.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from piezo_env import signals

__all__ = ["REFERENCES", "Reference", "fade_in", "make_reference", "register_reference"]


@dataclass(frozen=True)
class Reference:
    """A named reference.

    Attributes
    ----------
    name : str
        Registry key, e.g. ``"sine-50Hz"``.
    description : str
        One line for tables.
    build : callable
        ``build(n, dt, rng) -> ndarray`` of n samples (um).
    smooth : bool
        Whether the reference is smooth (feasible within the drive range), as opposed to steps.
    """

    name: str
    description: str
    build: Callable[[int, float, np.random.Generator], np.ndarray]
    smooth: bool = True


def _sine(frequency: float) -> Reference:
    return Reference(
        f"sine-{frequency:g}Hz",
        f"sine, 500 um, {frequency:g} Hz",
        lambda n, dt, rng: signals.sine(n, dt=dt, amplitude=500.0, frequency=frequency),
    )


def fade_in(x: np.ndarray, dt: float, duration: float = 0.05) -> np.ndarray:
    """A copy of ``x`` with a raised-cosine fade-in over its first ``duration`` (s).

    Sample k < K = round(duration / dt) is scaled by (1 - cos(pi k / K)) / 2, so a
    random-phase signal starts at 0 and reaches its own amplitude after ``duration``; ``dt``
    is the sample time (s).
    """
    k = min(len(x), round(duration / dt))
    x = x.copy()
    x[:k] *= 0.5 * (1.0 - np.cos(np.pi * np.arange(k) / k))
    return x


def _sine_chirp(n: int, dt: float, f0: float, f1: float) -> np.ndarray:
    """sin of a linear sweep from f0 (Hz) at t = 0 to f1 at t = n dt: starts at 0, rising."""
    t = np.arange(n) * dt
    return np.sin(2.0 * np.pi * (f0 * t + 0.5 * (f1 - f0) / (n * dt) * t**2))


REFERENCES: dict[str, Reference] = {
    r.name: r
    for r in (
        _sine(1.0),
        _sine(10.0),
        _sine(50.0),
        _sine(100.0),
        Reference(
            "triangle-10Hz",
            "triangle, 500 um, 10 Hz",
            lambda n, dt, rng: signals.triangle(n, dt=dt, amplitude=500.0, frequency=10.0),
        ),
        Reference(
            "multisine",
            "multisine, 8 tones 1-40 Hz, 500 um peak",
            lambda n, dt, rng: fade_in(
                signals.multisine(
                    n, dt=dt, amplitude=500.0, f_min=1.0, f_max=40.0, n_tones=8, rng=rng
                ),
                dt,
            ),
        ),
        Reference(
            "chirp",
            "chirp, 300 um, 1-100 Hz linear over the episode",
            lambda n, dt, rng: 300.0 * _sine_chirp(n, dt, 1.0, 100.0),
        ),
        Reference(
            "steps",
            "+-600 um steps every 0.2 s",
            lambda n, dt, rng: signals.square(n, dt=dt, amplitude=600.0, frequency=2.5),
            smooth=False,
        ),
        Reference(
            "random-steps",
            "random levels in +-600 um held 0.1 s",
            lambda n, dt, rng: signals.random_hold(
                n, amplitude=600.0, hold=max(1, round(0.1 / dt)), rng=rng
            ),
            smooth=False,
        ),
    )
}
"""Every named reference, in table order."""


def register_reference(reference: Reference) -> None:
    """Add a reference to :data:`REFERENCES` (ValueError if the name is taken)."""
    if reference.name in REFERENCES:
        raise ValueError(f"a reference named {reference.name!r} exists already")
    REFERENCES[reference.name] = reference


def make_reference(
    name: str, n: int, *, dt: float, seed: int, stroke_um: float = 1000.0
) -> np.ndarray:
    """Samples 0 .. n-1 (um) of the named reference for this seed.

    The amplitudes in the descriptions are the PL140's (one-sided stroke 1000 um); another
    bender's references are the same fractions of its own stroke ``stroke_um`` (um).

    Raises
    ------
    ValueError
        For an unknown name (the message lists the valid ones), or a reference this dt
        cannot sample (the message names the reference and the fix).
    """
    if name not in REFERENCES:
        raise ValueError(f"unknown reference {name!r}; valid: {', '.join(REFERENCES)}")
    rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
    try:
        reference = np.asarray(REFERENCES[name].build(n, dt, rng), dtype=float)
    except ValueError as error:
        if "Nyquist" not in str(error):
            raise
        raise ValueError(
            f"the reference {name!r} cannot be sampled at dt = {dt:g} s ({error}); pass a "
            "smaller dt, or leave the reference out (piezo benchmark --references)"
        ) from error
    return reference if stroke_um == 1000.0 else reference * (stroke_um / 1000.0)
