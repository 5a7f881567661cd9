"""The learned drive (:mod:`controllers.drive`): the hysteresis families' strength scaling is
the two-parameter model it assumes, the box holds the plant, the estimate converges, its
compiled kernel and numpy path agree to the bit, and the mixed map's inverse is a root."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import scipy.optimize

import controllers
from benchmarks.references import make_reference
from benchmarks.studies.corners import vertex_env
from controllers.drive import DriveEstimate, slope_range
from controllers.native.compiled_inverse import CompiledInverse, MixedMap
from controllers.native.step_kernels import kernels
from controllers.prediction import PlantHysteresis
from piezo_env.hysteresis import BoucWen, PrandtlIshlinskii
from piezo_env.randomization import scale_hysteresis

MODEL_DIR = "docs/benchmark/model"
U_RANGE = (-30.0, 30.0)


def run_map(nonlinearity, u):
    state, z = nonlinearity.initial_state(), np.empty(u.size)
    for i, v in enumerate(u):
        z[i], state = nonlinearity.step(float(v), state)
    return z


def drive_signal(seed, samples=1500):
    """Sines and noise over the drive range: both branches, minor loops, reversals."""
    rng = np.random.default_rng(seed)
    t = np.arange(samples) * 1e-3
    u = 22.0 * np.sin(2 * np.pi * 7.0 * t) + 6.0 * np.sin(2 * np.pi * 53.0 * t)
    return np.clip(u + rng.uniform(-2.0, 2.0, samples), *U_RANGE)


@pytest.mark.parametrize("family", [BoucWen(), PrandtlIshlinskii()])
@pytest.mark.parametrize("strength", [0.7, 1.3])
def test_a_scaled_strength_is_the_nominal_map_mixed_with_its_input(family, strength):
    """The env's randomisation (piezo_env.randomization.scale_hysteresis, independent code)
    gives exactly ``c (rho N + (1 - rho) w0 u)``: least squares on (N, u) leaves rounding, and
    the coefficients are the module docstring's with the family's linear weight w0."""
    scaled = scale_hysteresis(family, strength, U_RANGE[1])
    u = drive_signal(0)
    nominal = run_map(PlantHysteresis(family, U_RANGE), u)
    other = run_map(PlantHysteresis(scaled, U_RANGE), u)
    theta, *_ = np.linalg.lstsq(np.c_[nominal, u], other, rcond=None)
    residual = other - np.c_[nominal, u] @ theta
    assert np.sqrt(np.mean(residual**2)) < 1e-9 * np.sqrt(np.mean(other**2))
    w0 = family.k if isinstance(family, BoucWen) else family.linear_weight
    c = theta[0] / strength
    assert theta[1] == pytest.approx(c * (1.0 - strength) * w0, rel=1e-9)
    only_gain = other - nominal * (nominal @ other / (nominal @ nominal))
    assert np.sqrt(np.mean(only_gain**2)) > 1e6 * np.sqrt(np.mean(residual**2))


@pytest.mark.parametrize("family", [BoucWen(), PrandtlIshlinskii()])
def test_the_map_slopes_bound_the_linear_weight(family):
    """kappa in [z'_min, 2 z'_max - z'_min] (the module docstring's bound) for both families,
    with the step the controllers measure at."""
    low, high = slope_range(PlantHysteresis(family, U_RANGE), 60.0 / 240)
    w0 = family.k if isinstance(family, BoucWen) else family.linear_weight
    assert low <= w0 * (1 + 1e-9) and w0 <= 2.0 * high - low


def part(seed, n=4):
    """A stable random linear part (a, b, c)."""
    rng = np.random.default_rng(seed)
    a = np.diag(rng.uniform(0.3, 0.95, n)) + 0.05 * rng.standard_normal((n, n))
    assert np.abs(np.linalg.eigvals(a)).max() < 1.0
    return a, rng.standard_normal(n), rng.standard_normal(n)


def estimate(parts, **options):
    a, b, c = (np.array(x) for x in zip(*parts, strict=True))
    settings = {"tolerance": 0.31, "strength": 0.3, "slopes": (1.0, 1.4), "noise_std": 0.5}
    return DriveEstimate(a, b, c, **{**settings, **options})


@pytest.mark.parametrize("seed", range(4))
def test_the_estimate_converges_to_a_drive_in_the_box(seed):
    """Data from part 0 at a drawn (theta_z, theta_u) inside the box, the noise uniform within
    its bound: the posterior mean ends at the truth; the drive predicted with stays inside the
    box and predicts the output to within the noise (the credible ellipse's point nearest the
    nominal drive differs from the truth along the direction the data hardly determine: z and u
    are nearly proportional); part 0 fits best."""
    rng = np.random.default_rng(100 + seed)
    parts = [part(seed), part(seed + 50)]
    drive = estimate(parts)
    rho, g = rng.uniform(0.7, 1.3), rng.uniform(0.69, 1.31)
    truth = (g * rho, g * (1.0 - rho) * 1.2)  # kappa 1.2 within [1.0, 1.8]
    a, b, c = parts[0]
    xz, xu = np.zeros(4), np.zeros(4)
    u = drive_signal(seed, 3000)
    z = 1.2 * u - 6.0 * np.tanh(np.cumsum(np.diff(u, prepend=0.0)) / 10.0)  # a memory map
    errors = []
    for t in range(u.size):
        drive.update(truth[0] * c @ xz + truth[1] * c @ xu + rng.uniform(-0.8, 0.8))
        (z_low, z_high), (r_low, r_high) = drive.theta_z_bounds, drive.ratio_bounds
        value, theta_u = drive.theta_z[0], drive.theta_u[0]
        assert z_low <= value <= z_high and r_low * value - 1e-12 <= theta_u <= r_high * value
        errors.append((value - truth[0]) * c @ xz + (theta_u - truth[1]) * c @ xu)
        drive.advance(z[t], u[t])
        xz, xu = a @ xz + b * z[t], a @ xu + b * u[t]
    np.testing.assert_allclose((drive.mean_z[0], drive.mean_u[0]), truth, atol=0.03)
    assert np.sqrt(np.mean(np.square(errors[u.size // 2 :]))) < 0.8 / np.sqrt(3.0)
    assert drive.misfit[0] < drive.misfit[1]


@pytest.mark.skipif(kernels()[0] is None, reason="no compiled kernels on this machine")
def test_the_compiled_kernel_equals_the_numpy_path_to_the_bit():
    """Both paths over the same data, projections onto the box included (a drive far outside
    it at the start)."""
    parts = [part(s) for s in range(5)]
    compiled, plain = estimate(parts), estimate(parts)
    plain._update_drive = plain._advance_u = None
    rng = np.random.default_rng(3)
    u = drive_signal(1, 400)
    for t in range(u.size):
        y = 40.0 * np.sin(t / 9.0) + rng.uniform(-0.8, 0.8)
        compiled.update(y)
        plain.update(y)
        np.testing.assert_array_equal(compiled._state, plain._state)
        z = 1.5 * u[t] + rng.uniform(-1, 1)
        compiled.advance(z, u[t])
        plain.advance(z, u[t])
        np.testing.assert_array_equal(compiled._xz, plain._xz)
        np.testing.assert_array_equal(compiled._xu, plain._xu)


@pytest.mark.parametrize("seed", range(6))
def test_the_projection_is_the_nearest_point_of_the_box(seed):
    """Against scipy's SLSQP on the same problem (an independent method)."""
    rng = np.random.default_rng(seed)
    drive = estimate([part(0)])
    root = rng.standard_normal((2, 2))
    precision = root @ root.T + 0.1 * np.eye(2)
    point = np.array([rng.uniform(0.2, 2.2), rng.uniform(-1.5, 1.5)])
    (z_low, z_high), (r_low, r_high) = drive.theta_z_bounds, drive.ratio_bounds
    got = np.array(drive._project(*point, precision[0, 0], precision[0, 1], precision[1, 1]))
    constraints = [
        {"type": "ineq", "fun": lambda t: t[0] - z_low},
        {"type": "ineq", "fun": lambda t: z_high - t[0]},
        {"type": "ineq", "fun": lambda t: t[1] - r_low * t[0]},
        {"type": "ineq", "fun": lambda t: r_high * t[0] - t[1]},
    ]
    best = scipy.optimize.minimize(
        lambda t: (t - point) @ precision @ (t - point),
        x0=np.array([1.0, 0.0]),
        constraints=constraints,
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 500},
    )
    distance = (got - point) @ precision @ (got - point)
    assert distance <= best.fun + 1e-9 * (1.0 + best.fun)
    np.testing.assert_allclose(got, best.x, atol=1e-5)


