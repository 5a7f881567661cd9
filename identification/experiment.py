"""Open-loop experiments on the bender, through its Gymnasium interface, as on a real bender.

:func:`collect` drives the environment open loop; its ``y[t]`` is the deflection before
``u[t]`` is applied (the alignment of :meth:`HammersteinModel.simulate`). The measured (noisy)
deflection is all the identification sees.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike

import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from identification.config import IdentificationConfig

__all__ = ["collect", "identification_env", "sample_time"]


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
