"""The per-step fast paths of the closed loop give the bits of the plain code they replace.

The policy controller's step, the base class's ``act``, the observation check, the episode
loop and the env's observation run at every step of every benchmark episode, so they are
written for speed: buffers made once, Python floats for scalars, fewer numpy calls. Each is
held here to the plain numpy arithmetic it replaced, on short episodes of every committed
policy and of policies made here for the layouts and the activation those lack.
"""

from __future__ import annotations

import copy
import itertools
import pickle
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import controllers
import piezo_env  # noqa: F401  (registers the ids)
from benchmarks.references import make_reference
from controllers.base import Controller
from controllers.policy import _OneObservation, make_policy_controller, save_policy
from controllers.task import ControlTask
from piezo_env.wrappers import ObservationConfig

ENV_ID = "piezo_env:PiezoBender-v0"
POLICIES = Path(__file__).resolve().parents[1] / "docs" / "policies"
STEPS = 200


class PlainPolicy:
    """The policy controller's step as first written: numpy expressions, new arrays each step,
    and :meth:`controllers.policy.PolicyNetwork.mean` for the network."""

    def __init__(self, policy) -> None:
        config = self.config = policy.observation
        self.network = policy.network
        self.stroke, self.u_scale = np.float64(config.stroke_um), np.float64(config.u_max)
        self.x = np.zeros((1, config.size), dtype=np.float32)
        self.inputs = slice(config.raw_size, config._errors_start)
        self.errors = slice(config._errors_start, config._deflections_start)
        self.deflections = slice(config._deflections_start, config.size)
        self.past = np.zeros(config.n_deflections)

    def reset(self, observation: np.ndarray) -> None:
        raw = np.asarray(observation[: self.config.raw_size], dtype=np.float64)
        error = raw[1] - raw[0]
        x = self.x[0]
        x[self.inputs] = np.float64(0.0) / self.u_scale
        x[self.errors] = error / self.stroke
        self.past[:] = raw[0]
        self.last_error, self.last_measured = error, raw[0]
        self.last_voltage = None

    def act(self, observation: np.ndarray) -> float:
        raw = np.asarray(observation[: self.config.raw_size], dtype=np.float64)
        y, s = raw[0], self.stroke
        x = self.x[0]
        if self.last_voltage is not None:
            inputs, errors, past = self.inputs, self.errors, self.past
            if inputs.start != inputs.stop:
                x[inputs.start + 1 : inputs.stop] = x[inputs.start : inputs.stop - 1]
                x[inputs.start] = self.last_voltage / self.u_scale
            if errors.start != errors.stop:
                x[errors.start + 1 : errors.stop] = x[errors.start : errors.stop - 1]
                x[errors.start] = self.last_error / s
            if past.size:
                past[1:] = past[:-1]
                past[0] = self.last_measured
        x[0] = y / s
        x[1 : raw.size] = (raw[1:] - y) / s
        if self.past.size:
            x[self.deflections] = (self.past - y) / s
        self.last_error, self.last_measured = raw[1] - y, y
        mean = float(np.float32(self.network.mean(self.x)[0, 0]))
        voltage = float(np.float32(min(max(mean, -1.0), 1.0) * self.u_scale))
        self.last_voltage = voltage
        return voltage


def _env(**settings) -> gym.Env:
    return gym.make(ENV_ID, preview=20, max_episode_steps=STEPS, **settings)


def _steps_reference(env: gym.Env) -> np.ndarray:
    dt = float(env.unwrapped.model.dt)
    return make_reference("steps", STEPS + 21, dt=dt, seed=0)


def _made_policy(folder: Path, env: gym.Env, activation: str, seed: int, **layout) -> Path:
    """A policy of random weights (large enough that the mean leaves [-1, 1] at times)."""
    observation = ObservationConfig.from_env(env, **layout)
    observation = ObservationConfig(**{**observation.__dict__, "preview": 3})
    rng = np.random.default_rng(seed)
    sizes = [observation.size, 24, 16, 1]
    layers = [
        (rng.normal(0, 1.5 / np.sqrt(n_in), (n_out, n_in)), rng.normal(0, 0.3, n_out))
        for n_in, n_out in itertools.pairwise(sizes)
    ]
    return save_policy(folder, layers=layers, activation=activation, observation=observation)


