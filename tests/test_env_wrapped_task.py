"""What a wrapped env says about its task: the nominal one, whatever plant an episode drew.

With domain randomisation each reset draws a plant whose stroke differs from the datasheet's
(e.g. 1054.78 um instead of 1000 um). The RL wrappers scale by the task's (nominal) stroke and a
controller reads the raw env's task; a wrapper that changes the spaces cannot carry a
controller, and says so.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import RescaleAction

import piezo_env  # noqa: F401  (registers the ids)
from controllers import ControlTask
from piezo_env.wrappers import TrackingObservation, TrackingObservationVector, action_to_voltage

ENV_ID = "piezo_env:PiezoBender-v0"
STROKE_UM, U_MAX, PREVIEW = 1000.0, 30.0, 4  # the PL140's nominal stroke and rated voltage


def _expected_head(raw: np.ndarray) -> np.ndarray:
    """[y / s, (r_t+k - y) / s] of raw observations (rows), at the nominal stroke s."""
    raw = np.atleast_2d(np.asarray(raw, dtype=np.float64))
    y = raw[:, :1]
    return np.concatenate([y / STROKE_UM, (raw[:, 1:] - y) / STROKE_UM], axis=1).astype(np.float32)


def _actions(steps: int, n: int) -> np.ndarray:
    return np.random.default_rng(11).uniform(-1.0, 1.0, (steps, n, 1)).astype(np.float32)


def test_single_wrapper_scales_by_the_nominal_stroke_after_randomised_resets():
    raw_env = gym.make(ENV_ID, preview=PREVIEW, randomize=True, max_episode_steps=40)
    wrapped = TrackingObservation(
        gym.make(ENV_ID, preview=PREVIEW, randomize=True, max_episode_steps=40)
    )
    raw_env.reset(seed=5)
    assert raw_env.unwrapped.model.stroke_um != STROKE_UM  # this episode's plant is another one
    # Made after a randomised reset, the wrapper still reads the task's scales.
    late = TrackingObservation(raw_env)
    assert (late.config.stroke_um, late.config.u_max) == (STROKE_UM, U_MAX)

    raw, _ = raw_env.reset(seed=5)
    obs, _ = wrapped.reset(seed=5)
    strokes = set()
    for action in _actions(100, 1):
        np.testing.assert_array_equal(obs[: 2 + PREVIEW], _expected_head(raw)[0])
        raw, _, terminated, truncated, _ = raw_env.step(action_to_voltage(action[0], U_MAX))
        obs, *_ = wrapped.step(action[0])
        strokes.add(raw_env.unwrapped.model.stroke_um)
        if terminated or truncated:
            raw, _ = raw_env.reset()
            obs, _ = wrapped.reset()
    assert len(strokes) >= 3  # several drawn plants, one scale


def test_vector_wrapper_scales_by_the_nominal_stroke_after_randomised_resets():
    def make() -> gym.vector.VectorEnv:
        return gym.make_vec(
            ENV_ID,
            num_envs=3,
            vectorization_mode="vector_entry_point",
            preview=PREVIEW,
            randomize=True,
            max_episode_steps=40,
        )

    raw_env = make()
    raw_env.reset(seed=5)
    late = TrackingObservationVector(raw_env)
    assert (late.config.stroke_um, late.config.u_max) == (STROKE_UM, U_MAX)

    raw_env, wrapped = make(), TrackingObservationVector(make())
    raw, _ = raw_env.reset(seed=5)
    obs, _ = wrapped.reset(seed=5)
    for actions in _actions(100, 3):  # crosses two autoresets: new plants in every sub-env
        np.testing.assert_array_equal(obs[:, : 2 + PREVIEW], _expected_head(raw))
        raw, *_ = raw_env.step(action_to_voltage(actions, U_MAX))
        obs, *_ = wrapped.step(actions)


def test_control_task_reads_the_raw_env_through_wrappers_that_keep_the_spaces():
    env = gym.make(ENV_ID, preview=10, randomize=True)  # TimeLimit, OrderEnforcing, checker
    env.reset(seed=5)
    assert env.unwrapped.model.stroke_um != STROKE_UM
    task = ControlTask.from_env(env)
    assert (task.dt, task.u_max, task.stroke_um, task.preview) == (1e-3, U_MAX, STROKE_UM, 10)
    assert task.noise_bound_um == 1.0
    assert ControlTask.from_env(env.unwrapped) == task


@pytest.mark.parametrize(
    "wrap",
    [
        TrackingObservation,
        lambda env: RescaleAction(env, np.float32(-1.0), np.float32(1.0)),
    ],
    ids=["TrackingObservation", "RescaleAction"],
)
def test_control_task_refuses_a_wrapper_that_changes_the_spaces(wrap):
    """Through TrackingObservation it once read u_max = 1.0 and preview = 18."""
    with pytest.raises(
        ValueError,
        match=r"changes the env's observation or action space.*"
        r"env\.unwrapped",
    ):
        ControlTask.from_env(wrap(gym.make(ENV_ID, preview=10)))
