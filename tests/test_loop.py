"""The MPC and its observer as one linear controller, held to the controller itself and to
python-control: the same moves, the same closed-loop poles, the same modulus margins."""

from __future__ import annotations

import control
import numpy as np
import pytest
from handmade import synthetic_model

from controllers import ControlTask
from controllers.loop import (
    OutputFeedback,
    closed_loop_matrix,
    modulus_margins,
    output_feedback,
)
from controllers.mpc import LinearMPC, MPCSettings
from controllers.observer import ObserverBank

TASK = ControlTask(dt=1e-3, u_max=30.0, stroke_um=100.0, preview=10, noise_bound_um=1.0)


def _observation(y: float) -> np.ndarray:
    """[y_t, r_t, r_t+1 .. r_t+P] with every target 0: only the feedback acts."""
    return np.r_[y, np.zeros(TASK.preview + 1)]


def _controller_ss(feedback: OutputFeedback) -> control.StateSpace:
    return control.ss(feedback.a, feedback.b[:, None], feedback.c[None, :], feedback.d, TASK.dt)


@pytest.mark.parametrize("slope_std", [0.0, 0.05])
def test_the_unconstrained_mpc_is_the_output_feedback_controller(slope_std) -> None:
    """The moves the real controller applies to a measured sequence, against the state-space
    controller of its law and observer run from the same state."""
    settings = MPCSettings(
        observer="fixed",
        process_std=0.3,
        disturbance_std=0.5,
        slope_std=slope_std,
        gain_tolerance=0.0,  # a learned gain makes the law time-varying
    )
    mpc = LinearMPC(synthetic_model(), TASK, settings)
    mpc.reset(_observation(0.0))
    observer = mpc.observer
    k_e, k_z = mpc.feedback_law()
    feedback = output_feedback(
        observer.a_aug, observer.b_aug, observer.c_aug, observer.gain, k_e, k_z
    )
    state = np.r_[observer.estimate, mpc._z_prev]
    rng = np.random.default_rng(3)
    moves, expected = [], []
    for y in rng.normal(0.0, 2.0, 300):
        mpc.act(_observation(y))
        moves.append(mpc._z_prev)
        expected.append(feedback.c @ state + feedback.d * y)
        state = feedback.a @ state + feedback.b * y
    assert mpc.stats.status["unconstrained"] == 300  # the law holds only off the bounds
    np.testing.assert_allclose(moves, expected, rtol=1e-9, atol=1e-9)


def test_closed_loop_poles_are_python_controls() -> None:
    model = synthetic_model()
    mpc = LinearMPC(model, TASK, MPCSettings(observer="fixed"))
    observer = mpc.observer
    feedback = output_feedback(
        observer.a_aug, observer.b_aug, observer.c_aug, observer.gain, *mpc.feedback_law()
    )
    plant = control.ss(model.a, model.b, model.c, 0.0, TASK.dt)
    reference = control.feedback(plant, _controller_ss(feedback), sign=+1).poles()
    ours = np.linalg.eigvals(closed_loop_matrix(feedback, model.a, model.b, model.c))
    np.testing.assert_allclose(np.sort_complex(ours), np.sort_complex(reference), atol=1e-8)


def test_modulus_margins_are_python_controls_stability_margin() -> None:
    """The bank's batched margins (Sherman-Morrison over one resolvent per frequency) against
    python-control's stability margin of each filter's loop, built as a state-space series."""
    model = synthetic_model()
    mpc = LinearMPC(model, TASK, MPCSettings(observer="fixed"))
    k_e, k_z = mpc.feedback_law()
    bank = ObserverBank(model.a, model.b, model.c, measurement_std=0.5)
    margins = modulus_margins(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, k_e, k_z, n=bank.n)
    plant = control.ss(model.a, model.b, model.c, 0.0, TASK.dt)
    assert margins.max() > 0.9 and margins.min() < 0.6  # the grid spans slow and fast loops
    for k in range(len(margins)):
        feedback = output_feedback(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains[k], k_e, k_z)
        loop = -control.series(_controller_ss(feedback), plant)  # negative-feedback convention
        reference = control.stability_margins(loop)[2]
        assert margins[k] == pytest.approx(reference, rel=2e-3)


def test_the_mpcs_report_their_loop_margin_around_their_model() -> None:
    model = synthetic_model()
    fixed = LinearMPC(model, TASK, MPCSettings(observer="fixed")).describe()["observer"]
    bank = LinearMPC(model, TASK, MPCSettings()).describe()["observer"]
    low, high = bank["modulus_margin_range"]
    assert 0 < low <= bank["modulus_margin_prior"] <= high <= 1
    assert 0 < fixed["modulus_margin"] <= 1
