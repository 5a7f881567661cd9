"""Compiled NLS inverse held to the numpy inverse (NLS.solve_inverse) it replaces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from handmade import handmade_nls

from controllers import PredictionModel
from controllers.native.compiled_inverse import FALLBACK, OK, CompiledInverse, inverse_function
from identification.features import play_operators
from identification.hammerstein import HammersteinModel
from identification.nls import NLS, fit_nls

casadi = pytest.importorskip("casadi")

MODEL_DIR = Path(__file__).resolve().parents[1] / "docs" / "identify" / "model"
U_RANGE = (-30.0, 30.0)
TOL = 5e-7  # V: measured differences up to 9e-8 V (shipped model), 1e-6 V the accuracy target


@pytest.fixture(scope="module")
def shipped() -> NLS:
    """The shipped identified model's NLS (Bouc-Wen features, 3 x 32 tanh)."""
    return HammersteinModel.load(MODEL_DIR).nls


@pytest.fixture(scope="module")
def play() -> NLS:
    """A small play-feature NLS, quickly fitted to a Prandtl-Ishlinskii hysteresis."""
    rng = np.random.default_rng(1)
    knots = rng.uniform(-30.0, 30.0, 80)
    times = np.concatenate([[0], np.cumsum(rng.integers(5, 40, 79))])
    u = np.interp(np.arange(2000), times, knots)
    plays, _ = play_operators(u, [1.5, 4.0, 8.0, 13.0, 19.0])
    z = 0.6 * u + plays @ np.array([0.25, 0.2, 0.12, 0.08, 0.05]) - 2e-4 * u**3
    return fit_nls(
        u, z, features="play", n_play=6, hidden=(16, 16, 16), max_epochs=10, u_range=U_RANGE
    )


def reached_states(nls: NLS, n: int, seed: int) -> list[np.ndarray]:
    """Memory states reached from rest by a random walk with jumps over the drive range."""
    rng = np.random.default_rng(seed)
    u = np.clip(np.cumsum(rng.normal(0.0, 4.0, 400)), *U_RANGE)
    jumps = rng.random(u.size) < 0.1
    u[jumps] = rng.uniform(*U_RANGE, jumps.sum())
    state, states = nls.initial_state(), []
    for v in u:
        _, state = nls.step(float(v), state)
        states.append(state)
    return [states[i] for i in rng.choice(len(states), n, replace=False)]


def targets_for(nls: NLS, state: np.ndarray, rng: np.random.Generator) -> list[float]:
    """Targets inside the reachable range, beyond both ends, at both ends and at the kink."""
    z_low, z_high = nls.step(U_RANGE[0], state)[0], nls.step(U_RANGE[1], state)[0]
    at_kink = nls.step(float(state[0]), state)[0]  # u = previous input (Bouc-Wen) / warm start
    inside = rng.uniform(z_low, z_high, 4).tolist()
    return [*inside, z_low - 1.0, z_high + 1.0, z_low, z_high, at_kink]


def assert_same(compiled, numpy_result) -> None:
    assert compiled.status == numpy_result.status
    assert compiled.u == pytest.approx(numpy_result.u, abs=TOL)
    assert compiled.z == pytest.approx(numpy_result.z, abs=TOL)
    np.testing.assert_allclose(compiled.state, numpy_result.state, rtol=0.0, atol=TOL)


@pytest.mark.parametrize("name", ["shipped", "play"])
def test_compiled_inverse_equals_numpy_inverse(name, request):
    nls = request.getfixturevalue(name)
    inverse = CompiledInverse(nls, U_RANGE)
    assert inverse.compiled, inverse.backend
    rng = np.random.default_rng(5)
    statuses = set()
    for state in reached_states(nls, 60, seed=1):
        for target in targets_for(nls, state, rng):
            result = inverse.solve(target, state)
            assert_same(result, nls.solve_inverse(target, state, u_range=U_RANGE))
            statuses.add(result.status)
    assert statuses == {"ok", "out-of-range"}
    assert inverse.fallbacks == 0


@pytest.mark.parametrize("name", ["shipped", "play"])
def test_out_of_range_targets_are_clipped_and_flagged(name, request):
    nls = request.getfixturevalue(name)
    inverse = CompiledInverse(nls, U_RANGE)
    state = reached_states(nls, 1, seed=2)[0]
    for target, end in ((-1e6, U_RANGE[0]), (1e6, U_RANGE[1])):
        result = inverse.solve(target, state)
        assert (result.u, result.status) == (end, "out-of-range")
        assert result.z == pytest.approx(nls.step(end, state)[0], abs=1e-12)


def test_target_at_the_kink_gives_the_previous_input(shipped):
    inverse = CompiledInverse(shipped, U_RANGE)
    for state in reached_states(shipped, 20, seed=3):
        previous = float(state[0])
        z_prev = shipped.step(previous, state)[0]
        for target in (z_prev, np.nextafter(z_prev, np.inf), np.nextafter(z_prev, -np.inf)):
            result = inverse.solve(target, state)
            assert result.status == "ok"
            assert result.u == pytest.approx(previous, abs=1e-9)


def test_compiled_function_equals_casadi_virtual_machine(shipped):
    function = inverse_function(shipped)
    inverse = CompiledInverse(shipped, U_RANGE)
    state = reached_states(shipped, 1, seed=4)[0]
    u, z, status, next_state, _ = function(3.0, state, *U_RANGE, state[0], np.zeros(0))
    result = inverse.solve(3.0, state)
    assert int(status) == OK
    assert (result.u, result.z) == pytest.approx((float(u), float(z)), abs=1e-12)
    np.testing.assert_allclose(result.state, np.asarray(next_state).ravel(), atol=1e-12)


