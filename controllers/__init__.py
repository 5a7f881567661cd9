"""Tracking controllers for the piezo bender, on the identified model or the true plant.

- :func:`make` builds a controller by name (``"pid"``, ``"pid-notch"``, ``"pid-ff"``,
  ``"mpc"``, ``"nmpc"``, ``"nmpc-ipopt"``) on a :class:`PredictionModel`: the identified
  Hammerstein model, or ``"plant"`` for the oracle.
- :func:`run_episode` runs any controller (``reset(obs)``, ``act(obs)``, ``stats``) for one
  episode of ``PiezoBender-v0`` and returns an :class:`Episode` with its metrics.

Controllers see only the observation ``[y_t, r_t, r_t+1 .. r_t+P]`` (um); the action a_t is
scored against r_t+1, so a controller at step t aims at r_t+1 onwards.
"""

from controllers.base import Controller, ControllerStats
from controllers.episode import Episode, run_episode
from controllers.metrics import tracking_metrics
from controllers.prediction import InverseResult, PredictionModel
from controllers.registry import CONTROLLERS, make, prediction_model
from controllers.task import ControlTask

__all__ = [
    "CONTROLLERS",
    "ControlTask",
    "Controller",
    "ControllerStats",
    "Episode",
    "InverseResult",
    "PredictionModel",
    "make",
    "prediction_model",
    "run_episode",
    "tracking_metrics",
]
