"""Linear MPC held to independent computations: least squares, offset-free tracking, bounds."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import scipy.optimize
import scipy.signal
from handmade import AffineNonlinearity, synthetic_model

import controllers
from controllers import ControlTask, PredictionModel
from controllers.mpc import LinearMPC, MPCSettings

MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "identify" / "model")


TASK = ControlTask(dt=1e-3, u_max=30.0, stroke_um=100.0, preview=10, noise_bound_um=0.0)


def observation(y: float, targets: np.ndarray) -> np.ndarray:
    """[y_t, r_t, r_t+1 .. r_t+P] with r_t = r_t+1."""
    return np.r_[y, targets[0], targets[: TASK.preview]]


def least_squares_form(model, x0, d, targets, z_prev, lam):
    """(M, b) with the MPC's cost ``||M z - b||^2`` = ||y(z) - r||^2 + lam ||D z - z_prev e1||^2.

    Built without the controller's matrices: y(z) simulated by scipy's dlsim.
    """
    horizon = len(targets)
    system = (model.a, model.b, model.c, np.zeros((1, 1)), model.dt)

    def outputs(z):
        _, y, _ = scipy.signal.dlsim(system, np.r_[z, 0.0], x0=x0)
        return y[1:, 0] + d  # y_t+1 .. y_t+N

    free = outputs(np.zeros(horizon))
    columns = np.column_stack([outputs(np.eye(horizon)[j]) - free for j in range(horizon)])
    diff = np.eye(horizon) - np.eye(horizon, k=-1)
    matrix = np.vstack([columns, np.sqrt(lam) * diff])
    rhs = np.r_[targets - free, np.sqrt(lam) * z_prev * np.eye(horizon)[0]]
    return matrix, rhs


def bounded_least_squares(matrix, rhs, low, high):
    """scipy's bounded-variable least squares (an active-set method, independent of the MPC's
    QP solvers)."""
    return scipy.optimize.lsq_linear(matrix, rhs, bounds=(low, high), method="bvls", tol=1e-14).x


@pytest.mark.parametrize("shortcut", [True, False])
def test_unconstrained_first_move_equals_independent_least_squares(shortcut):
    model = synthetic_model()
    horizon, lam = 8, 0.05
    mpc = LinearMPC(
        model,
        TASK,
        MPCSettings(
            horizon=horizon,
            rate_weight=lam,
            shortcut=shortcut,
            eps_abs=1e-9,
            eps_rel=1e-9,
            max_iter=20000,
        ),
    )
    rng = np.random.default_rng(3)
    for _ in range(5):
        x0 = rng.normal(0.0, 5.0, model.n_states)
        d = rng.normal(0.0, 3.0)
        targets = rng.uniform(-20.0, 20.0, horizon)
        z_prev = rng.uniform(-5.0, 5.0)
        mpc._z_prev = z_prev
        got = mpc._solve(np.r_[x0, d], targets)
        matrix, rhs = least_squares_form(model, x0, d, targets, z_prev, lam)
        expected = np.linalg.lstsq(matrix, rhs, rcond=None)[0][0]
        # Measured: 2.8e-15 by the shortcut, 1.1e-9 by OSQP at eps 1e-9 (relative to 1 + |z|);
        # DAQP (the default) ends on the exact active set.
        assert got == pytest.approx(expected, abs=5e-9 * (1 + abs(expected)))


def run_loop(mpc, plant_step, reference, steps):
    """Closed loop on a plant given as a function (x, z) -> (x_next, y_next)."""
    model = mpc.model
    x = np.zeros(model.n_states)
    y = 0.0
    ys, us = [], []
    obs = observation(y, np.full(TASK.preview + 1, reference))
    mpc.reset(obs)
    memory = model.nonlinearity.initial_state()
    for _ in range(steps):
        u = float(mpc.act(obs)[0])
        z, memory = model.nonlinearity.step(u, memory)
        x, y = plant_step(x, z)
        ys.append(y)
        us.append(u)
        obs = observation(y, np.full(TASK.preview + 1, reference))
    return np.array(ys), np.array(us)


def test_constant_output_disturbance_leaves_no_steady_state_error():
    model = synthetic_model()
    mpc = LinearMPC(model, TASK, MPCSettings(horizon=10))

    def plant(x, z):  # the model with a 7 % gain error and a 40 um offset at the output
        x = model.a @ x + model.b[:, 0] * (1.07 * z)
        return x, float(model.c[0] @ x) + 40.0

    ys, _ = run_loop(mpc, plant, 25.0, 600)
    assert abs(ys[-1] - 25.0) < 1e-6
    assert np.max(np.abs(ys[-50:] - 25.0)) < 1e-6


def test_bounds_hold_and_volts_are_the_exact_inverse_of_z():
    model = synthetic_model()
    mpc = LinearMPC(model, TASK, MPCSettings(horizon=10))

    def plant(x, z):
        x = model.a @ x + model.b[:, 0] * z
        return x, float(model.c[0] @ x)

    _, us = run_loop(mpc, plant, 1e4, 50)  # far beyond reach: the upper bound binds
    assert np.all(np.abs(us) <= 30.0)
    assert us[-1] == pytest.approx(30.0)
    z_plan = mpc._plan
    assert np.all(z_plan <= 61.0 + 1e-6) and np.all(z_plan >= -59.0 - 1e-6)
    # Inside the range, the voltage is exactly the inverse of the planned first move.
    mpc2 = LinearMPC(model, TASK, MPCSettings(horizon=10))
    obs = observation(0.0, np.full(TASK.preview + 1, 3.0))
    mpc2.reset(obs)
    u = float(mpc2.act(obs)[0])
    assert u == pytest.approx(np.float32((mpc2._plan[0] - 1.0) / 2.0), abs=0)


@pytest.mark.parametrize(
    ("solver", "status"), [("daqp", "iteration limit"), ("osqp", "maximum iterations reached")]
)
def test_forced_solver_failure_falls_back_and_the_loop_goes_on(solver, status):
    model = synthetic_model()
    settings = MPCSettings(horizon=10, max_iter=1, shortcut=False, qp_solver=solver)
    mpc = LinearMPC(model, TASK, settings)

    def plant(x, z):
        x = model.a @ x + model.b[:, 0] * z
        return x, float(model.c[0] @ x)

    ys, us = run_loop(mpc, plant, 20.0, 100)
    assert mpc.stats.fallbacks > 0
    assert status in mpc.stats.status
    assert np.all(np.isfinite(ys)) and np.all(np.abs(us) <= 30.0)


@pytest.fixture(scope="module")
def env():
    return gym.make("piezo_env:PiezoBender-v0", preview=20)


def test_mpc_on_the_bender_is_accurate_finite_and_deterministic(env):
    controller = controllers.make("mpc", MODEL_DIR, env)
    t = np.arange(1, 402) * 1e-3
    reference = 500.0 * np.sin(2 * np.pi * 10.0 * t)
    first = controllers.run_episode(env, controller, seed=4, reference=reference, max_steps=400)
    second = controllers.run_episode(env, controller, seed=4, reference=reference, max_steps=400)
    np.testing.assert_array_equal(first.voltage_V, second.voltage_V)
    assert np.all(np.abs(first.voltage_V) <= 30.0) and np.all(np.isfinite(first.deflection_um))
    # measured 0.0060 % on seed 4 (0.0033-0.0062 % over seeds 0-5), docs/identify/model,
    # 400 steps of the 10 Hz 500 um sine
    assert first.metrics["rmse_percent"] < 0.012
    assert first.controller["stats"]["fallbacks"] == 0


def test_bad_observations_and_options_are_refused(env):
    controller = controllers.make("mpc", MODEL_DIR, env)
    obs, _ = env.reset(seed=0)
    controller.reset(obs)
    bad = obs.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match=r"observation\[3\]"):
        controller.act(bad)
    with pytest.raises(ValueError, match="shape"):
        controller.act(obs[:5])
    with pytest.raises(ValueError, match=r"valid: .*horizon"):
        controllers.make("mpc", MODEL_DIR, env, horizn=10)
    with pytest.raises(ValueError, match="valid: pid, pid-notch"):
        controllers.make("mcp", MODEL_DIR, env)
    with pytest.raises(ValueError, match="horizon"):
        controllers.make("mpc", MODEL_DIR, env, horizon=0)
    for name in ("mpc", "mpc-adaptive", "nmpc"):  # a flag is a bool, not a truthy value
        with pytest.raises(ValueError, match="shortcut must be True or False, got 'no'"):
            controllers.make(name, MODEL_DIR, env, shortcut="no")
    with pytest.raises(ValueError, match=r"damping_range must be a pair \(low, high\)"):
        controllers.make("mpc-adaptive", MODEL_DIR, env, damping_range=0.02)
    with pytest.raises(ValueError, match="a vector env of 2 benders"):
        controllers.make(
            "mpc", MODEL_DIR, gym.make_vec("piezo_env:PiezoBender-v0", num_envs=2, preview=20)
        )


def test_numpy_numbers_are_settings_as_python_numbers():
    """A numpy scalar is the number it holds (a setting read from an array, a sweep's grid),
    and the settings keep it as a Python number, so that describe() stays JSON."""
    settings = MPCSettings(rate_weight=np.float32(0.25), horizon=np.int64(12))
    assert settings.rate_weight == 0.25 and type(settings.rate_weight) is float
    assert settings.horizon == 12 and type(settings.horizon) is int
    with pytest.raises(ValueError, match="rate_weight"):
        MPCSettings(rate_weight=np.float64(np.nan))
    with pytest.raises(ValueError, match="rate_weight"):
        MPCSettings(rate_weight=np.bool_(True))


@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("pid", {"ms_max": np.float32(1.5)}),
        ("pid-ff", {"antiwindup_gain": np.float64(0.5), "derivative": np.bool_(True)}),
        ("mpc", {"prediction_horizon": np.int64(30), "rate_weight": np.float32(0.25)}),
        ("nmpc", {"horizon": np.int64(12)}),
    ],
)
def test_describe_is_json_with_numpy_settings(env, name, options):
    import json

    description = controllers.make(name, MODEL_DIR, env, **options).describe()
    json.dumps(description, allow_nan=False)


@pytest.mark.parametrize(
    ("name", "model"), [("mpc", MODEL_DIR), ("nmpc", MODEL_DIR), ("mpc", "plant")]
)
def test_a_reused_controller_equals_a_fresh_one(env, name, model):
    """Nothing carries over episodes: solver state included (steps make OSQP work)."""
    from benchmarks.references import make_reference

    steps = make_reference("steps", 321, dt=1e-3, seed=0)
    random_steps = make_reference("random-steps", 321, dt=1e-3, seed=0)
    reused = controllers.make(name, model, env)
    controllers.run_episode(env, reused, seed=1, reference=steps, max_steps=300)
    again = controllers.run_episode(env, reused, seed=2, reference=random_steps, max_steps=300)
    fresh = controllers.run_episode(
        env, controllers.make(name, model, env), seed=2, reference=random_steps, max_steps=300
    )
    assert sum(reused.stats.status.values()) == 300
    np.testing.assert_array_equal(again.voltage_V, fresh.voltage_V)


def test_a_singular_qp_is_refused_with_the_fix():
    """C B = 0 (two-sample lag) and no rate weight: the last move reaches no output."""
    a = np.array([[0.5, 0.0], [1.0, 0.0]])
    b, c = np.array([[1.0], [0.0]]), np.array([[0.0, 1.0]])
    lagged = PredictionModel(a, b, c, 1e-3, AffineNonlinearity(), "identified", (-59.0, 61.0))
    with pytest.raises(ValueError, match="set rate_weight > 0"):
        LinearMPC(lagged, TASK, MPCSettings(rate_weight=0.0))
    LinearMPC(lagged, TASK, MPCSettings(rate_weight=1e-2))  # well posed with a rate weight


class NarrowFirstMove(AffineNonlinearity):
    """The first move can reach less than the later ones (a memory state near the rail)."""

    def reachable(self, state: np.ndarray) -> tuple[float, float]:
        return -4.0, 6.0


@pytest.mark.parametrize(
    ("shortcut", "solver", "tolerance"),
    # Measured: DAQP 8e-15 on the first move, 8.2e-13 over the plan; OSQP at eps 1e-10
    # 2.5e-9 and 5.1e-7.
    [(True, "daqp", 1e-10), (False, "daqp", 1e-10), (False, "osqp", 3e-6)],
)
def test_constrained_plan_equals_bounded_least_squares(shortcut, solver, tolerance):
    """Bounds binding, first-move bounds narrower than the rest: the QP solver's plan against
    scipy's bounded-variable least squares (lsq_linear, an independent active-set solver)."""
    base = synthetic_model()
    model = PredictionModel(
        base.a, base.b, base.c, base.dt, NarrowFirstMove(), "identified", (-59.0, 61.0)
    )
    horizon, lam = 8, 0.05
    settings = MPCSettings(
        horizon=horizon,
        rate_weight=lam,
        shortcut=shortcut,
        eps_abs=1e-10,
        eps_rel=1e-10,
        max_iter=50000,
        qp_solver=solver,
    )
    mpc = LinearMPC(model, TASK, settings)
    rng = np.random.default_rng(7)
    for _ in range(4):
        x0, d = rng.normal(0.0, 5.0, model.n_states), rng.normal(0.0, 3.0)
        targets = rng.uniform(150.0, 250.0, horizon)  # far: the unconstrained plan leaves the box
        mpc._z_prev = z_prev = rng.uniform(-5.0, 5.0)
        got = mpc._solve(np.r_[x0, d], targets)
        low, high = np.full(horizon, -59.0), np.full(horizon, 61.0)
        low[0], high[0] = -4.0, 6.0
        matrix, rhs = least_squares_form(model, x0, d, targets, z_prev, lam)
        expected = bounded_least_squares(matrix, rhs, low, high)
        assert expected[0] == pytest.approx(6.0)  # the first-move bound binds ...
        assert expected[1] > 6.5  # ... and the later moves use their wider range
        assert got == mpc._plan[0]
        np.testing.assert_allclose(mpc._plan, expected, atol=tolerance)


@pytest.mark.parametrize(
    ("solver", "first", "plan"),
    # Measured over these 100 steps: DAQP 3.9e-12 on the first move and 1.2e-11 over the plan;
    # OSQP at its default tolerance 1.9e-3 (median 1.3e-5) and 3.6e-3 (equivalent V).
    [("daqp", 1e-9, 1e-9), ("osqp", 1e-2, 2e-2)],
)
def test_constrained_steps_on_the_bender_equal_bounded_least_squares(env, solver, first, plan):
    """Default settings on the identified model, the reference beyond reach (the drive bound
    binds): every step the QP solver solves against scipy's active-set solver, on its own
    QP."""
    mpc = controllers.make("mpc", MODEL_DIR, env, qp_solver=solver)
    mpc._fused = None  # the step in Python, whose _solve this test records
    reference = np.r_[np.full(60, -1300.0), np.full(100, 1300.0)]  # about 1030 um at 30 V
    obs, _ = env.reset(seed=0, options={"reference": reference})
    mpc.reset(obs)
    solve, steps = mpc._solve, []

    def recording(estimate, targets):
        qp = (estimate.copy(), targets.copy(), mpc._z_prev)
        unconstrained = mpc.stats.status["unconstrained"]
        z = solve(estimate, targets)
        if mpc.stats.status["unconstrained"] == unconstrained:  # the QP solver ran
            steps.append((*qp, mpc._lower.copy(), mpc._upper.copy(), mpc._plan.copy()))
        return z

    mpc._solve = recording
    for _ in range(100):
        obs, *_ = env.step(mpc.act(obs))
    n, first_move_bound_binds = mpc.model.n_states, 0
    for estimate, targets, z_prev, low, high, got in steps:
        matrix, rhs = least_squares_form(
            mpc.model, estimate[:n], estimate[n], targets, z_prev, mpc.settings.rate_weight
        )
        expected = bounded_least_squares(matrix, rhs, low, high)
        assert got[0] == pytest.approx(expected[0], abs=first)
        np.testing.assert_allclose(got, expected, atol=plan)
        own_lower = expected[0] == low[0] != low[1]
        own_upper = expected[0] == high[0] != high[1]
        first_move_bound_binds += own_lower or own_upper
    assert mpc.stats.fallbacks == 0 and len(steps) == 100
    assert first_move_bound_binds > 40  # at a bound of its own, not the later moves' (84)


@pytest.mark.parametrize("rate", [None, 0.4])
def test_daqp_and_osqp_agree_on_random_box_qps_of_the_mpc_shape(rate):
    """Random condensed tracking QPs (N = 20, a dense P of the MPC's form, bounds active) with
    and without the slew limit's rate rows: DAQP's workspace, updated in place step after
    step as the MPC does, against a fresh tight OSQP solve of the same QP."""
    from controllers.box_qp import box_qp

    rng = np.random.default_rng(11)
    n = 20
    responses = np.tril(rng.normal(0.0, 1.0, (n, n)) * np.exp(-0.2 * np.arange(n))[:, None])
    hessian = responses.T @ responses + 1e-2 * (2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1))
    low, high = np.full(n, -3.0), np.full(n, 3.0)
    daqp_qp = box_qp(
        "daqp", low, high, hessian=hessian, eps_abs=1e-6, eps_rel=1e-6, max_iter=1000, rate=rate
    )
    rows = n if rate is None else 2 * n - 1
    active = 0
    for trial in range(40):
        q = rng.normal(0.0, 20.0, n)
        bounds = (np.full(n, -3.0), np.full(n, 3.0))
        bounds[0][0], bounds[1][0] = rng.uniform(-3.0, 0.0), rng.uniform(0.0, 3.0)
        got = daqp_qp.solve(q, np.zeros(n), np.ones(rows), bounds=bounds)
        osqp_qp = box_qp(
            "osqp",
            *bounds,
            hessian=hessian,
            eps_abs=1e-10,
            eps_rel=1e-10,
            max_iter=200000,
            rate=rate,
        )
        reference = osqp_qp.solve(q, np.zeros(n), np.zeros(rows))
        assert got.status == "solved" and reference.status == "solved", trial
        np.testing.assert_allclose(got.x, reference.x, atol=1e-6)
        active += int(np.sum(np.isclose(np.abs(got.x), 3.0)) > 0)
        if rate is not None:
            # General rows are met to DAQP's primal tolerance (1e-6); measured 1.3e-12.
            assert np.max(np.abs(np.diff(got.x))) <= rate + 1e-9
    assert active > 20  # the bounds bind in most of the QPs


