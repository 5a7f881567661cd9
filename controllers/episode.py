"""One closed-loop episode, the same loop for every controller."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controllers.metrics import tracking_metrics

__all__ = ["Episode", "run_episode"]


@dataclass(frozen=True)
class Episode:
    """Record of one episode; sample t is the outcome of action a_t.

    Attributes
    ----------
    deflection_um : ndarray
        True tip deflection after each action (um).
    measured_um : ndarray
        Measured deflection the controller saw next (um, with sensor noise).
    reference_um : ndarray
        The reference sample each action is scored against, r_t+1 (um).
    voltage_V : ndarray
        Applied voltage (V).
    saturated : ndarray of bool
        Voltage at the drive limit (computed there or clipped by the amplifier).
    compute_s : ndarray
        Controller compute time of each action (s).
    reward : ndarray
        The env's reward of each action.
    metrics : dict
        :func:`controllers.metrics.tracking_metrics` of the episode, and
        ``observer_fallback_step``: the step at which the controller's observer bank fell back
        to its most robust filter (None if it did not, or has no bank), and
        ``set_invalidated_step``: the step at which the data invalidated the controller's
        model at the sensor's noise bound (None if they did not, or it learns no gain;
        :attr:`controllers.predictive.PredictiveController.set_invalidated_step`).
    controller : dict
        The controller's :meth:`~controllers.base.Controller.describe` and stats summary.
    """

    deflection_um: np.ndarray
    measured_um: np.ndarray
    reference_um: np.ndarray
    voltage_V: np.ndarray
    saturated: np.ndarray
    compute_s: np.ndarray
    reward: np.ndarray
    metrics: dict[str, Any] = field(default_factory=dict)
    controller: dict[str, Any] = field(default_factory=dict)


def run_episode(
    env: Any,
    controller: Any,
    *,
    seed: int,
    reference: np.ndarray | None = None,
    max_steps: int | None = None,
    stroke_um: float | None = None,
    describe: bool = True,
) -> Episode:
    """Run ``controller`` on ``env`` for one episode.

    Parameters
    ----------
    env : gymnasium.Env
        A ``PiezoBender-v0`` env (wrapped or not) with a reference in its observation.
    controller : object
        Anything that follows the controller protocol: ``reset(observation)`` and
        ``act(observation) -> (1,) volts``; ``stats`` (with ``fallbacks``) and ``describe()``
        are optional. The compute time of every ``act`` call is measured here, the same way
        for every controller.
    seed : int
        Seed of the env reset (noise and named references).
    reference : ndarray, optional
        Reference of this episode (um), passed as ``reset(options={"reference": ...})``.
    max_steps : int, optional
        Stop after this many steps (default: when the env truncates or terminates).
    stroke_um : float, optional
        One-sided stroke (um) the percentages refer to (default: the env's task stroke, the
        datasheet's; a benchmark over several plants passes the nominal one so that all share
        a scale).
    describe : bool
        Record the controller's ``describe()`` in :attr:`Episode.controller` (with the stats
        summary, which is always there). A caller that describes the controller once for many
        episodes, as the benchmark does, passes False: a description costs milliseconds.

    Returns
    -------
    Episode

    Raises
    ------
    ValueError
        If the controller was made for another sample time than the env's (its ``task.dt``):
        its model and gains mean per-sample things.
    """
    task_dt = getattr(getattr(controller, "task", None), "dt", None)
    env_dt = float(env.unwrapped.model.dt)
    if isinstance(task_dt, float) and not math.isclose(task_dt, env_dt, rel_tol=1e-9):
        raise ValueError(
            f"the controller was made for dt = {task_dt:g} s and the env steps every {env_dt:g} "
            "s: make the controller on an env of this sample time, or make this env with "
            f"dt={task_dt:g} (a bender's default dt follows its datasheet's resonance, so a "
            "bender of another resonance gets another default)"
        )
    options = None if reference is None else {"reference": np.asarray(reference, float)}
    obs, _ = env.reset(seed=seed, options=options)
    controller.reset(obs)
    arrays = _loop(env, controller, obs, max_steps)
    stats = getattr(controller, "stats", None)
    # The task's (nominal) stroke: with domain randomisation the plant's own changes per reset.
    stroke = float(env.unwrapped.task.stroke_um) if stroke_um is None else float(stroke_um)
    metrics = tracking_metrics(
        deflection_um=arrays["y"],
        reference_um=arrays["r"],
        voltage_v=arrays["u"],
        saturated=arrays["sat"],
        compute_s=arrays["compute"],
        stroke_um=stroke,
        fallbacks=int(getattr(stats, "fallbacks", 0)),
        dt=float(env.unwrapped.model.dt),
    )
    # A model-based controller's observer that fell back to its most robust filter: when.
    metrics["observer_fallback_step"] = getattr(stats, "observer_fallback_step", None)
    # A controller with exact sets of its model's gain: when the data invalidated the model.
    metrics["set_invalidated_step"] = getattr(controller, "set_invalidated_step", None)
    # The worst step's solver iterations (None without a solver): what sizes a real-time
    # target's worst case (a DAQP iteration adds or removes one active constraint).
    iterations = getattr(stats, "iterations", None)
    metrics["solver_iterations_max"] = int(max(iterations)) if iterations else None
    described = getattr(controller, "describe", dict)() if describe else {}
    summary = stats.summary() if hasattr(stats, "summary") else {}
    return Episode(
        deflection_um=arrays["y"],
        measured_um=arrays["m"],
        reference_um=arrays["r"],
        voltage_V=arrays["u"],
        saturated=arrays["sat"],
        compute_s=arrays["compute"],
        reward=arrays["rew"],
        metrics=metrics,
        controller={**described, "stats": summary},
    )


def _stepper(env: Any, max_steps: int | None) -> tuple[Any, int | None, list[Any]]:
    """``(step, max_steps, limits)``: the step the loop calls, where it stops, and the time
    limits it stepped below.

    ``gymnasium.make`` wraps the env in a time limit, a reset-before-step check and a checker
    of the first step's types, which leave every step's data as it is. The loop steps below
    them (exactly those classes, not subclasses of them), counting the time limit's episode
    length itself: the same data, without about 3 us per step of wrapper calls, a quarter of
    the env's step (2.6 million steps in the quick-start benchmark). The first other wrapper
    (a user's) is stepped through as given, with everything below it. The episode was reset
    through the whole stack, and the loop moves each time limit's step count on by the steps
    it took, so a caller who steps on after it truncates where the whole stack would.
    """
    from gymnasium.wrappers import OrderEnforcing, PassiveEnvChecker, TimeLimit

    inner, limits = env, []
    while type(inner) in (TimeLimit, OrderEnforcing, PassiveEnvChecker):
        if type(inner) is TimeLimit:
            limits.append(inner)
            limit = int(inner._max_episode_steps)
            max_steps = limit if max_steps is None else min(limit, max_steps)
        inner = inner.env
    return inner.step, max_steps, limits


def _loop(env: Any, controller: Any, obs: np.ndarray, max_steps: int | None) -> dict:
    """Step until the episode ends; the columns of the record as arrays.

    The loop runs once per step of every benchmark episode, so it binds what it calls to
    locals and appends each column to a list of its own (an append is cheaper than a store
    into a numpy array; each list becomes an array once, at the end), and steps the env below
    ``gymnasium.make``'s pass-through wrappers (:func:`_stepper`).
    """
    saturation = float(env.action_space.high[0]) * (1 - 1e-6)
    clock = time.perf_counter
    step, max_steps, limits = _stepper(env, max_steps)
    act = controller.act
    y, m, r, u, sat, rew, compute = columns = tuple([] for _ in range(7))
    add_y, add_m, add_r, add_u = y.append, m.append, r.append, u.append
    add_sat, add_rew, add_compute = sat.append, rew.append, compute.append
    steps = 0
    while max_steps is None or steps < max_steps:
        start = clock()
        action = act(obs)
        add_compute(clock() - start)
        try:
            obs, reward, terminated, truncated, info = step(action)
        except ValueError as error:  # the env's own message says what is wrong with it
            name = getattr(controller, "name", type(controller).__name__)
            raise ValueError(
                f"the env refused the action of {name!r} at step {steps}: {error}"
            ) from error
        voltage = info["voltage_V"]
        add_y(info["deflection_um"])
        add_m(float(obs[0]))
        add_r(info["reference_um"])
        add_u(voltage)
        add_sat(info["saturated"] or abs(voltage) >= saturation)
        add_rew(reward)
        steps += 1
        if terminated or truncated:
            break
    for limit in limits:
        limit._elapsed_steps += steps
    arrays = {
        k: np.asarray(v, dtype=float)
        for k, v in zip(("y", "m", "r", "u", "sat", "rew", "compute"), columns, strict=True)
    }
    arrays["sat"] = arrays["sat"].astype(bool)
    return arrays
