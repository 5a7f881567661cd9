"""PPO training (stable-baselines3) on the native vector env, written as a plain policy folder.

The recipe (:class:`PPOConfig` holds each default once): ``num_envs`` sub-envs of the natively
batched ``PiezoBender-v0`` with the env's random references (steps, sines, triangles,
multisines), episodes of 2000 steps, the observation of
:class:`piezo_env.wrappers.TrackingObservationVector` (stroke-scaled, relative to the
deflection, past voltages and errors, action in [-1, 1]), rewards scaled by a running estimate
of the return's spread (SB3 ``VecNormalize`` on the reward only, so the policy's input stays
the wrapper's), and SB3 PPO with a tanh MLP. Everything is seeded from one seed (torch, the
envs, the action sampling). The result is ``policy.json`` + ``weights.npz``
(:func:`controllers.policy.save_policy`); nothing is pickled.

SB3 takes its own ``VecEnv``, not Gymnasium's ``VectorEnv``: :class:`SB3VectorEnv` is the
adapter. This module needs the optional ``rl`` extra (stable-baselines3).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from piezo_env.checks import require_int
from piezo_env.randomization import DomainRandomization
from piezo_env.wrappers import TrackingObservationVector

__all__ = [
    "ENV_ID",
    "RANDOMIZED",
    "PPOConfig",
    "RandomizedRecipe",
    "SB3VectorEnv",
    "actor_layers",
    "make_ppo",
    "make_training_env",
    "refuse_existing_policies",
    "train_ppo",
    "train_seeds",
]

ENV_ID = "piezo_env:PiezoBender-v0"
EPISODE_STEPS = 2000
"""Steps per training episode (2 s at dt = 1 ms)."""


@dataclass(frozen=True, kw_only=True)
class PPOConfig:
    """PPO hyperparameters of :func:`train_ppo`, validated on construction.

    Attributes
    ----------
    n_steps : int
        Steps per sub-env per rollout.
    batch_size : int
        Minibatch size (samples).
    n_epochs : int
        Passes over each rollout.
    learning_rate : float
        Adam step size at the start; it decays linearly to ``final_lr_fraction`` of it.
    final_lr_fraction : float
        Learning rate at the end, as a fraction of the start (0..1).
    gamma : float
        Discount factor per step (1 ms).
    gae_lambda : float
        GAE lambda.
    clip_range : float
        PPO ratio clip.
    ent_coef : float
        Entropy bonus.
    vf_coef : float
        Value loss weight.
    max_grad_norm : float
        Gradient clipping (L2 norm).
    log_std_init : float
        Initial log standard deviation of the Gaussian action (action units of [-1, 1]).
    net_arch : tuple of int
        Hidden layer sizes of the actor and, separately, the critic.
    activation : str
        ``"tanh"`` or ``"relu"``.
    normalize_reward : bool
        Scale rewards by a running estimate of the discounted return's standard deviation.
    torch_threads : int
        torch intra-op threads during training (the machine is shared: 1 by default).
    """

    n_steps: int = 256
    batch_size: int = 512
    n_epochs: int = 10
    learning_rate: float = 5e-4
    final_lr_fraction: float = 0.1
    gamma: float = 0.98
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    log_std_init: float = -1.0
    net_arch: tuple[int, ...] = (64, 64)
    activation: str = "tanh"
    normalize_reward: bool = True
    torch_threads: int = 1

    def __post_init__(self) -> None:
        for name in ("n_steps", "batch_size", "n_epochs", "torch_threads"):
            require_int(name, getattr(self, name))
        for name in ("learning_rate", "clip_range", "max_grad_norm"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("gamma", "gae_lambda", "final_lr_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be within [0, 1], got {getattr(self, name)!r}")
        if not self.net_arch or any(int(n) < 1 for n in self.net_arch):
            raise ValueError(f"net_arch must be positive layer sizes, got {self.net_arch!r}")
        if self.activation not in ("tanh", "relu"):
            raise ValueError(f"activation must be 'tanh' or 'relu', got {self.activation!r}")


@dataclass(frozen=True, kw_only=True)
class RandomizedRecipe:
    """What ``piezo train-rl --randomize`` trains: a policy for every plant of the tolerances.

    Every sub-env draws its plant at each reset from the datasheet tolerances (``randomize``);
    the observation is version 2 (:mod:`piezo_env.wrappers`): with the past voltages and the
    past measured deflections the policy sees the plant's recent input-output history, from
    which it can tell a stiff, weak or lightly damped plant from the nominal one.

    Attributes
    ----------
    total_steps : int
        Env steps over all sub-envs.
    num_envs : int
        Sub-envs of the native vector env.
    n_inputs, n_errors, n_deflections : int
        Past voltages, errors and deflections in the observation.
    reference_band : tuple of float
        Frequency band (Hz) of the random training references.
    randomization : DomainRandomization or None
        Spread of the training plants; None: the env's (the datasheet tolerances, as the
        benchmark's random plants draw them).
    config : PPOConfig
        PPO hyperparameters: those of the nominal policies but 5 gradient epochs per rollout
        (half the update time, so more env steps fit in the same wall time).
    """

    total_steps: int = 5_000_000
    num_envs: int = 16
    n_inputs: int = 16
    n_errors: int = 8
    n_deflections: int = 16
    reference_band: tuple[float, float] = (0.5, 60.0)
    randomization: DomainRandomization | None = None
    config: PPOConfig = PPOConfig(n_epochs=5)

    def train_kwargs(self, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
        """Keyword arguments of :func:`train_ppo` (``env_kwargs`` override the band)."""
        return {
            "num_envs": self.num_envs,
            "n_inputs": self.n_inputs,
            "n_errors": self.n_errors,
            "n_deflections": self.n_deflections,
            "config": self.config,
            "env_kwargs": {
                "reference_band": self.reference_band,
                **(env_kwargs or {}),
                "randomize": True if self.randomization is None else self.randomization,
            },
        }


RANDOMIZED = RandomizedRecipe()
"""The recipe of the committed ``docs/policies/ppo-dr-seed*`` policies."""


def make_training_env(
    num_envs: int,
    *,
    preview: int = 10,
    n_inputs: int = 4,
    n_errors: int = 4,
    n_deflections: int = 0,
    max_episode_steps: int = EPISODE_STEPS,
    env_kwargs: dict[str, Any] | None = None,
) -> TrackingObservationVector:
    """The native vector env in the training observation (Gymnasium API).

    ``env_kwargs={"randomize": True}`` gives domain randomisation: every sub-env draws its
    plant at each of its resets from its own seeded generator.
    """
    vec = gym.make_vec(
        ENV_ID,
        num_envs=num_envs,
        vectorization_mode="vector_entry_point",
        preview=preview,
        max_episode_steps=max_episode_steps,
        **(env_kwargs or {}),
    )
    return TrackingObservationVector(
        vec, n_inputs=n_inputs, n_errors=n_errors, n_deflections=n_deflections
    )


class SB3VectorEnv(VecEnv):
    """A stable-baselines3 ``VecEnv`` over a Gymnasium ``VectorEnv`` with next-step autoreset.

    SB3 expects same-step autoreset: the step that ends an episode returns the next episode's
    first observation, the last one in ``info["terminal_observation"]``. When every sub-env
    ends at once (fixed-length episodes started together, as in training), the adapter steps
    the vector env once more (next-step autoreset ignores the actions of that step) and
    returns the reset observations: exactly SB3's semantics. When only some end (a
    ``deflection_limit`` termination), those rows return their last observation and their next
    transition is the reset's (reward 0): one extra transition per such episode.

    ``seed(s)`` (SB3) seeds sub-env i with s + i at the next reset, as the vector env does.

    Parameters
    ----------
    env : gymnasium.vector.VectorEnv
        With a Box action space of shape (num_envs, 1), e.g. :func:`make_training_env`.
    """

    def __init__(self, env: gym.vector.VectorEnv) -> None:
        self.env = env
        self.render_mode = None
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
        self._actions = np.zeros((env.num_envs, 1), dtype=np.float32)

    def reset(self) -> np.ndarray:
        obs, _ = self.env.reset(seed=self._seeds[0])
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, 1)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        obs, reward, terminated, truncated, _ = self.env.step(self._actions)
        done = np.logical_or(terminated, truncated)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if done.any():
            for i in np.flatnonzero(done):
                infos[i]["terminal_observation"] = obs[i].copy()
                infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            if done.all():
                obs = self.env.step(np.zeros_like(self._actions))[0]
        return obs, np.asarray(reward, dtype=np.float32), done, infos

    def close(self) -> None:
        self.env.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any):
        raise NotImplementedError("the sub-envs of a native vector env have no methods to call")

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))


def actor_layers(policy: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """The actor's (weight, bias) arrays of an SB3 ``ActorCriticPolicy`` (MLP), input first."""
    linears = [m for m in policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    linears.append(policy.action_net)
    return [(m.weight.detach().cpu().numpy(), m.bias.detach().cpu().numpy()) for m in linears]


def _linear_schedule(start: float, end_fraction: float) -> Callable[[float], float]:
    def rate(progress_remaining: float) -> float:
        return start * (end_fraction + (1.0 - end_fraction) * progress_remaining)

    return rate


class _ProgressCallback(BaseCallback):
    """Keeps the mean raw episode return of each rollout; reports every ``every`` steps."""

    def __init__(self, every: int, report: Callable[[str], None] | None) -> None:
        super().__init__()
        self.every, self.report = every, report
        self.returns: list[tuple[int, float]] = []
        self._next = every
        self._start = time.perf_counter()

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        episodes = self.model.ep_info_buffer
        if episodes:
            mean = float(np.mean([e["r"] for e in episodes]))
            self.returns.append((int(self.num_timesteps), mean))
        if self.report is not None and self.num_timesteps >= self._next and self.returns:
            elapsed = time.perf_counter() - self._start
            self.report(
                f"{self.num_timesteps:>9,d} steps  {elapsed:6.0f} s  "
                f"mean episode return {self.returns[-1][1]:.3f}"
            )
            self._next += self.every


def make_ppo(venv: VecEnv, config: PPOConfig, seed: int) -> PPO:
    """SB3 PPO on ``venv`` with the hyperparameters of ``config``, seeded (CPU).

    The minibatch is at most one rollout (``n_steps`` x the number of envs).
    """
    activation = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}[config.activation]
    arch = list(config.net_arch)
    return PPO(
        "MlpPolicy",
        venv,
        n_steps=config.n_steps,
        batch_size=min(config.batch_size, config.n_steps * venv.num_envs),
        n_epochs=config.n_epochs,
        learning_rate=_linear_schedule(config.learning_rate, config.final_lr_fraction),
        gamma=config.gamma,
        gae_lambda=config.gae_lambda,
        clip_range=config.clip_range,
        ent_coef=config.ent_coef,
        vf_coef=config.vf_coef,
        max_grad_norm=config.max_grad_norm,
        policy_kwargs={
            "net_arch": {"pi": arch, "vf": arch},
            "activation_fn": activation,
            "log_std_init": config.log_std_init,
        },
        seed=seed,
        device="cpu",
        verbose=0,
    )


