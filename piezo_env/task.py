"""What the single and the vector env share: the task settings, validated once, and their spaces.

:class:`TaskConfig` holds every setting of a PiezoBender-v0 task and its default, once; it is
frozen and validated at construction. :class:`BenderTask` builds the model from it, derives the
proven observation bound and makes the spaces and reference streams, so that ``PiezoBender-v0``
and its vector env cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces

from piezo_env.datasheet import BenderDatasheet, get_datasheet
from piezo_env.discrete import Creep
from piezo_env.fem import DEFAULT_ELEMENTS, check_damping_ratio
from piezo_env.hysteresis import Hysteresis, make_hysteresis
from piezo_env.reference import (
    DEFAULT_BAND,
    REFERENCE_NAMES,
    ReferenceStream,
    check_reference_array,
    check_reference_band,
)

if TYPE_CHECKING:
    from piezo_env.model import PiezoBenderModel
    from piezo_env.randomization import DomainRandomization, PlantDraw

__all__ = [
    "DEFAULT_HORIZON",
    "NOISE_BLOCK",
    "BenderTask",
    "TaskConfig",
    "check_max_episode_steps",
    "check_reset_options",
    "episode_reference",
    "observation_bound",
]

DEFAULT_HORIZON = 2000
"""Default episode length (steps): 2 s at dt = 1 ms."""

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
    dt : float
        Sample time (s), > 0: one env step.
    hysteresis : {"bouc-wen", "prandtl-ishlinskii", None} or Hysteresis
        Input hysteresis; None for a linear bender.
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
        0 < low <= high <= 0.25 / dt; the default (0.5, 20) is always accepted (its top is cut
        to 0.25 / dt at a coarser dt). Stored as a tuple of two floats.
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
        Stored as a DomainRandomization or None. The draw order and the proof of the
        observation bound over the whole range are in :mod:`piezo_env.randomization`.
    """

    bender: str | BenderDatasheet = "PL140"
    n_elements: int = DEFAULT_ELEMENTS
    dt: float = 1e-3
    hysteresis: str | Hysteresis | None = "bouc-wen"
    creep: bool | Creep = False
    noise_bound: float = 1.0
    reference: str | np.ndarray | None = "random"
    reference_band: tuple[float, float] = DEFAULT_BAND
    preview: int | None = None
    deflection_limit: float | None = None
    damping_ratio: float = 0.02
    randomize: bool | DomainRandomization | None = None

    def __post_init__(self) -> None:
        get_datasheet(self.bender)
        if (
            isinstance(self.n_elements, bool)
            or not isinstance(self.n_elements, (int, np.integer))
            or self.n_elements < 1
        ):
            raise ValueError(f"n_elements must be a positive integer, got {self.n_elements!r}")
        if not (isinstance(self.dt, numbers.Real) and math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {self.dt!r}")
        if not (self.hysteresis is None or isinstance(self.hysteresis, (str, Hysteresis))):
            raise ValueError(
                "hysteresis must be 'bouc-wen', 'prandtl-ishlinskii', None or a Hysteresis, "
                f"got {self.hysteresis!r}"
            )
        if isinstance(self.hysteresis, str):
            make_hysteresis(self.hysteresis, get_datasheet(self.bender).rated_voltage)
        if not isinstance(self.creep, (bool, Creep)):
            raise ValueError(f"creep must be a bool or a Creep, got {self.creep!r}")
        _check_noise_bound(self.noise_bound)
        reference = _check_reference(self.reference)
        object.__setattr__(self, "reference", reference)
        object.__setattr__(
            self, "reference_band", check_reference_band(self.reference_band, self.dt)
        )
        preview = _check_preview(self.preview, reference)
        object.__setattr__(self, "preview", preview)
        limit = self.deflection_limit
        if limit is not None and not (
            isinstance(limit, numbers.Real) and not isinstance(limit, bool) and limit > 0
        ):
            raise ValueError(f"deflection_limit must be > 0 um or None, got {limit!r}")
        check_damping_ratio(self.damping_ratio)
        object.__setattr__(self, "randomize", _check_randomize(self.randomize))

    @classmethod
    def from_kwargs(cls, config: TaskConfig | None = None, /, **settings: Any) -> TaskConfig:
        """A config from keyword ``settings`` (on top of ``config`` if given).

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


def _check_randomize(randomize: object) -> DomainRandomization | None:
    from piezo_env.randomization import DomainRandomization

    if randomize is None or randomize is False:
        return None
    if randomize is True:
        return DomainRandomization()
    if isinstance(randomize, DomainRandomization):
        return randomize
    raise ValueError(
        f"randomize must be True, False, None or a DomainRandomization, got {randomize!r}"
    )


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


class BenderTask:
    """The model, bound, spaces and reference streams of a validated :class:`TaskConfig`.

    ``model`` is the nominal plant. With ``config.randomize`` each episode's plant comes from
    :meth:`draw_plant`, and the observation bound covers every plant the spread can draw;
    references and rewards keep the nominal stroke (``stroke_um``), so that episodes on
    different plants score alike.
    """

    def __init__(self, config: TaskConfig) -> None:
        from piezo_env.model import PiezoBenderModel  # the model takes its defaults from here

        self.config = config
        self.model = PiezoBenderModel(
            config.bender,
            n_elements=config.n_elements,
            dt=config.dt,
            hysteresis=config.hysteresis,
            creep=config.creep,
            damping_ratio=config.damping_ratio,
        )
        self.noise_bound = float(config.noise_bound)
        self.preview = config.preview
        self.deflection_limit = config.deflection_limit
        self.reference = config.reference
        self.reference_band = config.reference_band
        self.randomization = config.randomize
        self.bound = observation_bound(self.model, self.noise_bound)
        if self.randomization is not None:
            from piezo_env.randomization import randomized_deflection_bound_um

            deflection = randomized_deflection_bound_um(self.model, self.randomization)
            self.bound = max(self.bound, _rounded_bound(deflection, self.noise_bound))
        if isinstance(self.reference, np.ndarray):  # fail at construction, not at the first reset
            self.reference_stream(self.reference, None)

    @property
    def stroke_um(self) -> float:
        """Nominal datasheet stroke (um): the scale of the references and the reward."""
        return self.model.stroke_um

    def draw_plant(self, rng: np.random.Generator) -> tuple[PiezoBenderModel, PlantDraw]:
        """The plant of a new episode and its drawn parameters (randomisation on only).

        Takes five uniforms from ``rng`` (:data:`piezo_env.randomization.DRAW_ORDER`) and
        rebuilds the model (FE, modes, matrix exponentials: about 1-5 ms).
        """
        from piezo_env.randomization import drawn_plant

        if self.randomization is None:
            raise ValueError("this task was made without randomize: its plant is fixed")
        draw = self.randomization.draw(rng, self.model.params.datasheet)
        return drawn_plant(self.model, draw), draw

    def observation_space(self) -> spaces.Box:
        """[measured y_t, r_t, r_{t+1} .. r_{t+preview}] (um), or the deflection alone."""
        size = 1 if self.reference is None else 2 + self.preview
        return spaces.Box(-self.bound, self.bound, (size,), np.float32)

    def action_space(self) -> spaces.Box:
        """Drive voltage (V) within the rated range."""
        u_max = self.model.rated_voltage
        return spaces.Box(-u_max, u_max, (1,), np.float32)

    def reference_stream(
        self, spec: object, rng: np.random.Generator | None, first: np.ndarray | None = None
    ) -> ReferenceStream:
        """The reference of one episode, drawn from ``rng`` (``first``: its rendered start)."""
        model = self.model
        return ReferenceStream(
            spec,
            dt=model.dt,
            stroke_um=model.stroke_um,
            bound=self.bound,
            rng=rng,
            first=first,
            band=self.reference_band,
        )


def check_max_episode_steps(max_episode_steps: object) -> int | None:
    """Episode limit as ``gym.make`` reads it: a positive int, or None / -1 for no limit.

    Returns the limit (steps) or None; raises ValueError for anything else.
    """
    if max_episode_steps is None or (
        isinstance(max_episode_steps, (int, np.integer))
        and not isinstance(max_episode_steps, bool)
        and max_episode_steps == -1
    ):
        return None
    if (
        isinstance(max_episode_steps, bool)
        or not isinstance(max_episode_steps, (int, np.integer))
        or max_episode_steps < 1
    ):
        raise ValueError(
            "max_episode_steps must be a positive integer (steps), or None or -1 for no time "
            f"limit (as in gymnasium.make), got {max_episode_steps!r}"
        )
    return int(max_episode_steps)


def observation_bound(model: PiezoBenderModel, noise_bound: float) -> float:
    """Finite bound (um) of every observation entry: deflection bound plus noise, rounded up."""
    return _rounded_bound(model.deflection_bound_um(), noise_bound)


def _rounded_bound(deflection_um: float, noise_bound: float) -> float:
    """Deflection bound plus noise (um), with a 0.1 % + 1 um margin, rounded up (float32)."""
    return float(np.float32(math.ceil((deflection_um + noise_bound) * 1.001 + 1.0)))


def episode_reference(options: dict[str, Any], made_with: object) -> object:
    """The reference spec of an episode: ``options["reference"]`` or the env's own.

    Raises ValueError when the options ask for a reference the env was not made for.
    """
    if "reference" not in options:
        return made_with
    spec = options["reference"]
    if made_with is None:
        raise ValueError(
            "this env was made with reference=None (no reference in the observation); "
            "make it with a reference to track one"
        )
    if spec is None:
        raise ValueError("this env was made with a reference; pass an array (um), not None")
    return spec


def check_reset_options(options: dict[str, Any], u_max: float) -> float:
    """Validate reset options; returns the initial voltage (V)."""
    unknown = set(options) - {"reference", "initial_voltage"}
    if unknown:
        raise ValueError(
            f"unknown reset options {sorted(unknown)}; "
            "valid: 'reference' (array, um) and 'initial_voltage' (V)"
        )
    voltage = float(options.get("initial_voltage", 0.0))
    if not (math.isfinite(voltage) and abs(voltage) <= u_max):
        raise ValueError(f"initial_voltage must be within [-{u_max}, {u_max}] V, got {voltage}")
    return voltage


def _check_noise_bound(noise_bound: object) -> None:
    if not (
        isinstance(noise_bound, numbers.Real)
        and not isinstance(noise_bound, bool)
        and math.isfinite(noise_bound)
        and noise_bound >= 0
    ):
        raise ValueError(f"noise_bound must be a finite number >= 0 (um), got {noise_bound!r}")


def _check_preview(preview: object, reference: object) -> int:
    if preview is None:
        return 0 if reference is None else 1
    if isinstance(preview, bool) or not isinstance(preview, (int, np.integer)) or preview < 0:
        raise ValueError(f"preview must be an integer >= 0 (samples), got {preview!r}")
    if reference is None and preview > 0:
        raise ValueError(
            f"preview={preview} needs a reference: reference=None means regulation to zero "
            "deflection and the observation is the deflection alone; pass preview=0 (or omit "
            "it), or pass a reference to preview"
        )
    return int(preview)
