"""Online estimators and the modal correction, held to known systems and independent methods."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from identification.arx import ARXModel
from identification.correction import (
    ModalCorrection,
    ModalSplit,
    first_mode_pole,
    fit_modal_correction,
    multi_step_errors,
    scale_modes,
)
from identification.online import RecursiveLeastSquares, SlidingWindowBayes, regressor_scales

DT = 1e-3
PLANT = ARXModel([1.5, -0.7], [1.0, 0.5], dt=DT)  # poles 0.75 +- 0.37j, zero -0.5
CHANGED = ARXModel([1.3, -0.6], [1.4, 0.3], dt=DT)  # the plant after a step change


def closed_loop(plants: list[tuple[ARXModel, int]], seed: int, noise: float = 0.02):
    """(u, y) of a proportional loop around the ARX plants in turn (samples each), driven by a
    random reference, with uniform equation noise: data where u depends on past y."""
    rng = np.random.default_rng(seed)
    n = sum(steps for _, steps in plants)
    reference = np.repeat(rng.uniform(-1.0, 1.0, n // 10 + 1), 10)[:n]
    u, y = np.zeros(n), np.zeros(n)
    t = 0
    for plant, steps in plants:
        for _ in range(steps):
            if t >= 2:
                y[t] = plant.a @ y[[t - 1, t - 2]] + plant.b @ u[[t - 1, t - 2]]
                y[t] += rng.uniform(-noise, noise)
            u[t] = 0.3 * (reference[t] - y[t]) + 0.2 * reference[t]
            t += 1
    return u, y


def rls_for(prior: ARXModel, forgetting: float) -> RecursiveLeastSquares:
    scales = regressor_scales(prior, 1.0)
    return RecursiveLeastSquares(prior, scales, forgetting=forgetting, prior_variance=100.0)


def test_rls_recovers_a_known_arx_from_closed_loop_data():
    u, y = closed_loop([(PLANT, 3000)], seed=1)
    rls = rls_for(ARXModel([1.0, 0.0], [0.5, 0.5], dt=DT), forgetting=1.0)
    for u_t, y_t in zip(u, y, strict=True):
        rls.update(u_t, y_t)
    np.testing.assert_allclose(rls.theta, PLANT.theta, atol=0.01)


def test_window_bayes_recovers_a_known_arx_and_its_noise_bound():
    u, y = closed_loop([(PLANT, 600)], seed=2, noise=0.02)
    bayes = SlidingWindowBayes(2, 2, window=500, dt=DT)
    for u_t, y_t in zip(u, y, strict=True):
        bayes.update(u_t, y_t)
    model = bayes.estimate()
    np.testing.assert_allclose(model.theta, PLANT.theta, atol=0.01)
    assert 0.018 < model.noise_bound <= 0.02  # the Chebyshev bound: at most the true one
    assert bayes.contains(PLANT, 0.02)
    assert not bayes.contains(CHANGED, 0.02)


@pytest.mark.parametrize("estimator", ["rls", "bayes"])
def test_estimators_follow_a_step_change_of_the_plant(estimator):
    """Before the change the estimate is within 0.05 of the plant's parameters; at most 400
    samples after it, within 0.05 of the new ones (RLS with forgetting 0.98, memory about 50
    samples; the window of 300 forgets exactly). Measured worst: 0.028 / 0.017 before,
    0.020 / 0.002 from 400 samples after."""
    u, y = closed_loop([(PLANT, 1500), (CHANGED, 1500)], seed=3)
    if estimator == "rls":
        est = rls_for(PLANT, forgetting=0.98)
    else:
        est = SlidingWindowBayes(2, 2, window=300, dt=DT)
    errors = []
    for t, (u_t, y_t) in enumerate(zip(u, y, strict=True)):
        est.update(u_t, y_t)
        if t % 50 == 49 and t > 1000:
            theta = est.theta if estimator == "rls" else est.estimate().theta
            target = PLANT if t < 1500 else CHANGED
            errors.append((t, np.max(np.abs(theta - target.theta))))
    before = [e for t, e in errors if t < 1500]
    settled = [e for t, e in errors if t >= 1500 + 400]
    assert max(before) < 0.05 and max(settled) < 0.05


SENSOR_NOISE = 0.1
"""Bound of the uniform output (sensor) noise of :func:`closed_loop_sensor_noise`: large enough
that the equation-error bias, which grows as its square, stands above the estimates' spread."""


