"""Nonlinear MPC held to independent computations: model simulation, derivatives, IPOPT, MPC."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

import controllers
from controllers import ControlTask, PredictionModel
from controllers.native.nmpc_horizon import GenericHorizon, StructuredHorizon
from controllers.nmpc import NMPCSettings, NonlinearMPC

MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "identify" / "model")
TASK = ControlTask(dt=1e-3, u_max=30.0, stroke_um=1000.0, preview=20, noise_bound_um=1.0)
HORIZON = 10


@pytest.fixture(scope="module")
def model() -> PredictionModel:
    return PredictionModel.from_hammerstein(MODEL_DIR, TASK.u_max)


@pytest.fixture(scope="module")
def env():
    environment = gym.make("piezo_env:PiezoBender-v0", preview=20)
    yield environment
    environment.close()


def random_plan(seed: int, n: int = HORIZON) -> np.ndarray:
    """Voltages with no repeated sample (the feature recursion is smooth away from du = 0)."""
    return np.random.default_rng(seed).uniform(-25.0, 25.0, n)


@pytest.mark.parametrize("jacobian", ["structured", "structured-vm", "generic-vm"])
def test_prediction_equals_the_model_simulation(model, jacobian):
    controller = NonlinearMPC(model, TASK, NMPCSettings(horizon=HORIZON, jacobian=jacobian))
    u = random_plan(1)
    predicted = controller.predict_deflection(u)
    # Measured: 3.4e-13 um at most (on deflections of hundreds of um).
    np.testing.assert_allclose(predicted, model.simulate(u), rtol=0, atol=2e-12)


RATE_MODEL_DIR = str(Path(MODEL_DIR).parents[1] / "benchmark" / "model-bench")
"""The committed run's model of the bench plant: rate-dependent plays (radii r_i + c |rate|)."""


@pytest.mark.parametrize("folder", [MODEL_DIR, RATE_MODEL_DIR], ids=["play", "rate-play"])
@pytest.mark.parametrize("jacobian", ["structured", "generic-vm"])
def test_prediction_equals_the_hammerstein_model_simulation(folder, jacobian):
    """Against the identification package's own free run (its y[t] is before u[t]), for the
    rate-independent and the rate-dependent model (whose radii grow with the previous
    sample's rate, carried in the NMPC's memory state)."""
    from identification.hammerstein import HammersteinModel

    hammerstein = HammersteinModel.load(folder)
    if folder == RATE_MODEL_DIR:
        assert hammerstein.nls.feature_map.rate_time > 0
    controller = NonlinearMPC(
        PredictionModel.from_hammerstein(folder, TASK.u_max),
        TASK,
        NMPCSettings(horizon=HORIZON, jacobian=jacobian),
    )
    u = random_plan(3)
    free_run = hammerstein.simulate(np.r_[u, 0.0])[1:]
    predicted = controller.predict_deflection(u)
    # Measured: 2.3e-13 um (play) and 6.8e-13 um (rate-play), on hundreds of um.
    np.testing.assert_allclose(predicted, free_run, rtol=0, atol=2e-12)


def memory_after(model: PredictionModel, voltages: np.ndarray) -> np.ndarray:
    state = model.nonlinearity.initial_state()
    for v in voltages:
        _, state = model.nonlinearity.step(float(v), state)
    return state


def test_structured_jacobian_equals_finite_differences_and_casadi(model):
    state = memory_after(model, 20.0 * np.sin(np.linspace(0.0, 7.0, 40)))
    structured = StructuredHorizon(model.nonlinearity.nls, HORIZON)
    generic = GenericHorizon(model.nonlinearity, HORIZON, compiled=False)
    u = random_plan(2)
    z, jac = structured.linearize(u, state)
    step = 1e-6
    columns = [
        (structured.evaluate(u + step * e, state) - structured.evaluate(u - step * e, state))
        / (2 * step)
        for e in np.eye(HORIZON)
    ]
    # Measured: 2.7e-9 (central differences at 1e-6 V; entries up to 1.3).
    np.testing.assert_allclose(jac, np.array(columns).T, rtol=0, atol=1.5e-8)
    z_generic, jac_generic = generic.linearize(u, state)
    np.testing.assert_allclose(z, z_generic, rtol=0, atol=2e-14)  # measured 3.6e-15
    np.testing.assert_allclose(jac, jac_generic, rtol=0, atol=2e-14)  # measured 4.4e-16
    assert np.all(np.triu(jac, 1) == 0.0)  # causal: z_t+k never depends on later voltages


