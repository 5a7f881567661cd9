"""The learned gain (controllers/gain.py): the estimate against the batch Bayesian formula, its
credible set's coverage, and the MPC that uses it on the corners of the datasheet box."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import controllers as ctl
from benchmarks.studies.corners import VERTICES, vertex_env
from controllers.gain import CREDIBLE_Z, GainEstimate
from controllers.loop import closed_loop_matrix, output_feedback
from controllers.mpc import MPCSettings

FIRST_ORDER = (np.array([[0.9]]), np.array([[1.0]]), np.array([[1.0]]))
"""A first-order lag, DC gain 10 um per equivalent V: a simple linear part."""


def _drive(estimate: GainEstimate, gain: float, noise: float, n: int, seed: int) -> list:
    """Feed ``estimate`` a plant ``gain`` times the model under uniform noise; the sets."""
    rng = np.random.default_rng(seed)
    a, b, c = FIRST_ORDER
    x, sets = np.zeros(1), []
    for t in range(n):
        z = 5.0 * np.sin(2 * np.pi * t / 50.0) + rng.uniform(-1.0, 1.0)
        estimate.update(gain * float(c[0] @ x) + rng.uniform(-noise, noise))
        sets.append((float(estimate.low[0]), float(estimate.high[0])))
        estimate.advance(z)
        x = a @ x + b[:, 0] * z
    return sets


def test_the_estimate_is_the_batch_bayesian_posterior_mean():
    """With the residuals below the noise floor the variance is the floor, and the recursion is
    the closed-form posterior of a Gaussian prior N(1, w^2 / 3): a ridge regression."""
    a, b, c = FIRST_ORDER
    w, noise = 0.2, 5.0
    estimate = GainEstimate(a, b, c, tolerance=w, noise_std=noise)
    rng = np.random.default_rng(0)
    z = rng.uniform(-1.0, 1.0, 300)
    s = np.zeros(z.size)
    for t in range(1, z.size):
        s[t] = a[0, 0] * s[t - 1] + z[t - 1]
    y = 1.1 * s
    for t in range(z.size):
        estimate.update(float(y[t]))
        estimate.advance(float(z[t]))
    # argmin (g - 1)^2 3 / w^2 + sum (y - g s)^2 / noise^2, by least squares on stacked rows
    rows = np.r_[s / noise, np.sqrt(3.0) / w]
    targets = np.r_[y / noise, np.sqrt(3.0) / w]
    expected = np.linalg.lstsq(rows[:, None], targets, rcond=None)[0][0]
    assert estimate.mean[0] == pytest.approx(expected, rel=1e-12)
    assert estimate.std[0] == pytest.approx(1.0 / np.linalg.norm(rows), rel=1e-12)


@pytest.mark.parametrize("gain", [0.8, 0.93, 1.0, 1.2])
@pytest.mark.parametrize("seed", range(5))
def test_the_credible_set_holds_the_plants_gain_and_shrinks(gain, seed):
    estimate = GainEstimate(*FIRST_ORDER, tolerance=0.2, noise_std=0.5 / np.sqrt(3.0))
    sets = _drive(estimate, gain, noise=0.5, n=400, seed=seed)
    low, high = sets[-1]
    assert low <= gain <= high
    assert high - low < 0.1 * 0.4  # from the datasheet's width 0.4 to under a tenth of it
    widths = [h - lo for lo, h in sets]
    assert widths[0] > 0.3 and max(widths[200:]) < widths[10]
    assert low <= estimate.value[0] <= high


def test_the_nominal_model_stands_while_the_data_allow_it():
    """A plant equal to the model: the controller's gain stays exactly 1 (the point of the set
    nearest the model's) on nearly every sample (a 95 % set misses 1 now and then)."""
    estimate = GainEstimate(*FIRST_ORDER, tolerance=0.2, noise_std=0.5 / np.sqrt(3.0))
    values = []
    rng = np.random.default_rng(3)
    a, b, c = FIRST_ORDER
    x = np.zeros(1)
    for t in range(500):
        z = 5.0 * np.sin(2 * np.pi * t / 50.0)
        values.append(estimate.update(float(c[0] @ x) + rng.uniform(-0.5, 0.5))[0])
        estimate.advance(z)
        x = a @ x + b[:, 0] * z
    values = np.array(values)
    assert np.mean(values == 1.0) > 0.9
    assert np.max(np.abs(values - 1.0)) < 0.01