@pytest.mark.parametrize("name", ["shipped", "play"])
def test_without_a_compiler_the_numpy_inverse_runs(name, request, monkeypatch, tmp_path):
    nls = request.getfixturevalue(name)
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    inverse = CompiledInverse(nls, U_RANGE)
    assert not inverse.compiled
    assert "no C compiler" in inverse.backend
    assert [build.path for build in inverse.native] == ["numpy"]
    rng = np.random.default_rng(6)
    for state in reached_states(nls, 5, seed=5):
        for target in targets_for(nls, state, rng):
            result = inverse.solve(target, state)
            expected = nls.solve_inverse(target, state, u_range=U_RANGE)
            assert (result.u, result.z, result.status) == (expected.u, expected.z, expected.status)


def test_identified_model_inverts_with_the_compiled_inverse(shipped, monkeypatch, tmp_path):
    model = PredictionModel.from_hammerstein(MODEL_DIR, U_RANGE[1])
    assert model.nonlinearity._inverse.compiled
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    fallback = PredictionModel.from_hammerstein(MODEL_DIR, U_RANGE[1])
    assert not fallback.nonlinearity._inverse.compiled
    rng = np.random.default_rng(7)
    for state in reached_states(shipped, 10, seed=6):
        for target in targets_for(shipped, state, rng):
            assert_same(
                model.nonlinearity.inverse(target, state),
                fallback.nonlinearity.inverse(target, state),
            )


@pytest.mark.parametrize(
    ("out_weight", "target", "previous"),
    [
        (-6.0, 0.0, 1.0),  # z(-5 V) > z(5 V): the range ends are out of order
        (-2.0, -0.05, 0.1),  # the first Newton iterate sees a negative slope
    ],
)
def test_non_monotone_map_falls_back_to_the_numpy_inverse(out_weight, target, previous):
    nls = handmade_nls(out_weight)
    inverse = CompiledInverse(nls, (-5.0, 5.0))
    function = inverse_function(nls)
    state = np.array([previous])
    assert int(function(target, state, -5.0, 5.0, previous, np.zeros(0))[2]) == FALLBACK
    result = inverse.solve(target, state)
    expected = nls.solve_inverse(target, state, u_range=(-5.0, 5.0))
    assert inverse.fallbacks == 1
    assert result.status == expected.status == "non-monotone"
    assert (result.u, result.z) == (expected.u, expected.z)


@pytest.mark.parametrize("compiler", [True, False])
def test_reachable_range_equals_the_prediction_model(shipped, compiler, monkeypatch, tmp_path):
    model = PredictionModel.from_hammerstein(MODEL_DIR, U_RANGE[1])
    if not compiler:
        monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    inverse = CompiledInverse(shipped, U_RANGE)
    assert inverse.compiled == compiler
    for state in reached_states(shipped, 10, seed=8):
        assert inverse.reachable(state) == pytest.approx(
            model.nonlinearity.reachable(state), abs=1e-12
        )


def test_a_warm_start_an_ulp_inside_the_range_is_no_evidence_of_a_non_monotone_map():
    """Regression: on the 0.1 ms model, one step of a 10 kHz episode (steps reference, sample
    8004) started from the previous input 29.999999999999996 V, an ulp below the drive's end,
    where z came out a rounding above z(30 V); the start test took that for a non-monotone map
    and handed the target to the numpy inverse (600-900 us). The map rises there (its grid is
    increasing), so the compiled iteration must solve it, as the numpy inverse does."""
    nls = HammersteinModel.load(Path(__file__).parent / "data" / "pl140-0.1ms-model").nls
    state = np.array([float.fromhex(h) for h in (
        "0x1.dffffffffffffp+4", "0x1.7fff6ed12927cp+1", "0x1.d4db402d4ef0fp+1",
        "0x1.1e254214a2030p+2", "0x1.5cd29ad57d84bp+2", "0x1.a7967f87d0127p+2",
        "0x1.fde79945b1bfep+2", "0x1.2e3edcb181b15p+3", "0x1.5eda74d2f0ae8p+3",
        "0x1.8e2a88e3acdf4p+3", "0x1.bb63defc900d6p+3", "0x1.e79472ff0b4b1p+3",
        "0x1.0a23510c534c4p+4", "0x1.215381701e402p+4", "0x1.39c84566e8e24p+4",
        "0x1.53bb18e97890ap+4", "0x1.6eeff9394d6c6p+4",
    )])  # fmt: skip
    target = float.fromhex("0x1.1ed88411cb2cdp+4")
    inverse = CompiledInverse(nls, (-30.0, 30.0))
    if not inverse.compiled:
        pytest.skip(f"no compiled inverse here: {inverse.backend}")
    assert state[0] < 30.0 and 30.0 - state[0] < 1e-14  # the warm start, an ulp inside
    result = inverse.solve(target, state)
    assert inverse.fallbacks == 0 and result.status == "ok"
    expected = inverse.map.solve_inverse(target, state, (-30.0, 30.0))
    assert result.u == pytest.approx(expected.u, abs=1e-7)
    assert result.z == pytest.approx(target, abs=1e-9)