def _policy_folders(tmp_path: Path, env: gym.Env) -> list[Path]:
    committed = sorted(p for p in POLICIES.iterdir() if (p / "policy.json").is_file())
    assert len(committed) == 6
    made = [
        _made_policy(tmp_path / "relu", env, "relu", 0, n_inputs=3, n_errors=0, n_deflections=5),
        _made_policy(tmp_path / "errors", env, "tanh", 1, n_inputs=0, n_errors=2),
        _made_policy(tmp_path / "bare", env, "relu", 2, n_inputs=0, n_errors=0),
    ]
    return committed + made


def test_the_policy_step_equals_the_plain_arithmetic_to_the_bit(tmp_path):
    env = _env()
    reference = _steps_reference(env)
    clipped = 0
    for folder in _policy_folders(tmp_path, env):
        controller = make_policy_controller(folder, env)
        plain = PlainPolicy(controller.policy)
        obs, _ = env.reset(seed=0, options={"reference": reference})
        controller.reset(obs)
        plain.reset(obs)
        for _ in range(STEPS):
            action = controller.act(obs)
            expected = plain.act(obs)
            assert action.tobytes() == np.array([expected], np.float32).tobytes(), folder.name
            assert controller._x.tobytes() == plain.x.tobytes(), folder.name
            clipped += abs(expected) == controller.task.u_max
            obs, *_ = env.step(action)
    assert clipped > 0  # the clip to [-1, 1] was exercised


@pytest.mark.parametrize("activation", ["tanh", "relu"])
def test_one_observation_forward_pass_equals_the_network_mean(tmp_path, activation):
    env = _env()
    folder = _made_policy(tmp_path, env, activation, 3, n_deflections=4)
    network = make_policy_controller(folder, env).policy.network
    forward = _OneObservation(network)
    rng = np.random.default_rng(0)
    for scale in (1e-3, 1.0, 30.0):
        for x in rng.normal(0.0, scale, (300, 1, network.layer_sizes[0])).astype(np.float32):
            assert forward(x) == float(network.mean(x)[0, 0])


def test_a_copied_or_pickled_policy_controller_continues_identically():
    """The step's views into the observation buffer are made again in a copy."""
    env = _env()
    controller = make_policy_controller(POLICIES / "ppo-dr-seed0", env)
    obs, _ = env.reset(seed=0, options={"reference": _steps_reference(env)})
    controller.reset(obs)
    for _ in range(20):
        obs, *_ = env.step(controller.act(obs))
    clones = [copy.deepcopy(controller), pickle.loads(pickle.dumps(controller))]
    for _ in range(50):
        action = controller.act(obs)
        for clone in clones:
            assert clone.act(obs).tobytes() == action.tobytes()
        obs, *_ = env.step(action)


def test_check_observation_converts_and_refuses_as_before():
    task = ControlTask(dt=1e-3, u_max=30.0, stroke_um=1000.0, preview=2)
    as_float64 = np.array([1.0, 2.0, 3.0, 4.0])
    assert task.check_observation(as_float64) is as_float64  # no copy
    single = np.array([1.5, -2.25, 3.1, 4e4], dtype=np.float32)
    checked = task.check_observation(single)
    assert checked.dtype == np.float64 and np.array_equal(checked, single.astype(np.float64))
    assert task.check_observation([1, 2, 3, 4]).dtype == np.float64
    huge = np.full(4, 1e300)  # finite entries whose squares overflow: accepted
    assert task.check_observation(huge) is huge
    with pytest.raises(ValueError, match="must be a numeric array"):
        task.check_observation(np.array(["a", "b", "c", "d"]))
    with pytest.raises(ValueError, match=r"must have shape \(4,\).*got shape \(3,\)"):
        task.check_observation(np.zeros(3))
    with pytest.raises(ValueError, match=r"got shape \(1, 4\)"):
        task.check_observation(np.zeros((1, 4)))
    for index, bad in ((0, np.nan), (2, np.inf), (3, -np.inf)):
        values = np.array([1.0, 2.0, 3.0, 4.0], dtype=np.float32)
        values[index] = bad
        with pytest.raises(ValueError, match=rf"observation\[{index}\] = {bad} is not finite"):
            task.check_observation(values)


