"""The golden trajectory of the default env: regenerate with ``python tests/golden.py``.

Regenerate only for an intended change of the physics, and say so in the change.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np

GOLDEN = Path(__file__).parent / "data" / "golden_pl140.npz"
STEPS = 300


def golden_trajectory() -> dict[str, np.ndarray]:
    """300 steps of the default PiezoBender-v0 under seed 7 and a fixed voltage sequence."""
    env = gym.make("piezo_env:PiezoBender-v0")
    obs0, _ = env.reset(seed=7)
    voltages = (
        30.0 * np.sin(2 * np.pi * 7.0 * 1e-3 * np.arange(STEPS)) * np.linspace(0.2, 1.2, STEPS)
    )
    observations, deflections = [obs0], []
    for v in voltages:
        obs, _, _, _, info = env.step(np.array([v], dtype=np.float32))
        observations.append(obs)
        deflections.append(info["deflection_um"])
    return {
        "voltage": voltages,
        "observation": np.array(observations),
        "deflection_um": np.array(deflections),
    }


if __name__ == "__main__":
    GOLDEN.parent.mkdir(exist_ok=True)
    np.savez(GOLDEN, **golden_trajectory())
    print(f"wrote {GOLDEN}")
