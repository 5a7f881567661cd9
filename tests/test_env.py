"""PiezoBender-v0 against Gymnasium's and stable-baselines3's checkers and its own contract."""

from __future__ import annotations

import dataclasses
import pickle
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import piezo_env  # noqa: F401  (registers the ids)
from piezo_env import TaskConfig
from piezo_env.env import PiezoBenderEnv

ENV_ID = "piezo_env:PiezoBender-v0"


def _rollout(env, actions, seed):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, reward, _terminated, _truncated, info = env.step(np.array([a], dtype=np.float32))
        out.append(np.r_[obs, reward, info["deflection_um"]])
    return out


def test_make_works_in_a_fresh_interpreter():
    code = (
        "import gymnasium as gym; env = gym.make('piezo_env:PiezoBender-v0'); "
        "obs, _ = env.reset(seed=0); print(env.spec.max_episode_steps, obs.dtype)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["2000", "float32"]


def test_make_vec_with_the_module_prefix_works_in_a_fresh_interpreter():
    code = (
        "import gymnasium as gym; "
        "vec = gym.make_vec('piezo_env:PiezoBender-v0', num_envs=4, "
        "vectorization_mode='vector_entry_point'); "
        "obs, _ = vec.reset(seed=0); vec.step(vec.action_space.sample()); "
        "print(type(vec.unwrapped).__name__, *obs.shape, vec.unwrapped.max_episode_steps)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["PiezoBenderVectorEnv", "4", "3", "2000"]


def test_package_exposes_its_public_names_lazily():
    """``import piezo_env`` registers the id without importing the env; names load on access."""
    code = (
        "import sys, piezo_env, gymnasium as gym\n"
        "from piezo_env.config import DEFAULT_HORIZON\n"
        "assert gym.spec('PiezoBender-v0').max_episode_steps == DEFAULT_HORIZON\n"
        "assert 'piezo_env.env' not in sys.modules and 'piezo_env.model' not in sys.modules\n"
        "assert set(piezo_env.__all__) <= set(dir(piezo_env))\n"
        "from piezo_env import PiezoBenderEnv, TaskConfig, DomainRandomization, CATALOGUE\n"
        "assert all(getattr(piezo_env, name) is not None for name in piezo_env.__all__)\n"
        "assert PiezoBenderEnv.__module__ == 'piezo_env.env'\n"
        "try:\n"
        "    piezo_env.no_such_name\n"
        "except AttributeError as error:\n"
        "    print(error)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "no_such_name" in out.stdout


def _checker_warnings(check, env) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check(env)
    return [str(w.message) for w in caught]


# The action is a voltage in volts, as the physics asks; both checkers recommend a [-1, 1] action
# for RL, which gymnasium.wrappers.RescaleAction gives. That recommendation is the only remark.
_RESCALE_HINT = "symmetric and normalized"


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"reference": None},
        {"preview": 5, "hysteresis": "prandtl-ishlinskii"},
        {"bender": "PL112", "noise_bound": 0.0},
    ],
)
def test_gymnasium_checker_passes_without_warnings(kwargs):
    env = gym.make(ENV_ID, **kwargs)
    remarks = _checker_warnings(lambda e: check_env(e, skip_render_check=True), env.unwrapped)
    assert all(_RESCALE_HINT in r for r in remarks), remarks


def test_stable_baselines3_checker_passes_without_warnings():
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env = gym.make(ENV_ID, preview=3)
    remarks = _checker_warnings(lambda e: sb3_checker.check_env(e, warn=True), env)
    assert all(_RESCALE_HINT in r for r in remarks), remarks
    unit = np.ones(1, dtype=np.float32)  # float32 bounds, as the action space's own
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the wrapper itself must not warn either
        rescaled = gym.wrappers.RescaleAction(gym.make(ENV_ID, preview=3), -unit, unit)
    assert _checker_warnings(lambda e: sb3_checker.check_env(e, warn=True), rescaled) == []