def closed_loop_sensor_noise(n: int, seed: int, noise: float = SENSOR_NOISE, impulse: int = -1):
    """(u, y_measured) of the proportional loop of :func:`closed_loop` around PLANT with the
    noise on the measured output instead (a sensor's: white, uniform, the loop feeding it
    back), which the ARX structure does not model: the equation error is A(q) v, coloured, and
    correlated with the regressors' past outputs. ``impulse >= 0`` runs instead the loop's
    response to a unit noise sample at that step, reference and noise zero."""
    rng = np.random.default_rng(seed)
    reference = np.repeat(rng.uniform(-1.0, 1.0, n // 10 + 1), 10)[:n]
    v = rng.uniform(-noise, noise, n)
    if impulse >= 0:
        reference, v = np.zeros(n), np.zeros(n)
        v[impulse] = 1.0
    u, y, measured = np.zeros(n), np.zeros(n), np.zeros(n)
    for t in range(n):
        if t >= 2:
            y[t] = PLANT.a @ y[[t - 1, t - 2]] + PLANT.b @ u[[t - 1, t - 2]]
        measured[t] = y[t] + v[t]
        u[t] = 0.3 * (reference[t] - measured[t]) + 0.2 * reference[t]
    return u, measured


def test_least_squares_bias_under_sensor_noise_is_the_equation_error_bias():
    """With the noise on the measured output, RLS without forgetting (least squares) converges
    to theta + R^-1 E[psi e], not to the plant: e_t = v_t - a1 v_t-1 - a2 v_t-2 and the
    regressors' y_t-1, y_t-2 hold v_t-1, v_t-2 (the bias that the output-error refinement of
    :mod:`identification.refine` removes offline; the online estimators keep it). E[psi e]
    comes here in closed form from the loop's impulse responses to the noise (E[x_t-d v_t-k] =
    sigma^2 h_x(k - d), sigma^2 = r^2 / 3), R from the data. Measured on seed 1, 20,000
    samples: bias -0.045 / +0.044 on a1 / a2; closed form -0.044 / +0.043, off by 0.0010 on
    the a's and 0.0054 on the b's (their spread across seeds is larger); RLS against numpy's
    batch least squares: 3e-5 (the prior's weight)."""
    n = 20_000
    u, y = closed_loop_sensor_noise(n, seed=1)
    rls = rls_for(ARXModel([1.0, 0.0], [0.5, 0.5], dt=DT), forgetting=1.0)
    for u_t, y_t in zip(u, y, strict=True):
        rls.update(u_t, y_t)
    psi = np.column_stack([y[1:-1], y[:-2], u[1:-1], u[:-2]])
    batch = np.linalg.lstsq(psi, y[2:], rcond=None)[0]
    np.testing.assert_allclose(rls.theta, batch, rtol=0, atol=1e-4)

    u_impulse, y_impulse = closed_loop_sensor_noise(8, seed=0, impulse=2)  # past its start
    h_u, h_y = u_impulse[2:], y_impulse[2:]  # h(0) .. h(5)
    c = np.r_[1.0, -PLANT.a]  # e_t = sum_k c_k v_t-k
    sigma2 = SENSOR_NOISE**2 / 3

    def cross(h: np.ndarray, d: int) -> float:
        return sigma2 * sum(c[k] * h[k - d] for k in range(d, c.size))

    p = np.array([cross(h_y, 1), cross(h_y, 2), cross(h_u, 1), cross(h_u, 2)])
    expected_bias = np.linalg.solve(psi.T @ psi / psi.shape[0], p)
    bias = rls.theta - PLANT.theta
    assert np.all(np.abs(expected_bias[:2]) > 0.03)  # a bias well above the a's spread
    np.testing.assert_allclose(bias[:2], expected_bias[:2], rtol=0, atol=0.003)
    np.testing.assert_allclose(bias[2:], expected_bias[2:], rtol=0, atol=0.015)


def test_window_bayes_under_sensor_noise_bounds_the_equation_error_not_the_sensor():
    """The uniform-noise posterior reads r as the bound of the equation error. With the noise
    on the measured output that is |A(q) v| <= r (1 + |a1| + |a2|) = 3.2 r, not the sensor's r:
    the plant leaves the posterior's support at the sensor's bound and is inside it at 3.2 r,
    the Chebyshev r_hat lies between (it is at most the plant's largest residual), and theta
    carries the equation-error bias, which the L-infinity fit takes worse than least squares
    on this record. Measured on seed 1, window 500: r_hat = 2.77 r, largest coefficient error
    0.34 (on b2 = 0.5), where least squares on the same 600 samples is 0.09 off."""
    r = SENSOR_NOISE
    u, y = closed_loop_sensor_noise(600, seed=1)
    bayes = SlidingWindowBayes(2, 2, window=500, dt=DT)
    for u_t, y_t in zip(u, y, strict=True):
        bayes.update(u_t, y_t)
    bound = r * (1.0 + np.abs(PLANT.a).sum())
    assert not bayes.contains(PLANT, r)
    assert bayes.contains(PLANT, bound)
    model = bayes.estimate()
    assert 1.8 * r < model.noise_bound <= bound
    error = np.abs(model.theta - PLANT.theta).max()
    assert 0.1 < error < 1.0


def test_estimators_refuse_bad_samples_and_settings():
    with pytest.raises(ValueError, match="forgetting"):
        rls_for(PLANT, forgetting=1.5)
    with pytest.raises(ValueError, match="non-finite"):
        rls_for(PLANT, forgetting=0.99).update(np.nan, 0.0)
    with pytest.raises(ValueError, match="window"):
        SlidingWindowBayes(2, 2, window=4)


def test_multi_step_errors_match_a_direct_recursion():
    """Each row equals the ARX recursion run by hand from the measured outputs at its start;
    horizon 1 is the one-step residual of ARXModel.predict."""
    rng = np.random.default_rng(4)
    u = rng.normal(size=200)
    y = PLANT.simulate(u) + rng.normal(scale=0.1, size=200)
    errors = multi_step_errors(PLANT, u, y, 10)
    for start in (1, 57, 180):
        known = {t: y[t] for t in range(start + 1)}
        for t in range(start + 1, start + 11):
            known[t] = sum(
                PLANT.a[i - 1] * known[t - i] + PLANT.b[i - 1] * (u[t - i] if t >= i else 0.0)
                for i in (1, 2)
            )
        expected = [y[t] - known[t] for t in range(start + 1, start + 11)]
        np.testing.assert_allclose(errors[start - 1], expected, atol=1e-12)
    one_step = multi_step_errors(PLANT, u, y, 1)[:, 0]
    np.testing.assert_allclose(one_step, (y - PLANT.predict(u, y))[2:], atol=1e-12)


def two_mode_arx(f1: float, zeta1: float, gain1: float) -> ARXModel:
    """ZOH image (scipy.signal.cont2discrete) of two bending modes: an independent model."""
    modes = [(f1, zeta1, gain1), (900.0, 0.03, 0.1)]
    num, den = np.array([0.0]), np.array([1.0])
    for f, zeta, k in modes:
        w = 2 * np.pi * f
        n_i, d_i = np.array([k * w**2]), np.array([1.0, 2 * zeta * w, w**2])
        num = np.polyadd(np.polymul(num, d_i), np.polymul(n_i, den))
        den = np.polymul(den, d_i)
    b, a, _ = scipy.signal.cont2discrete((num, den), DT, method="zoh")
    b, a = np.ravel(b) / a[0], a / a[0]
    assert abs(b[0]) < 1e-12
    return ARXModel(-a[1:], b[1:], dt=DT)


@pytest.mark.parametrize(("alpha", "gain"), [(1.2, 1.0), (0.8, 1.25), (1.1, 0.9)])
def test_frequency_scaling_is_the_zoh_image_of_the_scaled_mode(alpha, gain):
    """Scaling the first mode's frequency by alpha (damping ratio kept) equals discretising the
    continuous system whose first mode is alpha times faster, then scaling its gain."""
    base = two_mode_arx(160.0, 0.02, 1.0)
    expected = two_mode_arx(160.0 * alpha, 0.02, 1.0)
    expected = ARXModel(expected.a, gain * expected.b, dt=DT)
    # gain scales the whole model; the second mode's static share is kept, as in the plant
    got = scale_modes(base, ModalCorrection(gain=gain, frequency=alpha))
    np.testing.assert_allclose(got.a, expected.a, atol=1e-10)
    np.testing.assert_allclose(got.b, expected.b, atol=1e-10 * np.abs(expected.b).max())


def test_damping_factor_moves_the_pole_as_stated():
    base = two_mode_arx(160.0, 0.02, 1.0)
    got = scale_modes(base, ModalCorrection(damping=0.5))
    s = np.log(ModalSplit(base).p) / DT
    expected = np.exp((0.5 * s.real + 1j * s.imag) * DT)
    assert np.min(np.abs(got.poles() - expected)) < 1e-9
    assert got.static_gain() == pytest.approx(base.static_gain(), rel=1e-9)


def test_modal_fit_recovers_a_stiffer_bender():
    """The stiffer bender is the ZOH image (scipy) of the two-mode system with its first mode
    1.2x faster, damping ratio kept, and everything /1.2: correction (1/1.2, 1.2, 1) exactly.
    Measured relative errors on seed 5: gain 2.0e-5, frequency 5.8e-7, damping 2.2e-5."""
    base = two_mode_arx(160.0, 0.02, 1.0)
    stiffer = two_mode_arx(160.0 * 1.2, 0.02, 1.0)
    truth = ARXModel(stiffer.a, stiffer.b / 1.2, dt=DT)
    rng = np.random.default_rng(5)
    u = rng.uniform(-1, 1, 400)
    y = truth.simulate(u) + rng.uniform(-1e-3, 1e-3, 400)
    correction, _ = fit_modal_correction(base, u, y, horizon=20)
    assert correction.gain == pytest.approx(1 / 1.2, rel=6e-5)
    assert correction.frequency == pytest.approx(1.2, rel=2e-6)
    assert correction.damping == pytest.approx(1.0, rel=7e-5)


def test_modal_fit_finds_the_closed_form_pole_of_a_bender_damped_otherwise():
    """A bender whose first mode is 1.1x faster with damping ratio 0.03 instead of 0.02 (same
    static gains): the correction the fit finds moves the first pole to the continuous mode's
    closed-form image exp(s dt), s = -zeta w + j w sqrt(1 - zeta^2), and its factors to the
    closed-form ratios of s. The correction keeps the mode's static contribution but not the
    shape of its residue when the damping changes, so the fit is close, not exact: measured on
    seed 5, frequency factor 3.1e-4 and damping factor 1.4e-2 relative error, gain 1.6e-3 off
    1, the pole's log 5.2e-4 relative."""
    f, zeta, alpha_true = 160.0, 0.03, 1.1
    base = two_mode_arx(f, 0.02, 1.0)
    truth = two_mode_arx(f * alpha_true, zeta, 1.0)
    w, w0 = 2 * np.pi * f * alpha_true, 2 * np.pi * f
    s = -zeta * w + 1j * w * np.sqrt(1 - zeta**2)
    s0 = -0.02 * w0 + 1j * w0 * np.sqrt(1 - 0.02**2)
    frequency = s.imag / s0.imag  # s' = alpha (beta Re s0 + j Im s0)
    damping = s.real / (frequency * s0.real)
    rng = np.random.default_rng(5)
    u = rng.uniform(-1, 1, 400)
    y = truth.simulate(u) + rng.uniform(-1e-3, 1e-3, 400)
    correction, corrected = fit_modal_correction(base, u, y, horizon=20)
    assert correction.frequency == pytest.approx(frequency, rel=1e-3)
    assert correction.damping == pytest.approx(damping, rel=4e-2)
    assert correction.gain == pytest.approx(1.0, abs=5e-3)
    pole = first_mode_pole(corrected.poles())
    assert abs(np.log(pole) - s * DT) < 1.5e-3 * abs(s * DT)


def test_modal_correction_refuses_models_it_cannot_scale():
    with pytest.raises(ValueError, match="complex pole pair"):
        scale_modes(ARXModel([0.5, 0.1], [1.0, 0.2], dt=DT), ModalCorrection())
    with pytest.raises(ValueError, match="na <= nb"):
        scale_modes(ARXModel([1.5, -0.7, 0.01], [1.0], dt=DT), ModalCorrection())
    with pytest.raises(ValueError, match="gain"):
        ModalCorrection(gain=0.0)
