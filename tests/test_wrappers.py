"""The RL observation wrappers: proven bounds, both checkers, exact inverse, single == vector."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common import env_checker as sb3_checker

import piezo_env  # noqa: F401  (registers the ids)
from piezo_env.wrappers import (
    ObservationConfig,
    ObservationHistory,
    TrackingObservation,
    TrackingObservationVector,
    denormalize_observation,
    normalize_observation,
    observation_high,
)

ENV_ID = "piezo_env:PiezoBender-v0"
# gymnasium's checker says this of every wrapped env; it is the only remark allowed.
_WRAPPED_NOTICE = "is different from the unwrapped version"


def _remarks(check, env) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check(env)
    return [str(w.message) for w in caught]


def _vector(num_envs: int, **kwargs) -> TrackingObservationVector:
    vec = gym.make_vec(ENV_ID, num_envs=num_envs, vectorization_mode="vector_entry_point", **kwargs)
    return TrackingObservationVector(vec, n_inputs=3, n_errors=2)


@pytest.mark.parametrize(
    "kwargs", [{"preview": 10}, {"preview": 0, "bender": "PL112", "noise_bound": 0.0}]
)
def test_both_checkers_pass(kwargs):
    env = TrackingObservation(gym.make(ENV_ID, **kwargs))
    remarks = _remarks(lambda e: check_env(e, skip_render_check=True), env)
    assert all(_WRAPPED_NOTICE in r for r in remarks), remarks
    assert _remarks(lambda e: sb3_checker.check_env(e, warn=True), env) == []


def test_layout_and_spaces():
    env = TrackingObservation(gym.make(ENV_ID, preview=4), n_inputs=2, n_errors=3)
    assert env.observation_space.shape == (2 + 4 + 2 + 3,)
    assert env.observation_space.dtype == np.float32
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    raw_env = gym.make(ENV_ID, preview=4)
    raw, _ = raw_env.reset(seed=5)
    obs, _ = env.reset(seed=5)
    s = 1000.0
    np.testing.assert_allclose(obs[0], raw[0] / s, rtol=1e-6)
    np.testing.assert_allclose(obs[1:6], (raw[1:] - raw[0]) / s, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(obs[6:8], 0.0)  # rest under 0 V
    np.testing.assert_allclose(obs[8:], (raw[1] - raw[0]) / s, rtol=1e-6, atol=1e-9)
    obs, *_ = env.step(np.array([0.5], np.float32))
    assert obs[6] == np.float32(0.5) and obs[7] == 0.0  # u_t-1 = 15 V, u_t-2 = 0 V


def test_bounds_are_the_extreme_operands_through_the_same_arithmetic():
    config = ObservationConfig(stroke_um=1000.0, u_max=30.0, bound_um=41759.0, preview=2)
    high = observation_high(config)
    b = config.bound_um
    extreme = normalize_observation(
        np.array([[b, -b, -b, -b], [-b, b, b, b]], np.float32),
        np.array([[30.0] * 4, [-30.0] * 4]),
        np.array([[-2 * b] * 4, [2 * b] * 4]),
        config,
    )
    np.testing.assert_array_equal(np.abs(extreme).max(axis=0), high)
    assert high[0] == np.float32(41.759) and high[-1] == np.float32(83.518)


@pytest.mark.parametrize("drive", ["bang-bang", "random"])
def test_bounds_hold_under_extreme_drive(drive):
    vec = _vector(8, preview=5, max_episode_steps=300)
    space = vec.observation_space
    rng = np.random.default_rng(1)
    obs, _ = vec.reset(seed=0)
    assert space.contains(obs)
    worst = np.abs(obs).max(axis=0)
    for t in range(700):  # crosses two autoresets
        if drive == "bang-bang":  # alternate the rails at the first mode's period (~6 ms)
            level = 1.0 if (t // 3) % 2 == 0 else -1.0
            actions = np.full((8, 1), level, np.float32)
        else:
            actions = rng.uniform(-3.0, 3.0, (8, 1)).astype(np.float32)  # clipped to [-1, 1]
        obs, *_ = vec.step(actions)
        assert space.contains(obs)
        worst = np.maximum(worst, np.abs(obs).max(axis=0))
    assert worst[0] > 1.0  # the drive really reached past the stroke


def test_normalisation_is_invertible_to_float32_rounding():
    rng = np.random.default_rng(2)
    config = ObservationConfig(
        stroke_um=1000.0, u_max=30.0, bound_um=41759.0, preview=6, n_inputs=4, n_errors=5
    )
    b = config.bound_um
    scale = rng.choice([1e-3, 1.0, 1e3, b], size=(500, 1))
    raw = np.clip(rng.uniform(-1, 1, (500, config.raw_size)) * scale, -b, b).astype(np.float32)
    voltages = rng.uniform(-30.0, 30.0, (500, 4))
    errors = rng.uniform(-1, 1, (500, 5)) * scale * 2
    back_raw, back_v, back_e = denormalize_observation(
        normalize_observation(raw, voltages, errors, config), config
    )
    y = np.abs(raw[:, :1].astype(np.float64))
    tolerance = 2.0**-22 * (np.abs(raw) + y)
    assert np.all(np.abs(back_raw.astype(np.float64) - raw) <= tolerance)
    assert np.all(np.abs(back_v - voltages) <= 2.0**-22 * np.abs(voltages))
    assert np.all(np.abs(back_e - errors) <= 2.0**-22 * np.abs(errors))
    single = normalize_observation(raw[0], voltages[0], errors[0], config)
    np.testing.assert_array_equal(denormalize_observation(single, config)[0], back_raw[0])


def test_inverse_recovers_the_env_observations():
    env = TrackingObservation(gym.make(ENV_ID, preview=3), n_inputs=2, n_errors=2)
    raw_env = gym.make(ENV_ID, preview=3)
    obs, _ = env.reset(seed=9)
    raw, _ = raw_env.reset(seed=9)
    previous = 0.0
    for t in range(50):
        back, voltages, _ = denormalize_observation(obs, env.config)
        tolerance = 2.0**-22 * (np.abs(raw) + abs(raw[0]))
        assert np.all(np.abs(back.astype(np.float64) - raw) <= tolerance)
        assert abs(voltages[0] - previous) <= 2.0**-22 * 30.0
        action = np.array([np.sin(t / 5.0)], np.float32)
        obs, *_ = env.step(action)
        raw, *_ = raw_env.step(action * np.float32(30.0))
        previous = float(action[0] * np.float32(30.0))


def test_single_wrapper_equals_the_vector_wrapper_env_by_env():
    n = 3
    vec = _vector(n, preview=4, max_episode_steps=40)
    singles = [
        TrackingObservation(
            gym.make(ENV_ID, preview=4, max_episode_steps=40), n_inputs=3, n_errors=2
        )
        for _ in range(n)
    ]
    obs, _ = vec.reset(seed=11)
    for i, env in enumerate(singles):
        np.testing.assert_array_equal(env.reset(seed=11 + i)[0], obs[i])
    rng = np.random.default_rng(3)
    done = [False] * n
    for _ in range(100):  # two autoresets
        actions = rng.uniform(-1.2, 1.2, (n, 1)).astype(np.float32)
        obs, _, terminated, truncated, info = vec.step(actions)
        for i, env in enumerate(singles):
            if done[i]:
                single = env.reset()[0]
                done[i] = False
            else:
                single, _, term, trunc, single_info = env.step(actions[i])
                done[i] = term or trunc
                # An action beyond [-1, 1] is a drive the amplifier clips: saturated.
                clipped = abs(float(actions[i, 0])) > 1.0
                assert single_info["saturated"] == bool(info["saturated"][i]) == clipped
            np.testing.assert_array_equal(single, obs[i])
            assert done[i] == bool(terminated[i] or truncated[i])


def test_history_starts_from_the_reset_voltage():
    env = TrackingObservation(gym.make(ENV_ID, preview=1), n_inputs=2, n_errors=1)
    obs, _ = env.reset(seed=0, options={"initial_voltage": 12.0})
    np.testing.assert_array_equal(obs[3:5], np.float32(0.4))
    history = ObservationHistory(2, env.config)
    history.start(slice(None), np.array([[1.0, 3.0, 4.0], [0.0, 0.0, 0.0]]), [6.0, 0.0])
    np.testing.assert_array_equal(history.voltages, [[6.0, 6.0], [0.0, 0.0]])
    np.testing.assert_array_equal(history.errors, [[2.0], [0.0]])


def test_bad_actions_and_envs_raise():
    env = TrackingObservation(gym.make(ENV_ID))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan], np.float32))
    with pytest.raises(ValueError, match=r"one number in \[-1, 1\].*shape \(2,\)"):
        env.step(np.array([0.1, 0.2], np.float32))
    with pytest.raises(ValueError, match="no reference"):
        TrackingObservation(gym.make(ENV_ID, reference=None))
    with pytest.raises(ValueError, match="n_inputs"):
        TrackingObservation(gym.make(ENV_ID), n_inputs=-1)