def test_step_types_and_spaces():
    env = gym.make(ENV_ID)
    obs, info = env.reset(seed=3)
    assert obs.dtype == np.float32 and obs.shape == (3,)  # y_t, r_t, r_{t+1}
    assert env.action_space.low[0] == -30.0 and env.action_space.high[0] == 30.0
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
    assert set(info) == {
        "deflection_um",
        "voltage_V",
        "effective_voltage_V",
        "charge_uC",
        "reference_um",
        "saturated",
    }
    assert env.observation_space.contains(obs)


def test_same_seed_same_trajectory_bitwise():
    actions = np.random.default_rng(0).uniform(-30, 30, 300)
    a = _rollout(gym.make(ENV_ID), actions, seed=42)
    b = _rollout(gym.make(ENV_ID), actions, seed=42)
    c = _rollout(gym.make(ENV_ID), actions, seed=43)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_pickle_round_trip_continues_identically():
    env = gym.make(ENV_ID)
    env.reset(seed=5)
    for _ in range(50):
        env.step(np.array([7.0], dtype=np.float32))
    clone = pickle.loads(pickle.dumps(env))
    for v in np.linspace(-30, 30, 40):
        a = np.array([v], dtype=np.float32)
        assert np.array_equal(env.step(a)[0], clone.step(a)[0])


def test_named_reference_continues_past_its_first_segment():
    env = gym.make(ENV_ID, max_episode_steps=5000, reference="sine", noise_bound=0.0)
    env.reset(seed=2)
    refs = [env.step(np.zeros(1, np.float32))[0][1] for _ in range(5000)]
    assert np.std(refs[:2000]) > 1.0 and np.std(refs[2100:]) > 1.0


def test_observations_stay_inside_bounds_under_bang_bang_at_resonance():
    env = gym.make(ENV_ID, max_episode_steps=6000)
    env.reset(seed=0)
    f1 = env.unwrapped.model.beam.frequencies[0]
    proven = env.unwrapped.model.deflection_bound_um()
    assert proven + env.unwrapped.noise_bound <= env.observation_space.high[0]
    peak = 0.0
    for k in range(6000):
        v = 30.0 if np.sin(2 * np.pi * f1 * k * 1e-3) >= 0 else -30.0
        obs, *_, info = env.step(np.array([v], dtype=np.float32))
        assert env.observation_space.contains(obs)
        peak = max(peak, abs(info["deflection_um"]))
    assert peak > 10 * env.unwrapped.model.stroke_um  # resonance really was excited
    assert peak <= proven


def test_long_random_run_stays_finite_and_bounded():
    env = PiezoBenderEnv(hysteresis="bouc-wen", creep=True)
    env.reset(seed=1)
    actions = env.np_random.uniform(-30, 30, 100_000).astype(np.float32)
    high = env.observation_space.high[0]
    worst = 0.0
    for a in actions:
        obs, *_ = env.step(a.reshape(1))
        worst = max(worst, abs(float(obs[0])))
    assert np.isfinite(worst) and worst <= high


def test_saturation_is_clipped_and_reported():
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([45.0], dtype=np.float32))
    assert info["saturated"] and info["voltage_V"] == 30.0
    _, _, _, _, info = env.step(np.array([-12.0], dtype=np.float32))
    assert not info["saturated"] and info["voltage_V"] == pytest.approx(-12.0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_action_raises(bad):
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([bad], dtype=np.float32))


def test_wrong_action_shape_raises():
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.unwrapped.step(np.zeros(2, dtype=np.float32))


def test_bad_construction_raises():
    with pytest.raises(TypeError, match=r"voltage_gain.*damping_ratio"):  # names the valid ones
        gym.make(ENV_ID, voltage_gain=2.0)
    with pytest.raises(ValueError, match="unknown bender"):
        gym.make(ENV_ID, bender="PL999")
    with pytest.raises(ValueError, match="noise_bound"):
        gym.make(ENV_ID, noise_bound=-1.0)
    with pytest.raises(ValueError, match="reference"):
        gym.make(ENV_ID, reference="sawtooth")
    with pytest.raises(ValueError, match="render_mode"):
        PiezoBenderEnv(render_mode="ascii")  # gym.make would warn before the env raises


