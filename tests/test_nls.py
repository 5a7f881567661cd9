"""Neural static nonlinearity: features, exports, inverse, training, serialization."""

import json
import warnings

import numpy as np
import pytest
from handmade import handmade_nls

from identification.features import (
    BoucWenFeatures,
    PastInputFeatures,
    PlayFeatures,
    bouc_wen_update,
    default_play_radii,
    play_operators,
    reused_features,
    sequence_features,
)
from identification.metrics import fit_percent
from identification.nls import NLS, NLSInverseWarning, TrainingSettings, fit_nls

torch = pytest.importorskip("torch")
casadi = pytest.importorskip("casadi")

TRUE_RADII = np.array([1.5, 4.0, 8.0, 13.0, 19.0])
TRUE_WEIGHTS = np.array([0.25, 0.2, 0.12, 0.08, 0.05])


def pi_hysteresis(u):
    """A Prandtl-Ishlinskii hysteresis with a mild saturation: the NLS has to learn it."""
    plays, _ = play_operators(u, TRUE_RADII)
    return 0.6 * u + plays @ TRUE_WEIGHTS - 2e-4 * u**3


def rich_input(n, seed):
    """Random turning points joined by ramps of random length, within +-30 V."""
    rng = np.random.default_rng(seed)
    knots = rng.uniform(-30.0, 30.0, size=n // 20 + 2)
    knots[0] = 0.0
    times = np.concatenate([[0], np.cumsum(rng.integers(5, 40, size=knots.size - 1))])
    return np.interp(np.arange(n), times, knots)


@pytest.fixture(scope="module")
def trained():
    """Small, quickly trained NLS of each feature set on the PI hysteresis."""
    u = rich_input(3000, seed=1)
    z = pi_hysteresis(u)
    return {
        name: fit_nls(u, z, features=name, max_epochs=15, seed=3, u_range=(-30.0, 30.0))
        for name in ("play", "past-inputs", "bouc-wen")
    }


# -- play operators ---------------------------------------------------------------------------


def test_play_operator_on_triangle_gives_trapezoid():
    amplitude, radius = 10.0, 3.0
    # 0 -> A -> -A -> A -> -A, 0.01 V steps
    knots = [0.0, amplitude, -amplitude, amplitude, -amplitude]
    u = np.interp(np.linspace(0, 4, 8001), np.arange(5), knots)
    p, final = play_operators(u, [radius])
    p = p[:, 0]
    rising = np.r_[True, np.diff(u) > 0]
    # after the first peak: on falling branches p = min(A - r, u + r), on rising max(-A + r, u - r)
    expected = np.where(
        rising,
        np.maximum(-amplitude + radius, u - radius),
        np.minimum(amplitude - radius, u + radius),
    )
    start = 2001  # index of the first peak
    np.testing.assert_allclose(p[start:], expected[start:], atol=1e-12)
    # first rise from rest at 0: dead band until u reaches r
    np.testing.assert_allclose(p[:start], np.maximum(0.0, u[:start] - radius), atol=1e-12)
    assert final[0] == pytest.approx(-amplitude + radius)


def test_play_operator_is_rate_independent():
    knots = np.array([0.0, 25.0, -10.0, 18.0, -30.0, 5.0, -2.0, 30.0])
    coarse_t = np.arange(0, knots.size * 10 - 9)
    fine_t = np.linspace(0, coarse_t[-1], coarse_t.size * 13 - 12)
    u_coarse = np.interp(coarse_t, np.arange(knots.size) * 10, knots)
    u_fine = np.interp(fine_t, np.arange(knots.size) * 10, knots)
    radii = default_play_radii((-30.0, 30.0), 8)
    p_coarse, _ = play_operators(u_coarse, radii)
    p_fine, _ = play_operators(u_fine, radii)
    np.testing.assert_allclose(p_fine[::13], p_coarse, atol=1e-12)


def test_default_radii_span_half_range():
    r = default_play_radii((-30.0, 30.0), 5)
    np.testing.assert_allclose(r, [5.0, 10.0, 15.0, 20.0, 25.0])


@pytest.mark.parametrize(
    "feature_map",
    [
        PlayFeatures(radii=(1.0, 4.0, 9.0)),
        PastInputFeatures(n_past=4),
        BoucWenFeatures(levels=(3.0, 10.0, 40.0)),
    ],
)
def test_features_continue_across_calls_and_steps(feature_map):
    u = rich_input(200, seed=5)
    full, final = feature_map.features(u, feature_map.initial_state())
    first, mid = feature_map.features(u[:77], feature_map.initial_state())
    second, final2 = feature_map.features(u[77:], mid)
    np.testing.assert_array_equal(np.vstack([first, second]), full)
    np.testing.assert_array_equal(final, final2)
    state = feature_map.initial_state()
    for t in range(u.size):
        f, state = feature_map.step(u[t], state)
        np.testing.assert_array_equal(f, full[t])
    np.testing.assert_array_equal(state, final)


def test_past_input_features_layout():
    fm = PastInputFeatures(n_past=2, initial_input=0.5)
    f, state = fm.features(np.array([1.0, 2.0, 3.0]), fm.initial_state())
    np.testing.assert_array_equal(f, [[1.0, 0.5, 0.5], [2.0, 1.0, 0.5], [3.0, 2.0, 1.0]])
    np.testing.assert_array_equal(state, [3.0, 2.0])


def test_bouc_wen_operator_matches_fine_integration_and_is_rate_independent():
    levels = np.array([4.0, 15.0])
    knots = np.array([0.0, 25.0, -10.0, 18.0, -30.0, 5.0])
    u = np.interp(np.linspace(0, 5, 51), np.arange(6), knots)
    fm = BoucWenFeatures(levels=tuple(levels))
    exact, _ = fm.features(u, fm.initial_state())
    # explicit Euler in u with tiny steps of dh = du - b|du|h - b du|h|
    fine = np.interp(np.linspace(0, 5, 50001), np.arange(6), knots)
    h = np.zeros(2)
    euler = [h.copy()]
    b = 1.0 / (2.0 * levels)
    for du in np.diff(fine):
        h = h + du - b * abs(du) * h - b * du * np.abs(h)
        euler.append(h.copy())
    np.testing.assert_allclose(exact[:, 1:], np.array(euler)[::1000], atol=2e-3)
    coarse, _ = fm.features(u[::10], fm.initial_state())
    np.testing.assert_allclose(coarse, exact[::10], atol=1e-12)
    # saturation towards +-level, linear tracking while du and h have opposite signs
    assert bouc_wen_update(np.array([0.0]), 1e3, np.array([4.0]))[0] == pytest.approx(4.0)
    assert bouc_wen_update(np.array([-2.0]), 1.5, np.array([4.0]))[0] == pytest.approx(-0.5)


# -- exports ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["play", "past-inputs", "bouc-wen"])
def test_numpy_and_casadi_exports_equal_torch(trained, name):
    nls = trained[name]
    u = rich_input(400, seed=9) * 1.2  # includes extrapolation beyond the training range
    features, _ = nls.features(u)
    with torch.no_grad():
        z_torch = nls.to_torch()(torch.from_numpy(features)).numpy()
    z_numpy = nls.to_numpy()(features)
    np.testing.assert_allclose(z_numpy, z_torch, rtol=0, atol=1e-6)
    np.testing.assert_allclose(nls(u), z_torch, rtol=0, atol=1e-6)
    f_cas = nls.to_casadi()
    z_casadi = np.array([float(f_cas(row)) for row in features[::20]])
    np.testing.assert_allclose(z_casadi, z_torch[::20], rtol=0, atol=1e-6)
    # step-by-step: numpy step and casadi step (with the max/min play update) agree
    step_cas = nls.to_casadi_step()
    feat_cas = nls.to_casadi_features()
    state_np = state_cas = nls.initial_state()
    for t in range(120):
        z_np, state_np = nls.step(u[t], state_np)
        f_t, _ = feat_cas(u[t], state_cas)
        z_c, state_cas = step_cas(u[t], state_cas)
        state_cas = np.array(state_cas).ravel()
        assert abs(z_np - z_torch[t]) < 1e-6
        assert abs(float(z_c) - z_torch[t]) < 1e-6
        np.testing.assert_allclose(np.array(f_t).ravel(), features[t], atol=1e-12)
        np.testing.assert_allclose(state_cas, state_np, atol=1e-12)


def test_casadi_export_is_differentiable(trained):
    nls = trained["play"]
    step = nls.to_casadi_step()
    u = casadi.SX.sym("u")
    z, _ = step(u, nls.initial_state())
    dz = casadi.Function("dz", [u], [casadi.jacobian(z, u)])
    h = 1e-6
    numeric = (nls.step(10.0 + h, None)[0] - nls.step(10.0 - h, None)[0]) / (2 * h)
    assert float(dz(10.0)) == pytest.approx(numeric, rel=1e-5)


# -- inverse ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["play", "past-inputs", "bouc-wen"])
def test_inverse_round_trip_over_operating_range(trained, name):
    nls = trained[name]
    u = rich_input(300, seed=11) * 0.95
    z = nls(u)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NLSInverseWarning)
        u_back, final = nls.inverse_sequence(z)
    np.testing.assert_allclose(u_back, u, atol=1e-6)
    np.testing.assert_allclose(final, nls.features(u)[1], atol=1e-6)
    # scalar inverse from a mid-sequence memory state
    _, state = nls.features(u[:150])
    u_t = nls.inverse(z[150], state)
    assert u_t == pytest.approx(u[150], abs=1e-6)