def test_move_blocks_cover_the_prediction_first_move_alone():
    from controllers.condensed import blocking_matrix, move_blocks

    assert move_blocks(20, 20) == (1,) * 20
    for moves, samples in ((20, 79), (8, 9), (3, 50), (20, 1000)):
        blocks = move_blocks(moves, samples)
        assert len(blocks) == moves and sum(blocks) == samples and blocks[0] == 1
        assert list(blocks) == sorted(blocks)  # longer blocks later
        t = blocking_matrix(blocks)
        assert t.shape == (samples, moves) and np.all(t.sum(axis=1) == 1)
    with pytest.raises(ValueError, match="at least as many prediction samples"):
        move_blocks(20, 19)


def test_blocked_first_move_equals_independent_least_squares():
    """M = 6 moves over Np = 15 samples: the MPC's unconstrained first move against the
    least-squares minimiser of the same cost with z = T v written out independently (dlsim
    responses, each move held over its block)."""
    from controllers.condensed import blocking_matrix, move_blocks

    model = synthetic_model()
    moves, samples, lam = 6, 15, 0.05
    settings = MPCSettings(horizon=moves, prediction_horizon=samples, rate_weight=lam)
    mpc = LinearMPC(model, TASK, settings)
    assert mpc.blocks == move_blocks(moves, samples) and mpc.prediction_samples == samples
    assert mpc.describe()["move_blocks"] == list(mpc.blocks)
    hold = blocking_matrix(mpc.blocks)
    rng = np.random.default_rng(4)
    for _ in range(4):
        x0, d = rng.normal(0.0, 5.0, model.n_states), rng.normal(0.0, 3.0)
        targets = rng.uniform(-20.0, 20.0, samples)
        mpc._z_prev = z_prev = rng.uniform(-5.0, 5.0)
        got = mpc._solve(np.r_[x0, d], targets)
        matrix, rhs = least_squares_form(model, x0, d, targets, z_prev, lam)
        responses = matrix[:samples] @ hold  # outputs per move
        diff = np.eye(moves) - np.eye(moves, k=-1)
        blocked = np.vstack([responses, np.sqrt(lam) * diff])
        blocked_rhs = np.r_[rhs[:samples], np.sqrt(lam) * z_prev * np.eye(moves)[0]]
        expected = np.linalg.lstsq(blocked, blocked_rhs, rcond=None)[0][0]
        assert got == pytest.approx(expected, abs=1e-9 * (1 + abs(expected)))