def test_real_time_iteration_converges_to_the_ipopt_solution(model):
    targets = 300.0 * np.sin(np.linspace(0.1, 1.5, TASK.preview + 1))
    obs = np.r_[0.0, 0.0, targets[: TASK.preview]]
    plans = {}
    for solver, iterations in (("rti", 20), ("ipopt", 1)):
        settings = NMPCSettings(
            horizon=HORIZON, solver=solver, sqp_iterations=iterations, step_tolerance=1e-9
        )
        controller = NonlinearMPC(model, TASK, settings)
        controller.reset(obs)
        controller.act(obs)
        plans[solver] = controller._plan
        assert controller.stats.fallbacks == 0
    np.testing.assert_allclose(plans["rti"], plans["ipopt"], rtol=0, atol=1e-9)  # 1.3e-10 V


def sine(n: int, amplitude: float, frequency: float) -> np.ndarray:
    return amplitude * np.sin(2 * np.pi * frequency * np.arange(1, n + 2) * 1e-3)


def test_matches_linear_mpc_on_an_easy_reference(env):
    reference = sine(300, 300.0, 10.0)
    # Both predict with the model's gain here (each learns it by default), the linear one with
    # the nonlinear one's rate weight.
    options = {"mpc": {"gain_tolerance": 0.0, "rate_weight": 1e-2}, "nmpc": {"gain_tolerance": 0.0}}
    episodes = {
        name: controllers.run_episode(
            env,
            controllers.make(name, MODEL_DIR, env, **options[name]),
            seed=0,
            reference=reference,
            max_steps=300,
        )
        for name in ("mpc", "nmpc")
    }
    mpc, nmpc = episodes["mpc"], episodes["nmpc"]
    # Converged NMPC and linear MPC in z + exact inverse solve nearly the same problem (the
    # rate penalty acts on u in one and on z in the other): the same accuracy, similar volts.
    # Measured: RMSE 0.778 um (0.039 %) for both, 3.5e-5 um apart (up to 4.6e-4 over noise
    # seeds 0-5), voltages at most 0.014 V apart (0.0137-0.0148).
    assert abs(nmpc.metrics["rmse_um"] - mpc.metrics["rmse_um"]) < 2e-3
    assert nmpc.metrics["rmse_um"] < 1.2
    assert np.max(np.abs(nmpc.voltage_V - mpc.voltage_V)) < 0.05


@pytest.mark.parametrize(
    "options",
    [
        {"solver": "rti", "max_qp_iterations": 1, "shortcut": False},
        {"solver": "ipopt", "ipopt_max_iter": 1},
    ],
)
def test_forced_solver_failure_falls_back_and_the_loop_goes_on(model, env, options):
    task = ControlTask.from_env(env)
    controller = NonlinearMPC(model, task, NMPCSettings(horizon=5, **options))
    steps = 15
    episode = controllers.run_episode(
        env, controller, seed=0, reference=sine(steps, 300.0, 10.0), max_steps=steps
    )
    assert episode.voltage_V.size == steps
    assert controller.stats.fallbacks == steps
    assert sum(controller.stats.status.values()) == steps
    assert np.all(np.abs(episode.voltage_V) <= task.u_max)
    assert np.all(np.isfinite(episode.deflection_um))


def test_episode_is_finite_in_range_and_deterministic(env):
    reference = sine(400, 500.0, 50.0)
    controller = controllers.make("nmpc", MODEL_DIR, env)
    first, second = (
        controllers.run_episode(env, controller, seed=3, reference=reference, max_steps=400)
        for _ in range(2)
    )
    assert np.all(np.isfinite(first.deflection_um)) and np.all(np.isfinite(first.voltage_V))
    assert np.all(np.abs(first.voltage_V) <= float(env.action_space.high[0]))
    np.testing.assert_array_equal(first.voltage_V, second.voltage_V)
    np.testing.assert_array_equal(first.deflection_um, second.deflection_um)
    assert first.metrics["fallbacks"] == 0
    assert first.controller["jacobian"].startswith("StructuredHorizon")
    assert len(first.compute_s) == first.voltage_V.size == 400