def train_ppo(
    seed: int,
    total_steps: int,
    out_dir: str | Path,
    *,
    num_envs: int = 16,
    preview: int = 10,
    n_inputs: int = 4,
    n_errors: int = 4,
    n_deflections: int = 0,
    config: PPOConfig | None = None,
    env_kwargs: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Train PPO on the native vector env and write the policy folder.

    Parameters
    ----------
    seed : int
        Seeds torch, the action sampling and the envs (sub-env i: seed + i).
    total_steps : int
        Env steps over all sub-envs (rounded up to whole rollouts of num_envs x n_steps).
    out_dir : str or Path
        Folder for ``policy.json`` and ``weights.npz``.
    num_envs : int
        Sub-envs of the native vector env.
    preview : int
        Reference samples ahead in the observation (the env's ``preview``).
    n_inputs, n_errors, n_deflections : int
        Past voltages, errors and deflections in the observation (n_deflections > 0:
        observation version 2).
    config : PPOConfig, optional
        Hyperparameters (default :class:`PPOConfig`).
    env_kwargs : dict, optional
        Further ``PiezoBender-v0`` settings (bender, noise_bound, hysteresis ...);
        ``{"randomize": True}`` trains on plants drawn from the datasheet tolerances.
    progress : callable, optional
        Called with one line of progress about every 100k steps.

    Returns
    -------
    pathlib.Path
        The policy folder.
    """
    config = config or PPOConfig()
    require_int("total_steps", total_steps)
    env = make_training_env(
        num_envs,
        preview=preview,
        n_inputs=n_inputs,
        n_errors=n_errors,
        n_deflections=n_deflections,
        env_kwargs=env_kwargs,
    )
    venv: VecEnv = VecMonitor(SB3VectorEnv(env))
    if config.normalize_reward:
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=config.gamma)
    threads = torch.get_num_threads()
    torch.set_num_threads(config.torch_threads)
    try:
        model = make_ppo(venv, config, seed)
        callback = _ProgressCallback(100_000, progress)
        start = time.perf_counter()
        model.learn(total_timesteps=total_steps, callback=callback)
        wall = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
        venv.close()
    training = {
        "algorithm": "PPO (stable-baselines3)",
        "seed": seed,
        "total_steps": int(model.num_timesteps),
        "num_envs": num_envs,
        "episode_steps": EPISODE_STEPS,
        "reference": "random (steps, sines, triangles, multisines)",
        "plants": (
            "drawn from the datasheet tolerances at every reset (randomize)"
            if (env_kwargs or {}).get("randomize")
            else "the nominal bender"
        ),
        "env_kwargs": {**_json_safe(env_kwargs or {}), "preview": preview},
        "ppo": {**asdict(config), "net_arch": list(config.net_arch)},
        "wall_time_s": round(wall, 1),
        "episode_returns": [[t, round(r, 4)] for t, r in callback.returns[-20:]],
    }
    return _write(model, env, out_dir, config, training)


def _json_safe(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Env settings as JSON: a dataclass (a ``DomainRandomization``, a datasheet) as its fields."""
    out: dict[str, Any] = {}
    for key, value in kwargs.items():
        if is_dataclass(value) and not isinstance(value, type):
            value = {"type": type(value).__name__, **asdict(value)}
        out[key] = value
    return out


def _write(model: PPO, env: Any, out_dir: str | Path, config: PPOConfig, training: dict) -> Path:
    import stable_baselines3

    base = env.unwrapped
    extra = {
        "training": training,
        "versions": {
            "stable_baselines3": stable_baselines3.__version__,
            "torch": torch.__version__,
            "numpy": np.__version__,
            "gymnasium": gym.__version__,
        },
        "task": {
            "env_id": ENV_ID,
            "dt_s": float(base.model.dt),
            "noise_bound_um": float(base.noise_bound),
        },
    }
    from controllers.policy import save_policy

    return save_policy(
        out_dir,
        layers=actor_layers(model.policy),
        activation=config.activation,
        observation=env.config,
        extra=extra,
    )


def _train_task(seed: int, total_steps: int, out_dir: str, kwargs: dict[str, Any]) -> Path:
    return train_ppo(seed, total_steps, out_dir, **kwargs)


def train_seeds(
    seeds: Sequence[int],
    total_steps: int,
    out_root: str | Path,
    *,
    jobs: int = 1,
    backend: str = "local",
    address: str | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    overwrite: bool = False,
    name: str = "ppo",
    **train_kwargs: Any,
) -> list[Path]:
    """Train one policy per seed, each seed a task of :func:`piezo_parallel.backends.run_tasks`.

    The seeds are independent runs, so they spread over worker processes or a Ray cluster the
    way the benchmark's episodes do (one torch thread each, ``PPOConfig.torch_threads``), and
    every policy is the same as :func:`train_ppo` with that seed would write. RLlib is not used:
    the env is batched natively and PPO on a few cores is bound by the gradient updates, so
    parallelism across seeds (and sweeps) is what pays.

    Parameters
    ----------
    seeds : sequence of int
        One training run each.
    total_steps : int
        Env steps per run.
    out_root : str or Path
        Parent folder; run ``s`` writes ``out_root/{name}-seed{s}``.
    jobs, backend, address
        As for :func:`piezo_parallel.backends.run_tasks` (``"local"`` or ``"ray"``).
    progress : callable, optional
        ``progress(done, total, label)`` after each run.
    overwrite : bool
        Replace policy folders that exist already (else refused before any training).
    name : str
        Recipe name of the folders (``"ppo"``; ``"ppo-dr"`` for domain randomisation): the
        benchmark groups ``NAME-seedK`` rows into one mean +- std row.
    **train_kwargs
        Further keyword arguments of :func:`train_ppo` (not ``progress``).

    Raises
    ------
    ValueError
        For repeated seeds, or a policy folder that exists already without ``overwrite``.

    Returns
    -------
    list of pathlib.Path
        The policy folders, in the order of ``seeds``.
    """
    from piezo_parallel.backends import run_tasks

    seeds = [int(s) for s in seeds]
    if len(set(seeds)) != len(seeds) or not seeds:
        raise ValueError(f"seeds must be distinct and at least one, got {seeds}")
    if not name or "/" in name or name != name.strip():
        raise ValueError(f"name must be a plain folder prefix such as 'ppo-dr', got {name!r}")
    folders = [Path(out_root) / f"{name}-seed{seed}" for seed in seeds]
    if not overwrite:
        refuse_existing_policies(folders)
    tasks = [
        (seed, total_steps, str(folder), train_kwargs)
        for seed, folder in zip(seeds, folders, strict=True)
    ]
    return run_tasks(
        _train_task,
        tasks,
        jobs=jobs,
        backend=backend,
        address=address,
        labels=[f"{name} seed {s}" for s in seeds],
        progress=progress,
    )


def refuse_existing_policies(folders: Sequence[str | Path]) -> None:
    """Raise ValueError naming the folders that hold a policy already (nothing is trained)."""
    taken = [str(f) for f in folders if (Path(f) / "policy.json").exists()]
    if taken:
        raise ValueError(
            f"{', '.join(taken)} hold(s) a trained policy already; choose another --out or pass "
            "--overwrite to replace it"
        )
