"""PPO training, the SB3 adapter, policy files and the policy controller."""

from __future__ import annotations

import itertools
import json

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO

import piezo_env  # noqa: F401  (registers the ids)
from controllers import ControlTask, run_episode
from controllers.policy import (
    PolicyController,
    load_policy,
    make_policy_controller,
    save_policy,
)
from piezo_env.wrappers import ObservationConfig, TrackingObservation
from piezo_rl.ppo import (
    PPOConfig,
    SB3VectorEnv,
    actor_layers,
    make_training_env,
    train_ppo,
)

ENV_ID = "piezo_env:PiezoBender-v0"
TINY = PPOConfig(n_steps=32, batch_size=64, n_epochs=2, net_arch=(16, 16))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny PPO (256 steps) trained by train_ppo, and its folder."""
    folder = tmp_path_factory.mktemp("policy")
    train_ppo(0, 256, folder, num_envs=4, preview=3, n_inputs=2, n_errors=2, config=TINY)
    return folder


def test_train_ppo_writes_loadable_plain_files(trained):
    assert sorted(p.name for p in trained.iterdir()) == ["policy.json", "weights.npz"]
    policy = load_policy(trained)
    meta = policy.metadata
    assert policy.network.layer_sizes == [2 + 3 + 2 + 2, 16, 16, 1]
    assert meta["training"]["seed"] == 0 and meta["training"]["total_steps"] == 256
    assert meta["observation"]["preview"] == 3 and meta["action"]["volts_per_unit"] == 30.0
    assert {"stable_baselines3", "torch"} <= set(meta["versions"])
    with np.load(trained / "weights.npz", allow_pickle=False) as data:
        assert all(data[k].dtype == np.float32 for k in data.files)


def test_training_is_seeded(tmp_path, trained):
    train_ppo(0, 256, tmp_path, num_envs=4, preview=3, n_inputs=2, n_errors=2, config=TINY)
    assert (tmp_path / "weights.npz").read_bytes() == (trained / "weights.npz").read_bytes()


def test_saved_policy_acts_as_the_in_memory_sb3_policy(tmp_path):
    env = TrackingObservation(gym.make(ENV_ID, preview=2), n_inputs=3, n_errors=1)
    model = PPO("MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=1, seed=1, device="cpu")
    model.learn(256)
    save_policy(
        tmp_path, layers=actor_layers(model.policy), activation="tanh", observation=env.config
    )
    network = load_policy(tmp_path).network
    obs, _ = env.reset(seed=4)
    for _ in range(30):
        expected, _ = model.predict(obs, deterministic=True)
        mine = np.clip(network.mean(obs[None])[0], -1.0, 1.0)
        np.testing.assert_allclose(mine, expected, rtol=0, atol=2e-6)
        obs, *_ = env.step(model.predict(obs, deterministic=False)[0])


def test_controller_equals_the_policy_on_the_wrapped_env(trained):
    network = load_policy(trained).network
    wrapped = TrackingObservation(gym.make(ENV_ID, preview=3), n_inputs=2, n_errors=2)
    raw_env = gym.make(ENV_ID, preview=3)
    controller = make_policy_controller(trained, raw_env)
    obs, _ = wrapped.reset(seed=2)
    raw, _ = raw_env.reset(seed=2)
    controller.reset(raw)
    for _ in range(40):
        action = np.clip(network.mean(obs[None])[0], -1.0, 1.0).astype(np.float32)
        volts = controller.act(raw)
        assert volts == np.float32(action[0] * np.float32(30.0))
        obs, *_ = wrapped.step(action)
        raw, *_ = raw_env.step(volts)


@pytest.mark.parametrize(
    ("n_inputs", "n_errors", "n_deflections"), [(2, 2, 0), (0, 3, 4), (3, 0, 2), (5, 1, 0)]
)
def test_controller_keeps_the_wrappers_observation_to_the_bit(
    tmp_path, n_inputs, n_errors, n_deflections
):
    """The controller shifts its normalised history in place; the wrapper recomputes it every
    step (piezo_env.wrappers.ObservationHistory). Any layout, every step, the same bits."""
    wrapped = TrackingObservation(
        gym.make(ENV_ID, preview=4),
        n_inputs=n_inputs,
        n_errors=n_errors,
        n_deflections=n_deflections,
    )
    size = wrapped.config.size
    rng = np.random.default_rng(7)
    sizes = [size, 16, 16, 1]
    layers = [
        (rng.normal(0.0, 1.5 / np.sqrt(m), (n, m)), rng.normal(0.0, 0.1, n))
        for m, n in itertools.pairwise(sizes)
    ]
    save_policy(tmp_path, layers=layers, activation="tanh", observation=wrapped.config)
    network = load_policy(tmp_path).network
    raw_env = gym.make(ENV_ID, preview=6)
    controller = make_policy_controller(tmp_path, raw_env)
    obs, _ = wrapped.reset(seed=4)
    raw, _ = raw_env.reset(seed=4)
    controller.reset(raw)
    for _ in range(60):
        action = np.clip(network.mean(obs[None])[0], -1.0, 1.0).astype(np.float32)
        volts = controller.act(raw)
        np.testing.assert_array_equal(controller._x[0], obs)  # the observation, to the bit
        assert volts[0] == np.float32(action[0] * 30.0)
        obs, *_ = wrapped.step(action)
        raw, *_ = raw_env.step(volts)
    assert np.ptp(obs[wrapped.config.raw_size :]) > 0.0  # the history really moved


def test_controller_through_run_episode_is_finite_in_range_and_deterministic(trained):
    env = gym.make(ENV_ID, preview=3)
    controller = make_policy_controller(trained, env)
    reference = 300.0 * np.sin(np.arange(400) * 2 * np.pi * 10e-3)
    first = run_episode(env, controller, seed=0, reference=reference, max_steps=300)
    second = run_episode(env, controller, seed=0, reference=reference, max_steps=300)
    assert np.isfinite(first.voltage_V).all() and np.abs(first.voltage_V).max() <= 30.0
    np.testing.assert_array_equal(first.voltage_V, second.voltage_V)
    assert np.isfinite(first.metrics["rmse_percent"])
    assert first.controller["name"] == "policy"


def test_registry_style_construction(trained):
    task = ControlTask(dt=1e-3, u_max=30.0, stroke_um=1000.0, preview=3)
    controller = PolicyController(trained, task, PolicyController.Settings(), name="ppo")
    assert controller.describe()["name"] == "ppo"
    with pytest.raises(ValueError, match="preview"):
        PolicyController(trained, ControlTask(dt=1e-3, u_max=30.0, stroke_um=1000.0, preview=2))
    with pytest.raises(ValueError, match="unknown option"):
        make_policy_controller(trained, gym.make(ENV_ID, preview=3), gain=2.0)
    for voltage in (float("nan"), "5", 31.0):  # refused when built, not at the first act
        with pytest.raises(ValueError, match="initial_voltage must be a number within"):
            PolicyController(trained, task, PolicyController.Settings(initial_voltage=voltage))


def _copy(src, dst):
    dst.mkdir(exist_ok=True)
    for name in ("policy.json", "weights.npz"):
        (dst / name).write_bytes((src / name).read_bytes())
    return dst


def test_corrupted_weights_are_a_value_error_naming_the_file(trained, tmp_path):
    folder = _copy(trained, tmp_path / "p")
    data = bytearray((folder / "weights.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (folder / "weights.npz").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"weights\.npz.*sha256"):
        load_policy(folder)
    (folder / "weights.npz").unlink()
    with pytest.raises(ValueError, match=r"weights\.npz: missing"):
        load_policy(folder)


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d["architecture"].__setitem__("layer_sizes", [9, 8, 1]), "layer_sizes"),
        (lambda d: d["observation"].__setitem__("preview", -1), "observation"),
        (lambda d: d["observation"].pop("stroke_um"), "observation.stroke_um"),
        (lambda d: d.__setitem__("format", "pickle"), "format"),
        (lambda d: d["weights"].__setitem__("sha256", "0" * 64), "weights.sha256"),
        (lambda d: d["architecture"].__setitem__("activation", "gelu"), "activation"),
    ],
)
def test_tampered_json_is_a_value_error_naming_the_field(trained, tmp_path, edit, field):
    folder = _copy(trained, tmp_path / "p")
    document = json.loads((folder / "policy.json").read_text())
    edit(document)
    (folder / "policy.json").write_text(json.dumps(document))
    with pytest.raises(ValueError, match=rf"policy\.json.*{field}|{field}.*policy\.json"):
        load_policy(folder)


def test_missing_or_unreadable_json(tmp_path):
    with pytest.raises(ValueError, match=r"policy\.json: missing"):
        load_policy(tmp_path)
    (tmp_path / "policy.json").write_text("{not json")
    with pytest.raises(ValueError, match="not readable JSON"):
        load_policy(tmp_path)


def test_adapter_gives_sb3_same_step_autoreset():
    venv = SB3VectorEnv(make_training_env(2, preview=1, max_episode_steps=5))
    venv.seed(3)
    first = venv.reset()
    reference = make_training_env(2, preview=1, max_episode_steps=5)
    np.testing.assert_array_equal(first, reference.reset(seed=3)[0])
    actions = np.zeros((2, 1), np.float32)
    for _ in range(4):
        _, _, dones, infos = venv.step(actions)
        assert not dones.any() and infos == [{}, {}]
    obs, _, dones, infos = venv.step(actions)
    assert dones.all() and all(info["TimeLimit.truncated"] for info in infos)
    last = reference
    for _ in range(5):
        final, *_ = last.step(actions)
    np.testing.assert_array_equal(infos[0]["terminal_observation"], final[0])
    restarted, *_ = last.step(actions)  # next-step autoreset: the new episode's start
    np.testing.assert_array_equal(obs, restarted)


def test_ppo_config_and_train_arguments_are_validated(tmp_path):
    with pytest.raises(ValueError, match="gamma"):
        PPOConfig(gamma=1.5)
    with pytest.raises(ValueError, match="total_steps"):
        train_ppo(0, 0, tmp_path)
    with pytest.raises(ValueError, match="activation"):
        save_policy(
            tmp_path,
            layers=[(np.zeros((1, 4)), np.zeros(1))],
            activation="gelu",
            observation=ObservationConfig(stroke_um=1.0, u_max=1.0, bound_um=2.0, preview=0),
        )


def test_train_rl_subcommand_trains_and_refuses_without_the_extra(tmp_path, monkeypatch):
    import argparse
    import importlib.util

    from piezo_cli.command import CommandLineError
    from piezo_cli.train_rl import MISSING_EXTRA, TRAIN_RL

    parser = argparse.ArgumentParser()
    TRAIN_RL.add_arguments(parser)
    out = tmp_path / "cli"
    args = parser.parse_args(["--seed", "2", "--steps", "64", "--num-envs", "2", "--out", str(out)])
    assert TRAIN_RL.run(args) == 0
    assert load_policy(out).metadata["training"]["seed"] == 2
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == "stable_baselines3" else real(name, *a),
    )
    args.out = str(tmp_path / "never")
    with pytest.raises(CommandLineError, match=r"pip install \"piezo-testbed\[rl\]\""):
        TRAIN_RL.run(args)
    assert not (tmp_path / "never").exists()
    assert MISSING_EXTRA.startswith("piezo train-rl needs the optional extra")


def test_a_longer_preview_is_cut_to_the_policys_own(trained):
    """Same noise and reference: the samples beyond the policy's preview change nothing."""
    import controllers

    t = np.arange(1, 260) * 1e-3
    reference = 400.0 * np.sin(2 * np.pi * 10.0 * t)
    voltages = []
    for preview in (3, 8):
        env = gym.make(ENV_ID, preview=preview)
        controller = controllers.make("policy", trained, env)
        episode = controllers.run_episode(
            env, controller, seed=5, reference=reference, max_steps=200
        )
        voltages.append(episode.voltage_V)
    np.testing.assert_array_equal(voltages[0], voltages[1])


