"""The compiled estimator kernels against the numpy code they replace
(:mod:`controllers.native.step_kernels`): step by step on random data, and over closed-loop
episodes of the MPCs."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import controllers
import controllers.drive as drive_module
import controllers.gain as gain_module
import controllers.observer as observer_module
from benchmarks.references import make_reference
from controllers.gain import GainEstimate
from controllers.native.codegen import NUMPY, NativeBuild
from controllers.native.step_kernels import kernels
from controllers.observer import ObserverBank

MODEL_DIR = "docs/identify/model"

pytestmark = pytest.mark.skipif(
    kernels()[0] is None, reason="no compiled kernels on this machine (recorded in reports)"
)


def numpy_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Objects built from now on run their numpy code."""

    def switched_off(states):
        return None, NativeBuild("step_kernels", NUMPY, "switched off by the test")

    monkeypatch.setattr(gain_module, "kernels_for", switched_off)
    monkeypatch.setattr(drive_module, "kernels_for", switched_off)
    monkeypatch.setattr(observer_module, "kernels_for", switched_off)


def random_parts(rng: np.random.Generator, k: int, n: int):
    a = rng.normal(0.0, 0.3, (k, n, n)) / np.sqrt(n)
    return a, rng.normal(0.0, 1.0, (k, n)), rng.normal(0.0, 1.0, (k, n))


