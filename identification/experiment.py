"""Open-loop experiments on the bender, through its Gymnasium interface, as on a real bender.

:func:`collect` drives the environment open loop; its ``y[t]`` is the deflection before
``u[t]`` is applied (the alignment of :meth:`HammersteinModel.simulate`). The measured (noisy)
deflection is all the identification sees.
"""

from __future__ import annotations

from collections.abc import Mapping

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike

import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from identification.config import IdentificationConfig
from piezo_env.signals import make_signal

__all__ = [
    "RECORD_NAMES",
    "RECORD_PURPOSES",
    "collect",
    "experiment_inputs",
    "identification_env",
    "measure",
    "rand_signal",
    "sample_time",
    "step_seeds",
]

RECORD_NAMES: tuple[str, ...] = ("prbs", "rich", "selection", "validation")
"""The records of the procedure, in the order they are measured: the PRBS of step a (steps b
and b'), the rich record of step c (steps d, e, e'), the selection record of step e (chooses
the network's features, judges step e'; held out from training) and the validation record of
step f."""

RECORD_PURPOSES: dict[str, str] = {
    "prbs": "step a: PRBS for the ARX part (steps b, b'); two levels, so the hysteresis is affine",
    "rich": "step c: rich record for the hidden signal and the network (steps d, e, e')",
    "selection": "step e: held-out record that chooses the network's features and judges e'",
    "validation": "step f: fresh record for the free-run validation of the model",
}
"""What each record is for, one line each (the manifest of ``piezo excite`` carries them)."""


