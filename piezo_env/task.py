"""What the single and the vector env share: the task built from its settings, and its spaces.

:class:`BenderTask` builds the model from a :class:`~piezo_env.config.TaskConfig` (the settings,
each default held once), derives the proven observation bound and makes the spaces and
reference streams, so that ``PiezoBender-v0`` and its vector env cannot drift apart. With domain
randomisation it also builds each episode's plant (:func:`drawn_plant`).
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
from gymnasium import spaces

from piezo_env.blas import single_blas_thread
from piezo_env.checks import require_int, require_number
from piezo_env.config import DEFAULT_HORIZON, NOISE_BLOCK, TaskConfig
from piezo_env.disturbance import VibrationFilter, vibration_filter
from piezo_env.drift import DriftPlan, drift_deflection_bound_um
from piezo_env.memo import ContentCache
from piezo_env.model import PiezoBenderModel
from piezo_env.randomization import PlantDraw, scale_hysteresis
from piezo_env.randomized_bound import randomized_deflection_bound_um
from piezo_env.reference import ReferenceStream

__all__ = [
    "DEFAULT_HORIZON",
    "NOISE_BLOCK",
    "BenderTask",
    "TaskAttributes",
    "TaskConfig",
    "check_max_episode_steps",
    "check_reset_options",
    "drawn_plant",
    "episode_reference",
    "observation_bound",
]


class BenderTask:
    """The model, bound, spaces and reference streams of a validated :class:`TaskConfig`.

    ``model`` is the nominal plant; with ``config.drift``, ``drift_plan`` holds the step
    matrices of its drift (:class:`piezo_env.drift.DriftPlan`), and the bound covers the
    drifted plant too. With ``config.randomize`` each episode's plant comes from
    :meth:`draw_plant`, and the observation bound covers every plant the spread can draw;
    references and rewards keep the nominal stroke (``stroke_um``), so that episodes on
    different plants score alike. With a vibration in ``config.disturbance``, ``vibration``
    holds its filter (:func:`piezo_env.disturbance.vibration_filter`) and the bound adds its
    proven peak to the sensor noise's (the amplifier's voltage noise stays within the rails, so
    it adds nothing); with quantisation, ``sensor_range`` is the ADC's range (um), and the bound
    is at least that.
    """

    def __init__(self, config: TaskConfig) -> None:
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
        self.vibration: VibrationFilter | None = None
        beyond = self.noise_bound  # what the observation adds to the deflection bound (um)
        disturbance = config.disturbance
        if disturbance is not None and disturbance.vibration_um_rms > 0:
            self.vibration = vibration_filter(
                disturbance.vibration_um_rms, disturbance.vibration_band_Hz, config.dt
            )
            beyond = self.noise_bound + self.vibration.peak_um
        self.bound = observation_bound(self.model, beyond)
        self.sensor_range = (
            None if disturbance is None else disturbance.sensor_range(self.model.stroke_um)
        )
        self.drift_plan = None
        if config.drift is not None:
            self.drift_plan = DriftPlan(self.model, config.drift)
            deflection = _drift_bounds.get_or_compute(_drift_parts(config), self._drift_bound)
            self.bound = max(self.bound, _rounded_bound(deflection, beyond))
        if self.randomization is not None:
            deflection = randomized_deflection_bound_um(self.model, self.randomization)
            self.bound = max(self.bound, _rounded_bound(deflection, beyond))
        if self.sensor_range is not None:  # the quantised readings reach +-sensor_range
            self.bound = max(self.bound, float(np.float32(math.ceil(self.sensor_range))))
        if isinstance(self.reference, np.ndarray):  # fail at construction, not at the first reset
            self.reference_stream(self.reference, None)

    def _drift_bound(self) -> float:
        """The drifting plant's proven deflection bound (um)."""
        with single_blas_thread():  # tiny matrices: threads only stall (see drawn_plant)
            return drift_deflection_bound_um(self.model, self.drift_plan)

    @property
    def stroke_um(self) -> float:
        """Nominal datasheet stroke (um): the scale of the references and the reward."""
        return self.model.stroke_um

    def draw_plant(self, rng: np.random.Generator) -> tuple[PiezoBenderModel, PlantDraw]:
        """The plant of a new episode and its drawn parameters (randomisation on only).

        Takes five uniforms from ``rng`` (:data:`piezo_env.randomization.DRAW_ORDER`) and
        rebuilds the model (FE, modes, matrix exponentials: about 1-5 ms).
        """
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


