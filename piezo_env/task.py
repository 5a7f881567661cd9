"""What the single and the vector env share: the task built from its settings, and its spaces.

:class:`BenderTask` builds the model from a :class:`~piezo_env.config.TaskConfig` (the settings,
each default held once), derives the proven observation bound and makes the spaces and
reference streams, so that ``PiezoBender-v0`` and its vector env cannot drift apart. With domain
randomisation it also builds each episode's plant (:func:`drawn_plant`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium import spaces

from piezo_env.config import DEFAULT_HORIZON, NOISE_BLOCK, TaskConfig
from piezo_env.model import PiezoBenderModel
from piezo_env.randomization import (
    PlantDraw,
    randomized_deflection_bound_um,
    scale_hysteresis,
    single_blas_thread,
)
from piezo_env.reference import ReferenceStream

__all__ = [
    "DEFAULT_HORIZON",
    "NOISE_BLOCK",
    "BenderTask",
    "TaskConfig",
    "check_max_episode_steps",
    "check_reset_options",
    "drawn_plant",
    "episode_reference",
    "observation_bound",
]



class BenderTask:
    """The model, bound, spaces and reference streams of a validated :class:`TaskConfig`.

    ``model`` is the nominal plant. With ``config.randomize`` each episode's plant comes from
    :meth:`draw_plant`, and the observation bound covers every plant the spread can draw;
    references and rewards keep the nominal stroke (``stroke_um``), so that episodes on
    different plants score alike.
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
        self.bound = observation_bound(self.model, self.noise_bound)
        if self.randomization is not None:
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


def drawn_plant(nominal: PiezoBenderModel, draw: PlantDraw) -> PiezoBenderModel:
    """The plant of ``draw``: the nominal model's elements, dt and creep, drawn parameters.

    Built with one BLAS thread: the eigen-decomposition and the per-mode matrix exponentials
    are tiny, and multi-threaded OpenBLAS stalls on them (measured on 2 cores: median 9.7 ms,
    p90 220 ms per plant, against 1.4 ms and 9.6 ms single-threaded).
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