def test_a_measurement_beyond_the_env_s_bound_is_refused():
    """One sensor glitch of 1e30 um used to steer the MPC's state so far off that the QP stayed
    infeasible for the rest of the episode (the drive held at one end); a task read from an env
    knows the env's observation bound and refuses it, saying what it is."""
    env = gym.make("piezo_env:PiezoBender-v0", preview=2)
    task = ControlTask.from_env(env)
    assert task.observation_bound_um == float(env.observation_space.high[0])
    obs, _ = env.reset(seed=0)
    assert task.check_observation(obs) is not None
    for glitch in (1e30, -2.0 * task.observation_bound_um):
        bad = obs.astype(np.float64)
        bad[0] = glitch
        with pytest.raises(ValueError, match="beyond any deflection this bender can show"):
            task.check_observation(bad)
    bad = obs.astype(np.float64)
    bad[0] = 1e30
    mpc = controllers.make("mpc", "docs/benchmark/model", env)
    with pytest.raises(ValueError, match="sensor fault"):
        mpc.act(bad)


class Scripted(Controller):
    """A controller whose step returns the next of ``outputs``."""

    def __init__(self, task: ControlTask, outputs: list) -> None:
        super().__init__(task)
        self.outputs = outputs

    def _reset(self, observation: np.ndarray) -> None:
        self.calls = 0

    def _act(self, observation: np.ndarray) -> float:
        self.calls += 1
        return self.outputs[self.calls - 1]


def test_act_returns_the_float32_volts_of_the_plain_expression():
    task = ControlTask(dt=1e-3, u_max=30.0, stroke_um=1000.0, preview=1)
    outputs = [0.1, np.float64(-7.123456789), 12, 40.0, -1e9, 29.999999999, np.float32(0.3)]
    controller = Scripted(task, outputs)
    controller.reset(np.zeros(3))
    for output in outputs:
        action = controller.act(np.zeros(3, dtype=np.float32))
        expected = np.array([min(max(float(output), -30.0), 30.0)], dtype=np.float32)
        assert action.tobytes() == expected.tobytes()
        assert action.dtype == np.float32 and action.shape == (1,)
        assert action.flags.c_contiguous and action.flags.owndata and action.flags.writeable
    assert controller.stats.saturated == 2 and len(controller.stats.compute_s) == len(outputs)
    controller = Scripted(task, [float("nan")])
    controller.reset(np.zeros(3))
    with pytest.raises(RuntimeError, match="NaN voltage"):
        controller.act(np.zeros(3))


def _plain_loop(env, controller, obs, max_steps):
    """The episode loop as first written."""
    u_max = float(env.action_space.high[0])
    columns: dict[str, list] = {k: [] for k in ("y", "m", "r", "u", "sat", "rew", "compute")}
    clock = time.perf_counter
    steps = 0
    while max_steps is None or steps < max_steps:
        start = clock()
        action = controller.act(obs)
        columns["compute"].append(clock() - start)
        obs, reward, terminated, truncated, info = env.step(action)
        columns["y"].append(info["deflection_um"])
        columns["m"].append(float(obs[0]))
        columns["r"].append(info["reference_um"])
        columns["u"].append(info["voltage_V"])
        columns["sat"].append(info["saturated"] or abs(info["voltage_V"]) >= u_max * (1 - 1e-6))
        columns["rew"].append(reward)
        steps += 1
        if terminated or truncated:
            break
    arrays = {k: np.asarray(v, dtype=float) for k, v in columns.items()}
    arrays["sat"] = arrays["sat"].astype(bool)
    return arrays


