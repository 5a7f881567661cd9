"""NLS inverse: exact against the forward map, clipped and flagged out of range."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from identification.features import BoucWenFeatures, PastInputFeatures, PlayFeatures
from identification.nls import NLS, NLSInverse
from piezo_env.inverse import InverseResult

U_RANGE = (-30.0, 30.0)
FEATURE_MAPS = {
    "play": PlayFeatures(radii=(3.0, 8.0, 15.0, 22.0)),
    "past-inputs": PastInputFeatures(n_past=3),
    "bouc-wen": BoucWenFeatures(levels=(3.0, 7.0, 15.0, 30.0, 60.0)),
}


def random_nls(feature_map, seed: int, hidden=(16, 16, 16)) -> NLS:
    """A tanh MLP on top of an increasing affine map of the features: increasing in u.

    The memory features do not decrease when u rises, so positive skip weights and a small
    network keep z(u) strictly increasing from every state (the inverse's assumption).
    """
    rng = np.random.default_rng(seed)
    n_f = feature_map.n_features
    params = {
        "feature_mean": np.zeros(n_f),
        "feature_scale": np.full(n_f, 10.0),
        "z_mean": np.array(0.0),
        "z_scale": np.array(10.0),
        "skip_weight": np.r_[1.0, rng.uniform(0.0, 0.3, n_f - 1)],
        "skip_bias": np.array(0.1),
        "out_weight": rng.normal(0.0, 0.05, hidden[-1]),
        "out_bias": np.array(0.0),
    }
    width = n_f
    for i, n in enumerate(hidden):
        params[f"layer{i}_weight"] = rng.normal(0.0, 1.0 / np.sqrt(width), (n, width))
        params[f"layer{i}_bias"] = rng.normal(0.0, 0.3, n)
        width = n
    return NLS(feature_map, params, u_range=U_RANGE)


def random_state(nls: NLS, rng) -> np.ndarray:
    _, state = nls.features(rng.uniform(*U_RANGE, rng.integers(1, 40)))
    return state


@pytest.mark.parametrize("name", sorted(FEATURE_MAPS))
@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 2**16))
def test_inverse_is_exact_on_random_states_and_targets(name, seed):
    nls = random_nls(FEATURE_MAPS[name], seed % 7)
    rng = np.random.default_rng(seed)
    state = random_state(nls, rng)
    u_true = float(rng.uniform(*U_RANGE))
    target, state_true = nls.step(u_true, state)
    result = nls.solve_inverse(target, state)
    assert isinstance(result, InverseResult) and NLSInverse is InverseResult
    assert result.status == "ok"
    assert abs(result.u - u_true) <= 1e-6
    assert result.z == pytest.approx(nls.step(result.u, state)[0], abs=1e-6)
    np.testing.assert_allclose(result.state, nls.step(result.u, state)[1], atol=1e-12)
    np.testing.assert_allclose(result.state, state_true, atol=1e-5)


@pytest.mark.parametrize("name", sorted(FEATURE_MAPS))
def test_inverse_of_a_sequence_with_warm_starts(name):
    nls = random_nls(FEATURE_MAPS[name], 1)
    t = np.arange(400) * 1e-3
    u = 25.0 * np.sin(2 * np.pi * 30.0 * t) * np.sin(2 * np.pi * 2.0 * t)
    u_back, final = nls.inverse_sequence(nls(u))
    np.testing.assert_allclose(u_back, u, atol=1e-6)
    np.testing.assert_allclose(final, nls.features(u)[1], atol=1e-6)


@pytest.mark.parametrize("name", sorted(FEATURE_MAPS))
@pytest.mark.parametrize("end", [0, 1])
def test_out_of_range_targets_are_clipped_and_flagged(name, end):
    nls = random_nls(FEATURE_MAPS[name], 2)
    rng = np.random.default_rng(5)
    for _ in range(10):
        state = random_state(nls, rng)
        u_end = U_RANGE[end]
        z_end, state_end = nls.step(u_end, state)
        beyond = z_end + (1.0 if end else -1.0) * rng.uniform(1e-6, 50.0)
        result = nls.solve_inverse(beyond, state)
        assert result.status == "out-of-range"
        assert result.u == u_end
        assert result.z == pytest.approx(z_end, abs=1e-12)
        np.testing.assert_allclose(result.state, state_end)
        assert nls.solve_inverse(z_end, state).status == "ok"


def test_unpacks_like_the_plant_hysteresis_inverse():
    nls = random_nls(FEATURE_MAPS["bouc-wen"], 3)
    u, z, status, state = nls.solve_inverse(1.0)
    assert status == "ok" and z == pytest.approx(1.0, abs=1e-6) and state.shape == (6,)
    assert nls.step(u, None)[0] == pytest.approx(1.0, abs=1e-6)