def collect(
    env: gym.Env, u: ArrayLike, *, seed: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Drive ``env`` open loop with the voltage sequence ``u`` from rest; return ``(u, y)``.

    Alignment: ``y[t]`` is the measured deflection *before* ``u[t]`` is applied, i.e. the
    observation returned by ``reset`` (t = 0) or by the ``step`` that applied ``u[t-1]``. So
    ``y[t]`` depends on ``u[t-1], u[t-2], ...`` (the ARX convention, and the convention of
    :meth:`HammersteinModel.simulate`): compare ``model.simulate(u)`` with this ``y``. If you step
    the env yourself with ``u`` and collect the observations *returned by step*, you get
    ``y[1:]`` plus one more sample: a one-sample shift, which on white input costs almost all of
    the fit. ``u[-1]`` is never applied (no output of the record would see it).

    Parameters
    ----------
    env : gymnasium.Env
        A ``PiezoBender-v0`` environment (or wrapper) with deflection in um as ``obs[0]``; its
        ``reference`` should be None. Truncation flags are ignored (a record may be longer than
        an episode).
    u : array_like, shape (T,)
        Drive voltage, V.
    seed : int, optional
        Seed of ``env.reset`` (sensor noise and initial state draws).

    Returns
    -------
    u : numpy.ndarray, shape (T,)
        The voltage the env applied, V (``info["voltage_V"]``): ``u`` clipped to the action
        space, as the amplifier saturates, and with a current-limited amplifier
        (``amplifier=...``) its slew-limited output, as an amplifier's voltage monitor reads
        it: the model is identified from the voltage on the bender, not from the command. The
        last sample, never applied, is the clipped command.
    y : numpy.ndarray, shape (T,)
        Measured tip deflection, um, ``y[t]`` before ``u[t]``.

    Raises
    ------
    ValueError
        If ``u`` is not a finite 1-D sequence of at least 2 samples, or the env terminates
        (deflection limit).
    """
    u = np.asarray(u, dtype=float)
    if u.ndim != 1 or u.size < 2 or not np.all(np.isfinite(u)):
        raise ValueError(f"u must be a finite 1-D voltage sequence of >= 2 samples; got {u!r}")
    obs, _ = env.reset(seed=seed)
    y = np.empty(len(u))
    y[0] = obs[0]
    applied = np.clip(u, env.action_space.low[0], env.action_space.high[0])
    slewed = getattr(env.unwrapped, "slew_limit", None) is not None
    for t in range(len(u) - 1):
        obs, _, terminated, _, info = env.step(np.array([u[t]], dtype=np.float32))
        if slewed:
            applied[t] = info["voltage_V"]
        if terminated:
            raise ValueError(
                f"the env terminated at sample {t + 1} (deflection limit); identify on an env "
                "without deflection_limit or with a smaller excitation"
            )
        y[t + 1] = obs[0]
    return applied, y


def identification_env(config: IdentificationConfig) -> gym.Env:
    """The bender of ``config`` (PiezoBender-v0, open loop: no reference, no time limit)."""
    return gym.make(
        "piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, **config.env_kwargs
    )


def sample_time(env: gym.Env) -> float:
    """The sampling period of ``env``, s."""
    return float(env.unwrapped.model.dt)


def step_seeds(seed: int) -> dict[str, int]:
    """Independent seeds of the steps' signals, the env's noise and the training, from one."""
    names = ("prbs", "rich", "selection", "validation", "env", "nls")
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {name: int(c.generate_state(1)[0]) for name, c in zip(names, children, strict=True)}


def rand_signal(config: IdentificationConfig, n: int, dt: float, seed: int) -> np.ndarray:
    """``n`` samples of the RAND input of the selection and validation records, V (``dt`` in
    s counts the default hold, :data:`identification.config.RAND_HOLD_S`)."""
    return make_signal(
        "random",
        n,
        dt=dt,
        rng=np.random.default_rng(seed),
        amplitude=config.validation_amplitude,
        hold=config.at_sample_time(dt).validation_hold,
    )


def experiment_inputs(
    config: IdentificationConfig, dt: float, seeds: dict[str, int] | None = None
) -> dict[str, np.ndarray]:
    """The input voltages (V) of the procedure's records at the sample time ``dt`` (s).

    ``seeds``: the signals' seeds (default :func:`step_seeds` ``(config.seed)``).

    Returns
    -------
    dict of numpy.ndarray
        :data:`RECORD_NAMES` -> voltage sequence: the PRBS of level ``prbs_amplitude``
        (``prbs_samples``), the rich signal (``rich_samples``), and RAND records of
        ``validation_amplitude`` for the selection (half of ``validation_samples``) and the
        validation (``validation_samples``), each drawn from its own seed.
    """
    config = config.at_sample_time(dt)
    seeds = step_seeds(config.seed) if seeds is None else seeds
    prbs = make_signal(
        "prbs",
        config.prbs_samples,
        dt=dt,
        rng=np.random.default_rng(seeds["prbs"]),
        amplitude=config.prbs_amplitude,
        clock_period=config.prbs_clock,
    )
    rich = make_signal(
        config.rich_signal,
        config.rich_samples,
        dt=dt,
        rng=np.random.default_rng(seeds["rich"]),
        amplitude=config.rich_amplitude,
        **config.rich_signal_params(dt),
    )
    n = config.validation_samples
    return {
        "prbs": prbs,
        "rich": rich,
        "selection": rand_signal(config, n // 2, dt, seeds["selection"]),
        "validation": rand_signal(config, n, dt, seeds["validation"]),
    }


def measure(
    env: gym.Env, inputs: Mapping[str, ArrayLike], seed: int
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Drive ``env`` with each input record, from rest, as :func:`collect` does; ``(u, y)`` each.

    Parameters
    ----------
    env : gymnasium.Env
        The bender (see :func:`collect`).
    inputs : mapping of str to array_like
        Record name (one of :data:`RECORD_NAMES`) -> voltage sequence, V.
    seed : int
        The identification seed: record ``name`` resets the env with ``step_seeds(seed)["env"]``
        plus its place in :data:`RECORD_NAMES`, so each record has its own sensor noise.

    Returns
    -------
    dict
        Record name -> ``(u, y)``: applied voltage (V) and measured deflection (um).
    """
    env_seed = step_seeds(seed)["env"]
    unknown = sorted(set(inputs) - set(RECORD_NAMES))
    if unknown:
        raise ValueError(f"unknown record name(s) {unknown}; expected {', '.join(RECORD_NAMES)}")
    return {
        name: collect(env, inputs[name], seed=env_seed + RECORD_NAMES.index(name))
        for name in RECORD_NAMES
        if name in inputs
    }
