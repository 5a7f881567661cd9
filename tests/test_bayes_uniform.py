"""ARX estimation under uniformly bounded noise: Bayesian recursion, Chebyshev LP, least squares.

Accuracy is held against the true system that generated the data and against the exact
(Chebyshev) estimate; parameter errors are relative in the Euclidean norm. Tolerances are about
5x the errors measured on these fixed seeds (in the comments), so a loose update (e.g. interval
arithmetic instead of the tight slab bounds, which biases r_hat low by percents) fails them.
"""

import numpy as np
import pytest
import scipy.optimize
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from identification.arx import ARXModel
from identification.bayes_uniform import BayesUniformEstimator, slab_upper_bound
from identification.estimation import fit_arx
from piezo_env.signals import prbs

DT = 1e-3


def beam_arx22():
    rho, w = 0.99, 2 * np.pi * 50 * DT
    return ARXModel([2 * rho * np.cos(w), -(rho**2)], [0.5, 0.3], noise_bound=0.05, dt=DT)


def beam_arx32():
    w = 2 * np.pi * 50 * DT
    a = -np.poly([0.98 * np.exp(1j * w), 0.98 * np.exp(-1j * w), 0.6]).real[1:]
    return ARXModel(a, [0.4, 0.2], noise_bound=0.05, dt=DT)


def prbs_data(model, n, seed):
    rng = np.random.default_rng(seed)
    u = prbs(n, amplitude=1.0, rng=rng)
    return u, model.simulate(u, rng=rng)


def relative_error(theta, truth):
    return np.linalg.norm(theta - truth) / np.linalg.norm(truth)


@pytest.fixture(scope="module", params=["arx22", "arx32"])
def case(request):
    model = beam_arx22() if request.param == "arx22" else beam_arx32()
    u, y = prbs_data(model, 5000, seed=11)
    fits = {
        method: fit_arx(u, y, na=model.na, nb=model.nb, method=method, dt=DT)
        for method in ("chebyshev", "bayes-uniform", "least-squares")
    }
    return model, fits


def test_chebyshev_recovers_theta_and_r(case):
    truth, fits = case
    fit = fits["chebyshev"]
    # measured: theta 7.7e-6 / 2.3e-5, r -0.07 % / -0.10 % (arx22 / arx32)
    assert relative_error(fit.theta, truth.theta) < 1.2e-4
    assert fit.noise_bound == pytest.approx(truth.noise_bound, rel=5e-3)
    assert fit.noise_bound <= truth.noise_bound  # the max residual of the truth is <= r


def test_bayes_uniform_within_0_06_percent_theta_and_0_6_percent_r(case):
    truth, fits = case
    fit = fits["bayes-uniform"]
    # measured: theta 2.0e-5 / 1.2e-4 of the truth, 2.7e-5 / 1.0e-4 of the Chebyshev estimate;
    # r -0.05 % / -0.12 % of the truth, +0.02 % / -0.02 % of the Chebyshev r (arx22 / arx32)
    assert relative_error(fit.theta, truth.theta) < 6e-4
    assert relative_error(fit.theta, fits["chebyshev"].theta) < 5e-4
    assert fit.noise_bound == pytest.approx(truth.noise_bound, rel=6e-3)
    assert fit.noise_bound == pytest.approx(fits["chebyshev"].noise_bound, rel=1e-3)
    assert fit.method == "bayes-uniform" and fit.dt == DT


def test_least_squares_within_0_15_percent(case):
    truth, fits = case
    # measured: 3.6e-4 / 2.9e-4; uniform noise makes the L-infinity estimate the sharper one
    assert relative_error(fits["least-squares"].theta, truth.theta) < 1.5e-3


def test_bayes_history_is_the_time_course_of_the_estimates(case):
    truth, fits = case
    history = fits["bayes-uniform"].history
    assert history["theta"].shape == (history["t"].size, truth.na + truth.nb)
    assert history["noise_bound"].shape == history["t"].shape
    assert np.all(np.diff(history["t"]) > 0)
    np.testing.assert_allclose(history["theta"][-1], fits["bayes-uniform"].theta)


@pytest.mark.parametrize("window", [1, 16])
def test_true_parameters_stay_inside_the_parallelotope(window):
    truth = beam_arx32()
    u, y = prbs_data(truth, 1500, seed=3)
    estimator = BayesUniformEstimator(3, 2, window=window, reorient_every=8)
    for k in range(u.size):
        estimator.update(u[k], y[k])
        if estimator.initialized:
            assert estimator.contains(truth.theta, truth.noise_bound), f"excluded at sample {k}"
    v, lower, upper = estimator.parallelotope
    assert np.all(lower <= upper)
    assert np.allclose(np.diag(v), 1.0) and np.allclose(np.tril(v, -1), 0.0)


