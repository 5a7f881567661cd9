"""Output-error refinement of the linear part (identification.refine, step b')."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from identification.arx import ARXModel
from identification.config import IdentificationConfig
from identification.estimation import fit_arx
from identification.metrics import fit_percent
from identification.refine import _jacobian, refine_output_error
from identification.steps import ArxEstimate, estimate_arx, refine_linear_part

# A lightly damped resonance (|p| = 0.97 at 50 Hz for dt = 1 ms) with a zero at -0.6: the
# shape of the bender's first mode, as an output-error system y = B/F u + v.
POLE = 0.97 * np.exp(2j * np.pi * 50e-3)
F_TRUE = np.array([2 * POLE.real, -(abs(POLE) ** 2)])
B_TRUE = np.array([0.5, 0.3])


def _oe_record(n: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PRBS-like +-1 input, the noise-free output, and that output plus white uniform noise
    of half-width ``noise`` times the output's standard deviation (output error)."""
    rng = np.random.default_rng(seed)
    u = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    y0 = scipy.signal.lfilter(np.r_[0.0, B_TRUE], np.r_[1.0, -F_TRUE], u)
    return u, y0, y0 + noise * np.std(y0) * rng.uniform(-1.0, 1.0, n)


def test_noise_free_output_error_system_is_recovered_exactly():
    u, y0, _ = _oe_record(2000, 0.0, seed=0)
    start = ARXModel(F_TRUE * [0.97, 0.95], B_TRUE * [1.2, 0.7])
    fit = refine_output_error(start, u, y0)
    np.testing.assert_allclose(fit.model.theta, np.r_[F_TRUE, B_TRUE], atol=1e-8)
    assert fit.output_error_rms < 1e-9
    assert fit.model.method == "output-error"


def test_output_noise_biases_equation_error_arx_but_not_the_refinement():
    """The textbook case (Ljung 1999, sec. 7.3 and thm. 8.2): with white noise on the output,
    least-squares ARX is biased (its regressors hold the noisy past outputs), while the
    prediction-error estimate of the output-error model is consistent, with the asymptotic
    covariance sigma^2 (J^T J)^-1 (J: the output's sensitivities). Started from the biased ARX
    estimate, the refinement lands within four of its standard errors of the true parameters
    and zero; the ARX estimate lies dozens of them away, its zero pushed towards -1."""
    u, y0, y = _oe_record(8000, 0.25, seed=1)
    arx = fit_arx(u, y, na=2, nb=2, method="least-squares")
    fit = refine_output_error(arx, u, y)
    truth = np.r_[F_TRUE, B_TRUE]
    sigma = 0.25 * np.std(y0) / np.sqrt(3.0)  # RMS of the uniform output noise
    jac = _jacobian(F_TRUE, B_TRUE, u, y0)
    covariance = sigma**2 * np.linalg.inv(jac.T @ jac)
    std = np.sqrt(np.diag(covariance))
    assert np.all(std < 0.01)  # a tight test: the data pin the parameters to 1 %
    assert np.all(np.abs(fit.model.theta - truth) < 4 * std)
    assert np.max(np.abs(arx.theta - truth) / std) > 50  # biased: far from the truth
    # the zero -b2/b1, by the delta method
    grad = np.array([0.0, 0.0, B_TRUE[1] / B_TRUE[0] ** 2, -1.0 / B_TRUE[0]])
    zero_std = float(np.sqrt(grad @ covariance @ grad))
    true_zero = -B_TRUE[1] / B_TRUE[0]
    assert abs(fit.model.zeros()[0].real - true_zero) < 4 * zero_std
    # ARX's zero is pushed towards -1 (the Nyquist frequency), where the MPC's inverse rings
    assert arx.zeros()[0].real < true_zero - 10 * zero_std
    # the residual is the noise
    assert fit.output_error_rms == pytest.approx(sigma, rel=0.02)


def test_bayesian_start_gives_the_same_optimum_as_least_squares_start():
    u, _, y = _oe_record(4000, 0.3, seed=2)
    ends = [
        refine_output_error(fit_arx(u, y, na=2, nb=2, method=m), u, y).model.theta
        for m in ("least-squares", "bayes-uniform")
    ]
    np.testing.assert_allclose(ends[0], ends[1], atol=1e-6)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    z = rng.standard_normal(300)
    f, b = F_TRUE * 0.98, B_TRUE

    def simulate(theta: np.ndarray) -> np.ndarray:
        return scipy.signal.lfilter(np.r_[0.0, theta[2:]], np.r_[1.0, -theta[:2]], z)

    theta = np.r_[f, b]
    analytic = _jacobian(f, b, z, simulate(theta))
    step = 1e-6
    numeric = np.column_stack(
        [
            (simulate(theta + step * e) - simulate(theta - step * e)) / (2 * step)
            for e in np.eye(theta.size)
        ]
    )
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6)