def test_the_mixed_inverse_is_a_root_of_the_mixed_map():
    """Generated C, the numpy fallback and Brent's method on the identified network agree."""
    env = gym.make("piezo_env:PiezoBender-v0")
    nonlinearity = controllers.prediction_model(MODEL_DIR, env).nonlinearity
    inverse = CompiledInverse(MixedMap(nonlinearity.nls), U_RANGE)
    rng = np.random.default_rng(0)
    state = nonlinearity.initial_state()
    for a, b in ((0.65, 0.4), (1.4, -0.47), (1.0, 0.0)):
        inverse.set_parameters((a, b))
        for _ in range(40):
            u0 = rng.uniform(*U_RANGE)
            z0, state = nonlinearity.step(u0, state)
            target = a * z0 + b * u0 + rng.normal(0.0, 3.0)
            result = inverse.solve(target, state)
            numpy_result = MixedMap(nonlinearity.nls, a, b).solve_inverse(target, state, U_RANGE)
            assert result.u == pytest.approx(numpy_result.u, abs=1e-6)
            if result.status != "ok":
                continue
            root = scipy.optimize.brentq(
                lambda u, s=state, a=a, b=b, t=target: a * nonlinearity.step(u, s)[0] + b * u - t,
                *U_RANGE,
            )
            assert result.u == pytest.approx(root, abs=1e-7)


