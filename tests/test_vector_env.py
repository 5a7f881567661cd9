"""The natively batched PiezoBender-v0 against SyncVectorEnv and the single env."""

from __future__ import annotations

import copy

import gymnasium as gym
import numpy as np
import pytest

import piezo_env  # noqa: F401  (registers the ids)
from piezo_env.reference import segment_samples
from piezo_env.task import NOISE_BLOCK
from piezo_env.vector_env import PiezoBenderVectorEnv

ENV_ID = "piezo_env:PiezoBender-v0"


def _make_vec(num_envs, **kwargs):
    return gym.make_vec(
        ENV_ID, num_envs=num_envs, vectorization_mode="vector_entry_point", **kwargs
    )


def _record(obs, reward, terminated, truncated, info):
    return {"obs": obs, "reward": reward, "terminated": terminated, "truncated": truncated, **info}


def _assert_same_records(native, sync):
    """Step records (stacked over steps) of both vector envs agree, info and masks included."""
    assert [set(r) for r in native] == [set(r) for r in sync]
    for key in {k for r in sync for k in r}:
        steps = [i for i, r in enumerate(sync) if key in r]  # no reward at reset
        actual = np.stack([native[i][key] for i in steps])
        expected = np.stack([sync[i][key] for i in steps])
        assert actual.dtype == expected.dtype, key
        if key == "obs":  # measured deflection to float32 rounding, reference samples exactly
            np.testing.assert_allclose(actual[..., 0], expected[..., 0], rtol=1e-6, atol=1e-4)
            np.testing.assert_array_equal(actual[..., 1:], expected[..., 1:])
        elif expected.dtype == bool:
            np.testing.assert_array_equal(actual, expected, err_msg=key)
        else:
            np.testing.assert_allclose(actual, expected, rtol=1e-10, atol=1e-9, err_msg=key)


# Per-env action amplitudes (V): small ones run whole episodes, large ones ring the first mode
# up past the deflection limit within a few steps, so sub-envs reset at different times.
@pytest.mark.parametrize(
    ("amplitudes", "kwargs"),
    [
        ([1.0] * 3, {"preview": 3}),  # lockstep throughout: all truncate together
        ([1.0, 35.0, 1.0, 8.0, 35.0, 0.5], {}),
        (
            [0.5, 35.0, 2.0, 35.0, 1.0],
            {"hysteresis": "prandtl-ishlinskii", "creep": True, "reference": "steps"},
        ),
    ],
)
def test_vector_env_matches_sync_vector_env_info_included(amplitudes, kwargs):
    """5,000 steps across noise refills, reference segments, row blocks and partial resets."""
    n, steps, horizon, seed = len(amplitudes), 5_000, 2_300, 21
    kwargs = {"deflection_limit": 600.0, **kwargs}
    native = _make_vec(n, max_episode_steps=horizon, **kwargs)
    native.unwrapped._row_block = 2  # several matmul row blocks, one of them partial
    single = gym.make(ENV_ID, max_episode_steps=horizon, **kwargs)
    sync = gym.vector.SyncVectorEnv([lambda: copy.deepcopy(single) for _ in range(n)])
    rng = np.random.default_rng(5)
    actions = rng.uniform(-1.0, 1.0, (steps, n, 1)) * np.array(amplitudes)[:, None]
    actions = actions.astype(np.float32)

    obs, info = native.reset(seed=seed)
    records_n = [{"obs": obs, **info}]
    obs, info = sync.reset(seed=seed)
    records_s = [{"obs": obs, **info}]
    length = np.zeros(n, dtype=int)
    longest, ended_alone = 0, 0
    for a in actions:
        records_n.append(_record(*native.step(a)))
        records_s.append(_record(*sync.step(a)))
        length += 1
        done = records_s[-1]["terminated"] | records_s[-1]["truncated"]
        if done.any():
            longest = max(longest, int(length[done].max()))
            ended_alone += int(0 < done.sum() < n)
            length[done] = -1  # the next step is the autoreset
    _assert_same_records(records_n, records_s)
    # An episode crossed the refill and the segment.
    assert longest > segment_samples(1e-3) > NOISE_BLOCK
    if len(set(amplitudes)) > 1:
        assert ended_alone >= 10  # partial resets
    else:
        assert native.unwrapped._lockstep


