"""A start away from rest (env reset with initial_voltage) is bumpless for every controller
that has a model: it starts from the steady state that holds the first measurement."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import controllers

MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "identify" / "model")


@pytest.fixture(scope="module")
def env():
    return gym.make("piezo_env:PiezoBender-v0", preview=20)


@pytest.mark.parametrize("name", ["pid", "pid-notch", "pid-ff", "mpc", "nmpc"])
def test_a_start_at_20_volts_holds_the_deflection(name, env, identified_pid_presets):
    """The PID presets are the session's (tuned on the same model; reset restarts them)."""
    if name in identified_pid_presets:
        controller = identified_pid_presets[name]
    else:
        controller = controllers.make(name, MODEL_DIR, env)
    first, _ = env.reset(seed=0, options={"initial_voltage": 20.0, "reference": np.zeros(3)})
    ref = np.full(400, float(first[0]))  # hold the deflection the bender starts at (~660 um)
    obs, _ = env.reset(seed=1, options={"initial_voltage": 20.0, "reference": ref})
    controller.reset(obs)
    errors = []
    for t in range(200):
        obs, _, _, _, info = env.step(controller.act(obs))
        errors.append(info["deflection_um"] - ref[t + 1])
    # Measured: 0.7-1.5 um for the PID family and 1.6 um for the MPCs (1 um sensor noise),
    # against 665-1039 um when they assumed rest at 0 V.
    assert np.abs(errors).max() < 5.0


def test_a_first_measurement_within_the_noise_is_rest(env):
    model = controllers.prediction_model(MODEL_DIR, env)
    start = model.steady_start(0.9, noise_bound_um=1.0)
    assert start.u == 0.0 and not start.x.any()
    away = model.steady_start(300.0, noise_bound_um=1.0)
    assert float(model.c[0] @ away.x) == pytest.approx(300.0, rel=1e-9)


@pytest.mark.parametrize("name", ["pid-ff", "mpc", "nmpc"])
def test_a_known_start_voltage_keeps_the_amplifiers_slew_limit_from_the_first_move(name):
    """Estimated from the first measurement, the start voltage is off by the sensor's noise
    (and the model's gain error), so a first move at the slew limit from it can step further
    from the true voltage than the amplifier passes, and the offset recurs while the loop
    slews. Told the voltage (``initial_voltage``), the controller starts from it: no step is
    slew-limited (measured over 1000 steps: 72 for the MPCs and 1 for ``pid-ff`` without it)."""
    from benchmarks.references import make_reference
    from piezo_env.amplifier import Amplifier

    env = gym.make(
        "piezo_env:PiezoBender-v0",
        preview=20,
        max_episode_steps=300,
        amplifier=Amplifier(5.0, None),
    )
    reference = make_reference("steps", 321, dt=1e-3, seed=0)
    step = env.unwrapped.slew_limit * env.unwrapped.model.dt

    def limited(controller) -> tuple[int, float]:
        obs, _ = env.reset(seed=4, options={"reference": reference, "initial_voltage": -25.0})
        controller.reset(obs)
        first, count = None, 0
        for _ in range(300):
            action = controller.act(obs)
            first = float(action[0]) if first is None else first
            obs, _, _, _, info = env.step(action)
            count += bool(info["slew_limited"])
        return count, first

    told = controllers.make(name, MODEL_DIR, env, initial_voltage=-25.0)
    count, first = limited(told)
    assert count == 0 and abs(first + 25.0) <= step * (1 + 1e-6)
    if name != "pid-ff":  # the estimate's offset, which the setting removes, is seen here
        assert limited(controllers.make(name, MODEL_DIR, env))[0] > 0
    for bad in (31.0, float("nan")):
        with pytest.raises(ValueError, match="initial_voltage"):
            controllers.make(name, MODEL_DIR, env, initial_voltage=bad)
