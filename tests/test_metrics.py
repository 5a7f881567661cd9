"""Fit metrics: closed-form values and input validation."""

import math

import numpy as np
import pytest

from identification.metrics import fit_metrics, fit_percent, max_abs_error, rmse


def test_perfect_and_mean_models():
    y = np.array([1.0, -2.0, 3.0, 0.5])
    assert fit_percent(y, y) == 100.0
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0, abs=1e-12)
    assert fit_percent(y, -y + 2 * y.mean()) == pytest.approx(-100.0)


def test_closed_form_values():
    y = np.array([0.0, 2.0, 4.0])  # mean 2, ||y - mean|| = sqrt(8)
    y_hat = np.array([1.0, 2.0, 3.0])  # ||error|| = sqrt(2)
    assert fit_percent(y, y_hat) == pytest.approx(50.0)
    assert rmse(y, y_hat) == pytest.approx(math.sqrt(2.0 / 3.0))
    assert max_abs_error(y, y_hat) == pytest.approx(1.0)


def test_fit_metrics_with_stroke():
    y = np.array([0.0, 2.0, 4.0])
    y_hat = np.array([1.0, 2.0, 3.0])
    m = fit_metrics(y, y_hat, stroke=1000.0)  # one-sided: the full stroke is 2000
    assert m["fit_percent"] == pytest.approx(50.0)
    assert m["full_stroke"] == 2000.0
    assert m["rmse_percent_stroke"] == pytest.approx(100 * math.sqrt(2 / 3) / 2000)
    assert m["max_abs_error_percent_stroke"] == pytest.approx(0.05)
    assert m["n_samples"] == 3
    assert "rmse_percent_stroke" not in fit_metrics(y, y_hat)


@pytest.mark.parametrize(
    ("y", "y_hat", "match"),
    [
        ([1.0, 2.0], [1.0, 2.0, 3.0], "same length"),
        ([1.0, np.nan], [1.0, 2.0], "non-finite"),
        ([1.0, 2.0], [1.0, np.inf], "y_hat contains"),
        ([], [], "empty"),
        ([[1.0, 2.0], [3.0, 4.0]], [[1.0, 2.0], [3.0, 4.0]], "1-D"),
    ],
)
def test_bad_input_raises(y, y_hat, match):
    with pytest.raises(ValueError, match=match):
        fit_metrics(y, y_hat)


def test_constant_output_and_bad_stroke():
    with pytest.raises(ValueError, match="constant"):
        fit_percent([1.0, 1.0], [1.0, 2.0])
    assert rmse([1.0, 1.0], [1.0, 2.0]) == pytest.approx(math.sqrt(0.5))
    with pytest.raises(ValueError, match="stroke"):
        fit_metrics([0.0, 1.0], [0.0, 1.0], stroke=-1.0)


def test_column_vectors_accepted():
    y = np.arange(5.0)[:, None]
    assert fit_percent(y, y.ravel()) == 100.0