def test_bad_starting_points_are_refused_with_the_fix():
    u, y0, _ = _oe_record(500, 0.0, seed=4)
    with pytest.raises(ValueError, match="unstable"):
        refine_output_error(ARXModel([2.1, -1.0], [1.0]), u, y0)
    with pytest.raises(ValueError, match="na >= 1"):
        refine_output_error(ARXModel([], [1.0, 0.5]), u, y0)


def test_order_selection_prefers_the_true_order_over_larger_ones():
    u, _, y = _oe_record(8000, 0.3, seed=5)
    split = 6000  # step b's candidates: fitted to the first three quarters of the record
    candidates = {
        n: fit_arx(u[:split], y[:split], na=n, nb=n, method="least-squares") for n in (1, 2, 3, 4)
    }
    step_b = fit_arx(u, y, na=4, nb=4, method="least-squares")
    est = ArxEstimate(step_b, 4, {}, step_b, step_b, candidates)
    refinement = refine_linear_part(est, u, y)
    assert refinement.order == 2
    np.testing.assert_allclose(refinement.model.theta, np.r_[F_TRUE, B_TRUE], atol=0.02)
    assert refinement.fit.output_error_rms <= refinement.unrefined_output_error_rms


def test_an_unstable_step_b_estimate_is_reported_without_a_free_run():
    """Step b's equation-error estimate can come out unstable (seen on the PL140 with seed 9);
    step b' still refines its stable candidates, and the step b model's free-run figures are
    None (no free run), not an overflow that stops the identification."""
    from identification.report import format_free_run
    from identification.steps import validate

    u, _, y = _oe_record(4000, 0.3, seed=6)
    candidates = {2: fit_arx(u[:3000], y[:3000], na=2, nb=2, method="least-squares")}
    unstable = ARXModel([2.1, -1.0], [1.0, 0.5])
    assert not unstable.is_stable()
    est = ArxEstimate(unstable, 2, {}, unstable, unstable, candidates)
    refinement = refine_linear_part(est, u, y)
    assert refinement.unrefined_output_error_rms is None
    np.testing.assert_allclose(refinement.model.theta, np.r_[F_TRUE, B_TRUE], atol=0.02)
    assert format_free_run(refinement.unrefined_output_error_rms, ".3f") == (
        "unstable (no free run)"
    )

    import gymnasium as gym

    from identification.hammerstein import HammersteinModel
    from identification.nls import fit_nls

    env = gym.make("piezo_env:PiezoBender-v0")
    ramp = np.linspace(-30.0, 30.0, 400)
    nls = fit_nls(ramp, ramp, features="past-inputs", max_epochs=0, u_range=(-30.0, 30.0))
    model = HammersteinModel(nls, ARXModel([0.5], [1.0], dt=1e-3))
    from identification.experiment import collect, rand_signal

    record = collect(env, rand_signal(IdentificationConfig(), 400, 1e-3, seed=1), seed=2)
    val = validate(record, model, stroke_um=1000.0, unrefined=unstable)
    assert val.metrics["linear_arx_unrefined"] is None
    assert np.isfinite(val.metrics["hammerstein"]["fit_percent"])


def test_refined_pl140_linear_part_fits_fresh_prbs_data_at_least_as_well():
    """On the default PL140 (sensor noise on), the refined linear part's free-run fit on a
    fresh PRBS record (the linear regime: under a two-level input the hysteresis is affine) is
    at least the step b estimate's."""
    import gymnasium as gym

    from identification.experiment import collect
    from identification.steps import excite_prbs, step_seeds
    from piezo_env.signals import make_signal

    env = gym.make("piezo_env:PiezoBender-v0")
    config = IdentificationConfig(prbs_samples=4000, orders=(4, 6))
    seeds = step_seeds(0)
    u, y = excite_prbs(env, config, seeds)
    est = estimate_arx(u, y, config, dt=1e-3)
    refinement = refine_linear_part(est, u, y)
    fresh = make_signal(
        "prbs", 3000, dt=1e-3, rng=np.random.default_rng(11), amplitude=config.prbs_amplitude
    )
    u_val, y_val = collect(env, fresh, seed=12)
    before = fit_percent(y_val, est.model.simulate(u_val))
    after = fit_percent(y_val, refinement.model.simulate(u_val))
    assert after >= before
    assert refinement.model.is_stable() and refinement.model.is_minimum_phase()
