"""A closed-loop episode that records the controller's internals after each step, so that two
paths of the same controller (compiled and numpy) can be compared to the bit."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

import controllers


def recorded_episode(
    controller: Any, env: Any, reference: np.ndarray, steps: int, row: Callable[[Any], Any]
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Volts, ``row(controller)`` after each step (stacked), and the stats' summary of one
    episode (seed 0, at most ``steps`` steps)."""
    record = []
    act = controller.act

    def recorded(observation):
        action = act(observation)
        record.append(row(controller))
        return action

    controller.act = recorded
    run = controllers.run_episode(env, controller, seed=0, reference=reference, max_steps=steps)
    return run.voltage_V, np.array(record), controller.stats.summary()
