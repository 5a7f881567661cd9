"""Piezoelectric bender physics and the PiezoBender-v0 Gymnasium environment.

``import piezo_env`` registers ``PiezoBender-v0``; the module-prefixed id imports the package on
demand, so ``gymnasium.make("piezo_env:PiezoBender-v0")`` works without a prior import. The
natively batched vector env is the id's vector entry point, reached the same way:
``gymnasium.make_vec("piezo_env:PiezoBender-v0", num_envs=N,
vectorization_mode="vector_entry_point")``. The task settings and their defaults live in
:class:`TaskConfig`; the default sample time follows the bender's first resonance
(:func:`default_dt`: 1 ms for the PL140, finer for the faster benders). ``randomize=True``
(or a :class:`DomainRandomization`) draws the plant from the datasheet tolerances at each
reset. The bench options (:class:`Amplifier`,
:class:`Sensor`, :class:`Drift`, :class:`Disturbance`, ``hysteresis="rate-dependent"``) make the
plant behave like a real bench; all are off by default.

The package is light to import: registering the ids needs only
``gymnasium.envs.registration``, and every public name below is imported from its submodule on
first access (PEP 562), so ``import piezo_env.operators`` (what a saved identified model needs)
does not pull in the env, the finite elements or scipy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from gymnasium.envs.registration import register, registry

if TYPE_CHECKING:
    from piezo_env.amplifier import Amplifier
    from piezo_env.datasheet import CATALOGUE, BenderDatasheet, get_datasheet
    from piezo_env.discrete import Creep
    from piezo_env.disturbance import Disturbance
    from piezo_env.drift import Drift
    from piezo_env.env import PiezoBenderEnv
    from piezo_env.hysteresis import (
        BoucWen,
        NoHysteresis,
        PrandtlIshlinskii,
        RateDependentPrandtlIshlinskii,
    )
    from piezo_env.model import BenderSimulator, PiezoBenderModel
    from piezo_env.parameters import BenderParameters, bender_parameters
    from piezo_env.randomization import DomainRandomization
    from piezo_env.sampling import DT_LADDER, default_dt
    from piezo_env.sensor import Sensor
    from piezo_env.task import TaskConfig

__all__ = [
    "CATALOGUE",
    "DT_LADDER",
    "Amplifier",
    "BenderDatasheet",
    "BenderParameters",
    "BenderSimulator",
    "BoucWen",
    "Creep",
    "Disturbance",
    "DomainRandomization",
    "Drift",
    "NoHysteresis",
    "PiezoBenderEnv",
    "PiezoBenderModel",
    "PrandtlIshlinskii",
    "RateDependentPrandtlIshlinskii",
    "Sensor",
    "TaskConfig",
    "bender_parameters",
    "default_dt",
    "get_datasheet",
]

_HOMES = {
    "Amplifier": "piezo_env.amplifier",
    "Drift": "piezo_env.drift",
    "RateDependentPrandtlIshlinskii": "piezo_env.hysteresis",
    "Sensor": "piezo_env.sensor",
    "CATALOGUE": "piezo_env.datasheet",
    "BenderDatasheet": "piezo_env.datasheet",
    "get_datasheet": "piezo_env.datasheet",
    "Creep": "piezo_env.discrete",
    "Disturbance": "piezo_env.disturbance",
    "PiezoBenderEnv": "piezo_env.env",
    "BoucWen": "piezo_env.hysteresis",
    "NoHysteresis": "piezo_env.hysteresis",
    "PrandtlIshlinskii": "piezo_env.hysteresis",
    "BenderSimulator": "piezo_env.model",
    "PiezoBenderModel": "piezo_env.model",
    "BenderParameters": "piezo_env.parameters",
    "bender_parameters": "piezo_env.parameters",
    "DomainRandomization": "piezo_env.randomization",
    "DT_LADDER": "piezo_env.sampling",
    "default_dt": "piezo_env.sampling",
    "TaskConfig": "piezo_env.task",
}
"""Submodule that defines each public name (imported on first access)."""

_DEFAULT_HORIZON = 2000
"""``max_episode_steps`` of the registered id; equals ``piezo_env.config.DEFAULT_HORIZON`` (a test
checks it), written here so that registering does not import the task module."""


def __getattr__(name: str) -> Any:
    """Import a public name from its submodule on first access (PEP 562)."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'piezo_env' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if "PiezoBender-v0" not in registry:
    register(
        id="PiezoBender-v0",
        entry_point="piezo_env.env:PiezoBenderEnv",
        vector_entry_point="piezo_env.vector_env:PiezoBenderVectorEnv",
        max_episode_steps=_DEFAULT_HORIZON,
    )
