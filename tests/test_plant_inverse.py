"""The oracle's generated inverse of the plant's own hysteresis, held to the exact numpy inverse
(safeguarded Newton on the closed-form step to 1e-12 V, piezo_env.hysteresis)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import controllers
from benchmarks.plants import PLANTS
from benchmarks.references import make_reference
from controllers.prediction import HysteresisMap, PlantHysteresis
from piezo_env.hysteresis import (
    BoucWen,
    Hysteresis,
    PrandtlIshlinskii,
    RateDependentPrandtlIshlinskii,
)
from piezo_env.randomization import scale_hysteresis

U_MAX = 30.0
TOL = 5e-9  # V: the generated iteration stops at an estimated error of 1e-9 V (measured: 1.3e-9)

CASES = {
    "bouc-wen": BoucWen.for_voltage(U_MAX),
    "bouc-wen x0.7": scale_hysteresis(BoucWen.for_voltage(U_MAX), 0.7, U_MAX),
    "bouc-wen x1.3": scale_hysteresis(BoucWen.for_voltage(U_MAX), 1.3, U_MAX),
    "bouc-wen 120 V": BoucWen.for_voltage(120.0),
    "prandtl-ishlinskii": PrandtlIshlinskii.for_voltage(U_MAX),
    "prandtl-ishlinskii x1.3": scale_hysteresis(PrandtlIshlinskii.for_voltage(U_MAX), 1.3, U_MAX),
}


def reached_states(hysteresis: Hysteresis, u_max: float, n: int, seed: int) -> list[np.ndarray]:
    """States reached from rest by a random walk with jumps over the drive range."""
    rng = np.random.default_rng(seed)
    u = np.clip(np.cumsum(rng.normal(0.0, 0.13 * u_max, 300)), -u_max, u_max)
    jumps = rng.random(u.size) < 0.1
    u[jumps] = rng.uniform(-u_max, u_max, jumps.sum())
    state, states = hysteresis.initial_state(0.0), []
    for v in u:
        state, _ = hysteresis.step(state, float(v))
        states.append(state)
    return [states[i] for i in rng.choice(len(states), n, replace=False)]


@pytest.mark.parametrize("name", CASES)
def test_generated_inverse_equals_the_exact_inverse(name):
    hysteresis = CASES[name]
    u_max = 120.0 if "120" in name else U_MAX
    u_range = (-u_max, u_max)
    plant = PlantHysteresis(hysteresis, u_range)
    assert plant._inverse is not None and plant._inverse.compiled, plant.native
    rng = np.random.default_rng(3)
    statuses, worst = set(), 0.0
    for state in reached_states(hysteresis, u_max, 40, seed=1):
        low, high = (hysteresis.step(state, end)[1] for end in u_range)
        at_kink = hysteresis.step(state, float(state[0]))[1]
        targets = [*rng.uniform(low, high, 4), low - 1.0, high + 1.0, low, high, at_kink]
        for target in targets:
            compiled = plant.inverse(float(target), state)
            exact = hysteresis.inverse(float(target), state, u_range)
            assert compiled.status == exact.status, (target, state)
            assert compiled.u == pytest.approx(exact.u, abs=TOL)
            assert compiled.z == pytest.approx(exact.z, abs=TOL)
            np.testing.assert_allclose(compiled.state, exact.state, rtol=0.0, atol=TOL)
            statuses.add(compiled.status)
            worst = max(worst, abs(compiled.u - exact.u))
        assert plant.reachable(state) == pytest.approx((min(low, high), max(low, high)), abs=1e-12)
    assert statuses == {"ok", "out-of-range"}
    assert plant._inverse.fallbacks == 0


def test_every_strength_of_one_loop_shares_one_compiled_function():
    """The strength is an input of the generated code, so the Monte Carlo's draws (which
    scale it) compile once."""
    builds = [PlantHysteresis(CASES[n], (-U_MAX, U_MAX)).native for n in CASES if "wen x" in n]
    builds.append(PlantHysteresis(CASES["bouc-wen"], (-U_MAX, U_MAX)).native)
    assert len({tuple(b.key for b in native) for native in builds}) == 1
    pi = PlantHysteresis(CASES["prandtl-ishlinskii"], (-U_MAX, U_MAX)).native
    assert pi[0].key != builds[0][0].key


def test_the_rate_dependent_plant_keeps_its_exact_inverse():
    """Its map jumps at the previous input; the numpy inverse detects the jump."""
    hysteresis = RateDependentPrandtlIshlinskii.for_voltage(U_MAX)
    plant = PlantHysteresis(hysteresis, (-U_MAX, U_MAX))
    assert plant._inverse is None and plant.native == []
    with pytest.raises(ValueError, match="no generated inverse"):
        HysteresisMap(hysteresis)
    with pytest.raises(ValueError, match="state must be"):  # checked as the numpy inverse
        PlantHysteresis(BoucWen.for_voltage(U_MAX), (-U_MAX, U_MAX)).inverse(1.0, np.zeros(1))


@pytest.mark.parametrize("plant", ["nominal", "prandtl-ishlinskii"])
def test_the_oracle_closes_the_same_loop_with_either_inverse(plant, monkeypatch):
    """The oracle MPC with the generated inverse (in its compiled step) against the one with
    the exact numpy inverse: the voltages the plant receives agree to float32 rounding."""
    env = gym.make("piezo_env:PiezoBender-v0", preview=20, **PLANTS[plant]("PL140"))
    reference = make_reference("sine-50Hz", 421, dt=1e-3, seed=0)

    def voltages() -> np.ndarray:
        c = controllers.make("mpc", "plant", env)
        episode = controllers.run_episode(
            env, c, seed=0, reference=reference, max_steps=400, stroke_um=1000.0
        )
        return episode.voltage_V, c.describe()["native"]["mpc_step"]["path"]

    generated, path = voltages()
    assert path == "compiled"
    monkeypatch.setattr(Hysteresis, "inverse_parameters", lambda self: None)
    for kind in (BoucWen, PrandtlIshlinskii):
        monkeypatch.setattr(kind, "inverse_parameters", lambda self: None)
    exact, path = voltages()
    assert path == "numpy"
    np.testing.assert_allclose(generated, exact, rtol=0.0, atol=4e-6)  # 2 float32 ulps at 30 V
    assert np.ptp(exact) > 10.0
