"""Step-response figures of the report held to closed-form responses.

A first-order response y_k = 1 - a^k and a sampled second-order underdamped response
y(t) = 1 - exp(-zeta wn t) (cos(wd t) + zeta / sqrt(1 - zeta^2) sin(wd t)) have rise times,
overshoots and settling times known in closed form (or as a root of the closed form); the
sampled figures are those times rounded up to the next sample. python-control's ``step_info``
is a second, independent reading of the same arrays.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.optimize

from controllers.metrics import step_metrics

DT = 1e-3
STROKE_UM = 1000.0


def _first_order(a: float, n: int) -> np.ndarray:
    return 1.0 - a ** np.arange(n)


def _second_order(zeta: float, peak_s: float, t: np.ndarray) -> np.ndarray:
    wd = math.pi / peak_s  # the first peak sits at pi / wd
    sigma = zeta * wd / math.sqrt(1.0 - zeta**2)  # zeta wn
    return 1.0 - np.exp(-sigma * t) * (np.cos(wd * t) + sigma / wd * np.sin(wd * t))


def _levels(levels: list[float], hold: int, unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A staircase reference and the response made of one ``unit`` step response per level."""
    reference, deflection = [np.full(hold, levels[0])], [np.full(hold, levels[0])]
    for before, after in itertools.pairwise(levels):
        reference.append(np.full(hold, after))
        deflection.append(before + (after - before) * unit[:hold])
    return np.concatenate(reference), np.concatenate(deflection)


def _ceil_ms(t_s: float) -> float:
    """The first sample at or after ``t_s``, in ms."""
    return math.ceil(t_s / DT - 1e-9) * DT * 1e3


def test_first_order_steps_up_and_down_have_the_closed_form_figures():
    a, hold = 0.95, 400  # tau = -dt / ln a = 19.5 ms
    reference, deflection = _levels([0.0, 400.0, -200.0, 300.0], hold, _first_order(a, hold))
    figures = step_metrics(deflection, reference, DT, STROKE_UM)
    # 1 - a^k >= s  <=>  k >= ln(1 - s) / ln a
    k10, k90 = math.ceil(math.log(0.9) / math.log(a)), math.ceil(math.log(0.1) / math.log(a))
    settle = math.ceil(math.log(0.02) / math.log(a))  # a^k <= 2 % from this sample on
    assert figures["steps_settled"] == "3 of 3"
    assert figures["rise_time_ms"] == pytest.approx((k90 - k10) * DT * 1e3)  # 42 ms
    assert figures["overshoot_percent"] == 0.0
    assert figures["settling_time_ms"] == pytest.approx(settle * DT * 1e3)  # 77 ms
    tau_ms = -DT / math.log(a) * 1e3  # the continuous first order: rise tau ln 9
    assert figures["rise_time_ms"] == pytest.approx(tau_ms * math.log(9.0), abs=1.0)


def test_second_order_step_has_the_closed_form_overshoot_rise_and_settling():
    zeta, peak_s, hold = 0.5, 0.020, 500
    t = np.arange(hold) * DT
    unit = _second_order(zeta, peak_s, t)
    reference, deflection = _levels([-300.0, 500.0], hold, unit)
    figures = step_metrics(deflection, reference, DT, STROKE_UM)

    def response(time: float) -> float:
        return float(_second_order(zeta, peak_s, np.array([time]))[0])

    t10 = scipy.optimize.brentq(lambda x: response(x) - 0.1, 0.0, peak_s)
    t90 = scipy.optimize.brentq(lambda x: response(x) - 0.9, 0.0, peak_s)
    # The last time |y - 1| crosses 2 %: the last sign change on a fine grid, then its root.
    fine = np.linspace(0.0, hold * DT * 0.75, 200_001)
    outside = np.abs(_second_order(zeta, peak_s, fine) - 1.0) - 0.02
    last = np.flatnonzero(np.diff(np.sign(outside)))[-1]
    t_settle = scipy.optimize.brentq(
        lambda x: abs(response(x) - 1.0) - 0.02, fine[last], fine[last + 1]
    )
    overshoot = 100.0 * math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta**2))  # 16.3 %
    assert figures["steps_settled"] == "1 of 1"
    assert figures["overshoot_percent"] == pytest.approx(overshoot, rel=1e-9)  # peak sampled
    assert figures["rise_time_ms"] == pytest.approx(_ceil_ms(t90) - _ceil_ms(t10))
    assert figures["settling_time_ms"] == pytest.approx(_ceil_ms(t_settle))


def test_python_control_step_info_reads_the_same_second_order_response():
    import control

    zeta, peak_s, n = 0.3, 0.015, 400
    t = np.arange(n) * DT
    unit = _second_order(zeta, peak_s, t)
    reference, deflection = _levels([0.0, 250.0], n, unit)
    ours = step_metrics(deflection, reference, DT, STROKE_UM)
    # step_info reads the whole array; ours reads the first 3/4 of the hold: settled by then.
    info = control.step_info(unit[: 3 * n // 4], T=t[: 3 * n // 4], yfinal=1.0)
    assert ours["overshoot_percent"] == pytest.approx(info["Overshoot"], rel=1e-9)
    assert ours["rise_time_ms"] == pytest.approx(1e3 * info["RiseTime"], abs=1e-9)
    assert ours["settling_time_ms"] == pytest.approx(1e3 * info["SettlingTime"], abs=1.0 + 1e-9)


def test_a_hold_too_short_to_settle_is_counted_but_not_timed():
    a, hold = 0.99, 100  # tau ~ 100 ms: 3/4 of a 100 ms hold ends far outside the 2 % band
    reference, deflection = _levels([0.0, 400.0, 0.0], hold, _first_order(a, hold))
    figures = step_metrics(deflection, reference, DT, STROKE_UM)
    assert figures["steps_settled"] == "0 of 2"
    assert figures["settling_time_ms"] is None
    assert figures["rise_time_ms"] is None  # 90 % is reached after 229 ms, not within 75 ms
