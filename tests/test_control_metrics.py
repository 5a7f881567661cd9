"""Closed-loop metrics: step-response figures checked against python-control."""

import numpy as np
import pytest

from controllers.metrics import step_metrics


@pytest.mark.parametrize(
    ("num", "den"),
    [([0.2], [1.0, -0.8]), ([0.0, 0.3, 0.1], [1.0, -1.2, 0.6])],  # first order; 2nd, ~15 % over
    ids=["first-order", "second-order"],
)
def test_step_metrics_agree_with_python_control_step_info(num, den):
    import control

    dt, n = 1e-3, 300
    system = control.tf(num, den, dt)
    gain = float(np.real(system(1.0)))
    response = control.step_response(system / gain, T=np.arange(n) * dt).outputs
    lead = 5
    # Two levels, 0 -> 400 um: the reference jumps at sample `lead`.
    reference = np.r_[np.zeros(lead), np.full(n, 400.0)]
    deflection = np.r_[np.zeros(lead), 400.0 * response]
    ours = step_metrics(deflection, reference, dt, stroke_um=1000.0)
    info = control.step_info(system / gain, T=np.arange(n) * dt)
    assert ours["steps_settled"] == "1 of 1"
    assert ours["rise_time_ms"] == pytest.approx(1e3 * info["RiseTime"], abs=1.01)  # 1 sample
    assert ours["settling_time_ms"] == pytest.approx(1e3 * info["SettlingTime"], abs=1.01)
    assert ours["overshoot_percent"] == pytest.approx(info["Overshoot"], abs=0.05)


def test_a_fast_sine_is_not_a_step():
    t = np.arange(2000) * 1e-3
    reference = 500.0 * np.sin(2 * np.pi * 100 * t)  # 314 um per sample, but never level
    figures = step_metrics(reference, reference, 1e-3, stroke_um=1000.0)
    assert figures["steps_settled"] is None and figures["rise_time_ms"] is None