def test_the_adaptive_mpc_learns_the_strength_of_a_bender(benchmark_adaptive_mpc):
    """On the nominal bender with its hysteresis at x0.7, the drive it predicts with ends near
    the least-squares drive of the plant's own map on the identified network's (both run on
    the episode's volts): the strength is learned, not only the gain."""
    controller = benchmark_adaptive_mpc
    plant = vertex_env((1.0, 1.0, 0.02), hysteresis_scale=0.7)
    reference = make_reference("sine-10Hz", 2021, dt=1e-3, seed=0)
    episode = controllers.run_episode(plant, controller, seed=0, reference=reference)
    u = np.asarray(episode.voltage_V, float)
    network = run_map(controller.model.nonlinearity, u)
    own = run_map(PlantHysteresis(plant.unwrapped.model.hysteresis, U_RANGE), u)
    nominal = run_map(PlantHysteresis(BoucWen.for_voltage(30.0), U_RANGE), u)
    scale = nominal @ network / (network @ network)  # the network's units: the nominal map's
    truth, *_ = np.linalg.lstsq(np.c_[network, u], own / scale, rcond=None)
    member = controller._member
    learned = (controller._gain.theta_z[member], controller._gain.theta_u[member])
    assert truth[1] > 0.3  # the weaker loop's input share
    np.testing.assert_allclose(learned, truth, rtol=0.1)


def test_bad_strength_settings_say_what_to_change():
    env = gym.make("piezo_env:PiezoBender-v0")
    with pytest.raises(ValueError, match="strength_tolerance must be < 1"):
        controllers.make("mpc", MODEL_DIR, env, strength_tolerance=1.0)
    with pytest.raises(ValueError, match="gain_tolerance > 0 too"):
        controllers.make("mpc", MODEL_DIR, env, strength_tolerance=0.3, gain_tolerance=0.0)
    with pytest.raises(ValueError, match="identified model's network"):
        controllers.make("mpc", "plant", env, strength_tolerance=0.3)
    with pytest.raises(ValueError, match="not increasing on the box's edge"):
        estimate([part(0)], slopes=(0.2, 2.0))


def test_the_fixed_mpc_learns_the_drive_when_asked_and_runs_compiled():
    """``strength_tolerance`` on the fixed MPC: the drive estimate replaces the gain's, and the
    step stays one compiled call (its record says so)."""
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    controller = controllers.make("mpc", MODEL_DIR, env, strength_tolerance=0.3)
    assert isinstance(controller._gain, DriveEstimate)
    if kernels()[0] is not None:
        assert controller._fused is not None, controller._fused_build
    plain = controllers.make("mpc", MODEL_DIR, env)
    assert controller.describe()["settings"]["strength_tolerance"] == 0.3
    assert plain.describe()["settings"]["strength_tolerance"] == 0.0