def test_batch_and_online_updates_agree():
    truth = beam_arx22()
    u, y = prbs_data(truth, 2000, seed=4)
    batch = BayesUniformEstimator(2, 2)
    batch.update_many(u, y)
    online = BayesUniformEstimator(2, 2)
    for k in range(u.size):
        online.update(u[k], y[k])
    assert batch.contains(truth.theta, truth.noise_bound)
    # measured: theta 4.2e-5, r 0.05 %
    assert relative_error(online.theta, batch.theta) < 2e-4
    assert online.noise_bound == pytest.approx(batch.noise_bound, rel=2.5e-3)


def test_mean_point_estimate_averages_the_steady_part():
    truth = beam_arx22()
    u, y = prbs_data(truth, 3000, seed=5)
    fit = fit_arx(u, y, point_estimate="mean", steady_fraction=0.5)
    history = fit.history
    start = int(history["t"].size * 0.5)
    np.testing.assert_allclose(fit.theta, history["theta"][start:].mean(axis=0))
    # measured: r -0.14 %, theta 3.3e-5
    assert fit.noise_bound == pytest.approx(truth.noise_bound, rel=7e-3)
    assert relative_error(fit.theta, truth.theta) < 2e-4


def test_slab_bound_is_the_linear_program_optimum():
    rng = np.random.default_rng(0)
    for _ in range(50):
        lower, upper = -rng.uniform(0.1, 2.0, 4), rng.uniform(0.1, 2.0, 4)
        h, g = rng.standard_normal(4), rng.standard_normal(4) * rng.uniform(0.0, 3.0)
        exact = -scipy.optimize.linprog(
            -h,
            A_ub=np.vstack([g, -g]),
            b_ub=[1.0, 1.0],
            bounds=list(zip(lower, upper, strict=True)),
        ).fun
        bound = slab_upper_bound(h[None], g[None], lower, upper)[0]
        assert exact - 1e-9 <= bound <= exact + 1e-7


@st.composite
def stable_arx(draw):
    """ARX of orders 1-4 with poles inside radius 0.95 (conjugate pairs plus one real pole)."""
    na = draw(st.integers(1, 4))
    nb = draw(st.integers(1, 4))
    poles = []
    for _ in range(na // 2):
        radius, angle = draw(st.floats(0.1, 0.95)), draw(st.floats(0.05, 3.0))
        poles += [radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]
    if na % 2:
        poles.append(draw(st.floats(-0.95, 0.95)))
    a = -np.poly(poles).real[1:]
    b = draw(st.lists(st.floats(0.2, 1.0), min_size=nb, max_size=nb))
    seed = draw(st.integers(0, 2**16))
    return ARXModel(a, b, noise_bound=0.02), seed


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(stable_arx())
def test_random_stable_systems_are_recovered_and_bounded(system):
    truth, seed = system
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1.0, 1.0, 2000)
    y = truth.simulate(u, rng=rng)
    cheb = fit_arx(u, y, na=truth.na, nb=truth.nb, method="chebyshev")
    estimator = BayesUniformEstimator(truth.na, truth.nb)
    estimator.update_many(u, y)
    assert estimator.contains(truth.theta, truth.noise_bound)
    # measured over 150 drawn systems: r within 0.56 % of the Chebyshev r and in
    # [0.991, 0.9999] r_true; theta within 0.47 % of the truth
    assert estimator.noise_bound == pytest.approx(cheb.noise_bound, rel=0.02)
    assert 0.96 * truth.noise_bound <= estimator.noise_bound <= truth.noise_bound * 1.005
    assert relative_error(estimator.theta, truth.theta) < 0.02


@pytest.mark.parametrize("method", ["bayes-uniform", "chebyshev", "least-squares"])
def test_degenerate_data_get_clear_errors(method):
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, 200)
    y = beam_arx22().simulate(u, rng=rng)
    with pytest.raises(ValueError, match="persistently exciting"):
        fit_arx(np.ones(200), y, method=method)
    with pytest.raises(ValueError, match="too few samples"):
        fit_arx(u[:8], y[:8], method=method)
    with pytest.raises(ValueError, match="non-finite"):
        fit_arx(np.where(np.arange(200) == 7, np.nan, u), y, method=method)
    with pytest.raises(ValueError, match="non-finite"):
        fit_arx(u, np.where(np.arange(200) == 9, np.inf, y), method=method)
    with pytest.raises(ValueError, match="same length"):
        fit_arx(u, y[:-1], method=method)


def test_unknown_methods_and_options_are_rejected():
    u = np.random.default_rng(0).uniform(-1, 1, 100)
    y = beam_arx22().simulate(u)
    with pytest.raises(ValueError, match="valid methods"):
        fit_arx(u, y, method="magic")
    with pytest.raises(ValueError, match="accepted"):
        fit_arx(u, y, method="bayes-uniform", windw=3)
    with pytest.raises(ValueError, match="no options"):
        fit_arx(u, y, method="chebyshev", window=3)
