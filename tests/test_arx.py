"""ARX model: simulation, prediction, transfer function, poles/zeros, JSON files."""

import json

import control
import numpy as np
import pytest

from identification.arx import ARXModel, regressors
from identification.estimation import fit_arx

DT = 1e-3


def beam_like(noise_bound=0.0):
    """Lightly damped second-order system, a bending mode at 50 Hz sampled at 1 kHz."""
    rho, w = 0.99, 2 * np.pi * 50 * DT
    return ARXModel([2 * rho * np.cos(w), -(rho**2)], [0.5, 0.3], noise_bound=noise_bound, dt=DT)


def loop_simulate(model, u, nu):
    y = np.zeros(len(u))
    for t in range(len(u)):
        y[t] = nu[t]
        y[t] += sum(model.a[i - 1] * y[t - i] for i in range(1, model.na + 1) if t - i >= 0)
        y[t] += sum(model.b[j - 1] * u[t - j] for j in range(1, model.nb + 1) if t - j >= 0)
    return y


def test_simulate_matches_the_difference_equation():
    model = ARXModel([0.5, -0.2, 0.1], [1.0, -0.4], noise_bound=0.1)
    u = np.random.default_rng(0).standard_normal(200)
    np.testing.assert_allclose(model.simulate(u), loop_simulate(model, u, np.zeros(200)))
    nu = np.random.default_rng(5).uniform(-0.1, 0.1, 200)
    np.testing.assert_allclose(
        model.simulate(u, rng=np.random.default_rng(5)), loop_simulate(model, u, nu)
    )


def test_simulate_of_no_input_is_no_output():
    model = ARXModel([0.5, -0.2, 0.1], [1.0, -0.4], noise_bound=0.1)
    assert model.simulate(np.array([])).shape == (0,)


def test_simulate_continues_from_given_initial_outputs():
    model = beam_like()
    u = np.random.default_rng(1).standard_normal(100)
    y = model.simulate(u, rng=np.random.default_rng(2))
    y_free = model.simulate(u, y0=y[:2])
    np.testing.assert_array_equal(y_free[:2], y[:2])
    expected = (
        model.a[0] * y_free[1] + model.a[1] * y_free[0] + model.b[0] * u[1] + model.b[1] * u[0]
    )
    assert y_free[2] == pytest.approx(expected)


def test_predict_is_one_step_ahead_with_the_record_start_taken_as_zero():
    model = beam_like(noise_bound=0.05)
    u = np.random.default_rng(3).standard_normal(300)
    y = model.simulate(u, rng=np.random.default_rng(4))
    y_hat = model.predict(u, y)
    psi, _ = regressors(u, y, 2, 2)
    np.testing.assert_allclose(y_hat[2:], psi @ model.theta)
    assert np.max(np.abs(y_hat[2:] - y[2:])) <= 0.05
    assert y_hat[0] == 0.0
    assert y_hat[1] == pytest.approx(model.a[0] * y[0] + model.b[0] * u[0])


def test_transfer_function_agrees_with_simulate_on_a_step():
    model = ARXModel([1.2, -0.5, 0.1], [0.3, 0.2], dt=DT)
    u = np.ones(200)
    response = control.forced_response(model.to_transfer_function(), T=np.arange(200) * DT, U=u)
    np.testing.assert_allclose(response.outputs, model.simulate(u), atol=1e-12)
    assert model.to_transfer_function().dt == DT
    assert model.simulate(np.ones(5000))[-1] == pytest.approx(model.static_gain())


def test_poles_zeros_and_phase():
    model = beam_like()
    np.testing.assert_allclose(np.abs(model.poles()), [0.99, 0.99])
    np.testing.assert_allclose(model.zeros(), [-0.6])
    assert model.is_stable() and model.is_minimum_phase()
    tf = model.to_transfer_function()
    np.testing.assert_allclose(np.sort_complex(tf.poles()), np.sort_complex(model.poles()))
    assert not ARXModel([0.5], [0.2, 0.5]).is_minimum_phase()