def test_gain_estimate_kernels_equal_numpy(monkeypatch):
    rng = np.random.default_rng(5)
    a, b, c = random_parts(rng, 7, 6)
    compiled = GainEstimate(a, b, c, tolerance=0.2, noise_std=0.5)
    numpy_only(monkeypatch)
    reference = GainEstimate(a, b, c, tolerance=0.2, noise_std=0.5)
    assert compiled._update_native is not None and reference._update_native is None
    x0 = rng.normal(0.0, 1.0, (7, 6))
    compiled.reset(x0)
    reference.reset(x0)
    for _ in range(300):
        y, z = rng.normal(0.0, 5.0), rng.normal(0.0, 3.0)
        np.testing.assert_allclose(compiled.update(y), reference.update(y), rtol=1e-13)
        compiled.advance(z)
        reference.advance(z)
        # The dot products may be summed in another order: last-bit differences only.
        np.testing.assert_allclose(compiled._state, reference._state, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(compiled._x, reference._x, rtol=1e-12, atol=1e-12)
    assert compiled.count == reference.count == 300


def test_observer_bank_kernels_equal_numpy_guard_included(monkeypatch):
    """The model's own data with a slow offset (the selection moves among the filters), part
    of the bank disallowed midway, then an alternating output the model cannot follow: the
    likelihoods, the selection and the runaway guard's fall-back all agree."""
    a = np.array([[1.6, -0.8], [1.0, 0.0]])
    b, c = np.array([[1.0], [0.0]]), np.array([[0.1, 0.05]])
    compiled = ObserverBank(a, b, c, measurement_std=0.5)
    numpy_only(monkeypatch)
    reference = ObserverBank(a, b, c, measurement_std=0.5)
    assert compiled._correct_native is not None and reference._correct_native is None
    mask = np.ones(len(compiled.noise_levels), dtype=bool)
    mask[1::3] = False
    rng = np.random.default_rng(2)
    x, y, selected = np.zeros(2), 0.0, set()
    for t in range(1500):
        if t == 400:
            compiled.allow(mask)
            reference.allow(mask)
        z = rng.normal(0.0, 1.0)
        if t < 700:
            y = c[0] @ x + 2.0 * np.sin(0.02 * t) + rng.normal(0.0, 0.5)
        else:  # alternating in sign: a runaway for the guard
            y = -0.9 * y + 3.0 * np.sin(2.9 * t) + rng.normal(0.0, 0.5)
        np.testing.assert_allclose(
            compiled.correct(y), reference.correct(y), rtol=1e-12, atol=1e-12
        )
        assert compiled.selected == reference.selected
        selected.add(compiled.selected)
        compiled.predict(z)
        reference.predict(z)
        x = a @ x + b[:, 0] * z
    np.testing.assert_allclose(compiled._state, reference._state, rtol=1e-11, atol=1e-12)
    np.testing.assert_array_equal(compiled.selection_counts, reference.selection_counts)
    assert len(selected) > 3  # the selection moved
    assert compiled.runaway_at == reference.runaway_at and compiled.runaway_at > 700


@pytest.mark.parametrize("name", ["mpc", "mpc-adaptive"])
def test_closed_loop_episodes_with_the_kernels_equal_numpy(monkeypatch, name):
    """The same voltages (float32) over whole episodes, smooth and jumping references: measured
    bitwise equal on x86-64 (gcc 12); allowed two float32 steps at 30 V, should a last-bit
    difference of a dot product round one voltage the other way."""
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    compiled = controllers.make(name, MODEL_DIR, env)
    numpy_only(monkeypatch)
    reference = controllers.make(name, MODEL_DIR, env)
    assert compiled.observer._correct_native is not None
    assert reference.observer._correct_native is None
    assert compiled.describe()["native"]["step_kernels"]["compiled"]
    for signal in ("sine-50Hz", "random-steps"):
        ref = make_reference(signal, 821, dt=1e-3, seed=1)
        got = controllers.run_episode(env, compiled, seed=3, reference=ref, max_steps=800)
        expected = controllers.run_episode(env, reference, seed=3, reference=ref, max_steps=800)
        np.testing.assert_allclose(got.voltage_V, expected.voltage_V, rtol=0, atol=4e-6)


def test_estimators_beyond_the_kernels_size_say_numpy_runs_them():
    from controllers.native.step_kernels import MAX_STATES

    n = MAX_STATES + 1
    estimate = GainEstimate(np.eye(n) * 0.5, np.ones(n), np.ones(n), tolerance=0.2, noise_std=1.0)
    assert estimate._update_native is None
    assert estimate.native[0].path == NUMPY and "more than" in estimate.native[0].reason


def test_gain_kernel_propagates_nan_as_numpy(monkeypatch):
    """A NaN measurement makes every derived quantity NaN in both paths (numpy's maximum and
    minimum propagate NaN; a C comparison would not)."""
    a, b, c = np.array([[0.5]]), np.array([1.0]), np.array([1.0])
    compiled = GainEstimate(a, b, c, tolerance=0.2, noise_std=0.5)
    numpy_only(monkeypatch)
    reference = GainEstimate(a, b, c, tolerance=0.2, noise_std=0.5)
    for estimate in (compiled, reference):
        estimate.advance(1.0)
        estimate.update(float("nan"))
    np.testing.assert_array_equal(compiled._state, reference._state)  # NaN == NaN here
    assert np.isnan(compiled.value).all()


def test_the_exact_set_of_a_vanishing_model_output_stays_a_number(monkeypatch):
    """A model output so small (subnormal) that a constraint's ends overflow to infinity: the
    infinite end is not widened (inf - inf would be NaN), so the set stays an interval, and
    both paths agree; a sample the bound cannot explain with s = 0 empties it, in both."""
    a, b, c = np.array([[0.0]]), np.array([1.0]), np.array([1.0])
    compiled = GainEstimate(a, b, c, tolerance=0.2, noise_std=0.5)
    numpy_only(monkeypatch)
    reference = GainEstimate(a, b, c, tolerance=0.2, noise_std=0.5)
    for estimate in (compiled, reference):
        estimate.advance(5e-324)  # s = 5e-324 at the next update
        estimate.update(0.3)
        assert np.isfinite(estimate.exact_low).all() and np.isfinite(estimate.exact_high).all()
        assert estimate.emptied_at[0] == 0
        estimate.advance(0.0)  # s = 0
        estimate.update(5.0)  # beyond the bound sqrt(3) 0.5: no gain explains it
        assert estimate.exact_low[0] > estimate.exact_high[0] and estimate.emptied_at[0] == 2
    np.testing.assert_array_equal(compiled._state, reference._state)
