"""A controller of your own in the benchmark: static-gain feedforward plus integral action.

It follows the controller protocol (:mod:`controllers.protocol`): a factory called as
``factory(model, env, **options)`` returns an object with ``reset(observation)`` and
``act(observation) -> (1,) volts``. Run it beside the built-ins, from the project folder::

    piezo benchmark --model docs/identify/model --policies none \\
        --controllers mpc,examples.feedforward_pi:FeedforwardPI \\
        --references sine-10Hz,sine-50Hz --plants nominal,stiffness+20%

The row is named ``FeedforwardPI`` (or ``--controllers mine=examples.feedforward_pi:...``), and
``--option FeedforwardPI.ki=0.3`` sets an option.
"""

from __future__ import annotations

import numpy as np


class FeedforwardPI:
    """Static-gain feedforward of r_t+1 plus an integral on the error; clipped to the drive.

    Parameters
    ----------
    model : controllers.PredictionModel
        The model the benchmark runs on; only its DC gain (um per volt) is used here.
    env : gymnasium.Env
        The nominal env, read once for the drive range.
    ki : float
        Integral gain (V / (um s)).
    """

    def __init__(self, model, env, *, ki: float = 0.5) -> None:
        a, b, c = model.a, model.b, model.c
        self.dc_gain = float(c[0] @ np.linalg.solve(np.eye(a.shape[0]) - a, b[:, 0]))
        self.u_max = float(env.action_space.high[0])
        self.dt = float(env.unwrapped.model.dt)
        self.ki = float(ki)
        self.integral = 0.0

    def reset(self, observation: np.ndarray) -> None:
        self.integral = 0.0

    def act(self, observation: np.ndarray) -> np.ndarray:
        y, r_next = float(observation[0]), float(observation[2])
        self.integral += self.ki * self.dt * (r_next - y)
        u = r_next / self.dc_gain + self.integral
        u = min(max(u, -self.u_max), self.u_max)
        self.integral = u - r_next / self.dc_gain  # anti-windup: the integral holds what is used
        return np.array([u], dtype=np.float32)

    def describe(self) -> dict:
        return {"name": "FeedforwardPI", "ki": self.ki, "dc_gain_um_per_V": self.dc_gain}