def test_regressors_layout():
    u = np.arange(10.0)
    y = 100 + np.arange(10.0)
    psi, target = regressors(u, y, 2, 3)
    assert psi.shape == (7, 5)
    np.testing.assert_array_equal(psi[0], [102, 101, 2, 1, 0])
    np.testing.assert_array_equal(target, y[3:])


def test_json_round_trip_with_and_without_history(tmp_path):
    history = {"t": np.arange(3.0), "theta": np.ones((3, 4)), "noise_bound": [np.nan, 2, 3]}
    model = ARXModel(
        [1.8, -0.9], [0.1, 0.2], noise_bound=0.3, dt=DT, history=history, method="chebyshev"
    )
    path = tmp_path / "arx.json"
    model.save(path)
    loaded = ARXModel.load(path)
    np.testing.assert_array_equal(loaded.theta, model.theta)
    assert (loaded.noise_bound, loaded.dt, loaded.method) == (0.3, DT, "chebyshev")
    np.testing.assert_array_equal(loaded.history["noise_bound"], [np.nan, 2, 3])
    model.save(path, include_history=False)
    assert ARXModel.load(path).history is None
    json.loads(path.read_text())  # strict JSON, no NaN tokens


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("{not json", "not valid JSON"),
        ('{"format": "something-else"}', "not an ARX model"),
        ('{"format": "piezo-arx", "version": 1, "a": [1.0]}', "lacks"),
        (
            '{"format": "piezo-arx", "version": 1, "a": [1.0], "b": [1.0], "noise_bound": -1,'
            ' "dt": 1.0}',
            "noise_bound",
        ),
        (
            '{"format": "piezo-arx", "version": 1, "a": [1.0], "b": [1.0], "noise_bound": 0,'
            ' "dt": 1.0, "history": {"theta": [[1.0]]}}',
            "history",
        ),
    ],
)
def test_corrupted_files_raise_value_error(tmp_path, content, match):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=match):
        ARXModel.load(path)


def test_constructor_rejects_bad_values():
    with pytest.raises(ValueError, match="finite"):
        ARXModel([np.nan], [1.0])
    with pytest.raises(ValueError, match="dt"):
        ARXModel([0.5], [1.0], dt=0.0)
    with pytest.raises(ValueError, match="na \\+ nb"):
        ARXModel([], [])


@pytest.mark.parametrize(("na", "nb"), [(2, 2), (4, 4), (3, 1), (1, 3), (0, 2), (6, 6)])
def test_state_space_matches_the_arx_recursion_and_transfer_function(na, nb):
    rng = np.random.default_rng(na * 10 + nb)
    a = rng.uniform(-0.3, 0.3, na) / max(na, 1)
    b = rng.uniform(0.5, 2.0, nb)
    model = ARXModel(a, b, dt=DT)
    u = rng.uniform(-1.0, 1.0, 150)
    ss = model.to_state_space()
    assert ss.dt == DT and ss.ninputs == 1 and ss.noutputs == 1
    response = control.forced_response(ss, T=np.arange(u.size) * DT, U=u)
    np.testing.assert_allclose(response.outputs, model.simulate(u), atol=1e-12)
    # Same transfer function: equal frequency responses at a few frequencies.
    z = np.exp(1j * np.array([0.1, 1.0, 10.0, 100.0, 1000.0]) * DT)
    np.testing.assert_allclose(
        np.asarray(ss(z)).ravel(),
        np.asarray(model.to_transfer_function()(z)).ravel(),
        rtol=1e-10,
    )


