"""Domain randomisation: seeded draws, tolerances, the bound over the range, single == vector."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import piezo_env  # noqa: F401  (registers the ids)
from piezo_env import DomainRandomization, TaskConfig
from piezo_env.env import PiezoBenderEnv
from piezo_env.hysteresis import BoucWen, PrandtlIshlinskii
from piezo_env.parameters import cantilever_frequencies
from piezo_env.randomization import (
    DRAW_ORDER,
    PLANT_INFO_KEYS,
    PlantDraw,
    gain_tolerance,
    major_loop_peak,
    strength_gain_range,
)
from piezo_env.randomized_bound import randomized_deflection_bound_um
from piezo_env.task import BenderTask, drawn_plant
from piezo_env.vector_env import PiezoBenderVectorEnv

ENV_ID = "piezo_env:PiezoBender-v0"


def test_option_values_and_validation():
    assert TaskConfig(randomize=True).randomize == DomainRandomization()
    assert TaskConfig(randomize=False).randomize is None
    assert TaskConfig().randomize is None
    spread = DomainRandomization(resonance=0.1, damping_ratio=(0.02, 0.03))
    assert TaskConfig(randomize=spread).randomize is spread
    for bad in ({"resonance": 1.0}, {"free_deflection": -0.1}, {"damping_ratio": (0.04, 0.01)}):
        with pytest.raises(ValueError, match="DomainRandomization"):
            DomainRandomization(**bad)
    with pytest.raises(ValueError, match="damping_ratio"):
        DomainRandomization(damping_ratio=(0.0, 0.02))
    with pytest.raises(ValueError, match="randomize"):
        TaskConfig(randomize="yes")
    # alpha x 1.9 breaks the monotone domain of Bouc-Wen (2 alpha beta / (beta + gamma) < 1)
    strong = BoucWen(alpha=0.6)
    with pytest.raises(ValueError, match="alpha"):
        PiezoBenderEnv(hysteresis=strong, randomize=DomainRandomization(hysteresis_strength=0.9))


def test_same_seed_same_plant_and_a_new_plant_each_reset():
    env = PiezoBenderEnv(randomize=True)
    _, first = env.reset(seed=7)
    matrix = env.unwrapped.model.discrete.step_matrix.copy()
    _, second = env.reset()
    assert first["plant"] != second["plant"]
    _, again = env.reset(seed=7)
    assert again["plant"] == first["plant"]
    assert np.array_equal(env.unwrapped.model.discrete.step_matrix, matrix)
    assert tuple(first["plant"]) == PLANT_INFO_KEYS
    assert all(f"``{key}``" in PiezoBenderEnv.__doc__ for key in PLANT_INFO_KEYS)  # documented
    assert env.unwrapped.task.model is not env.unwrapped.model  # the nominal stays in the task
    # the default env draws nothing and reports no plant
    assert "plant" not in PiezoBenderEnv().reset(seed=7)[1]


def test_draw_order_is_one_uniform_call_in_the_documented_order():
    spread = DomainRandomization()
    nominal = BenderTask(TaskConfig()).model.params.datasheet
    draw = spread.draw(np.random.default_rng(3), nominal)
    low, high = spread.limits(nominal)
    expected = np.random.default_rng(3).uniform(low, high)
    assert [getattr(draw, name) for name in DRAW_ORDER] == expected.tolist()


def test_every_drawn_plant_stays_inside_the_stated_tolerances():
    spread = DomainRandomization()
    nominal_model = BenderTask(TaskConfig()).model
    nominal = nominal_model.params.datasheet
    rng = np.random.default_rng(11)
    draws = np.array(
        [[getattr(spread.draw(rng, nominal), n) for n in DRAW_ORDER] for _ in range(20_000)]
    )
    centre = np.array([nominal.free_deflection, nominal.blocking_force, nominal.resonance])
    relative = draws[:, :3] / centre
    assert relative.min() >= 0.8 and relative.max() <= 1.2
    assert relative.min() < 0.81 and relative.max() > 1.19  # the whole range is used
    assert draws[:, 3].min() >= 0.01 and draws[:, 3].max() <= 0.04
    assert draws[:, 4].min() >= 0.7 and draws[:, 4].max() <= 1.3
    assert abs(np.corrcoef(draws.T)[np.triu_indices(5, 1)]).max() < 0.05  # independent
    peak = major_loop_peak(nominal_model.hysteresis, 30.0)
    for row in draws[:6]:
        draw = PlantDraw(*row)
        model = drawn_plant(nominal_model, draw)
        params = model.params
        # the plant realises the drawn datasheet values exactly (the design's analytic oracles)
        assert params.static_tip_deflection(30.0) == pytest.approx(draw.free_deflection, 1e-12)
        assert params.blocking_force(30.0) == pytest.approx(draw.blocking_force, 1e-12)
        assert cantilever_frequencies(params, 1)[0] == pytest.approx(draw.resonance, 1e-12)
        assert model.beam.frequencies[0] == pytest.approx(draw.resonance, rel=1e-3)
        assert model.beam.damping_ratios[0] == pytest.approx(draw.damping_ratio, 1e-12)
        hyst = model.hysteresis
        assert hyst.alpha == pytest.approx(draw.hysteresis_scale * 0.32, 1e-12)
        assert major_loop_peak(hyst, 30.0) == pytest.approx(peak, 1e-12)  # stroke kept


# The range bound uses the continuous-time L1 norm; sampling a resonance near or above 1/dt
# hides part of it (PL122: 600 Hz at 1 kHz), so the bound is looser there.
@pytest.mark.parametrize(
    ("settings", "slack"),
    [
        ({}, 1.2),
        ({"creep": True}, 1.25),
        ({"hysteresis": "prandtl-ishlinskii", "bender": "PL122"}, 1.6),
        ({"hysteresis": "rate-dependent"}, 1.2),
    ],
)
def test_observation_bound_covers_every_corner_of_the_range(settings, slack):
    """The proven per-plant bound at each of the 32 corners lies inside the env's bound."""
    task = BenderTask(TaskConfig(randomize=True, **settings))
    spread = task.randomization
    low, high = spread.limits(task.model.params.datasheet)
    sup = randomized_deflection_bound_um(task.model, spread)
    assert sup + task.noise_bound <= task.bound
    worst = 0.0
    for corner in itertools.product(*zip(low, high, strict=True)):
        model = drawn_plant(task.model, PlantDraw(*map(float, corner)))
        worst = max(worst, model.deflection_bound_um())
        if isinstance(model.hysteresis, PrandtlIshlinskii):
            assert min(model.hysteresis.weights) > 0 and model.hysteresis.linear_weight > 0
    assert worst <= sup < slack * worst  # covers the range, and not by much