def test_resonance_prediction_covers_the_slowest_first_mode_of_the_datasheet():
    """On the oracle's model of the PL140 at 0.1 ms: one period of its first mode moved 20 %
    down, from the mode's analytic frequency (the env calibrates it to the datasheet's)."""
    import math

    from controllers.tolerance_box import RESONANCE_TOLERANCE

    env = gym.make("piezo_env:PiezoBender-v0", preview=20, dt=1e-4)
    mpc = controllers.make("mpc", "plant", env, prediction_horizon="resonance")
    f1 = env.unwrapped.model.params.datasheet.resonance  # Hz: the FE mode is calibrated to it
    expected = math.ceil(1.0 / (f1 * (1.0 - RESONANCE_TOLERANCE) * 1e-4))
    assert abs(mpc.prediction_samples - expected) <= 1  # modal damping moves |ln p| slightly
    assert mpc.prediction_samples > 70 and mpc.blocks[0] == 1 and len(mpc.blocks) == 20
    default = controllers.make("mpc", "plant", env)
    assert default.prediction_samples == 20 and default.blocks == (1,) * 20
    with pytest.raises(ValueError, match="at least horizon"):
        MPCSettings(horizon=20, prediction_horizon=10)


def test_daqp_refuses_crossed_bounds_and_starts_afresh_after_a_failure():
    """Data DAQP refuses at update (lower above upper) give no solution, never the previous
    one; the next solve of a good QP starts from no active set and is right."""
    from controllers.box_qp import box_qp

    n = 5
    hessian = np.eye(n) + 0.1
    qp = box_qp(
        "daqp",
        np.full(n, -1.0),
        np.full(n, 1.0),
        hessian=hessian,
        eps_abs=1e-6,
        eps_rel=1e-6,
        max_iter=100,
    )
    good = qp.solve(np.full(n, 5.0), np.zeros(n), np.zeros(n))
    assert good.status == "solved" and np.allclose(good.x, -1.0, atol=1e-12)
    crossed = (np.full(n, 1.0), np.full(n, -1.0))
    failed = qp.solve(np.full(n, 5.0), np.zeros(n), np.ones(n), bounds=crossed)
    assert failed.x is None and failed.status != "solved"
    again = qp.solve(np.zeros(n), np.zeros(n), np.ones(n), bounds=(np.full(n, -1.0), np.ones(n)))
    assert again.status == "solved" and np.allclose(again.x, 0.0)


