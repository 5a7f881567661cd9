"""Per-step cost of the closed loop: a PPO policy's and the MPC's act against a CartPole-v1 step.

The benchmark runs millions of closed-loop steps (:func:`controllers.run_episode`), so the
Python work of every step counts: the controller's ``act`` (the observation check, the
controller's own step, the float32 action), the env step through ``gymnasium.make``'s
wrappers, and the loop's record keeping. This script times each for the committed PPO
policies ``ppo-seed0`` (version 1 observation) and ``ppo-dr-seed0`` (version 2, with past
deflections) and for ``mpc`` on the committed identified model, on the benchmark's 50 Hz sine
(PL140 at 1 ms, preview 20, 2000 steps), with one BLAS thread and the garbage collector off
inside episodes (as the benchmark runs them):

- **act**: the median of the episode's ``act`` times (:attr:`Episode.compute_s`);
- **env step**: the same episode's actions replayed through the env alone;
- **loop step**: the episode's wall time over its steps (act, env step and the loop).

Rounds alternate the controllers and measure a CartPole-v1 step through ``gymnasium.make`` in
between; every figure is the median over rounds, and each is also given as a ratio to the
CartPole median of the same run (absolute times on shared machines drift; ratios travel).
Writes ``benchmarks/results/step_overhead.md``.

Run: ``python -m benchmarks.speed.step_overhead`` (a few seconds).
"""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np
from threadpoolctl import threadpool_limits

import controllers
import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from benchmarks._common import header, markdown_table, single_env_step_times, write_result
from benchmarks.plants import EPISODE_S, sample_time
from benchmarks.references import make_reference
from benchmarks.runner import no_collection

MODEL_DIR = "docs/identify/model"
POLICIES = "docs/policies"
ROWS = {
    "ppo-seed0": ("policy", f"{POLICIES}/ppo-seed0"),
    "ppo-dr-seed0": ("policy", f"{POLICIES}/ppo-dr-seed0"),
    "mpc": ("mpc", MODEL_DIR),
}
TIMES = ("act", "env", "loop")
REFERENCE = "sine-50Hz"
PREVIEW = 20
ROUNDS = 15
CARTPOLE_STEPS = 5000


def episode_times(env: Any, controller: Any, reference: np.ndarray) -> dict[str, float]:
    """Median act time, loop time per step and replayed env step time (s) of one episode."""
    start = time.perf_counter()
    episode = controllers.run_episode(env, controller, seed=0, reference=reference)
    loop = (time.perf_counter() - start) / episode.voltage_V.size
    actions = [np.array([u], dtype=np.float32) for u in episode.voltage_V]
    env.reset(seed=0, options={"reference": reference})
    step = env.step
    start = time.perf_counter()
    for action in actions:
        step(action)
    env_step = (time.perf_counter() - start) / len(actions)
    return {"act": float(np.median(episode.compute_s)), "env": env_step, "loop": loop}


def main() -> None:
    dt = sample_time("PL140")
    steps = round(EPISODE_S / dt)
    env = gym.make("piezo_env:PiezoBender-v0", preview=PREVIEW, max_episode_steps=steps)
    reference = make_reference(REFERENCE, steps + PREVIEW + 1, dt=dt, seed=0)
    times: dict[str, list[dict[str, float]]] = {name: [] for name in ROWS}
    cart: list[float] = []
    with threadpool_limits(1):
        built = {name: controllers.make(kind, path, env) for name, (kind, path) in ROWS.items()}
        for controller in built.values():  # warm-up: caches, generated code
            controllers.run_episode(env, controller, seed=0, reference=reference, max_steps=50)
        with no_collection():
            for _ in range(ROUNDS):
                for name, controller in built.items():
                    times[name].append(episode_times(env, controller, reference))
                cart.append(float(np.median(single_env_step_times("CartPole-v1", CARTPOLE_STEPS))))
        lines = header("Closed-loop step overhead (one BLAS thread)", __spec__.name)
    cart_s = float(np.median(cart))
    rows = []
    for name, runs in times.items():
        act, env_step, loop = (float(np.median([run[k] for run in runs])) for k in TIMES)
        rows.append(
            [
                name,
                f"{act * 1e6:.1f}",
                f"{act / cart_s:.2f}",
                f"{env_step * 1e6:.1f}",
                f"{env_step / cart_s:.2f}",
                f"{loop * 1e6:.1f}",
                f"{loop / cart_s:.2f}",
            ]
        )
    lines += [
        f"CartPole-v1 step through gym.make, same run: median {cart_s * 1e6:.2f} us. Episodes: "
        f"PL140 at {dt * 1e3:g} ms, {steps} steps, noise on, preview {PREVIEW}, the benchmark's "
        f"{REFERENCE} reference; medians over {ROUNDS} rounds.",
        "",
        markdown_table(
            [
                "controller",
                "act (us)",
                "act / CartPole step",
                "env step (us)",
                "env step / CartPole step",
                "loop step (us)",
                "loop step / CartPole step",
            ],
            rows,
        ),
    ]
    write_result("step_overhead", lines)


if __name__ == "__main__":
    main()
