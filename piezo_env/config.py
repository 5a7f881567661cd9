"""The settings of a PiezoBender-v0 task: each default held once, validated at construction.

:class:`TaskConfig` is frozen; the single env, the vector env and the physics model
(:class:`piezo_env.model.PiezoBenderModel`, whose keyword defaults are these fields) read it.
:class:`piezo_env.task.BenderTask` builds the model, spaces and references from it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from piezo_env.amplifier import Amplifier
from piezo_env.checks import require_int, require_number
from piezo_env.datasheet import BenderDatasheet, get_datasheet
from piezo_env.discrete import Creep
from piezo_env.disturbance import Disturbance
from piezo_env.drift import Drift
from piezo_env.fem import DEFAULT_ELEMENTS, check_damping_ratio
from piezo_env.hysteresis import HYSTERESIS_NAMES, Hysteresis, make_hysteresis
from piezo_env.randomization import DomainRandomization
from piezo_env.reference import (
    DEFAULT_BAND,
    REFERENCE_NAMES,
    check_reference_array,
    check_reference_band,
)
from piezo_env.sampling import default_dt, warn_if_resonance_aliases
from piezo_env.sensor import Sensor

__all__ = ["DEFAULT_HORIZON", "NOISE_BLOCK", "TaskConfig"]

DEFAULT_HORIZON = 2000
"""Default episode length (steps) of the registered id: 2 s at dt = 1 ms (the PL140's default;
at another dt pass ``max_episode_steps=round(2.0 / dt)`` for 2 s)."""

NOISE_BLOCK = 1024
"""Sensor-noise samples drawn at a time. The single and the vector env must agree on it: it
fixes when each draws from its generator."""


@dataclass(frozen=True, kw_only=True, eq=False)
class TaskConfig:
    """Settings of a PiezoBender-v0 task, each default held here once; validated on construction.

    The keyword arguments of :class:`piezo_env.env.PiezoBenderEnv` and of the vector env are
    these fields. Construction raises ValueError naming the field and its valid values.
    Use :meth:`from_kwargs` to build one from keyword arguments with a clear error for unknown
    names, and :func:`dataclasses.replace` to derive a variant.

    Attributes
    ----------
    bender : str or BenderDatasheet
        Catalogue name (``"PL140"``, ``"PL112"``, ``"PL122"``, ``"PL127"``, ``"PL128"``; the
        ``".10"`` suffix is optional) or a :class:`~piezo_env.datasheet.BenderDatasheet`.
    n_elements : int
        Hermite beam finite elements (positive integer).
    dt : float or None
        Sample time (s), > 0: one env step. None (the default): the bender's default,
        :func:`piezo_env.default_dt`, the largest of :data:`piezo_env.sampling.DT_LADDER` with
        4 (1 + s) f_1 dt <= 1 (f_1 the datasheet resonance, s its tolerance): 1 ms for the
        PL140, 0.5 ms for the PL128, 0.25 ms for the PL122 and PL127, 0.1 ms for the PL112.
        Stored as a float. :meth:`from_kwargs` with a new ``bender`` and no ``dt`` chooses it
        again when the rule chose it; :func:`dataclasses.replace` keeps it.
    hysteresis : {"bouc-wen", "prandtl-ishlinskii", "rate-dependent", None} or Hysteresis
        Input hysteresis; None for a linear bender. ``"rate-dependent"`` is the
        Prandtl-Ishlinskii map whose play radii grow with the drive's rate (at a full-stroke
        50 Hz sine the loop is 1.5x as wide as quasi-static in continuous time, 1.33x sampled
        at 1 ms and 1.47x at 0.25 ms: :data:`~piezo_env.hysteresis.RATE_TIME`;
        :class:`~piezo_env.hysteresis.RateDependentPrandtlIshlinskii`).
    creep : bool or Creep
        Linear creep: False (off), True (1.5 % per decade) or a
        :class:`~piezo_env.discrete.Creep`.
    noise_bound : float
        Sensor noise bound r (um), >= 0: the measured deflection carries nu ~ U(-r, r).
    reference : {"random", "steps", "sine", "triangle", "multisine"}, array_like or None
        What the tip tracks: a name, drawn from the env's generator at each reset; a 1-D finite
        array (um), whose last value holds past its end; or None: regulation to zero
        deflection, and the observation is the measured deflection alone (then ``preview``
        must be 0). An array is stored as a read-only float64 copy.
    reference_band : (float, float)
        Frequency band ``(low, high)`` (Hz) of the named references' sines and triangles (drawn
        log-uniform in it) and multisines (tones spread over it); steps and arrays ignore it.
        0 < low <= high <= 0.25 / dt; the default (0.5, 20) is accepted at any dt (its top is
        cut to 0.25 / dt at a coarser dt), but a named random reference is refused at a dt so
        coarse that the cut band is empty (dt > 0.5 s). Stored as a tuple of two floats.
    preview : int or None
        Future reference samples in the observation, integer >= 0. None (the default) becomes
        1 with a reference and 0 without. With ``preview >= 1`` the observation holds r_{t+1},
        the sample the reward of a_t is scored against; with 0 it does not.
    deflection_limit : float or None
        Terminate the episode when |true tip deflection| exceeds this (um), > 0; None: never.
    damping_ratio : float
        First-mode damping ratio zeta_1 (-), in [1e-4, 1): the bender must be underdamped.
        With ``randomize`` it is the nominal plant's only; each episode draws its own.
    randomize : bool, DomainRandomization or None
        Domain randomisation: None or False (the default) keeps the nominal plant; True draws
        the plant at every reset with the default :class:`~piezo_env.randomization.
        DomainRandomization` (free deflection, blocking force and resonance +-20 %, damping
        ratio 0.01-0.04, hysteresis strength +-30 %); a DomainRandomization sets the spread.
        Stored as a DomainRandomization or None. The draw order is in
        :mod:`piezo_env.randomization`, the proof of the observation bound over the whole
        range in :mod:`piezo_env.randomized_bound`.
    amplifier : bool, Amplifier or None
        The drive amplifier's current (slew) limit and bandwidth
        (:class:`~piezo_env.amplifier.Amplifier`): None or False (the default): an ideal
        amplifier; True: 100 mA, i.e. a slew limit I_max / C_p = 12.2 V/ms on a PL140
        (C_p = 8.2 uF), full-stroke sines up to 64.7 Hz; an Amplifier sets the current (mA)
        and an optional small-signal bandwidth (Hz). The action is then the amplifier's
        command; ``info["voltage_V"]`` is the voltage on the bender, ``info["command_V"]`` the
        clipped command, ``info["slew_limited"]`` whether the limit was active and
        ``info["current_mA"]`` the drive current dQ/dt. Stored as an Amplifier or None.
    sensor : bool, Sensor or None
        Dynamics of the displacement sensor, on the observed deflection only
        (:class:`~piezo_env.sensor.Sensor`): None or False (the default): ideal; True: no delay
        and a 20 kHz first-order bandwidth; a Sensor sets the delay (0, 1 or 2 samples) and the
        bandwidth (Hz, or None). Stored as a Sensor or None.
    drift : bool, Drift or None
        Slow drift of the piezoelectric coefficient and the stiffness over the episode
        (:class:`~piezo_env.drift.Drift`, factors relative to the datasheet, linear in time):
        None or False (the default): a constant plant; True: piezoelectric coefficient 1 ->
        1.05, stiffness 1 -> 0.95 over 2 s. Not with ``randomize``. Stored as a Drift or None.
    disturbance : bool, Disturbance or None
        The bench's disturbances (:class:`~piezo_env.disturbance.Disturbance`): amplifier
        output voltage noise (white, on the voltage the bender gets, held within the rails),
        band-limited tip vibration (on the deflection the sensor sees and the reward scores)
        and sensor quantisation (the measured deflection held within the sensor's range and
        rounded to its ADC's LSB). None or False (the default): none; True: the typical bench
        values (0.7 mV RMS, 0.08 um RMS in 8-80 Hz, 16 bits over +-2 strokes); a Disturbance
        sets each. The vibration's
        band must lie below 0.5 / dt. Stored as a Disturbance or None.
    """

    bender: str | BenderDatasheet = "PL140"
    n_elements: int = DEFAULT_ELEMENTS
    dt: float | None = None
    hysteresis: str | Hysteresis | None = "bouc-wen"
    creep: bool | Creep = False
    noise_bound: float = 1.0
    reference: str | np.ndarray | None = "random"
    reference_band: tuple[float, float] = DEFAULT_BAND
    preview: int | None = None
    deflection_limit: float | None = None
    damping_ratio: float = 0.02
    randomize: bool | DomainRandomization | None = None
    amplifier: bool | Amplifier | None = None
    sensor: bool | Sensor | None = None
    drift: bool | Drift | None = None
    disturbance: bool | Disturbance | None = None

    def __post_init__(self) -> None:
        sheet = get_datasheet(self.bender)
        require_int("n_elements", self.n_elements)
        object.__setattr__(self, "_dt_from_rule", self.dt is None)
        if self.dt is None:
            object.__setattr__(self, "dt", default_dt(sheet))
        require_number("dt (s; None for the bender's default)", self.dt, low=0.0, low_open=True)
        if not self._dt_from_rule:
            warn_if_resonance_aliases(sheet, self.dt)
        if not (self.hysteresis is None or isinstance(self.hysteresis, (str, Hysteresis))):
            raise ValueError(
                f"hysteresis must be one of {HYSTERESIS_NAMES}, None or a Hysteresis, "
                f"got {self.hysteresis!r}"
            )
        if isinstance(self.hysteresis, str):
            make_hysteresis(self.hysteresis, sheet.rated_voltage, dt=self.dt)
        if not isinstance(self.creep, (bool, Creep)):
            raise ValueError(f"creep must be a bool or a Creep, got {self.creep!r}")
        require_number("noise_bound (um)", self.noise_bound, low=0.0)
        reference = _check_reference(self.reference)
        object.__setattr__(self, "reference", reference)
        object.__setattr__(
            self, "reference_band", check_reference_band(self.reference_band, self.dt)
        )
        preview = _check_preview(self.preview, reference)
        object.__setattr__(self, "preview", preview)
        if self.deflection_limit is not None:
            require_number(
                "deflection_limit (um, or None)", self.deflection_limit, low=0.0, low_open=True
            )
        check_damping_ratio(self.damping_ratio)
        object.__setattr__(
            self, "randomize", _check_option("randomize", self.randomize, DomainRandomization)
        )
        object.__setattr__(self, "amplifier", _check_option("amplifier", self.amplifier, Amplifier))
        object.__setattr__(self, "sensor", _check_option("sensor", self.sensor, Sensor))
        object.__setattr__(self, "drift", _check_option("drift", self.drift, Drift))
        disturbance = _check_option("disturbance", self.disturbance, Disturbance)
        object.__setattr__(self, "disturbance", disturbance)
        if disturbance is not None:
            disturbance.check_sample_time(self.dt)
        if self.drift is not None and self.randomize is not None:
            raise ValueError(
                "drift and randomize cannot be combined: the observation bound is proven for "
                "a drift of the nominal plant; pass one of them"
            )

    @property
    def bench_options(self) -> bool:
        """Whether an amplifier, a sensor, a drift or a disturbance is on (the env then steps
        through them)."""
        return (
            self.amplifier is not None
            or self.sensor is not None
            or self.drift is not None
            or self.disturbance is not None
        )

    @classmethod
    def from_kwargs(cls, config: TaskConfig | None = None, /, **settings: Any) -> TaskConfig:
        """A config from keyword ``settings`` (on top of ``config`` if given).

        A new ``bender`` without a ``dt`` on top of a config whose dt the rule chose
        (:func:`piezo_env.default_dt`) gets the new bender's default dt; an explicit dt is kept.
        Raises TypeError naming the valid keywords when a keyword is not a field.
        """
        if config is not None and not isinstance(config, TaskConfig):
            raise TypeError(f"config must be a TaskConfig or None, got {type(config).__name__}")
        unknown = sorted(set(settings) - set(_FIELDS))
        if unknown:
            raise TypeError(
                f"unknown keyword argument(s) {', '.join(map(repr, unknown))}; "
                f"the task settings are {', '.join(_FIELDS)} (see piezo_env.TaskConfig)"
            )
        if config is None:
            return cls(**settings)
        rule_chose_dt = getattr(config, "_dt_from_rule", False)
        if "bender" in settings and "dt" not in settings and rule_chose_dt:
            settings = {**settings, "dt": None}
        return dataclasses.replace(config, **settings) if settings else config

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, TaskConfig):
            return NotImplemented
        return all(_same(getattr(self, f), getattr(other, f)) for f in _FIELDS)

    __hash__ = None  # equality compares reference arrays by value, so no hash


_FIELDS = tuple(f.name for f in dataclasses.fields(TaskConfig))


def _same(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and np.array_equal(a, b)
    return a == b


def _check_option(name: str, value: object, kind: type) -> Any:
    """None for None or False, the default ``kind()`` for True, or ``value`` if a ``kind``."""
    if value is None or value is False:
        return None
    if value is True:
        return kind()
    if isinstance(value, kind):
        return value
    raise ValueError(f"{name} must be True, False, None or a {kind.__name__}, got {value!r}")


def _check_reference(reference: object) -> str | np.ndarray | None:
    if reference is None:
        return None
    if isinstance(reference, str):
        if reference not in REFERENCE_NAMES:
            raise ValueError(
                f"unknown reference {reference!r}; use one of {REFERENCE_NAMES}, "
                "an array (um) or None (regulate to zero)"
            )
        return reference
    return check_reference_array(reference)


def _check_preview(preview: object, reference: object) -> int:
    if preview is None:
        return 0 if reference is None else 1
    require_int("preview", preview, minimum=0)
    if reference is None and preview > 0:
        raise ValueError(
            f"preview={preview} needs a reference: reference=None means regulation to zero "
            "deflection and the observation is the deflection alone; pass preview=0 (or omit "
            "it), or pass a reference to preview"
        )
    return int(preview)
