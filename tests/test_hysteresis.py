"""Plant hysteresis: accepted parameters, proven bounds, monotonicity, inverse and casadi step."""

from __future__ import annotations

import casadi
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_env import PiezoBenderEnv
from piezo_env.hysteresis import BoucWen, NoHysteresis, PrandtlIshlinskii

U_MAX = 30.0
DT = 1e-3
RESONANCE_HZ = 160.0  # PL140 first mode (datasheet)
FAST = settings(deadline=None, max_examples=100)


@st.composite
def bouc_wen(draw):
    """Any accepted Bouc-Wen: k, alpha > 0, beta + gamma > 0, beta >= gamma, 2 alpha sigma < 1."""
    beta = draw(st.floats(1e-3, 0.3))
    gamma = draw(st.floats(-0.99 * beta, beta))
    sigma = beta / (beta + gamma)
    alpha = draw(st.floats(0.01, 0.999)) / (2.0 * sigma)
    return BoucWen(k=draw(st.floats(0.2, 3.0)), alpha=alpha, beta=beta, gamma=gamma)


@st.composite
def prandtl_ishlinskii(draw):
    """Any accepted Prandtl-Ishlinskii: w_0 > 0, w_i >= 0, r_i >= 0."""
    n = draw(st.integers(1, 5))
    radii = tuple(draw(st.lists(st.floats(0.0, 40.0), min_size=n, max_size=n)))
    weights = tuple(draw(st.lists(st.floats(0.0, 2.0), min_size=n, max_size=n)))
    return PrandtlIshlinskii(draw(st.floats(0.01, 2.0)), radii, weights)


def bang_bang(steps: int) -> np.ndarray:
    """+-U_MAX square wave at the bender's first resonance."""
    t = np.arange(steps) * DT
    return U_MAX * np.where(np.sin(2 * np.pi * RESONANCE_HZ * t) >= 0.0, 1.0, -1.0)


def drive(hyst, u: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    state = hyst.initial_state(0.0)
    out, states = [], []
    for v in u:
        state, u_eff = hyst.step(state, float(v))
        out.append(float(u_eff))
        states.append(state)
    return np.array(out), states


def random_drive(seed: int, steps: int = 300) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(-U_MAX, U_MAX, steps // 3), 3)


@FAST
@given(hyst=st.one_of(bouc_wen(), prandtl_ishlinskii()), seed=st.integers(0, 2**16))
def test_effective_voltage_never_leaves_the_proven_bound(hyst, seed):
    bound = hyst.max_effective_voltage(U_MAX)
    for u in (bang_bang(400), random_drive(seed)):
        u_eff, _ = drive(hyst, u)
        assert np.abs(u_eff).max() <= bound * (1 + 1e-12)


@FAST
@given(hyst=st.one_of(bouc_wen(), prandtl_ishlinskii()), seed=st.integers(0, 2**16))
def test_effective_voltage_strictly_increases_with_the_input(hyst, seed):
    _, states = drive(hyst, random_drive(seed, 30))
    grid = np.linspace(-U_MAX, U_MAX, 241)
    for state in states[::7]:
        _, u_eff = hyst.step(np.broadcast_to(state, (grid.size, state.size)), grid)
        assert np.all(np.diff(u_eff) > 0.0)


@FAST
@given(hyst=st.one_of(bouc_wen(), prandtl_ishlinskii()), seed=st.integers(0, 2**16))
def test_inverse_is_exact_and_clips_out_of_range(hyst, seed):
    rng = np.random.default_rng(seed)
    _, states = drive(hyst, random_drive(seed, 30))
    for state in states[::5]:
        u_true = float(rng.uniform(-U_MAX, U_MAX))
        target = float(hyst.step(state, u_true)[1])
        u, z, status, new_state = hyst.inverse(target, state, (-U_MAX, U_MAX))
        assert status == "ok"
        assert abs(u - u_true) <= 1e-6
        assert z == pytest.approx(target, abs=1e-9)
        np.testing.assert_allclose(new_state, hyst.step(state, u)[0], atol=1e-12)
        top = float(hyst.step(state, U_MAX)[1])
        result = hyst.inverse(top + 1.0, state, (-U_MAX, U_MAX))
        assert (result.u, result.z, result.status) == (U_MAX, top, "out-of-range")


@pytest.mark.parametrize(
    "hyst", [BoucWen(), BoucWen(beta=0.04, gamma=0.0), PrandtlIshlinskii(), NoHysteresis()]
)
def test_casadi_step_equals_step(hyst):
    u = casadi.SX.sym("u")
    s = casadi.SX.sym("s", hyst.state_size)
    f = casadi.Function("f", [u, s], list(hyst.casadi_step(u, s)))
    state = hyst.initial_state(0.0)
    for v in random_drive(3, 90):
        z, new = f(v, state)
        state, u_eff = hyst.step(state, float(v))
        assert float(z) == pytest.approx(float(u_eff), abs=1e-12)
        np.testing.assert_allclose(np.array(new).ravel(), state, atol=1e-12)


def test_no_hysteresis_inverse_clips():
    assert tuple(NoHysteresis().inverse(3.0, np.zeros(1), (-5.0, 5.0)))[:3] == (3.0, 3.0, "ok")
    assert NoHysteresis().inverse(9.0, np.zeros(1), (-5.0, 5.0)).status == "out-of-range"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"beta": -0.01, "gamma": 0.05}, "beta >= gamma"),
        ({"beta": 0.01, "gamma": 0.03}, "beta >= gamma"),
        ({"beta": -0.02, "gamma": 0.01}, "beta \\+ gamma > 0"),
        ({"alpha": 0.0}, "alpha > 0"),
        ({"k": -1.0}, "k > 0"),
        ({"alpha": 0.9, "beta": 0.05, "gamma": 0.0}, "u_eff fall"),
        ({"beta": float("nan")}, "finite"),
    ],
)
def test_bouc_wen_rejects_unbounded_or_non_monotone_sets(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BoucWen(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"weights": (0.1, -0.1, 0.1)}, "weights must be >= 0"),
        ({"linear_weight": 0.0}, "linear_weight must be > 0"),
        ({"radii": (-1.0, 2.0, 3.0)}, "radii must be >= 0"),
        ({"radii": (1.0, 2.0)}, "equal length"),
    ],
)
def test_prandtl_ishlinskii_rejects_bad_weights(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PrandtlIshlinskii(**kwargs)


@settings(deadline=None, max_examples=4)
@given(hyst=st.one_of(bouc_wen(), prandtl_ishlinskii()))
def test_env_observations_stay_in_the_space_under_bang_bang_at_resonance(hyst):
    env = PiezoBenderEnv(hysteresis=hyst, noise_bound=0.0)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for v in bang_bang(150):
        obs, *_ = env.step(np.array([v], dtype=np.float32))
        assert env.observation_space.contains(obs), obs