@pytest.mark.parametrize("ratio", [2, 1.0, 0.0, -0.1, 1e-5, float("nan"), "0.02"])
def test_damping_ratio_outside_its_range_says_the_range(ratio):
    with pytest.raises(ValueError, match=r"damping_ratio .* >= 0\.0001 and < 1, got") as caught:
        PiezoBenderEnv(damping_ratio=ratio)
    assert "undamped" not in str(caught.value)


def test_reference_array_with_a_nan_reports_index_and_value():
    ref = np.linspace(0.0, 100.0, 10)
    ref[7] = np.nan
    with pytest.raises(ValueError, match=r"finite.*nan at index 7"):
        PiezoBenderEnv(reference=ref)
    env = PiezoBenderEnv()
    ref[7], ref[3] = 1.0, np.inf
    with pytest.raises(ValueError, match="inf at index 3"):
        env.reset(seed=0, options={"reference": ref})


def test_reference_none_is_regulation_and_rejects_a_preview():
    env = PiezoBenderEnv(reference=None, noise_bound=0.0)
    assert env.preview == 0 and env.observation_space.shape == (1,)
    env.reset(seed=0)
    obs, reward, *_, info = env.step(np.array([10.0], dtype=np.float32))
    assert obs.shape == (1,) and "reference_um" not in info
    assert reward == pytest.approx(-((info["deflection_um"] / env.model.stroke_um) ** 2))
    with pytest.raises(ValueError, match="preview=2 needs a reference"):
        PiezoBenderEnv(reference=None, preview=2)
    assert PiezoBenderEnv(reference=None, preview=0).observation_space.shape == (1,)


def test_task_config_holds_the_defaults_and_builds_the_env():
    config = TaskConfig()
    assert (config.bender, config.preview, config.noise_bound) == ("PL140", 1, 1.0)
    assert TaskConfig(reference=None).preview == 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.preview = 3
    assert PiezoBenderEnv().config == config
    env = gym.make(ENV_ID, config=TaskConfig(bender="PL112", preview=4), noise_bound=0.5)
    assert env.unwrapped.config == TaskConfig(bender="PL112", preview=4, noise_bound=0.5)
    assert env.observation_space.shape == (6,)
    ref = np.arange(5.0)
    assert TaskConfig(reference=ref) == TaskConfig(reference=ref.copy())
    assert TaskConfig(reference=ref) != TaskConfig(reference=ref + 1)
    with pytest.raises(TypeError, match=r"unknown keyword argument.*'steps'"):
        TaskConfig.from_kwargs(steps=3)
    with pytest.raises(ValueError, match="deflection_limit"):
        TaskConfig(deflection_limit=0.0)


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (None, "None, which is not a voltage"),
        ("5", "numeric array of shape \\(1,\\)"),
        (np.array(["5"]), "numeric array of shape \\(1,\\)"),
        (np.array([True]), "numeric array"),
        (np.array([[1.0]]), "shape \\(1,\\)"),
    ],
)
def test_action_that_is_not_a_voltage_is_rejected(action, message):
    env = PiezoBenderEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        env.step(action)


@pytest.mark.parametrize(
    "action",
    [
        np.array([5.0], dtype=np.float32),
        np.array([5.0]),
        np.float32(5.0),
        np.float64(5.0),
        np.array([5], dtype=np.int16),
        5,
        5.0,
    ],
)
def test_numeric_actions_are_accepted(action):
    env = PiezoBenderEnv()
    env.reset(seed=0)
    *_, info = env.step(action)
    assert info["voltage_V"] == 5.0 and not info["saturated"]


def test_reference_array_and_initial_voltage_options():
    env = gym.make(ENV_ID, noise_bound=0.0, preview=2)
    ref = np.linspace(0, 500, 10)
    obs, _info = env.reset(seed=0, options={"reference": ref, "initial_voltage": 15.0})
    model = env.unwrapped.model
    state, _ = model.static_state(15.0)
    assert obs[0] == pytest.approx(model.discrete.output_matrix[0] @ state * 1e6, rel=1e-6)
    np.testing.assert_allclose(obs[1:], ref[:3], rtol=1e-6)
    for _ in range(20):
        obs, *_ = env.step(np.array([15.0], dtype=np.float32))
    np.testing.assert_allclose(obs[1:], [500.0] * 3)  # the last value holds past the end
    with pytest.raises(ValueError, match="reset options"):
        env.reset(options={"reference_um": ref})
    with pytest.raises(ValueError, match="beyond"):
        env.reset(options={"reference": np.full(5, 1e9)})


