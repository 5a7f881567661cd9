"""What the single and the vector env share: the validated task settings and their spaces.

:class:`BenderTask` builds the model from the environment's keyword arguments, checks every
setting once, derives the proven observation bound and makes the spaces and reference streams,
so that ``PiezoBender-v0`` and its vector env cannot drift apart.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
from gymnasium import spaces

from piezo_env.datasheet import BenderDatasheet
from piezo_env.discrete import Creep
from piezo_env.fem import DEFAULT_ELEMENTS
from piezo_env.hysteresis import Hysteresis
from piezo_env.model import PiezoBenderModel
from piezo_env.reference import ReferenceStream

__all__ = [
    "DEFAULT_HORIZON",
    "NOISE_BLOCK",
    "BenderTask",
    "check_reset_options",
    "episode_reference",
    "observation_bound",
]

DEFAULT_HORIZON = 2000
"""Default episode length (steps): 2 s at dt = 1 ms."""

NOISE_BLOCK = 1024
"""Sensor-noise samples drawn at a time. The single and the vector env must agree on it: it
fixes when each draws from its generator."""


class BenderTask:
    """Validated settings of a PiezoBender-v0 task (keyword arguments as the env's)."""

    def __init__(
        self,
        *,
        bender: str | BenderDatasheet = "PL140",
        n_elements: int = DEFAULT_ELEMENTS,
        dt: float = 1e-3,
        hysteresis: str | Hysteresis | None = "bouc-wen",
        creep: bool | Creep = False,
        noise_bound: float = 1.0,
        reference: str | np.ndarray | None = "random",
        preview: int = 0,
        deflection_limit: float | None = None,
        damping_ratio: float = 0.02,
    ) -> None:
        if deflection_limit is not None and not deflection_limit > 0:
            raise ValueError(f"deflection_limit must be > 0 um or None, got {deflection_limit!r}")
        self.model = PiezoBenderModel(
            bender,
            n_elements=n_elements,
            dt=dt,
            hysteresis=hysteresis,
            creep=creep,
            damping_ratio=damping_ratio,
        )
        self.noise_bound = _check_noise_bound(noise_bound)
        self.preview = _check_preview(preview)
        self.deflection_limit = deflection_limit
        self.reference = reference
        self.bound = observation_bound(self.model, self.noise_bound)
        if reference is not None:  # fail at construction, not at the first reset
            self.reference_stream(reference, np.random.default_rng(0))

    def observation_space(self) -> spaces.Box:
        """[measured deflection, r_t, r_t+1 .. r_t+preview] (um), or the deflection alone."""
        size = 1 if self.reference is None else 2 + self.preview
        return spaces.Box(-self.bound, self.bound, (size,), np.float32)

    def action_space(self) -> spaces.Box:
        """Drive voltage (V) within the rated range."""
        u_max = self.model.rated_voltage
        return spaces.Box(-u_max, u_max, (1,), np.float32)

    def reference_stream(
        self, spec: object, rng: np.random.Generator, first: np.ndarray | None = None
    ) -> ReferenceStream:
        """The reference of one episode, drawn from ``rng`` (``first``: its rendered start)."""
        model = self.model
        return ReferenceStream(
            spec, dt=model.dt, stroke_um=model.stroke_um, bound=self.bound, rng=rng, first=first
        )


def observation_bound(model: PiezoBenderModel, noise_bound: float) -> float:
    """Finite bound (um) of every observation entry: deflection bound plus noise, rounded up."""
    return float(np.float32(math.ceil((model.deflection_bound_um() + noise_bound) * 1.001 + 1.0)))


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


def _check_noise_bound(noise_bound: float) -> float:
    if not (
        isinstance(noise_bound, numbers.Real) and math.isfinite(noise_bound) and noise_bound >= 0
    ):
        raise ValueError(f"noise_bound must be a finite number >= 0 (um), got {noise_bound!r}")
    return float(noise_bound)


def _check_preview(preview: int) -> int:
    if isinstance(preview, bool) or not isinstance(preview, (int, np.integer)) or preview < 0:
        raise ValueError(f"preview must be an integer >= 0 (samples), got {preview!r}")
    return int(preview)