@pytest.mark.parametrize(("noise", "offset"), [(1e-7, 0.0), (1e-6, 0.0), (0.03, 1e4)])
def test_the_chebyshev_bound_is_the_minimum_whatever_the_noise_s_share_of_the_output(
    noise, offset
):
    """The exact MAP's bound is the smallest largest residual, so at most the true
    parameters' and least squares' (an independent upper bound each), also with a noise far
    below the output's level or an input offset far above its swing (solved for y directly,
    the LP's absolute tolerance made it up to twice the minimum)."""

    rng = np.random.default_rng(0)
    true = ARXModel([1.5, -0.7], [1.0, 0.5], noise_bound=noise)
    u = offset + rng.choice([-1.0, 1.0], 3000)
    y = true.simulate(u, rng=np.random.default_rng(1))
    psi, target = regressors(u, y, 2, 2)
    at_truth = np.max(np.abs(target - psi @ np.r_[true.a, true.b]))
    exact = fit_arx(u, y, method="chebyshev")
    ls = fit_arx(u, y, method="least-squares")
    assert exact.noise_bound <= at_truth * (1 + 1e-9)
    assert exact.noise_bound <= ls.noise_bound
    assert exact.noise_bound > 0.9 * noise  # the uniform noise reaches near its bound


def test_bayes_uniform_says_why_it_cannot_start():
    """Noise-free data (an unbounded 1/r) and a record shorter than its start: each named,
    where both used to read "not persistently exciting"; the exact fit takes the first."""
    u = np.random.default_rng(0).choice([-1.0, 1.0], 500)
    clean = ARXModel([1.5, -0.7], [1.0, 0.5]).simulate(u)
    with pytest.raises(ValueError, match=r"with \(almost\) no noise.*method='chebyshev'"):
        fit_arx(u, clean)
    assert fit_arx(u, clean, method="chebyshev").noise_bound < 1e-12
    noisy = ARXModel([1.5, -0.7], [1.0, 0.5], noise_bound=0.1).simulate(
        u, rng=np.random.default_rng(1)
    )
    with pytest.raises(ValueError, match="needs at least 22 samples, 21 given"):
        fit_arx(u[:21], noisy[:21])
    assert fit_arx(u[:22], noisy[:22]).noise_bound > 0


@pytest.mark.parametrize("split", [1500, 1537, 2999])
def test_the_bayes_uniform_estimator_continued_is_the_whole_record_s_estimate(split):
    """Step b's chosen order goes on from the three-quarter record's estimator: the estimate,
    its bound and its history equal those of the whole record at once (to rounding where a
    reorientation period straddles the split); the history also holds the estimate at the
    split, where the first record's last block ended."""
    from identification.estimation import bayes_uniform_estimator

    rng = np.random.default_rng(2)
    true = ARXModel([1.5, -0.7], [1.0, 0.5], noise_bound=0.05)
    u = rng.choice([-1.0, 1.0], 3000)
    y = true.simulate(u, rng=np.random.default_rng(3))
    whole = fit_arx(u, y, dt=1e-3)
    estimator = bayes_uniform_estimator(u[:split], y[:split], na=2, nb=2, dt=1e-3)
    estimator.update_many(u[split:], y[split:])
    continued = estimator.model()
    np.testing.assert_allclose(continued.theta, whole.theta, rtol=1e-12, atol=1e-12)
    assert continued.noise_bound == pytest.approx(whole.noise_bound, rel=1e-12)
    times = np.asarray(continued.history["t"])
    shared = np.isin(times, whole.history["t"])
    assert set(times[~shared]) <= {split - 2}  # rows counted: the first two samples fill them
    for key, values in whole.history.items():
        np.testing.assert_allclose(
            np.asarray(continued.history[key])[shared], values, rtol=1e-12, atol=1e-12
        )


def test_an_input_free_arx_has_a_realization():
    """nb = 0: the input does not enter (B = 0), the states are the past outputs."""
    model = ARXModel([0.5, 0.2], [])
    a, b, c, _ = model.state_space_matrices()
    assert a.shape == (2, 2) and not b.any()
    x, y = np.array([1.0, 0.0]), []
    for _ in range(5):
        y.append((c @ x).item())
        x = a @ x
    np.testing.assert_allclose(y, [1.0, 0.5, 0.45, 0.325, 0.2525])