def test_resonance_horizon_refuses_a_pole_that_is_no_bending_mode():
    from controllers.mpc import covering_samples

    slow = np.exp(1e-3 * (-0.01 + 2j * np.pi * 1.0))  # a lightly damped 1 Hz pair at 1 ms
    a = np.array([[2 * slow.real, -(abs(slow) ** 2)], [1.0, 0.0]])
    with pytest.raises(ValueError, match="not a bending mode"):
        covering_samples(a, 1e-3, 20)
    with pytest.raises(ValueError, match="at least 2 moves"):
        from controllers.condensed import move_blocks

        move_blocks(1, 10)


def test_the_oracle_model_drops_only_the_modes_its_error_budget_allows():
    """The plant's prediction model carries the overdamped high modes as their one-step
    response while the proven error stays within PLANT_REDUCTION_ERROR of the full stroke,
    checked by simulating both models on a drive-range random input; where no mode fits the
    budget (the nominal PL140 at 1 ms) the model is the plant's own, bit for bit."""
    from controllers.prediction import PLANT_REDUCTION_ERROR
    from piezo_env import PiezoBenderModel

    nominal = PiezoBenderModel("PL140")
    kept, full = PredictionModel.from_plant(nominal), nominal.state_space_matrices()
    for mine, theirs in zip((kept.a, kept.b, kept.c), full[:3], strict=True):
        np.testing.assert_array_equal(mine, theirs)

    plant = PiezoBenderModel("PL127", dt=2.5e-4)  # 42 states: high modes of radius ~1e-6
    reduced = PredictionModel.from_plant(plant)
    exact = PredictionModel.from_plant(plant, reduce=False)
    assert reduced.n_states <= 12 < exact.n_states == plant.discrete.n_states
    z = np.random.default_rng(3).uniform(*reduced.z_bounds, 4000)
    outputs = []
    for model in (reduced, exact):
        x, y = np.zeros(model.n_states), []
        for value in z:
            x = model.a @ x + model.b[:, 0] * value
            y.append(float(model.c[0] @ x))
        outputs.append(np.array(y))
    error = np.abs(outputs[0] - outputs[1]).max()
    assert 0.0 < error <= PLANT_REDUCTION_ERROR * 2.0 * plant.stroke_um