class Protocol:
    """A bare protocol controller answering with lists, floats, tuples and arrays in turn,
    some beyond the drive range and some just inside its saturation margin."""

    def reset(self, observation) -> None:
        self.t = 0

    def act(self, observation):
        self.t += 1
        u = 29.99999 if self.t % 7 == 1 else 45.0 * np.sin(0.05 * self.t)
        kind = self.t % 4
        if kind == 0:
            return [u]
        if kind == 1:
            return u
        if kind == 2:
            return (np.float64(u),)
        return np.array([u], dtype=np.float32)


@pytest.mark.parametrize(
    ("settings", "max_steps"),
    [({}, None), ({}, 120), ({"deflection_limit": 300.0}, None), ({"amplifier": True}, None)],
)
def test_the_episode_loop_records_the_plain_loops_columns(settings, max_steps):
    from piezo_env import Amplifier

    if settings.get("amplifier"):
        settings = {"amplifier": Amplifier(current_limit_mA=20.0)}
    env = _env(**settings)
    reference = _steps_reference(env)
    saturated = []
    for controller in (Protocol(), make_policy_controller(POLICIES / "ppo-seed1", env)):
        episode = controllers.run_episode(
            env, controller, seed=3, reference=reference, max_steps=max_steps
        )
        saturated.append(episode.saturated.any())
        obs, _ = env.reset(seed=3, options={"reference": np.asarray(reference, float)})
        controller.reset(obs)
        plain = _plain_loop(env, controller, obs, max_steps)
        for name, key in (
            ("deflection_um", "y"),
            ("measured_um", "m"),
            ("reference_um", "r"),
            ("voltage_V", "u"),
            ("saturated", "sat"),
            ("reward", "rew"),
        ):
            mine = getattr(episode, name)
            assert mine.dtype == plain[key].dtype and mine.tobytes() == plain[key].tobytes(), name
        assert episode.compute_s.shape == plain["compute"].shape
        assert episode.compute_s.dtype == np.float64
        if "deflection_limit" in settings:
            assert episode.voltage_V.size < STEPS  # terminated early
    assert saturated[0]  # the protocol controller drives into the limits


@pytest.mark.parametrize("settings", [{"preview": 20}, {"preview": 0}, {"reference": None}])
def test_the_env_observation_is_the_plain_one(settings):
    env = gym.make(ENV_ID, max_episode_steps=300, **settings)
    base = env.unwrapped
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(300):
        obs, *_ = env.step(env.action_space.sample())
        if base._reference is None:
            plain = np.array([obs[0]], dtype=np.float32)
        else:
            plain = np.empty(2 + base.preview, dtype=np.float32)
            plain[0] = obs[0]
            plain[1:] = base._ref_values[base._t : base._t + base.preview + 1]
        assert obs.dtype == np.float32 and obs.tobytes() == plain.tobytes()
        assert obs.flags.c_contiguous and obs.flags.owndata and obs.flags.writeable


def test_an_episode_without_its_description_is_the_same_episode():
    env = _env()
    reference = _steps_reference(env)
    controller = make_policy_controller(POLICIES / "ppo-seed1", env)
    runs = [
        controllers.run_episode(env, controller, seed=3, reference=reference, describe=describe)
        for describe in (True, False, True)
    ]
    assert runs[0].voltage_V.tobytes() == runs[1].voltage_V.tobytes() == runs[2].voltage_V.tobytes()
    timed = ("compute_median_us", "compute_p99_us", "compute_max_us", "deadline_misses")
    assert {k: v for k, v in runs[0].metrics.items() if k not in timed} == {
        k: v for k, v in runs[1].metrics.items() if k not in timed
    }
    assert "name" in runs[0].controller and set(runs[1].controller) == {"stats"}