def test_observations_stay_inside_the_space_under_bang_bang_at_each_resonance():
    env = PiezoBenderEnv(randomize=True, noise_bound=1.0)
    high = env.observation_space.high[0]
    for seed in range(4):
        _, info = env.reset(seed=seed)
        model = env.unwrapped.model
        f1 = model.beam.frequencies[0]
        proven = model.deflection_bound_um()
        assert proven + env.noise_bound <= high
        peak = 0.0
        for k in range(1500):
            v = 30.0 if np.sin(2 * np.pi * f1 * k * model.dt) >= 0 else -30.0
            obs, *_, step_info = env.step(np.array([v], dtype=np.float32))
            assert env.observation_space.contains(obs)
            peak = max(peak, abs(step_info["deflection_um"]))
        assert peak <= proven
        assert peak > 8 * info["plant"]["free_deflection_um"]  # resonance really was excited


@pytest.mark.parametrize("hysteresis", ["bouc-wen", "rate-dependent"])
def test_single_env_equals_the_vector_env_across_resets(hysteresis):
    """Sub-env i equals the single env seeded seed + i: draws, obs, rewards, info, plants
    (each drawn plant's hysteresis scaled, the rate-dependent one's too)."""
    n, steps, seed = 4, 900, 5
    kwargs = {
        "randomize": True,
        "deflection_limit": 2500.0,
        "max_episode_steps": 250,
        "hysteresis": hysteresis,
    }
    native = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", **kwargs)
    single = gym.make(ENV_ID, **kwargs)
    sync = gym.vector.SyncVectorEnv([lambda: copy.deepcopy(single) for _ in range(n)])
    amplitudes = np.array([1.0, 30.0, 4.0, 30.0])[:, None]
    actions = np.random.default_rng(2).uniform(-1, 1, (steps, n, 1)) * amplitudes
    records = [(native.reset(seed=seed), sync.reset(seed=seed))]
    for a in actions.astype(np.float32):
        records.append((native.step(a), sync.step(a)))
    plants = 0
    for got, want in records:
        np.testing.assert_allclose(got[0][:, 0], want[0][:, 0], rtol=1e-6, atol=1e-4)
        np.testing.assert_array_equal(got[0][:, 1:], want[0][:, 1:])
        for g, w in zip(got[1:-1], want[1:-1], strict=True):  # rewards and flags
            np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-12)
        g_info, w_info = got[-1], want[-1]
        assert set(g_info) == set(w_info)
        for key in w_info:
            if key == "plant":
                plants += int(w_info["_plant"].sum())
                assert set(g_info[key]) == set(w_info[key])
                for inner, value in w_info[key].items():
                    np.testing.assert_array_equal(g_info[key][inner], value, err_msg=inner)
            else:
                np.testing.assert_allclose(g_info[key], w_info[key], rtol=1e-10, atol=1e-9)
    assert plants > 2 * n  # autoresets drew new plants, at different times
    first = records[0][0][1]["plant"]
    assert len(set(first["resonance_Hz"])) == n  # every sub-env has its own plant