def test_a_bad_tolerance_or_noise_is_refused():
    with pytest.raises(ValueError, match="tolerance"):
        GainEstimate(*FIRST_ORDER, tolerance=1.0, noise_std=1.0)
    with pytest.raises(ValueError, match="noise_std"):
        GainEstimate(*FIRST_ORDER, tolerance=0.2, noise_std=0.0)
    with pytest.raises(ValueError, match="gain_tolerance"):
        MPCSettings(gain_tolerance=1.5)


@pytest.mark.parametrize("vertex", VERTICES)
def test_the_loop_with_the_learned_gain_is_stable_on_every_vertex(vertex):
    """The argument behind the learned gain: the unconstrained MPC with its observer (the
    bank's prior filter), built on the nominal bender's model, closes a stable loop around
    every vertex of the box once it predicts with that vertex's gain; with the nominal gain it
    does not around the softer, slower benders (a spectral radius above 1)."""
    nominal = gym.make("piezo_env:PiezoBender-v0", preview=20)
    controller = ctl.make("mpc", ctl.PredictionModel.from_plant(nominal.unwrapped.model), nominal)
    bank = controller.observer
    law = controller.feedback_law()
    loop = output_feedback(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains[bank.prior], *law)
    a, b, c, _ = vertex_env(vertex).unwrapped.model.state_space_matrices()
    radius = np.max(np.abs(np.linalg.eigvals(closed_loop_matrix(loop, a, b / vertex[0], c))))
    assert radius < 1.0


def test_credible_z_is_the_normal_quantile():
    import scipy.stats

    assert CREDIBLE_Z == pytest.approx(scipy.stats.norm.ppf(0.975), rel=1e-12)


@pytest.mark.parametrize("tolerance, limit", [(0.0, None), (None, 0.5)])
def test_the_mpc_learns_a_softer_benders_gain(tolerance, limit):
    """The nominal bender's own model on a bender 20 % softer and 20 % slower (damping 0.04):
    with the nominal gain the MPC leaves a tracking error of several % of the stroke at 10 Hz;
    learning the gain takes it under half a per cent, and the credible set holds 1.2."""
    from benchmarks.references import make_reference

    nominal = gym.make("piezo_env:PiezoBender-v0", preview=20, max_episode_steps=2000)
    options = {} if tolerance is None else {"gain_tolerance": tolerance}
    controller = ctl.make(
        "mpc", ctl.PredictionModel.from_plant(nominal.unwrapped.model), nominal, **options
    )
    env = vertex_env((1.2, 0.8, 0.04))
    reference = make_reference("sine-10Hz", 2001, dt=1e-3, seed=0)
    episode = ctl.run_episode(env, controller, seed=0, reference=reference)
    if limit is None:
        assert episode.metrics["rmse_percent"] > 2.0
        assert controller.gain == 1.0
    else:
        assert episode.metrics["rmse_percent"] < limit
        low, high = controller.gain_set
        assert low <= 1.2 <= high + 1e-12
        assert high - low < 0.05


def test_side_by_side_estimates_are_each_ones_own():
    """K linear parts run at once give, bitwise, what each gives alone; the misfit is the mean
    squared residual at the posterior mean, recomputed here from the stored data."""
    rng = np.random.default_rng(5)
    parts = [(np.array([[p]]), np.array([[1.0]]), np.array([[1.0]])) for p in (0.5, 0.9, 0.95)]
    together = GainEstimate(
        np.array([a for a, _, _ in parts]),
        np.array([b[:, 0] for _, b, _ in parts]),
        np.array([c[0] for _, _, c in parts]),
        tolerance=0.2,
        noise_std=0.3,
    )
    alone = [GainEstimate(*part, tolerance=0.2, noise_std=0.3) for part in parts]
    ys, ss = [], []
    x = np.zeros(1)
    for _ in range(200):
        y = float(x[0]) * 1.1 + rng.uniform(-0.5, 0.5)
        ss.append([float(e._c[0] @ e._x[0]) for e in alone])
        ys.append(y)
        together.update(y)
        for estimate in alone:
            estimate.update(y)
        z = rng.uniform(-1.0, 1.0)
        together.advance(z)
        for estimate in alone:
            estimate.advance(z)
        x = 0.9 * x + z
    for k, estimate in enumerate(alone):
        assert together.mean[k] == estimate.mean[0]
        assert together.value[k] == estimate.value[0]
        residual = np.array(ys) - estimate.mean[0] * np.array(ss)[:, k]
        assert together.misfit[k] == pytest.approx(np.mean(residual**2), rel=1e-9)