def test_inverse_saturates_out_of_range(trained):
    nls = trained["play"]
    result = nls.solve_inverse(1e6, None, u_range=(-30.0, 30.0))
    assert result.status == "out-of-range"
    assert result.u == pytest.approx(30.0)
    assert nls.inverse(-1e6) == pytest.approx(-30.0)


def test_inverse_of_non_monotone_map_warns_and_picks_nearest_root():
    nls = handmade_nls(-2.0)  # z = u - 2 tanh(u): roots of z = 0 at 0 and about +-1.915
    result = nls.solve_inverse(0.0, [1.8])  # previous input 1.8 V is the reference
    assert result.status == "non-monotone"
    assert result.u == pytest.approx(1.91501, abs=1e-4)
    with pytest.warns(NLSInverseWarning, match="not monotone"):
        nls.inverse(0.0, [0.1])
    with pytest.warns(NLSInverseWarning):
        nls.inverse_sequence([0.0, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert handmade_nls(2.0).inverse(0.0) == pytest.approx(0.0, abs=1e-9)


# -- training ---------------------------------------------------------------------------------


def test_bouc_wen_features_learn_bouc_wen_hysteresis():
    u = rich_input(4000, seed=23)

    def bouc_wen(u):  # the plant's hysteresis form, z = k u - alpha k h (beta = gamma)
        fm = BoucWenFeatures(levels=(1.0 / (2 * 0.0233),))
        h = fm.features(u, fm.initial_state())[0][:, 1]
        return 1.245 * u - 0.32 * 1.245 * h

    nls = fit_nls(u, bouc_wen(u), features="bouc-wen", max_epochs=30)
    u_test = rich_input(2000, seed=24)
    assert fit_percent(bouc_wen(u_test), nls(u_test)) > 99.5


def test_learns_known_prandtl_ishlinskii_hysteresis():
    u = rich_input(6000, seed=21)
    nls = fit_nls(u, pi_hysteresis(u), features="play", seed=0)
    u_test = rich_input(3000, seed=22)
    assert fit_percent(pi_hysteresis(u_test), nls(u_test)) > 99.0  # measured 99.25
    assert nls.training["validation_mse"] < nls.training["affine_validation_mse"]


@pytest.mark.parametrize("name", ["play", "past-inputs", "bouc-wen"])
def test_learns_identity_exactly(name):
    u = rich_input(1500, seed=4)
    nls = fit_nls(u, u, features=name, max_epochs=5)
    u_test = rich_input(500, seed=5) * 1.5
    np.testing.assert_allclose(nls(u_test), u_test, atol=1e-9)


def _record_without_time(nls):
    return {k: v for k, v in nls.training.items() if k != "wall_time_s"}


@pytest.mark.parametrize("name", ["play", "past-inputs", "bouc-wen"])
def test_same_seed_same_model_bitwise(name):
    u = rich_input(1500, seed=2)
    z = pi_hysteresis(u)
    kwargs = {"features": name, "hidden": (8, 8), "max_epochs": 4, "lbfgs_iterations": 5}
    a = fit_nls(u, z, seed=7, **kwargs)
    b = fit_nls(u, z, seed=7, **kwargs)
    c = fit_nls(u, z, seed=8, **kwargs)
    assert a.arrays().keys() == b.arrays().keys()
    for key, value in a.arrays().items():
        np.testing.assert_array_equal(value, b.arrays()[key])
    assert _record_without_time(a) == _record_without_time(b)
    assert any(not np.array_equal(v, c.arrays()[k]) for k, v in a.arrays().items())


def test_settings_object_and_keywords_train_the_same_model():
    u = rich_input(1500, seed=2)
    z = pi_hysteresis(u)
    kwargs = {"features": "bouc-wen", "hidden": (8, 8), "max_epochs": 3, "seed": 5}
    by_keywords = fit_nls(u, z, **kwargs)
    by_settings = fit_nls(u, z, settings=TrainingSettings(**kwargs))
    for key, value in by_keywords.arrays().items():
        np.testing.assert_array_equal(value, by_settings.arrays()[key])
    assert _record_without_time(by_keywords) == _record_without_time(by_settings)
    with pytest.raises(ValueError, match="either settings or keyword overrides"):
        fit_nls(u, z, settings=TrainingSettings(), max_epochs=3)
    with pytest.raises(TypeError, match="no_such_setting"):
        fit_nls(u, z, no_such_setting=1)


def test_settings_resolve_the_ridge_default_per_feature_set():
    assert TrainingSettings(features="past-inputs").skip_ridge == 1.0
    assert TrainingSettings(features="play").skip_ridge == 1e-3
    assert TrainingSettings(features="play", skip_ridge=0.5).skip_ridge == 0.5


def test_early_stopping_keeps_the_best_validating_weights():
    u = rich_input(2000, seed=2)
    z = pi_hysteresis(u)
    kwargs = {"hidden": (8, 8), "learning_rate": 1e-2, "batch_size": 128, "seed": 1}
    nls = fit_nls(u, z, max_epochs=40, patience=3, **kwargs)
    record = nls.training
    assert 1 <= record["best_epoch"] < record["epochs"] < 40  # improved, then stopped early
    assert record["epochs"] - record["best_epoch"] == 3  # after `patience` epochs
    # the recorded validation loss is that of the returned network on the held-out block
    held_out = slice(record["n_train"], None)
    validation_mse = np.mean((nls(u)[held_out] - z[held_out]) ** 2)
    assert record["validation_mse"] == pytest.approx(validation_mse, rel=1e-9, abs=0.0)
    assert record["validation_mse"] < record["affine_validation_mse"]
    # and that network is the one of epoch best_epoch: a run that ends there returns it too
    ended = fit_nls(u, z, max_epochs=record["best_epoch"], patience=3, **kwargs)
    assert ended.training["validation_mse"] == record["validation_mse"]
    for key, value in nls.arrays().items():
        np.testing.assert_array_equal(value, ended.arrays()[key])


def test_without_validation_block_the_training_loss_is_monitored():
    u = rich_input(1000, seed=2)
    z = pi_hysteresis(u)
    nls = fit_nls(u, z, hidden=(8,), max_epochs=3, validation_fraction=0.0, lbfgs_iterations=2)
    record = nls.training
    assert record["n_validation"] == 0 and record["epochs"] == 3  # no early stopping
    assert record["validation_mse"] == record["train_mse"]
    assert record["train_mse"] == pytest.approx(np.mean((nls(u) - z) ** 2), rel=1e-9, abs=0.0)


@pytest.mark.parametrize(
    ("feature_map", "kwargs"),
    [
        (PlayFeatures(radii=(2.0, 7.0, 15.0)), {"features": "play", "radii": (2.0, 7.0, 15.0)}),
        (PastInputFeatures(n_past=3), {"features": "past-inputs", "n_past": 3}),
        (BoucWenFeatures(levels=(3.0, 12.0)), {"features": "bouc-wen", "levels": (3.0, 12.0)}),
    ],
)
def test_affine_start_is_exact_for_a_map_affine_in_the_features(feature_map, kwargs):
    coef = np.linspace(0.8, -0.3, feature_map.n_features)

    def affine(u):
        return 1.5 + feature_map.features(u, feature_map.initial_state())[0] @ coef

    u = rich_input(1500, seed=6)
    nls = fit_nls(u, affine(u), max_epochs=0, skip_ridge=0.0, hidden=(8,), **kwargs)
    assert nls.training["epochs"] == 0
    assert nls.training["affine_validation_mse"] < 1e-20
    u_test = rich_input(700, seed=7) * 1.3  # other turning points, beyond the training range
    np.testing.assert_allclose(nls(u_test), affine(u_test), rtol=0.0, atol=1e-9)


def test_training_restores_torch_threads():
    before = torch.get_num_threads()
    u = rich_input(600, seed=2)
    fit_nls(u, u, max_epochs=1, num_threads=1)
    assert torch.get_num_threads() == before


def test_z_weights_validation_and_effect():
    u = rich_input(800, seed=2)
    with pytest.raises(ValueError, match="z_weights"):
        fit_nls(u, u, z_weights=-np.ones(800))
    # samples of zero weight do not pull the fit: z = u learnt exactly despite corrupted samples
    z = u.copy()
    z[100:200] += 5.0
    weights = np.ones(800)
    weights[100:200] = 0.0
    kwargs = {"max_epochs": 0, "skip_ridge": 0.0, "hidden": (4,)}
    weighted = fit_nls(u, z, z_weights=weights, **kwargs)
    np.testing.assert_allclose(weighted(u), u, rtol=0.0, atol=1e-9)
    unweighted = fit_nls(u, z, **kwargs)
    assert np.max(np.abs(unweighted(u) - u)) > 0.1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"features": "bouc"}, "features must be one of"),
        ({"hidden": (32, 0)}, "hidden width"),
        ({"validation_fraction": 0.95}, "validation_fraction"),
        ({"max_epochs": -1}, "max_epochs"),
        ({"learning_rate": 0.0}, "learning_rate"),
        ({"batch_size": True}, "batch_size"),
        ({"patience": 2.0}, "patience"),
        ({"weight_decay": float("nan")}, "weight_decay"),
        ({"skip_ridge": -1.0}, "skip_ridge"),
        ({"u_range": (1.0, -1.0)}, "u_range"),
    ],
)
def test_fit_rejects_bad_configuration(kwargs, match):
    u = rich_input(200, seed=1)
    with pytest.raises(ValueError, match=match):
        fit_nls(u, u, **kwargs)