def test_vector_env_plant_matches_the_single_env_plant():
    vec = PiezoBenderVectorEnv(3, randomize=True)
    vec.reset(seed=40)
    env = PiezoBenderEnv(randomize=True)
    _, info = env.reset(seed=42)
    assert vec.plant_draws[2].info() == info["plant"]
    layout = vec._steps_t[2]  # the padded per-env step reproduces the single env's plant
    assert np.count_nonzero(layout) > 0


_RESCALE_HINT = "symmetric and normalized"


def test_both_env_checkers_pass_with_randomisation():
    env = gym.make(ENV_ID, randomize=True, preview=3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=True)
    assert all(_RESCALE_HINT in str(w.message) for w in caught)
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sb3_checker.check_env(gym.make(ENV_ID, randomize=True, preview=3), warn=True)
    assert all(_RESCALE_HINT in str(w.message) for w in caught)


def test_a_drawn_rate_dependent_map_is_its_rate_independent_twin_scaled_at_the_same_rate():
    """Scaled as the Prandtl-Ishlinskii map with its weights and base radii (the same weights
    to the bit), with its rate constant and sample time kept: its quasi-static loop scales
    as the twin's and its major-loop peak, the observation bound's, stays."""
    from piezo_env.hysteresis import RateDependentPrandtlIshlinskii
    from piezo_env.randomization import scale_hysteresis

    nominal = RateDependentPrandtlIshlinskii.for_voltage(30.0, dt=2.5e-4)
    twin = PrandtlIshlinskii(nominal.linear_weight, nominal.radii, nominal.weights)
    for scale in (0.7, 1.3):
        drawn, twin_drawn = (scale_hysteresis(h, scale, 30.0) for h in (nominal, twin))
        kept = (drawn.rate_time, drawn.dt, drawn.radii)
        assert kept == (nominal.rate_time, 2.5e-4, nominal.radii)
        assert drawn.weights == twin_drawn.weights
        assert drawn.linear_weight == twin_drawn.linear_weight
        assert major_loop_peak(twin_drawn, 30.0) == pytest.approx(major_loop_peak(twin, 30.0))
        bound = nominal.max_effective_voltage(30.0)
        assert drawn.max_effective_voltage(30.0) == pytest.approx(bound)


def _pi_peak_factor(hysteresis: PrandtlIshlinskii, scale: float, u_max: float) -> float:
    """c of :func:`scale_hysteresis` in closed form: on the major loop every play sits at
    u_max - r at +u_max, so the peak is ``w_0 u_max + sum w_i (u_max - r_i)``."""
    reach = sum(w * (u_max - r) for w, r in zip(hysteresis.weights, hysteresis.radii, strict=True))
    return (hysteresis.linear_weight * u_max + reach) / (
        hysteresis.linear_weight * u_max + scale * reach
    )