def _run_against_singles(vec, singles, actions, seed):
    """Step the vector env and single envs seeded seed + i; compare sample for sample.

    Returns the number of autoresets.
    """
    n = len(singles)
    obs_v, _ = vec.reset(seed=seed)
    obs_s = [env.reset(seed=seed + i)[0] for i, env in enumerate(singles)]
    np.testing.assert_array_equal(obs_v, np.stack(obs_s))
    done = [False] * n
    vector, single = [], []
    for a in actions:
        obs_v, rew_v, term_v, trunc_v, info_v = vec.step(a)
        vector.append((obs_v, rew_v, term_v, trunc_v, info_v["deflection_um"], info_v["voltage_V"]))
        rows = []
        for i, env in enumerate(singles):
            if done[i]:  # next-step autoreset: the reset's observation and info
                obs, info = env.reset()
                rew, term, trunc = 0.0, False, False
            else:
                obs, rew, term, trunc, info = env.step(a[i])
            rows.append((obs, rew, term, trunc, info["deflection_um"], info["voltage_V"]))
            done[i] = term or trunc
        single.append([np.array(column) for column in zip(*rows, strict=True)])
    vector = [np.array(column) for column in zip(*vector, strict=True)]
    single = [np.array(column) for column in zip(*single, strict=True)]
    obs, reward, terminated, truncated, deflection, voltage = vector
    np.testing.assert_array_equal(obs, single[0])  # bitwise
    np.testing.assert_allclose(reward, single[1], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(terminated, single[2])
    np.testing.assert_array_equal(truncated, single[3])
    np.testing.assert_allclose(deflection, single[4], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(voltage, single[5])
    return int((terminated | truncated)[:-1].sum())


@pytest.mark.parametrize(
    "kwargs",
    [
        {"preview": 2},
        {"max_episode_steps": 7, "reference": "sine", "hysteresis": "prandtl-ishlinskii"},
        {"max_episode_steps": 40, "deflection_limit": 600.0, "preview": 3},
    ],
)
def test_vector_env_equals_single_envs_across_autoresets(kwargs):
    """Sub-env i of the vector env is the single env seeded seed + i, autoresets included."""
    n, seed, steps = 3, 11, 300
    horizon = kwargs.pop("max_episode_steps", 2000)
    vec = _make_vec(n, max_episode_steps=horizon, **kwargs)
    single = gym.make(ENV_ID, max_episode_steps=horizon, **kwargs)
    singles = [copy.deepcopy(single) for _ in range(n)]
    actions = np.random.default_rng(1).uniform(-35, 35, (steps, n, 1)).astype(np.float32)
    resets = _run_against_singles(vec, singles, actions, seed)
    if horizon < steps:
        assert resets >= n


@pytest.mark.parametrize("no_limit", [None, -1])
def test_vector_env_without_a_time_limit_runs_past_its_buffers(no_limit):
    """None and -1 mean no limit, as for gym.make; the reference buffer grows on demand."""
    n, steps = 2, 4_500  # past the initial buffer of two segments
    vec = _make_vec(n, max_episode_steps=no_limit, preview=5)
    assert vec.unwrapped.max_episode_steps is None
    single = gym.make(ENV_ID, max_episode_steps=-1, preview=5)
    singles = [copy.deepcopy(single) for _ in range(n)]
    actions = np.random.default_rng(2).uniform(-1, 1, (steps, n, 1)).astype(np.float32)
    assert _run_against_singles(vec, singles, actions, seed=3) == 0
    assert vec.unwrapped._ref_len > steps


@pytest.mark.parametrize("bad", [0, -2, 2.5, "100", True])
def test_vector_env_rejects_a_bad_episode_limit(bad):
    with pytest.raises(ValueError, match=r"max_episode_steps \(steps\) must be an integer >= 1"):
        PiezoBenderVectorEnv(2, max_episode_steps=bad)


def test_vector_env_autoresets_next_step():
    vec = _make_vec(2, max_episode_steps=5)
    vec.reset(seed=0)
    for _ in range(4):
        _, _, _, truncated, _ = vec.step(np.full((2, 1), 10.0, np.float32))
        assert not truncated.any()
    _, _, _, truncated, _ = vec.step(np.full((2, 1), 10.0, np.float32))
    assert truncated.all()
    _, reward, _, truncated, info = vec.step(np.full((2, 1), 45.0, np.float32))
    assert not truncated.any() and np.all(reward == 0.0)
    assert np.all(info["deflection_um"] == 0.0)
    # The reset's info, not the discarded action's.
    assert np.all(info["voltage_V"] == 0.0) and not info["saturated"].any()


@pytest.mark.parametrize("actions", [None, np.array([["5"], ["5"]]), np.zeros((3, 1))])
def test_vector_env_rejects_actions_that_are_not_voltages(actions):
    vec = _make_vec(2)
    vec.reset(seed=0)
    with pytest.raises(ValueError, match=r"numeric array of shape \(2, 1\)"):
        vec.step(actions)