def test_bad_settings_and_options_are_refused(env):
    with pytest.raises(ValueError, match="solver"):
        NMPCSettings(solver="sqpmethod")
    with pytest.raises(ValueError, match="sqp_iterations"):
        NMPCSettings(sqp_iterations=0)
    with pytest.raises(ValueError, match="rate_weight"):
        NMPCSettings(rate_weight=-1.0)
    with pytest.raises(ValueError, match="valid"):
        controllers.make("nmpc", MODEL_DIR, env, horizon_length=5)
    controller = controllers.make("nmpc", MODEL_DIR, env, horizon=5)
    with pytest.raises(ValueError, match="observation"):
        controller.reset(np.zeros(3))


def test_a_failing_second_sqp_iteration_keeps_the_first_iterate(model, env):
    from controllers.nmpc import KEPT

    task = ControlTask.from_env(env)
    settings = NMPCSettings(horizon=5, sqp_iterations=2, step_tolerance=0.0, shortcut=False)
    controller = NonlinearMPC(model, task, settings)
    solve = controller._solve_qp
    calls = {"n": 0, "first": []}

    def second_fails(hessian, q, u_bar, bounds):
        calls["n"] += 1
        if calls["n"] % 2 == 0:
            return None, "iteration limit", 1
        result = solve(hessian, q, u_bar, bounds)
        calls["first"].append(result[0][0])
        return result

    controller._solve_qp = second_fails
    steps = 12
    episode = controllers.run_episode(
        env, controller, seed=0, reference=sine(steps, 300.0, 10.0), max_steps=steps
    )
    assert controller.stats.fallbacks == 0
    assert controller.stats.status[KEPT] == steps
    # The first iterate is applied as it is, rounded to float32 volts like every action.
    np.testing.assert_array_equal(episode.voltage_V, np.float32(np.clip(calls["first"], -30, 30)))


def test_constrained_qps_on_the_bender_equal_bounded_least_squares(env):
    """Default settings, the reference beyond reach and not clamped to it (the drive bound binds
    in every QP of that chattering regime): each QP DAQP solves (P updated in its workspace)
    against scipy's bounded least squares."""
    controller = controllers.make("nmpc", MODEL_DIR, env)
    controller._reach = (-np.inf, np.inf)  # the reference unclamped: the bound binds in every QP
    reference = np.r_[np.full(60, -1300.0), np.full(100, 1300.0)]  # about 1030 um at 30 V
    obs, _ = env.reset(seed=0, options={"reference": reference})
    controller.reset(obs)
    solve, qps = controller._solve_qp, []

    def recording(hessian, q, u_bar, bounds):
        solution = solve(hessian, q, u_bar, bounds)
        qps.append((hessian, q, *solution))
        return solution

    controller._solve_qp = recording
    for _ in range(150):
        obs, *_ = env.step(controller.act(obs))
    solved = [(h, q, u) for h, q, u, status, _ in qps if status == "solved"]
    assert controller.stats.fallbacks == 0 and len(solved) > 200
    errors = []
    for hessian, q, u in solved:
        root = scipy.linalg.cholesky(hessian)  # 1/2 u'Pu + q'u = 1/2 |R u + R^-T q|^2 + const
        rhs = -scipy.linalg.solve_triangular(root, q, trans="T")
        # BVLS stops after n = 20 iterations by default, short of the optimum on some QPs of
        # this chattering regime (its cost there is above DAQP's): 200 lets it finish.
        expected = scipy.optimize.lsq_linear(
            root, rhs, bounds=(-30.0, 30.0), method="bvls", tol=1e-14, max_iter=200
        ).x
        assert np.any(np.abs(expected) == 30.0)  # the drive bound binds
        errors.append(np.max(np.abs(u - expected)))
    # An active-set solution is exact up to the factorisation's rounding: measured up to
    # 1.5e-12 V over these 300 QPs (OSQP at its tolerances 1e-6: 2.4e-3 V on the first move,
    # 0.105 V over a plan).
    assert max(errors) < 1e-9, max(errors)