def test_strength_gain_range_matches_the_small_signal_slopes_in_closed_form():
    """Below its smallest play radius a Prandtl-Ishlinskii map is its linear weight, so the
    scaled map's gain is the peak factor c alone; a Bouc-Wen map from rest has slope
    k (1 - alpha), so the scaled one's is c (1 - s alpha) / (1 - alpha) of it (h, of order
    alpha k a, shifts it by beta a, under 1e-4 at a = 1e-3 u_max)."""
    u_max = 30.0
    play = PrandtlIshlinskii.for_voltage(u_max)
    low, high = strength_gain_range(play, 0.3, u_max, amplitudes=(0.05,))
    assert low == pytest.approx(_pi_peak_factor(play, 1.3, u_max), rel=1e-12)
    assert high == pytest.approx(_pi_peak_factor(play, 0.7, u_max), rel=1e-12)
    bouc = BoucWen.for_voltage(u_max)
    low, high = strength_gain_range(bouc, 0.3, u_max, amplitudes=(1e-3,))
    for scale, value in ((1.3, low), (0.7, high)):
        raw = dataclasses.replace(bouc, alpha=bouc.alpha * scale)
        c = major_loop_peak(bouc, u_max) / major_loop_peak(raw, u_max)
        assert value == pytest.approx(c * (1 - scale * bouc.alpha) / (1 - bouc.alpha), rel=1e-4)


@pytest.mark.parametrize("family", [BoucWen, PrandtlIshlinskii])
def test_every_strength_in_the_range_has_a_gain_inside_its_ends(family):
    """The range is taken at the two extreme strengths: every strength between, at every
    amplitude, must give a gain inside it (the gain moves monotonically with the strength)."""
    u_max = 60.0
    hysteresis = family.for_voltage(u_max)
    low, high = strength_gain_range(hysteresis, 0.3, u_max)
    for strength in (0.05, 0.1, 0.2):
        inner = strength_gain_range(hysteresis, strength, u_max)
        assert low - 1e-12 <= inner[0] and inner[1] <= high + 1e-12
    assert low < 1.0 < high


def test_gain_tolerance_holds_every_drawn_bender_and_the_constant_is_its_value():
    """The MPCs' LEARNED_GAIN_TOLERANCE is the derivation's value rounded up; a bender drawn
    anywhere in the box (free deflection and strength together) has a gain, relative to the
    nominal map's, inside [1 - w, 1 + w] at every amplitude; without the strength's spread the
    tolerance is the free deflection's alone; another rated voltage gives the same width."""
    from controllers.settings import GAIN_TOLERANCE, LEARNED_GAIN_TOLERANCE, MS_MAX

    w = gain_tolerance()
    assert w <= LEARNED_GAIN_TOLERANCE < w + 1e-4
    # The strength's factor beyond the screened box lies in the gain change a loop with
    # Ms <= MS_MAX on a box vertex stays stable under (controllers.predictive.screen_bank).
    assert (1 + LEARNED_GAIN_TOLERANCE) / (1 + GAIN_TOLERANCE) < 1 / (1 - 1 / MS_MAX)
    assert (1 - LEARNED_GAIN_TOLERANCE) / (1 - GAIN_TOLERANCE) > 1 / (1 + 1 / MS_MAX)
    assert gain_tolerance(rated_voltage=120.0) == pytest.approx(w, rel=1e-9)
    assert gain_tolerance(DomainRandomization(hysteresis_strength=0.0)) == pytest.approx(0.2)
    rng = np.random.default_rng(11)
    for family in (BoucWen, PrandtlIshlinskii):
        hysteresis = family.for_voltage(30.0)
        for _ in range(4):
            free, strength = rng.uniform(0.8, 1.2), rng.uniform(0.0, 0.3)
            low, high = strength_gain_range(hysteresis, strength, 30.0)
            assert 1 - w <= free * low and free * high <= 1 + w


def test_strength_gain_range_refuses_a_strength_outside_zero_to_one():
    with pytest.raises(ValueError, match="strength"):
        strength_gain_range(BoucWen.for_voltage(30.0), 1.0, 30.0)
