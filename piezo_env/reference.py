"""Tracking references for the environment, built from piezo_env.signals.

A reference is a deflection trajectory in micrometres, one sample per environment step.
Named references draw their free parameters from the environment's ``np_random``, so each
reset under a seed gives the same reference.

``"random"`` (the default) picks one of the shapes below with random parameters:

- ``"steps"``: random levels held 50..400 samples (RAND of the paper, in um),
- ``"sine"`` / ``"triangle"``: 0.5..20 Hz (log-uniform), random phase,
- ``"multisine"``: 5 tones in 0.5..20 Hz with random phases.

Amplitudes are 20..80 % of the stroke, so every reference is reachable inside the drive range.
An episode's reference is a :class:`ReferenceStream`: segments of 2048 samples, each a fresh
draw, as many as the episode needs.
"""

from __future__ import annotations

import math

import numpy as np

from piezo_env import signals

__all__ = ["REFERENCE_SHAPES", "SEGMENT", "ReferenceStream", "make_reference"]

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


SEGMENT = 2048
"""Samples per drawn segment of a named reference."""


class ReferenceStream:
    """The reference of one episode (um, float32), drawn lazily in segments.

    A named reference draws ``SEGMENT`` samples at a time from the env's generator: the first
    segment at reset, each further one at the step whose preview first reaches past the samples
    drawn so far, so an episode of any length has a reference and the draws happen at the same
    moments in the single and the vector env. An array reference is used as given and its last
    value holds past its end.

    Parameters
    ----------
    spec : str or array_like
        A reference name (see :func:`make_reference`) or an array (um).
    dt : float
        Sample time (s).
    stroke_um : float
        One-sided stroke (um), the scale of named references.
    bound : float
        Largest admissible |reference| (um); arrays beyond it raise ValueError.
    rng : numpy.random.Generator or None
        Source of the named reference's segments (unused for arrays).
    """

    def __init__(
        self,
        spec: str | np.ndarray,
        *,
        dt: float,
        stroke_um: float,
        bound: float,
        rng: np.random.Generator | None,
    ) -> None:
        self._name = spec if isinstance(spec, str) else None
        self._dt, self._stroke, self._rng = dt, stroke_um, rng
        if self._name is not None:
            first = make_reference(self._name, SEGMENT, dt=dt, stroke_um=stroke_um, rng=rng)
            self._values = first.astype(np.float32)
        else:
            values = np.asarray(spec, dtype=np.float64)
            if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
                raise ValueError(
                    "a reference array must be one-dimensional, non-empty and finite (um), "
                    f"got shape {values.shape}"
                )
            if np.abs(values).max() > bound:
                raise ValueError(
                    f"reference reaches {np.abs(values).max():.1f} um, beyond what the bender "
                    f"can reach (observation bound {bound:.1f} um); scale it down"
                )
            self._values = values.astype(np.float32)

    @property
    def values(self) -> np.ndarray:
        """The samples drawn so far (um, float32)."""
        return self._values

    def ensure(self, n: int) -> np.ndarray:
        """Make at least ``n`` samples available; returns all samples drawn so far."""
        missing = n - len(self._values)
        if missing > 0:
            if self._name is None:
                extra = np.full(max(missing, len(self._values)), self._values[-1], np.float32)
            else:
                count = -(-missing // SEGMENT)
                extra = np.concatenate(
                    [
                        make_reference(
                            self._name, SEGMENT, dt=self._dt, stroke_um=self._stroke, rng=self._rng
                        ).astype(np.float32)
                        for _ in range(count)
                    ]
                )
            self._values = np.concatenate([self._values, extra])
        return self._values
