"""The interface every controller implements, and the statistics it keeps.

A controller is state (observer, previous plan, integrator) plus a step. The loop is the same
for all of them, classical, model-based or a trained policy::

    obs, info = env.reset(seed=0)
    controller.reset(obs)
    while True:
        obs, reward, terminated, truncated, info = env.step(controller.act(obs))

``act`` validates the observation (NaN or a wrong shape raise ValueError naming it), times the
step, and returns one float32 voltage inside the drive range. A solver that fails never stops
the loop: the controller falls back to a safe input and counts it in :attr:`Controller.stats`.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from controllers.task import ControlTask

__all__ = ["Controller", "ControllerStats"]

_clock = time.perf_counter


@dataclass
class ControllerStats:
    """What a controller did since its last reset (data for benchmarks, not log lines).

    Attributes
    ----------
    compute_s : list of float
        Wall time of each ``act`` call (s).
    status : collections.Counter
        Solver status per step (e.g. ``"solved"``, ``"max-iter"``), counted.
    iterations : list of int
        Solver iterations per step (empty for controllers without a solver).
    inverse : collections.Counter
        Status of the nonlinearity inverse per step (``"ok"``, ``"out-of-range"``,
        ``"non-monotone"``), for controllers that convert z to volts.
    fallbacks : int
        Steps where the controller used its fallback input instead of a solution.
    saturated : int
        Steps whose computed voltage was clipped to the drive range.
    observer_fallback_step : int or None
        Step (from 0) at which a model-based controller's observer bank detected a runaway loop
        and fell back to its most robust filter (:class:`controllers.observer.ObserverBank`);
        None if it did not.
    """

    compute_s: list[float] = field(default_factory=list)
    status: Counter = field(default_factory=Counter)
    iterations: list[int] = field(default_factory=list)
    inverse: Counter = field(default_factory=Counter)
    fallbacks: int = 0
    saturated: int = 0
    observer_fallback_step: int | None = None

    def summary(self) -> dict[str, Any]:
        """Median, p99 and max compute time (s), status counts, mean and worst solver
        iterations per step, and fallbacks."""
        times = np.asarray(self.compute_s)
        values = np.quantile(times, [0.5, 0.99, 1.0]) if times.size else np.zeros(3)
        quantiles = dict(zip(("median_s", "p99_s", "max_s"), values, strict=True))
        return {
            **{k: float(v) for k, v in quantiles.items()},
            "steps": int(times.size),
            "status": dict(self.status),
            "inverse": dict(self.inverse),
            "mean_iterations": float(np.mean(self.iterations)) if self.iterations else 0.0,
            "max_iterations": int(max(self.iterations)) if self.iterations else 0,
            "fallbacks": self.fallbacks,
            "saturated": self.saturated,
            "observer_fallback_step": self.observer_fallback_step,
        }


class Controller:
    """Base class: validated observation in, one clipped voltage out, timed.

    Subclasses implement :meth:`_reset` and :meth:`_act`; they read ``self.task`` for the
    sample time, drive range and preview layout, and record solver facts in ``self.stats``.

    Parameters
    ----------
    task : ControlTask
        What the controller knows of the task.
    """

    name: ClassVar[str] = "controller"
    stats_type: ClassVar[type[ControllerStats]] = ControllerStats
    """The class of :attr:`stats` (a subclass may record more)."""

    def __init__(self, task: ControlTask) -> None:
        self.task = task
        self.stats = self.stats_type()
        self._u_max = task.u_max
        bound = task.observation_bound_um
        self._observation_bound = math.inf if bound is None else bound  # the fused steps' check

    def reset(self, observation: Any) -> None:
        """Start an episode from its first observation (um); clears :attr:`stats`."""
        obs = self.task.check_observation(observation)
        self.stats = self.stats_type()
        self._reset(obs)

    def act(self, observation: Any) -> np.ndarray:
        """Voltage (V) for this observation: shape (1,), float32, inside the drive range."""
        start = _clock()
        u = float(self._act(self.task.check_observation(observation)))
        u_max = self._u_max
        if not -u_max <= u <= u_max:
            if u != u:  # NaN: a controller bug, never a voltage
                raise RuntimeError(f"{self.name} computed a NaN voltage")
            u = u_max if u > 0 else -u_max
            self.stats.saturated += 1
        action = np.empty(1, dtype=np.float32)  # cheaper than np.array([u], ...); same bits
        action[0] = u
        self.stats.compute_s.append(_clock() - start)
        return action

    def describe(self) -> dict[str, Any]:
        """JSON-safe settings and derived facts (gains, margins, horizon) for reports; under
        ``"native"``, what runs each generated function (:meth:`native_code`)."""
        return {"name": self.name, "native": self.native_code()}

    def native_code(self) -> dict[str, dict[str, Any]]:
        """Generated function name -> the record of its native build (JSON-safe).

        Collected from the prediction model (``self.model``: the NLS inverse), the NMPC
        horizon (``self.horizon``) and the estimators (``self.observer``, ``self._gain``: the
        step kernels), whichever this controller holds; each record says whether
        generated C or a fallback (numpy, casadi's virtual machine) runs, and why (see
        :class:`controllers.native.codegen.NativeBuild`). Empty for a controller without
        generated code.
        """
        owners = (
            getattr(self, "model", None),
            getattr(self, "horizon", None),
            getattr(self, "observer", None),
            getattr(self, "_gain", None),
        )
        return {
            build.function: build.to_dict()
            for owner in owners
            for build in getattr(owner, "native", ())
        }

    def _reset(self, observation: np.ndarray) -> None:
        raise NotImplementedError

    def _act(self, observation: np.ndarray) -> float:
        raise NotImplementedError
