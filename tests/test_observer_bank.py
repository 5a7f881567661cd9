"""The observer bank: each filter is the fixed observer, its innovation variance is what the
data show, and the likelihood picks the noise levels the data were made with."""

import gymnasium as gym
import numpy as np
import pytest
from handmade import first_mode, run_observer

import controllers as ctl
from controllers.observer import DisturbanceObserver, ObserverBank

SIGMA = 0.5  # sensor noise (um)


def _simulate(a, b, c, z, rng, *, process_std=0.0, disturbance_std=0.0):
    """y of the model under input z with input-referred process noise, a random-walk output
    disturbance and Gaussian sensor noise (the filters' own noise model)."""
    x = np.zeros(a.shape[0])
    d = 0.0
    y = np.empty(z.size)
    for t, zt in enumerate(z):
        y[t] = (c @ x).item() + d + SIGMA * rng.standard_normal()
        x = a @ x + b[:, 0] * (zt + process_std * rng.standard_normal())
        d += disturbance_std * rng.standard_normal()
    return y


def test_a_one_filter_bank_is_the_fixed_observer() -> None:
    a, b, c = first_mode()
    rng = np.random.default_rng(0)
    z = rng.uniform(-5, 5, 500)
    y = _simulate(a, b, c, z, rng, process_std=0.05, disturbance_std=0.3)
    dc = abs((c @ np.linalg.solve(np.eye(2) - a, b)).item())
    bank = ObserverBank(
        a, b, c, measurement_std=SIGMA, process_ratios=(0.5,), disturbance_ratios=(0.6,)
    )
    fixed = DisturbanceObserver(
        a, b, c, measurement_std=SIGMA, process_std=0.5 * SIGMA / dc, disturbance_std=0.3
    )
    for t in range(z.size):
        np.testing.assert_allclose(bank.correct(y[t]), fixed.correct(y[t]), rtol=1e-12, atol=1e-9)
        bank.predict(z[t])
        fixed.predict(z[t])


@pytest.mark.parametrize(("process_std", "disturbance_std"), [(0.0, 0.05), (0.02, 0.5)])
def test_innovation_variance_is_what_the_data_show(process_std, disturbance_std) -> None:
    """The Riccati solution's C P C^T + R against the empirical variance of the innovations
    on data made with the filter's own noise model (Monte Carlo, 40,000 samples)."""
    a, b, c = first_mode()
    rng = np.random.default_rng(1)
    z = rng.uniform(-5, 5, 40_000)
    y = _simulate(a, b, c, z, rng, process_std=process_std, disturbance_std=disturbance_std)
    observer = DisturbanceObserver(
        a, b, c, measurement_std=SIGMA, process_std=process_std, disturbance_std=disturbance_std
    )
    innovations = run_observer(observer, z, y)[1000:]
    assert np.var(innovations) == pytest.approx(observer.innovation_var, rel=0.04)
    # and they are white, as the innovations of the optimal filter are
    lag1 = np.corrcoef(innovations[:-1], innovations[1:])[0, 1]
    assert abs(lag1) < 0.03


@pytest.mark.parametrize(("disturbance_std", "expected_ratio"), [(0.0, 1 / 27), (0.5, 1.0)])
def test_the_likelihood_picks_the_noise_the_data_were_made_with(
    disturbance_std, expected_ratio
) -> None:
    a, b, c = first_mode()
    rng = np.random.default_rng(2)
    z = 3 * np.sin(2 * np.pi * 10 * 1e-3 * np.arange(6000))
    y = _simulate(a, b, c, z, rng, disturbance_std=disturbance_std)
    bank = ObserverBank(a, b, c, measurement_std=SIGMA, memory=1000)
    run_observer(bank, z, y)
    process, disturbance = bank.noise_levels[int(np.argmax(bank.selection_counts))]
    assert disturbance == pytest.approx(expected_ratio * SIGMA)
    assert process <= 0.25 * SIGMA / 16.0  # no process noise was made: little is chosen


def test_reset_returns_to_the_prior_and_forgets() -> None:
    a, b, c = first_mode()
    bank = ObserverBank(a, b, c, measurement_std=SIGMA)
    assert bank.noise_level == pytest.approx((SIGMA / 16.0, SIGMA), rel=1e-9)
    for _ in range(50):
        bank.correct(100.0)
        bank.predict(0.0)
    assert bank.selected != bank.prior
    bank.reset()
    assert bank.selected == bank.prior and not bank.selection_counts.any()
    assert not bank.estimate.any()


def test_bad_observer_settings_are_refused() -> None:
    env = gym.make("piezo_env:PiezoBender-v0")
    with pytest.raises(ValueError, match="observer must be 'bank' or 'fixed'"):
        ctl.make("mpc", "plant", env, observer="kalman")
    with pytest.raises(ValueError, match="bank_memory"):
        ctl.make("mpc", "plant", env, bank_memory=0)
    a, b, c = first_mode()
    with pytest.raises(ValueError, match="memory must be an integer"):
        ObserverBank(a, b, c, measurement_std=SIGMA, memory=0)