@pytest.mark.parametrize(
    "sensor", [(1, None), (2, 2000.0), (0, 20e3)], ids=["delay-1", "delay-2-2kHz", "20kHz"]
)
@pytest.mark.parametrize("name", ["mpc", "nmpc"])
def test_the_oracle_steers_the_tip_through_the_envs_sensor(sensor, name):
    """``make(name, "plant", env)`` estimates through the env's sensor and steers the true
    deflection: behind a sensor read late or slowly it tracks a 50 Hz half-stroke sine to
    the error it reaches without a sensor, while the same MPC blind to the sensor chases a
    lagging measurement (a phase error of 2 pi f dt per sample of delay: 31 % of the amplitude
    at 50 Hz and 1 ms; 2 pi f tau = 0.25 % for the 20 kHz sensor's lag tau)."""
    from piezo_env import Sensor

    reference = 500.0 * np.sin(2 * np.pi * 50.0 * 1e-3 * np.arange(621))
    errors = {}
    for label, setting, model in (
        ("through", Sensor(*sensor), "plant"),
        ("blind", Sensor(*sensor), None),
        ("no sensor", None, "plant"),
    ):
        env = gym.make(
            "piezo_env:PiezoBender-v0", preview=20, sensor=setting, max_episode_steps=600
        )
        model = model or PredictionModel.from_plant(env.unwrapped.model)
        episode = controllers.run_episode(
            env, controllers.make(name, model, env), seed=0, reference=reference
        )
        errors[label] = episode.metrics["rmse_percent"]
    assert errors["through"] <= 1.05 * errors["no sensor"]
    assert errors["blind"] > 5 * errors["through"]


