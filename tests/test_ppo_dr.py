"""Domain-randomised PPO: the randomised training env, observation version 2, old policy files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO

import piezo_env  # noqa: F401  (registers the ids)
from controllers.policy import load_policy, make_policy_controller, save_policy
from piezo_env.wrappers import (
    ObservationConfig,
    ObservationHistory,
    TrackingObservation,
    TrackingObservationVector,
    normalize_observation,
    observation_high,
    past_deflections,
)
from piezo_rl.ppo import (
    RANDOMIZED,
    PPOConfig,
    SB3VectorEnv,
    actor_layers,
    make_training_env,
    train_ppo,
    train_seeds,
)

ENV_ID = "piezo_env:PiezoBender-v0"
TINY = PPOConfig(n_steps=32, batch_size=64, n_epochs=2, net_arch=(16, 16))
POLICIES = Path(__file__).resolve().parents[1] / "docs" / "policies"
DR_KWARGS = {"n_inputs": 3, "n_errors": 2, "n_deflections": 4, "config": TINY}


def _tiny_dr(folder: Path, seed: int = 0) -> Path:
    return train_ppo(
        seed, 128, folder, num_envs=4, preview=3, env_kwargs={"randomize": True}, **DR_KWARGS
    )


# -- training --------------------------------------------------------------------------------


def test_randomised_training_is_seeded_and_records_version_2(tmp_path):
    first = _tiny_dr(tmp_path / "a")
    second = _tiny_dr(tmp_path / "b")
    other = _tiny_dr(tmp_path / "c", seed=1)
    weights = [(f / "weights.npz").read_bytes() for f in (first, second, other)]
    assert weights[0] == weights[1] and weights[0] != weights[2]
    meta = json.loads((first / "policy.json").read_text())
    assert meta["observation"]["version"] == 2 and meta["observation"]["n_deflections"] == 4
    assert meta["training"]["env_kwargs"]["randomize"] is True
    assert "tolerances" in meta["training"]["plants"]
    assert load_policy(first).network.layer_sizes == [2 + 3 + 3 + 2 + 4, 16, 16, 1]


def test_randomised_vector_env_draws_a_plant_per_sub_env_and_reset():
    """Different plants across sub-envs and across autoresets; the same for the same seed."""
    env = make_training_env(4, preview=2, max_episode_steps=5, env_kwargs={"randomize": True})
    venv = SB3VectorEnv(env)
    venv.seed(7)
    venv.reset()
    base = env.unwrapped

    def resonances():
        return np.array([draw.resonance for draw in base.plant_draws])

    first = resonances()
    assert len(set(first.round(9))) == 4  # each sub-env its own plant
    zeros = np.zeros((4, 1), np.float32)
    for _ in range(5):  # the fifth step ends every episode: the adapter autoresets
        venv.step(zeros)
    second = resonances()
    assert len(set(second.round(9))) == 4 and not np.any(np.isclose(first, second))
    again = make_training_env(4, preview=2, max_episode_steps=5, env_kwargs={"randomize": True})
    again.reset(seed=7)
    np.testing.assert_array_equal(
        [d.resonance for d in again.unwrapped.plant_draws], first
    )  # seeded: the same draws for the same seed


def test_randomised_plants_change_the_dynamics_the_policy_sees():
    """The same drive gives different deflections on the plants of different sub-envs."""
    env = make_training_env(
        3, preview=0, max_episode_steps=50, env_kwargs={"randomize": True, "noise_bound": 0.0}
    )
    env.reset(seed=0)
    for _ in range(20):
        obs, *_ = env.step(np.full((3, 1), 0.5, np.float32))
    assert len(set(np.round(obs[:, 0], 6))) == 3


def test_train_seeds_names_the_folders_after_the_recipe(tmp_path):
    folders = train_seeds(
        [0], 64, tmp_path, name="ppo-dr", num_envs=2, env_kwargs={"randomize": True}, config=TINY
    )
    assert folders == [tmp_path / "ppo-dr-seed0"]
    with pytest.raises(ValueError, match="plain folder prefix"):
        train_seeds([0], 64, tmp_path, name="a/b")


def test_train_rl_randomize_uses_the_recipe(tmp_path, monkeypatch):
    from piezo_cli.train_rl import TRAIN_RL

    seen = {}

    def fake_train(seed, steps, out, **kwargs):
        seen.update(seed=seed, steps=steps, **kwargs)
        return Path(out)

    monkeypatch.setattr("piezo_rl.ppo.train_ppo", fake_train)
    parser = argparse.ArgumentParser()
    TRAIN_RL.add_arguments(parser)
    TRAIN_RL.run(parser.parse_args(["--randomize", "--out", str(tmp_path / "dr")]))
    assert seen["steps"] == RANDOMIZED.total_steps
    assert seen["n_deflections"] == RANDOMIZED.n_deflections > 0
    assert seen["env_kwargs"]["randomize"] is True
    assert seen["env_kwargs"]["reference_band"] == RANDOMIZED.reference_band
    seen.clear()
    TRAIN_RL.run(parser.parse_args(["--out", str(tmp_path / "nominal")]))
    assert seen["steps"] == 3_000_000 and "n_deflections" not in seen
    assert "randomize" not in seen["env_kwargs"]


# -- observation version 2 -------------------------------------------------------------------


def test_version_2_layout_and_scaling_by_hand():
    """Measured deflections 10, 40, 70, 100 um at t = 0..3: the entries written out."""
    config = ObservationConfig(
        stroke_um=1000.0,
        u_max=30.0,
        bound_um=5000.0,
        preview=1,
        n_inputs=2,
        n_errors=1,
        n_deflections=3,
    )
    assert config.size == 2 + 1 + 2 + 1 + 3 and config.version == 2
    history = ObservationHistory(1, config)
    ys, refs, volts = [10.0, 40.0, 70.0, 100.0], [20.0, 50.0, 90.0, 150.0], [3.0, 6.0, 9.0]
    history.start(slice(None), np.array([[ys[0], refs[0], refs[0]]]), 0.0)
    obs = history.observe(np.array([[ys[0], refs[0], refs[0]]]))[0]
    np.testing.assert_array_equal(obs[-3:], 0.0)  # at rest: every past deflection is y_0
    for t in (1, 2, 3):
        raw = np.array([[ys[t], refs[t], refs[t]]])
        history.push(slice(None), raw, volts[t - 1])
        obs = history.observe(raw)[0]
    expected = [
        ys[3] / 1000.0,
        (refs[3] - ys[3]) / 1000.0,
        (refs[3] - ys[3]) / 1000.0,
        9.0 / 30.0,
        6.0 / 30.0,
        (refs[2] - ys[2]) / 1000.0,
        (ys[2] - ys[3]) / 1000.0,
        (ys[1] - ys[3]) / 1000.0,
        (ys[0] - ys[3]) / 1000.0,
    ]
    np.testing.assert_array_equal(obs, np.array(expected, dtype=np.float32))
    np.testing.assert_allclose(past_deflections(obs, config), ys[2::-1], rtol=0, atol=1e-4)


def test_version_2_bounds_and_missing_deflections():
    config = ObservationConfig(
        stroke_um=1000.0, u_max=30.0, bound_um=41759.0, preview=2, n_deflections=3
    )
    high = observation_high(config)
    b = config.bound_um
    extreme = normalize_observation(
        np.array([[b, -b, -b, -b], [-b, b, b, b]], np.float32),
        np.array([[30.0] * 4, [-30.0] * 4]),
        np.array([[-2 * b] * 4, [2 * b] * 4]),
        config,
        np.array([[-b] * 3, [b] * 3]),
    )
    np.testing.assert_array_equal(np.abs(extreme).max(axis=0), high)
    assert high[-1] == np.float32(2 * b / 1000.0)
    with pytest.raises(ValueError, match="past deflections"):
        normalize_observation(np.zeros(4), np.zeros(4), np.zeros(4), config)
    with pytest.raises(ValueError, match="n_deflections"):
        ObservationConfig(stroke_um=1.0, u_max=1.0, bound_um=2.0, preview=0, n_deflections=-1)


def test_version_2_single_wrapper_equals_the_vector_wrapper_on_random_plants():
    n, kwargs = 3, {"preview": 2, "max_episode_steps": 30, "randomize": True}
    vec = TrackingObservationVector(
        gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", **kwargs),
        n_inputs=2,
        n_errors=1,
        n_deflections=3,
    )
    singles = [
        TrackingObservation(gym.make(ENV_ID, **kwargs), n_inputs=2, n_errors=1, n_deflections=3)
        for _ in range(n)
    ]
    obs, _ = vec.reset(seed=5)
    for i, env in enumerate(singles):
        np.testing.assert_array_equal(env.reset(seed=5 + i)[0], obs[i])
    rng = np.random.default_rng(0)
    done = [False] * n
    for _ in range(70):  # two autoresets
        actions = rng.uniform(-1.0, 1.0, (n, 1)).astype(np.float32)
        obs, *_ = vec.step(actions)
        for i, env in enumerate(singles):
            if done[i]:
                single, done[i] = env.reset()[0], False
            else:
                single, _, term, trunc, _ = env.step(actions[i])
                done[i] = term or trunc
            np.testing.assert_array_equal(single, obs[i])
            assert vec.observation_space.contains(obs)


def test_version_2_controller_acts_as_the_in_memory_sb3_policy(tmp_path):
    env = TrackingObservation(gym.make(ENV_ID, preview=2), n_inputs=3, n_errors=1, n_deflections=4)
    model = PPO("MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=1, seed=1, device="cpu")
    model.learn(128)
    save_policy(
        tmp_path, layers=actor_layers(model.policy), activation="tanh", observation=env.config
    )
    raw_env = gym.make(ENV_ID, preview=5)  # a longer preview is cut to the policy's
    controller = make_policy_controller(tmp_path, raw_env)
    obs, _ = env.reset(seed=3)
    raw, _ = raw_env.reset(seed=3)
    controller.reset(raw)
    for _ in range(40):
        expected, _ = model.predict(obs, deterministic=True)
        volts = float(np.asarray(controller.act(raw)).reshape(-1)[0])
        assert abs(volts - float(expected[0]) * 30.0) <= 30.0 * 2e-6
        action = np.float32(volts / 30.0)
        obs, *_ = env.step(np.array([action]))
        raw, *_ = raw_env.step(np.array([volts], np.float32))


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        ({"version": 3}, "must be 1 or 2"),
        ({"version": 2}, "n_deflections"),
        ({"version": 2, "n_deflections": 0}, "positive integer"),
        ({"n_deflections": 2}, "needs 'observation.version' 2"),
    ],
)
def test_observation_version_is_checked_on_load(tmp_path, edit, match):
    for name in ("policy.json", "weights.npz"):
        (tmp_path / name).write_bytes((POLICIES / "ppo-seed0" / name).read_bytes())
    document = json.loads((tmp_path / "policy.json").read_text())
    document["observation"].update(edit)
    (tmp_path / "policy.json").write_text(json.dumps(document))
    with pytest.raises(ValueError, match=match):
        load_policy(tmp_path)


# -- the committed nominal policies ----------------------------------------------------------


def _version_1_actions(folder: Path, raws: list[np.ndarray], volts: list[float]) -> np.ndarray:
    """Actions of a version 1 policy file written out from its documented layout, by hand."""
    meta = json.loads((folder / "policy.json").read_text())
    o = meta["observation"]
    s, u_max, p = o["stroke_um"], o["u_max"], o["preview"]
    with np.load(folder / "weights.npz") as data:
        layers = [
            (data[f"layer{i}.weight"].astype(float), data[f"layer{i}.bias"].astype(float))
            for i in range(len(data.files) // 2)
        ]
    actions = []
    past_u = [volts[0]] * o["n_inputs"]  # at rest under the reset's voltage
    past_e = [raws[0][1] - raws[0][0]] * o["n_errors"]
    for t, raw in enumerate(raws):
        if t > 0:
            past_u = [volts[t], *past_u[:-1]]
            past_e = [raws[t - 1][1] - raws[t - 1][0], *past_e[:-1]]
        y = float(raw[0])
        x = [y / s] + [(float(r) - y) / s for r in raw[1 : 2 + p]]
        x += [u / u_max for u in past_u] + [e / s for e in past_e]
        h = np.asarray(x, dtype=np.float32).astype(float)
        for i, (w, b) in enumerate(layers):
            h = w @ h + b
            if i < len(layers) - 1:
                h = np.tanh(h)
        actions.append(np.clip(np.float32(h[0]), -1.0, 1.0) * np.float32(u_max))
    return np.asarray(actions, dtype=np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_committed_nominal_policies_load_as_version_1_and_act_as_before(seed):
    folder = POLICIES / f"ppo-seed{seed}"
    policy = load_policy(folder)
    assert "version" not in policy.metadata["observation"]
    assert policy.observation.version == 1 and policy.observation.size == 20
    env = gym.make(ENV_ID, preview=20, max_episode_steps=200)
    controller = make_policy_controller(folder, env)
    raw, _ = env.reset(seed=0)
    controller.reset(raw)
    raws, volts = [raw], [0.0]
    for _ in range(150):
        voltage = float(np.asarray(controller.act(raws[-1])).reshape(-1)[0])
        volts.append(voltage)
        raw, *_ = env.step(np.array([voltage], np.float32))
        raws.append(raw)
    expected = _version_1_actions(folder, raws[:-1], volts)
    np.testing.assert_allclose(volts[1:], expected, rtol=0, atol=1e-5)
    assert np.ptp(volts) > 1.0  # the policy really acts