def test_seeds_trained_in_worker_processes_equal_train_ppo(trained, tmp_path):
    """Each seed a task of the benchmark's backends: the same policy as a run on its own."""
    from piezo_rl.ppo import train_seeds

    folders = train_seeds(
        [0, 1],
        256,
        tmp_path,
        jobs=2,
        num_envs=4,
        preview=3,
        n_inputs=2,
        n_errors=2,
        config=TINY,
    )
    assert [f.name for f in folders] == ["ppo-seed0", "ppo-seed1"]
    assert (folders[0] / "weights.npz").read_bytes() == (trained / "weights.npz").read_bytes()
    assert (folders[1] / "weights.npz").read_bytes() != (trained / "weights.npz").read_bytes()
    with pytest.raises(ValueError, match="distinct"):
        train_seeds([1, 1], 256, tmp_path)


def test_train_seeds_refuses_to_overwrite_a_policy_before_training(tmp_path, monkeypatch):
    from piezo_rl.ppo import train_seeds

    def refuse(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr("piezo_parallel.backends.run_tasks", refuse)
    (tmp_path / "ppo-seed1").mkdir()
    (tmp_path / "ppo-seed1" / "policy.json").write_text("{}")
    with pytest.raises(ValueError, match="ppo-seed1 hold"):
        train_seeds([0, 1], 10, tmp_path)
    from piezo_cli.main import main

    (tmp_path / "single").mkdir()
    (tmp_path / "single" / "policy.json").write_text("{}")
    assert main(["train-rl", "--out", str(tmp_path / "single"), "--steps", "10"]) == 2
