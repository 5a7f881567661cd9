"""RL throughput: env-steps/s under stable-baselines3 PPO, native vector env against SyncVectorEnv.

Three ways to give PPO N = 16 PiezoBender-v0 envs in the training observation
(:mod:`piezo_env.wrappers`), measured in the same process, alternating in rounds:

- **native**: the natively batched vector env + ``TrackingObservationVector``, through
  :class:`piezo_rl.ppo.SB3VectorEnv` (the adapter ``piezo train-rl`` uses);
- **sync**: Gymnasium's ``SyncVectorEnv`` of N ``gym.make`` envs each wrapped in
  ``TrackingObservation``, through the same adapter;
- **dummy**: SB3's usual wrapping, ``DummyVecEnv`` of N ``Monitor``-wrapped single envs.

PPO runs the recipe's hyperparameters (:class:`piezo_rl.ppo.PPOConfig`, one torch thread)
for a fixed number of steps; the env-steps/s include the PPO updates. The raw rates (random
actions in [-1, 1], no PPO, autoreset included) show what the env side alone costs. Ratios > 1
mean the native vector env is faster. Writes ``benchmarks/results/rl_throughput.md``.

Run: ``python -m benchmarks.rl_throughput`` (about two minutes).
"""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from benchmarks._common import header, markdown_table, write_result
from piezo_env.wrappers import TrackingObservation
from piezo_rl.ppo import (
    ENV_ID,
    EPISODE_STEPS,
    PPOConfig,
    SB3VectorEnv,
    make_ppo,
    make_training_env,
)

NUM_ENVS = 16
PREVIEW = 10
PPO_STEPS = 49_152  # 12 rollouts of 16 x 256
RAW_BATCHES = 2_001  # one episode and its autoreset
ROUNDS = 3


def _single() -> gym.Env:
    env = gym.make(ENV_ID, preview=PREVIEW, max_episode_steps=EPISODE_STEPS)
    return TrackingObservation(env)


def gym_vector(kind: str) -> gym.vector.VectorEnv:
    """The N envs in the training observation as a Gymnasium vector env."""
    if kind == "native":
        return make_training_env(NUM_ENVS, preview=PREVIEW)
    return gym.vector.SyncVectorEnv([_single for _ in range(NUM_ENVS)])


def sb3_vector(kind: str) -> VecEnv:
    """The N envs as SB3 sees them."""
    if kind == "dummy":
        return DummyVecEnv([lambda: Monitor(_single()) for _ in range(NUM_ENVS)])
    return SB3VectorEnv(gym_vector(kind))


def ppo_rate(kind: str, seed: int = 0) -> float:
    """Env-steps/s of PPO learning PPO_STEPS steps (rollouts and updates)."""
    venv = sb3_vector(kind)
    model = make_ppo(venv, PPOConfig(), seed)
    start = time.perf_counter()
    model.learn(total_timesteps=PPO_STEPS)
    elapsed = time.perf_counter() - start
    venv.close()
    return model.num_timesteps / elapsed


def raw_rate(kind: str, seed: int = 0) -> float:
    """Env-steps/s of the Gymnasium vector env alone, random actions, autoreset included."""
    env = gym_vector(kind)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, (64, NUM_ENVS, 1)).astype(np.float32)
    start = time.perf_counter()
    for i in range(RAW_BATCHES):
        env.step(actions[i % 64])
    elapsed = time.perf_counter() - start
    env.close()
    return RAW_BATCHES * NUM_ENVS / elapsed


def main() -> None:
    torch.set_num_threads(1)
    ppo = {k: [] for k in ("native", "sync", "dummy")}
    raw = {k: [] for k in ("native", "sync")}
    for r in range(ROUNDS):  # alternate, so that a slow spell of the machine hits all
        for kind in ppo:
            ppo[kind].append(ppo_rate(kind, seed=r))
        for kind in raw:
            raw[kind].append(raw_rate(kind, seed=r))
    med = {
        k: float(np.median(v))
        for k, v in {**ppo, **{f"raw-{k}": v for k, v in raw.items()}}.items()
    }
    ratio = {
        "sync": float(np.median(np.divide(ppo["native"], ppo["sync"]))),
        "dummy": float(np.median(np.divide(ppo["native"], ppo["dummy"]))),
        "raw": float(np.median(np.divide(raw["native"], raw["sync"]))),
    }
    rows = [
        ["native vector env + SB3VectorEnv", f"{med['native']:,.0f}", f"{med['raw-native']:,.0f}"],
        ["SyncVectorEnv + SB3VectorEnv", f"{med['sync']:,.0f}", f"{med['raw-sync']:,.0f}"],
        ["DummyVecEnv + Monitor (SB3's usual)", f"{med['dummy']:,.0f}", "-"],
    ]
    lines = header("RL throughput under stable-baselines3 PPO", "rl_throughput.py")
    lines += [
        f"N = {NUM_ENVS} PiezoBender-v0 envs (preview {PREVIEW}, 2000-step episodes, random "
        "references, 1 um noise) in the training observation of piezo_env.wrappers. PPO: the "
        f"recipe of piezo_rl.ppo.PPOConfig, {PPO_STEPS:,} steps per run, one torch thread; "
        "raw: random actions, no PPO. Medians over "
        f"{ROUNDS} alternating rounds; ratios are medians of the per-round ratios.",
        "",
        markdown_table(["vectorisation", "PPO env-steps/s", "raw env-steps/s"], rows),
        "",
        f"Native / SyncVectorEnv under PPO: {ratio['sync']:.2f}x; native / DummyVecEnv under "
        f"PPO: {ratio['dummy']:.2f}x; native / SyncVectorEnv raw: {ratio['raw']:.2f}x.",
        "",
        "Under PPO the policy's forward pass and the updates take most of the time, so the "
        "env's share, and with it the ratio, is smaller than raw.",
    ]
    write_result("rl_throughput", lines)


if __name__ == "__main__":
    main()
