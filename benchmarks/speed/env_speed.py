"""Environment speed: PiezoBender-v0 against CartPole-v1 measured in the same run.

Single env: step time through ``gymnasium.make`` (all default wrappers) with default settings
(FE beam + Bouc-Wen hysteresis + sensor noise + random reference), random actions, autoreset
included, beside CartPole-v1 made the same way. Vector env: native vector env-steps/s at
N = 1, 64, 1024, 4096 beside CartPole-v1's native vector env. Ratios > 1 mean PiezoBender is
faster. Every bench option on (amplifier with bandwidth, sensor with delay and bandwidth, drift,
rate-dependent hysteresis): single-env step time as a ratio to the default env's, measured
in alternating rounds (target <= 1.5). Writes ``benchmarks/results/env_speed.md``.

Run: ``python -m benchmarks.speed.env_speed`` (about a minute).
"""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np

import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from benchmarks._common import header, markdown_table, single_env_step_times, write_result

SINGLE_STEPS = 60_000
VECTOR_BATCHES = 2_001  # one PiezoBender episode and its autoreset
ROUNDS = 5
OPTION_STEPS = 20_000


def every_option() -> dict:
    """PiezoBender-v0 keyword arguments with every bench option on."""
    from piezo_env import Amplifier, Drift, Sensor

    return {
        "amplifier": Amplifier(current_limit_mA=100.0, bandwidth_Hz=5e3),
        "sensor": Sensor(delay=1, bandwidth_Hz=20e3),
        "drift": Drift(),
        "hysteresis": "rate-dependent",
    }


def option_ratio(rounds: int = ROUNDS) -> tuple[float, float, float]:
    """Median step times (s) of the default and the every-option env, and the median of their
    per-round ratios (the two alternate within each round)."""

    def median(r: int, **settings: object) -> float:
        times = single_env_step_times("PiezoBender-v0", OPTION_STEPS, r, **settings)
        return float(np.median(times))

    pairs = [(median(r), median(r, **every_option())) for r in range(rounds)]
    default, options = np.array(pairs).T
    return float(np.median(default)), float(np.median(options)), float(np.median(options / default))


def vector_env_rate(env_id: str, num_envs: int, seed: int = 0) -> float:
    """Env-steps per second of the native vector env (autoreset included)."""
    env = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point")
    env.reset(seed=seed)
    env.action_space.seed(seed)
    batches = VECTOR_BATCHES
    actions = [env.action_space.sample() for _ in range(64)]
    for a in actions[:10]:
        env.step(a)
    start = time.perf_counter()
    for i in range(batches):
        env.step(actions[i % len(actions)])
    elapsed = time.perf_counter() - start
    env.close()
    return batches * num_envs / elapsed


def paired_rates(num_envs: int, rounds: int = ROUNDS) -> tuple[float, float, float]:
    """Median env-steps/s of both vector envs and the median of their per-round ratios.

    The two envs alternate within each round, so a slow spell of the machine hits both.
    """
    pairs = [
        (vector_env_rate("PiezoBender-v0", num_envs), vector_env_rate("CartPole-v1", num_envs))
        for _ in range(rounds)
    ]
    piezo, cart = np.array(pairs).T
    return float(np.median(piezo)), float(np.median(cart)), float(np.median(piezo / cart))


def main() -> None:
    rows_single = []
    # Alternate the two envs in rounds, so that a slow spell of the machine hits both.
    rounds = [
        (
            single_env_step_times("PiezoBender-v0", SINGLE_STEPS // ROUNDS, seed=r),
            single_env_step_times("CartPole-v1", SINGLE_STEPS // ROUNDS, seed=r),
        )
        for r in range(ROUNDS)
    ]
    piezo = np.concatenate([p for p, _ in rounds])
    cart = np.concatenate([c for _, c in rounds])
    for name, t in (("PiezoBender-v0", piezo), ("CartPole-v1", cart)):
        rows_single.append(
            [
                name,
                f"{np.median(t) * 1e6:.2f}",
                f"{np.percentile(t, 99) * 1e6:.2f}",
                f"{t.mean() * 1e6:.2f}",
                f"{1 / t.mean():,.0f}",
            ]
        )
    ratio_single = float(np.median([np.median(p) / np.median(c) for p, c in rounds]))
    ratio_mean = float(np.median([p.mean() / c.mean() for p, c in rounds]))

    default_s, options_s, options_ratio = option_ratio()

    rows_vector = []
    for n in (1, 64, 1024, 4096):
        p, c, ratio = paired_rates(n)
        rows_vector.append([f"{n}", f"{p:,.0f}", f"{c:,.0f}", f"{ratio:.2f}"])

    lines = [
        *header("Environment speed", __spec__.name),
        "Default settings: FE beam (10 elements, reduced exactly to the modes that outlive one",
        "sample), Bouc-Wen hysteresis, 1 um sensor noise, random reference; random actions,",
        "autoreset included. CartPole-v1 is measured in the same run as the reference.",
        "",
        "## Single env through gymnasium.make",
        "",
        markdown_table(
            ["env", "median us/step", "p99 us/step", "mean us/step", "steps/s"], rows_single
        ),
        "",
        f"PiezoBender / CartPole step time (median of {ROUNDS} alternating rounds): median "
        f"{ratio_single:.2f}, mean {ratio_mean:.2f} (target: <= 1).",
        "",
        "## Every bench option on",
        "",
        "Amplifier (100 mA, 5 kHz), sensor (1 sample delay, 20 kHz), drift (the default Drift),",
        "rate-dependent hysteresis; single env through gymnasium.make, random actions (mostly",
        "slew-limited), resets included, alternating with the default env in each round.",
        "",
        markdown_table(
            ["env", "median us/step"],
            [["default", f"{default_s * 1e6:.2f}"], ["every option on", f"{options_s * 1e6:.2f}"]],
        ),
        "",
        f"Every option on / default step time (median of {ROUNDS} rounds' ratios): "
        f"{options_ratio:.2f} (target: <= 1.5).",
        "",
        "## Native vector env (vector_entry_point), env-steps/s",
        "",
        f"Medians over {ROUNDS} rounds; each round runs both envs back to back, and the ratio is",
        "the median of the per-round ratios.",
        "",
        markdown_table(["N", "PiezoBender-v0", "CartPole-v1", "ratio"], rows_vector),
        "",
        "Target: ratio >= 1 at N = 1024. The batched state update is split into blocks of 1024",
        "rows so that no matrix product reaches OpenBLAS's multi-threading threshold.",
    ]
    write_result("env_speed", lines)


if __name__ == "__main__":
    main()