@pytest.mark.parametrize(("preview", "hysteresis"), [(None, None), (3, "bouc-wen")])
def test_timing_reward_observation_and_info_against_an_independent_computation(preview, hysteresis):
    """The reward of a_t is scored against r_{t+1}, which the default observation shows.

    The reference changes every sample (r_t = 5 t um), so scoring against r_t, or showing the
    wrong window, fails. The deflection comes from the model's own open-loop simulation.
    """
    steps = 150
    ref = 5.0 * np.arange(steps + 10)
    env = gym.make(ENV_ID, reference=ref, noise_bound=0.0, preview=preview, hysteresis=hysteresis)
    p = env.unwrapped.preview
    assert p == (1 if preview is None else preview)
    voltage = np.random.default_rng(4).uniform(-30, 30, steps).astype(np.float32)
    model = env.unwrapped.model
    y = model.simulate(voltage.astype(np.float64)).deflection_um  # y[t] = y_{t+1}: after u[t]
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs[1:], ref[: p + 1].astype(np.float32))
    assert info["reference_um"] == ref[0] and info["deflection_um"] == 0.0
    for t in range(steps):
        obs, reward, _, _, info = env.step(voltage[t : t + 1])
        assert info["deflection_um"] == pytest.approx(y[t], rel=1e-9, abs=1e-9)
        assert info["reference_um"] == ref[t + 1]
        assert reward == pytest.approx(-(((y[t] - ref[t + 1]) / model.stroke_um) ** 2), rel=1e-9)
        assert obs[0] == pytest.approx(y[t], rel=1e-6, abs=1e-3)
        np.testing.assert_array_equal(obs[1:], ref[t + 1 : t + p + 2].astype(np.float32))
        if p >= 1:  # index 2 holds the sample the next reward is scored against
            assert obs[2] == ref[t + 2]


def test_reward_is_normalised_squared_tracking_error():
    env = gym.make(ENV_ID, noise_bound=0.0, reference=np.full(50, 200.0))
    env.reset(seed=0)
    _, reward, _, _, info = env.step(np.array([10.0], dtype=np.float32))
    expected = -(((info["deflection_um"] - 200.0) / env.unwrapped.model.stroke_um) ** 2)
    assert reward == pytest.approx(expected)


def test_deflection_limit_terminates():
    env = gym.make(ENV_ID, deflection_limit=300.0)
    env.reset(seed=0)
    terminated = False
    for _ in range(100):
        _, _, terminated, _, info = env.step(np.array([30.0], dtype=np.float32))
        if terminated:
            break
    assert terminated and abs(info["deflection_um"]) > 300.0


def test_truncation_at_max_episode_steps():
    env = gym.make(ENV_ID, max_episode_steps=10)
    env.reset(seed=0)
    flags = [env.step(np.zeros(1, np.float32))[3] for _ in range(10)]
    assert flags == [False] * 9 + [True]


def test_rgb_array_render_draws_the_beam():
    env = gym.make(ENV_ID, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(20):
        env.step(np.array([25.0], dtype=np.float32))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.std() > 10  # something was drawn
    env.close()


def test_default_env_reproduces_the_golden_trajectory():
    from golden import GOLDEN, golden_trajectory

    expected = np.load(GOLDEN, allow_pickle=False)
    actual = golden_trajectory()
    np.testing.assert_allclose(actual["voltage"], expected["voltage"])
    np.testing.assert_allclose(
        actual["deflection_um"], expected["deflection_um"], rtol=1e-9, atol=1e-6
    )
    np.testing.assert_allclose(actual["observation"], expected["observation"], rtol=1e-6, atol=1e-3)