class TaskAttributes:
    """The attributes the single and the vector env read from their task (a mixin).

    :meth:`_adopt_task` sets ``config`` (:class:`TaskConfig`), ``task`` (:class:`BenderTask`),
    ``model`` (the nominal plant; the single env replaces it by each episode's drawn plant
    under randomisation), ``noise_bound`` (um), ``preview``, ``deflection_limit`` (um or None)
    and ``bound`` (um, the observation bound).
    """

    def _adopt_task(self, config: TaskConfig | None, settings: dict[str, Any]) -> None:
        """Build the task of ``config`` with keyword ``settings`` on top; copy its attributes."""
        self.config = TaskConfig.from_kwargs(config, **settings)
        self.task = BenderTask(self.config)
        self.model = self.task.model
        self.noise_bound = self.task.noise_bound
        self.preview = self.task.preview
        self.deflection_limit = self.task.deflection_limit
        self.bound = self.task.bound
        self._reference_spec = self.config.reference
        self._u_max = self.model.rated_voltage


DRIFT_BOUNDS_KEPT = 16
"""Drift deflection bounds kept in a process (:func:`_drift_parts`): a benchmark worker meets
one drifting setting (the bender at its dt) and builds it once per controller; 16 leaves room
for a process that builds several benders and drifts (a test run). Each takes 0.3 s on the
PL140 and about 1 s on the PL127 at 0.25 ms."""

_drift_bounds = ContentCache(DRIFT_BOUNDS_KEPT)


def _drift_parts(config: TaskConfig) -> list[Any]:
    """The settings the drifting plant and its bound are built from: the bound is kept by
    their content (:class:`piezo_env.memo.ContentCache`; a setting whose content it cannot see
    computes the bound afresh)."""
    return [
        config.bender,
        config.n_elements,
        config.dt,
        config.hysteresis,
        config.creep,
        config.damping_ratio,
        config.drift,
    ]


def check_max_episode_steps(max_episode_steps: object) -> int | None:
    """Episode limit as ``gym.make`` reads it: a positive int, or None / -1 for no limit.

    Returns the limit (steps) or None; raises ValueError for anything else.
    """
    if max_episode_steps is None or (
        isinstance(max_episode_steps, numbers.Integral) and max_episode_steps == -1
    ):
        return None
    try:
        return require_int("max_episode_steps (steps)", max_episode_steps)
    except ValueError as error:
        raise ValueError(
            f"{error}; pass None or -1 for no time limit (as in gymnasium.make)"
        ) from None


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
    return require_number(
        "initial_voltage (V)", options.get("initial_voltage", 0.0), low=-u_max, high=u_max
    )


def drawn_plant(nominal: PiezoBenderModel, draw: PlantDraw) -> PiezoBenderModel:
    """The plant of ``draw``: the nominal model's elements, dt and creep, drawn parameters.

    Built with one BLAS thread (:mod:`piezo_env.blas`): the eigen-decomposition and the
    per-mode matrix exponentials are tiny, and multi-threaded OpenBLAS stalls on them.
    """
    hysteresis = scale_hysteresis(nominal.hysteresis, draw.hysteresis_scale, nominal.rated_voltage)
    with single_blas_thread():
        return PiezoBenderModel(
            draw.datasheet(nominal.params.datasheet),
            n_elements=nominal.beam.n_elements,
            dt=nominal.dt,
            hysteresis=hysteresis,
            creep=nominal.creep if nominal.creep is not None else False,
            damping_ratio=draw.damping_ratio,
        )
