"""Piezoelectric bender physics and the PiezoBender-v0 Gymnasium environment.

``import piezo_env`` registers ``PiezoBender-v0``; the module-prefixed id imports the package on
demand, so ``gymnasium.make("piezo_env:PiezoBender-v0")`` works without a prior import. The
natively batched vector env is the id's vector entry point, reached the same way:
``gymnasium.make_vec("piezo_env:PiezoBender-v0", num_envs=N,
vectorization_mode="vector_entry_point")``. The task settings and their defaults live in
:class:`TaskConfig`.
"""

from gymnasium.envs.registration import register, registry

from piezo_env.datasheet import CATALOGUE, BenderDatasheet, get_datasheet
from piezo_env.discrete import Creep
from piezo_env.env import PiezoBenderEnv
from piezo_env.hysteresis import BoucWen, NoHysteresis, PrandtlIshlinskii
from piezo_env.model import BenderSimulator, PiezoBenderModel
from piezo_env.parameters import BenderParameters, bender_parameters
from piezo_env.task import DEFAULT_HORIZON, TaskConfig

__all__ = [
    "CATALOGUE",
    "BenderDatasheet",
    "BenderParameters",
    "BenderSimulator",
    "BoucWen",
    "Creep",
    "NoHysteresis",
    "PiezoBenderEnv",
    "PiezoBenderModel",
    "PrandtlIshlinskii",
    "TaskConfig",
    "bender_parameters",
    "get_datasheet",
]

if "PiezoBender-v0" not in registry:
    register(
        id="PiezoBender-v0",
        entry_point="piezo_env.env:PiezoBenderEnv",
        vector_entry_point="piezo_env.vector_env:PiezoBenderVectorEnv",
        max_episode_steps=DEFAULT_HORIZON,
    )