@pytest.mark.parametrize("name", ["pid-notch", "pid-ff"])
def test_pid_oracles_build_behind_a_sensor_and_pid_ff_steers_the_tip(name):
    """The PIDs' tuning box is built from the oracle's measured output behind a sensor, and
    ``pid-ff``'s feedforward inverts the tip's model: behind the bench's 20 kHz sensor it
    tracks a 10 Hz sine to the error it reaches without a sensor."""
    from piezo_env import Sensor

    reference = 500.0 * np.sin(2 * np.pi * 10.0 * 1e-3 * np.arange(421))
    errors = []
    for sensor in (Sensor(0, 20e3), None):
        env = gym.make("piezo_env:PiezoBender-v0", preview=20, sensor=sensor, max_episode_steps=400)
        controller = controllers.make(name, "plant", env)
        episode = controllers.run_episode(env, controller, seed=0, reference=reference)
        errors.append(episode.metrics["rmse_percent"])
    assert np.isfinite(errors).all()
    if name == "pid-ff":
        assert errors[0] <= 1.05 * errors[1]


def test_the_task_holds_its_numbers_as_python_floats():
    """A task made with numpy scalars holds Python floats, so that the controllers' arithmetic
    on them does not hang on numpy's promotion rules (numpy 1 and 2 differ)."""
    task = ControlTask(
        dt=np.float64(1e-3),
        u_max=np.float32(30.0),
        stroke_um=np.int64(100),
        preview=10,
        noise_bound_um=np.float64(1.0),
        slew_limit=np.float64(9000.0),
        observation_bound_um=np.float32(1500.0),
    )
    names = ("dt", "u_max", "stroke_um", "noise_bound_um", "slew_limit", "observation_bound_um")
    for name in names:
        assert type(getattr(task, name)) is float, name
    assert type(task.slew_step) is float


def test_float32_within_compares_the_window_in_float32_under_any_numpy():
    """The window's ends are rounded to float32 before the comparison, whatever numpy's
    promotion of a float32 against a Python or numpy float64 (numpy 1: float64; numpy 2:
    float32): a voltage that rounds to the float32 of the window's end stays there (past the
    end by less than half a float32 step), as in the compiled steps."""
    from controllers.mpc import float32_within

    high = 12.7456689
    end = float(np.float32(high))
    assert end > high  # the end's float32 lies beyond the end
    assert float32_within(high, -30.0, high) == end
    assert float32_within(high, -30.0, np.float64(high)) == end
    assert float32_within(-high, np.float64(-high), 30.0) == -end
