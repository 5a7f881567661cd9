"""Tracking references for the environment: the shapes of piezo_env.signals, drawn per episode.

A reference is a deflection trajectory in micrometres, one sample per environment step.
Named references draw their free parameters from the environment's ``np_random``, so each
reset under a seed gives the same reference.

``"random"`` (the default) picks one of the shapes below with random parameters:

- ``"steps"``: random levels held 50..400 ms (RAND of the paper: 50..400 samples at its 1 ms;
  in um),
- ``"sine"`` / ``"triangle"``: a frequency drawn log-uniform in the band, random phase,
- ``"multisine"``: 5 tones spread over the band with random phases.

The band is 0.5..20 Hz by default (:data:`DEFAULT_BAND`); the env option
``TaskConfig.reference_band`` sets another (checked by :func:`check_reference_band`).

Amplitudes are 20..80 % of the stroke, so every reference is reachable inside the drive range.
Every duration is in time, not samples, so that a reference is a function of time whatever the
sample time (the same seed draws the same shape, frequency and hold at 1 ms and at 0.1 ms).
An episode's reference is a :class:`ReferenceStream`: segments of :data:`SEGMENT_S` (2.048 s,
longer than the 2 s episodes of the benchmark), each a fresh draw, as many as the episode
needs. Drawing (:func:`draw_reference`) and rendering
(:func:`render_references`) are split so that the vector env renders the references of all
sub-envs that reset together in one batch; the shapes are those of piezo_env.signals
(random_hold, sine, triangle, multisine), rendered element-wise so that a batch and a single
env give the same samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from piezo_env.waveforms import sums_of_sines, triangle_wave

__all__ = [
    "DEFAULT_BAND",
    "REFERENCE_NAMES",
    "REFERENCE_SHAPES",
    "SEGMENT_S",
    "ReferenceDraw",
    "ReferenceStream",
    "check_reference_array",
    "check_reference_band",
    "draw_reference",
    "make_reference",
    "render_references",
    "segment_samples",
]

REFERENCE_SHAPES = ("steps", "sine", "triangle", "multisine")
"""Shapes a named reference can take; ``"random"`` draws one of them."""

REFERENCE_NAMES = ("random", *REFERENCE_SHAPES)
"""Every valid reference name."""

DEFAULT_BAND = (0.5, 20.0)
"""Frequency band (Hz) of the random sines, triangles and multisines unless the env sets one."""

_TONES = 5


def check_reference_band(band: object, dt: float) -> tuple[float, float]:
    """The band ``(low, high)`` (Hz) as two floats, or ValueError saying what is wrong.

    A band needs 0 < low <= high <= 0.25 / dt (half the Nyquist frequency, so that a period
    has at least four samples). :data:`DEFAULT_BAND` is accepted at any dt: at a sample time
    too coarse for it, its top is cut to 0.25 / dt when drawing, and a dt so coarse that the
    cut band is empty (dt > 0.25 / low, half a second) is refused then, with the reason.
    """
    try:
        low, high = (float(f) for f in band)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(
            f"reference_band must be a pair (low, high) of frequencies in Hz, got {band!r}"
        ) from None
    if (low, high) == DEFAULT_BAND:
        return DEFAULT_BAND
    top = 0.25 / dt
    if not (0.0 < low <= high <= top):
        raise ValueError(
            f"reference_band must satisfy 0 < low <= high <= 0.25/dt = {top:g} Hz, "
            f"got {band!r}; e.g. reference_band=(0.5, {min(100.0, top):g})"
        )
    return low, high


@dataclass(frozen=True)
class ReferenceDraw:
    """The random parameters of one reference segment (every draw already made).

    Attributes
    ----------
    shape : str
        One of REFERENCE_SHAPES.
    amplitude : float
        Peak value (um).
    frequency : float
        Frequency (Hz) of the sine and triangle shapes; the top tone of the multisine.
    phase : float
        Phase at t = 0 (rad) of the sine and triangle shapes.
    levels : ndarray or None
        Step levels (um), one per hold period, for ``"steps"``.
    hold : int
        Samples per step level (50..400 ms at the draw's sample time).
    tone_phases : ndarray or None
        Phases (rad) of the multisine tones.
    low_frequency : float
        Lowest multisine tone (Hz): the bottom of the band.
    """

    shape: str
    amplitude: float
    frequency: float
    phase: float = 0.0
    levels: np.ndarray | None = None
    hold: int = 1
    tone_phases: np.ndarray | None = None
    low_frequency: float = DEFAULT_BAND[0]


def draw_reference(
    kind: str,
    n: int,
    *,
    dt: float,
    stroke_um: float,
    rng: np.random.Generator,
    band: tuple[float, float] = DEFAULT_BAND,
) -> ReferenceDraw:
    """Draw the parameters of an ``n``-sample reference of the named ``kind`` from ``rng``.

    ``band`` (Hz, see :func:`check_reference_band`) bounds the sine, triangle and multisine
    frequencies; the number of draws from ``rng`` does not depend on it.
    """
    steps_only = kind == "steps"  # steps use no frequency: any band will do
    if kind == "random":
        kind = REFERENCE_SHAPES[int(rng.integers(len(REFERENCE_SHAPES)))]
    if kind not in REFERENCE_SHAPES:
        raise ValueError(
            f"unknown reference {kind!r}; use one of {REFERENCE_NAMES} or an array (um)"
        )
    f_min, f_max = band[0], min(band[1], 0.25 / dt)
    if steps_only:
        f_max = max(f_max, f_min)  # drawn as for the other shapes (the same draws), unused
    if f_max < f_min:  # only the default band gets here: a given one was checked at dt
        raise ValueError(
            f"the reference band {band[0]:g}-{band[1]:g} Hz, cut to 0.25/dt = {f_max:g} Hz "
            f"at dt = {dt:g} s, is empty: use dt <= {0.25 / f_min:g} s, a band "
            f"reference_band=(low, high) with high <= {f_max:g} Hz, or an array reference (um)"
        )
    amplitude = stroke_um * rng.uniform(0.2, 0.8)
    frequency = math.exp(rng.uniform(math.log(f_min), math.log(f_max)))
    if kind == "steps":  # held 50..400 ms: samples at 1 ms, the paper's RAND
        hold = max(1, round(int(rng.integers(50, 401)) * 1e-3 / dt))
        levels = rng.uniform(-amplitude, amplitude, size=-(-n // hold))
        return ReferenceDraw(kind, amplitude, frequency, levels=levels, hold=hold)
    if kind == "multisine":
        phases = rng.uniform(0.0, 2.0 * np.pi, size=_TONES)
        return ReferenceDraw(kind, amplitude, f_max, tone_phases=phases, low_frequency=f_min)
    return ReferenceDraw(kind, amplitude, frequency, phase=rng.uniform(0.0, 2.0 * math.pi))


def render_references(draws: list[ReferenceDraw], n: int, *, dt: float) -> np.ndarray:
    """Samples of the drawn references, shape (len(draws), n), in um.

    Shapes are rendered in batches with element-wise operations only, so a reference comes
    out the same, bit for bit, whether it is rendered alone or among many.
    """
    out = np.empty((len(draws), n))
    t = np.arange(n) * dt
    for shape in REFERENCE_SHAPES:
        index = [i for i, d in enumerate(draws) if d.shape == shape]
        if not index:
            continue
        group = [draws[i] for i in index]
        amplitude = np.array([d.amplitude for d in group])[:, None]
        if shape == "steps":
            out[index] = [np.repeat(d.levels, d.hold)[:n] for d in group]  # random_hold
        elif shape == "triangle":
            frequency = np.array([d.frequency for d in group])[:, None]
            phase = np.array([d.phase for d in group])[:, None]
            # Fraction of the period, shifted so that phase 0 starts at 0 and rising.
            cycles = frequency * t
            cycles += phase / (2.0 * np.pi)
            out[index] = amplitude * triangle_wave(cycles)
        elif shape == "sine":
            w = 2.0 * np.pi * dt * np.array([d.frequency for d in group])[:, None]
            phase = np.array([d.phase for d in group])[:, None]
            out[index] = amplitude * sums_of_sines(w, phase, n)
        else:  # multisine: _TONES tones spread over the draw's band
            tones = np.array([np.linspace(d.low_frequency, d.frequency, _TONES) for d in group])
            phase = np.array([d.tone_phases for d in group])
            x = sums_of_sines(2.0 * np.pi * dt * tones, phase, n)
            out[index] = x * (amplitude / np.abs(x).max(axis=1, keepdims=True))
    return out


def make_reference(
    kind: str,
    n: int,
    *,
    dt: float,
    stroke_um: float,
    rng: np.random.Generator,
    band: tuple[float, float] = DEFAULT_BAND,
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
    band : (float, float)
        Frequency band (Hz) of the sine, triangle and multisine shapes.
    """
    draw = draw_reference(kind, n, dt=dt, stroke_um=stroke_um, rng=rng, band=band)
    return render_references([draw], n, dt=dt)[0]


def check_reference_array(spec: object) -> np.ndarray:
    """A reference array as a read-only float64 copy (um), or ValueError saying what is wrong.

    The array must be one-dimensional, non-empty, numeric and finite; a non-finite sample is
    reported by its index and value.
    """
    try:
        values = np.array(spec, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"a reference array must hold numbers (um), got {type(spec).__name__}: {exc}"
        ) from None
    if values.ndim != 1 or values.size == 0:
        raise ValueError(
            "a reference array must be one-dimensional and non-empty (um), "
            f"got shape {values.shape}"
        )
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise ValueError(
            f"a reference array must be finite (um), got {values[bad[0]]} at index {bad[0]}"
            + (f" ({bad.size} non-finite samples)" if bad.size > 1 else "")
        )
    values.flags.writeable = False
    return values


SEGMENT_S = 2.048
"""Duration (s) of one drawn segment of a named reference: 2048 samples at 1 ms."""


def segment_samples(dt: float) -> int:
    """Samples of one reference segment at the sample time ``dt`` (s): :data:`SEGMENT_S` in
    whole samples (2048 at 1 ms, 8192 at 0.25 ms)."""
    return max(1, round(SEGMENT_S / dt))


class ReferenceStream:
    """The reference of one episode (um, float32), drawn lazily in segments.

    A named reference draws :func:`segment_samples` at a time from the env's generator: the first
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
    first : ndarray, optional
        The first segment of a named reference, already drawn from ``rng`` and rendered (the
        vector env renders the segments of many sub-envs in one batch).
    band : (float, float)
        Frequency band (Hz) of the named reference's segments.
    """

    def __init__(
        self,
        spec: str | np.ndarray,
        *,
        dt: float,
        stroke_um: float,
        bound: float,
        rng: np.random.Generator | None,
        first: np.ndarray | None = None,
        band: tuple[float, float] = DEFAULT_BAND,
    ) -> None:
        self._name = spec if isinstance(spec, str) else None
        self._dt, self._stroke, self._rng, self._band = dt, stroke_um, rng, band
        if self._name is not None:
            if first is None:
                first = make_reference(
                    self._name, segment_samples(dt), dt=dt, stroke_um=stroke_um, rng=rng, band=band
                )
            self._values = np.asarray(first, dtype=np.float32)
        else:
            values = check_reference_array(spec)
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
                segment = segment_samples(self._dt)
                count = -(-missing // segment)
                extra = np.concatenate(
                    [
                        make_reference(
                            self._name,
                            segment,
                            dt=self._dt,
                            stroke_um=self._stroke,
                            rng=self._rng,
                            band=self._band,
                        ).astype(np.float32)
                        for _ in range(count)
                    ]
                )
            self._values = np.concatenate([self._values, extra])
        return self._values