def test_a_singular_qp_is_refused_with_the_fix(model):
    """C B = 0 (two-sample lag) and no rate weight: the last move reaches no output."""
    a = np.array([[0.5, 0.0], [1.0, 0.0]])
    b, c = np.array([[1.0], [0.0]]), np.array([[0.0, 1.0]])
    lagged = PredictionModel(a, b, c, 1e-3, model.nonlinearity, "identified", model.z_bounds)
    with pytest.raises(ValueError, match="set rate_weight > 0"):
        NonlinearMPC(lagged, TASK, NMPCSettings(rate_weight=0.0, horizon=HORIZON))
    NonlinearMPC(lagged, TASK, NMPCSettings(horizon=HORIZON))  # well posed with a rate weight


@pytest.mark.parametrize("tolerance", [0.0, None])
def test_the_nmpc_learns_a_softer_benders_gain(tolerance):
    """Built for the nominal bender, on one 20 % softer and 20 % slower (damping 0.04): with
    the model's gain the NMPC leaves the gain error to its observer (0.75 % of the stroke at
    10 Hz, measured); learning the gain and tracking over it takes it under 0.15 % (0.069 %),
    and the gain it learns is the datasheet's end the plant lies at (1.2 relative to the
    nominal bender)."""
    from benchmarks.references import make_reference
    from benchmarks.studies.corners import vertex_env

    nominal = gym.make("piezo_env:PiezoBender-v0", preview=20, max_episode_steps=2000)
    options = {} if tolerance is None else {"gain_tolerance": tolerance}
    controller = controllers.make("nmpc", MODEL_DIR, nominal, **options)
    reference = make_reference("sine-10Hz", 2001, dt=1e-3, seed=0)
    episode = controllers.run_episode(
        vertex_env((1.2, 0.8, 0.04)), controller, seed=0, reference=reference
    )
    if tolerance == 0.0:
        assert episode.metrics["rmse_percent"] > 0.5
        assert controller.gain == 1.0 and controller.gain_set == (1.0, 1.0)
    else:
        assert episode.metrics["rmse_percent"] < 0.15
        assert controller.gain == pytest.approx(1.2, abs=0.01)


def test_while_the_gain_stays_the_models_the_nmpc_steps_as_without_learning(env):
    """g is exactly 1 while the credible set holds the model's gain, and the NMPC then reads
    the observation as it is: the same volts, to the bit, as the NMPC that does not learn, up
    to the first step at which g moved (on this episode, none: every step)."""
    reference = sine(400, 300.0, 10.0)
    learning = controllers.make("nmpc", MODEL_DIR, env)
    gains = []
    act = learning.act

    def recorded(observation):
        action = act(observation)
        gains.append(learning.gain)
        return action

    learning.act = recorded
    first = controllers.run_episode(env, learning, seed=2, reference=reference, max_steps=400)
    fixed = controllers.make("nmpc", MODEL_DIR, env, gain_tolerance=0.0)
    second = controllers.run_episode(env, fixed, seed=2, reference=reference, max_steps=400)
    moved = np.flatnonzero(np.asarray(gains) != 1.0)
    until = moved[0] if moved.size else len(gains)
    assert until > 0
    np.testing.assert_array_equal(first.voltage_V[:until], second.voltage_V[:until])


def test_a_level_the_drive_cannot_hold_is_held_at_the_limit_not_rung(env):
    """A constant reference beyond the static reach (the model's deflection after a ramp to
    the drive's end and a hold there): the NMPC settles at that reach, as the linear MPC
    settles at the drive limit, instead of switching between the drive's ends through the
    first resonance. A reference within it is not touched (the clamp's path is not taken)."""
    from controllers.nmpc import static_reach

    controller = controllers.make("nmpc", MODEL_DIR, env)
    low, high = static_reach(controller.model, 30.0)
    assert low < 0.0 < high
    episode = controllers.run_episode(
        env, controller, seed=0, reference=np.full(621, 3000.0), max_steps=600
    )
    u, y = episode.voltage_V, episode.deflection_um
    assert np.count_nonzero(np.diff(np.sign(u))) == 0  # no swing between the drive's ends
    assert y.max() < 1.1 * high  # no ringing beyond the reach
    assert abs(np.mean(y[-100:]) - high) < 0.05 * high  # held at the reach
