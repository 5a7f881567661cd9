"""The identification pipeline (paper section 3.4) end to end on the environment."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from identification.arx import ARXModel
from identification.metrics import fit_percent
from identification.pipeline import IdentificationConfig, identify, inverse_arx

# A short run: half the default record lengths and epochs.
SHORT = {
    "prbs_samples": 4000,
    "rich_samples": 6000,
    "validation_samples": 3000,
    "max_epochs": 100,
}


@pytest.fixture(scope="module")
def short_default_run():
    return identify(config=IdentificationConfig(seed=0, features="auto", **SHORT))


def test_short_default_run_fits_held_out_rand_and_beats_linear_arx(short_default_run):
    val = short_default_run.report["validation"]
    # The full default run reaches ~99 % (benchmarks/results/identification.md).
    assert val["hammerstein"]["fit_percent"] > 95.0
    assert val["hammerstein"]["rmse"] < val["linear_arx"]["rmse"] / 3
    assert short_default_run.report["arx"]["minimum_phase"]


def test_nls_has_unit_small_signal_gain(short_default_run):
    """Under the two-level PRBS the NLS is affine with slope 1 (z in equivalent volts)."""
    data = short_default_run.data
    z = short_default_run.model.nls_output(data["u_prbs"])
    slope = np.polyfit(data["u_prbs"], z, 1)[0]
    assert slope == pytest.approx(1.0, abs=0.03)
    assert short_default_run.report["nls"]["small_signal_gain"] == pytest.approx(slope)


def test_report_is_complete_and_consistent(short_default_run):
    report = short_default_run.report
    assert set(report) >= {"arx", "nls", "validation", "timings_s", "environment", "inversion"}
    arx = short_default_run.model.arx
    assert report["arx"]["order"] == arx.na == arx.nb
    assert report["nls"]["features"] in report["nls"]["selection_fit_percent"]
    chosen = report["nls"]["features"]
    assert report["nls"]["selection_fit_percent"][chosen] == max(
        report["nls"]["selection_fit_percent"].values()
    )


def test_without_hysteresis_the_nls_is_the_identity_and_the_model_is_the_arx():
    result = identify(
        config=IdentificationConfig(
            seed=1, features="play", env_kwargs={"hysteresis": None}, **SHORT
        )
    )
    model = result.model
    u = np.random.default_rng(5).uniform(-30, 30, 2000)
    z = model.nls_output(u)
    assert np.max(np.abs(z - u)) < 0.02 * 30
    assert fit_percent(model.arx.simulate(u), model.simulate(u)) > 99.0


def test_same_seed_same_model():
    config = IdentificationConfig(seed=3, features="play", **{**SHORT, "max_epochs": 10})
    a = identify(config=config).model
    b = identify(config=config).model
    u = np.random.default_rng(0).uniform(-30, 30, 500)
    assert np.array_equal(a.simulate(u), b.simulate(u))
    assert np.array_equal(a.arx.theta, b.arx.theta)


def test_inverse_arx_recovers_the_input_of_a_minimum_phase_model():
    arx = ARXModel([1.5, -0.7], [0.5, 0.3], dt=1e-3)  # zero at -0.6
    z = np.random.default_rng(2).uniform(-1, 1, 1000)
    y = arx.simulate(z)
    z_hat, method = inverse_arx(arx, y)
    assert method == "eq25"
    np.testing.assert_allclose(z_hat[:-1], z[:-1], atol=1e-9)


def test_inverse_arx_falls_back_to_deconvolution_for_a_non_minimum_phase_model():
    arx = ARXModel([1.5, -0.7], [0.3, 0.5], dt=1e-3)  # zero at -1.67: eq. 25 would diverge
    assert not arx.is_minimum_phase()
    z = scipy.signal.lfilter([1.0], [1.0, -0.9], np.random.default_rng(3).uniform(-1, 1, 1000))
    y = arx.simulate(z)
    z_hat, method = inverse_arx(arx, y, regularization=1e-8)
    assert method == "regularized-deconvolution"
    assert np.all(np.isfinite(z_hat))
    assert fit_percent(z[:-50], z_hat[:-50]) > 95.0


def test_bad_configuration_is_rejected():
    with pytest.raises(ValueError, match="features"):
        IdentificationConfig(features="spline")
    with pytest.raises(ValueError, match="reference"):
        IdentificationConfig(env_kwargs={"reference": "sine"})
    with pytest.raises(ValueError, match="prbs_samples"):
        IdentificationConfig(prbs_samples=10)
    with pytest.raises(ValueError, match="prbs_amplitude"):
        IdentificationConfig(prbs_amplitude=-1.0)
    with pytest.raises(ValueError, match="hidden"):
        IdentificationConfig(hidden=())
    with pytest.raises(ValueError, match="unknown signal"):
        IdentificationConfig(rich_signal="nope")
    with pytest.raises(ValueError, match="does not accept"):
        IdentificationConfig(rich_signal="multisine", rich_params={"frequency": 5.0})
    assert IdentificationConfig(rich_signal="multisine").rich_signal_params()["n_tones"] == 10