def test_fit_rejects_bad_data():
    with pytest.raises(ValueError, match="same length"):
        fit_nls(np.zeros(10), np.zeros(11))
    with pytest.raises(ValueError, match="non-finite"):
        fit_nls([0.0, np.nan, 1.0], [0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="too few samples"):
        fit_nls(np.arange(6.0), np.arange(6.0))


# -- evaluation API and serialization ---------------------------------------------------------


def test_step_matches_evaluate_and_validates_state(trained):
    nls = trained["play"]
    u = rich_input(100, seed=3)
    z = nls(u)
    state = None
    for t in range(u.size):
        z_t, state = nls.step(u[t], state)
        assert z_t == pytest.approx(z[t], abs=1e-12)
    with pytest.raises(ValueError, match="play feature state"):
        nls.step(0.0, np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        nls.evaluate([0.0, np.inf])


@pytest.mark.parametrize("name", ["play", "past-inputs", "bouc-wen"])
def test_dict_round_trip(trained, name):
    nls = trained[name]
    config = json.loads(json.dumps(nls.to_dict(), allow_nan=False))
    again = NLS.from_dict(config, nls.arrays())
    u = rich_input(300, seed=8)
    np.testing.assert_array_equal(again(u), nls(u))
    assert again.feature_set == name
    assert again.u_range == nls.u_range


def test_from_dict_reports_problems(trained):
    nls = trained["play"]
    arrays = nls.arrays()
    with pytest.raises(ValueError, match="version"):
        NLS.from_dict({**nls.to_dict(), "version": 99}, arrays)
    with pytest.raises(ValueError, match="missing array"):
        NLS.from_dict(nls.to_dict(), {k: v for k, v in arrays.items() if k != "out_bias"})
    bad = dict(arrays, layer1_weight=arrays["layer1_weight"][:, :-1])
    with pytest.raises(ValueError, match="layer1_weight"):
        NLS.from_dict(nls.to_dict(), bad)
    with pytest.raises(ValueError, match="hidden widths"):
        NLS.from_dict({**nls.to_dict(), "hidden": [8, 8, 8]}, arrays)


def test_reused_features_are_computed_once_and_handed_out_as_copies():
    """Inside reused_features, one map's features of one record are computed once; a caller
    that writes into its copy does not change what the next caller gets, and outside the block
    nothing is reused."""
    feature_map = BoucWenFeatures(levels=(10.0, 20.0))
    u = np.sin(np.linspace(0.0, 20.0, 500)) * 30.0
    state = feature_map.initial_state()
    expected, expected_final = feature_map.features(u, state)
    calls = []
    original = feature_map.features

    def counted(u_seq, s):
        calls.append(1)
        return original(u_seq, s)

    object.__setattr__(feature_map, "features", counted)
    with reused_features():
        first, final = sequence_features(feature_map, u, state)
        first[:] = 0.0
        final[:] = 0.0
        second, second_final = sequence_features(feature_map, u.copy(), state.copy())
        sequence_features(feature_map, u[:-1], state)
    np.testing.assert_array_equal(second, expected)
    np.testing.assert_array_equal(second_final, expected_final)
    assert len(calls) == 2
    sequence_features(feature_map, u, state)
    assert len(calls) == 3


def test_reused_features_keep_at_most_their_byte_budget(monkeypatch):
    """Features beyond REUSE_BYTES are computed afresh each time (and still right); those
    within it are reused."""
    import identification.features as features_module

    feature_map = BoucWenFeatures(levels=(10.0, 20.0))
    short = np.sin(np.linspace(0.0, 5.0, 100)) * 30.0
    long = np.sin(np.linspace(0.0, 20.0, 1000)) * 30.0
    state = feature_map.initial_state()
    short_bytes = sum(a.nbytes for a in feature_map.features(short, state))
    monkeypatch.setattr(features_module, "REUSE_BYTES", short_bytes)
    calls = []
    original = feature_map.features

    def counted(u_seq, s):
        calls.append(u_seq.size)
        return original(u_seq, s)

    object.__setattr__(feature_map, "features", counted)
    with reused_features():
        for _ in range(2):
            got, _final = sequence_features(feature_map, long, state)
            sequence_features(feature_map, short, state)
    np.testing.assert_array_equal(got, original(long, state)[0])
    assert calls == [1000, 100, 1000]  # the long record over the budget, the short one kept
