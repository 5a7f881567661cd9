"""The bench-realistic plant options: amplifier, sensor, rate-dependent hysteresis, bounds."""

from __future__ import annotations

import copy
import math
import pickle

import gymnasium as gym
import numpy as np
import pytest

from piezo_env import TaskConfig
from piezo_env.amplifier import Amplifier
from piezo_env.drift import Drift
from piezo_env.env import PiezoBenderEnv
from piezo_env.hysteresis import PrandtlIshlinskii, RateDependentPrandtlIshlinskii
from piezo_env.sensor import Sensor

C_PL140 = 8.2e-6  # F, 2 x 4.1 uF (datasheet)


def _env(**settings) -> PiezoBenderEnv:
    settings.setdefault("noise_bound", 0.0)
    env = PiezoBenderEnv(**settings)
    env.reset(seed=0)
    return env


# -- amplifier --------------------------------------------------------------------------------


def test_slew_limit_is_current_over_capacitance():
    env = _env(amplifier=Amplifier(current_limit_mA=77.0))
    assert env.slew_limit == pytest.approx(77e-3 / C_PL140, rel=1e-12)
    # The figure: 30 V at 50 Hz needs C 2 pi f U = 77 mA on a PL140.
    assert C_PL140 * 2 * math.pi * 50 * 30 * 1e3 == pytest.approx(77.3, abs=0.05)
    assert Amplifier().full_stroke_frequency(C_PL140, 30.0) == pytest.approx(64.7, abs=0.05)


def test_current_limit_matches_c_dv_dt_on_a_ramp():
    """A command ramp steeper than the slew limit moves the voltage by exactly S dt per sample,
    so C_p dV/dt equals the current limit; a slower ramp passes unchanged."""
    limit_ma = 60.0
    env = _env(amplifier=Amplifier(current_limit_mA=limit_ma), hysteresis=None)
    dt = env.config.dt
    steep = np.minimum(np.arange(1, 11) * 20.0, 30.0)  # 20 V/ms command, limit 7.3 V/ms
    voltages, limited, currents = [0.0], [], []
    for c in steep:
        *_, info = env.step(np.array([c]))
        voltages.append(info["voltage_V"])
        limited.append(info["slew_limited"])
        currents.append(info["current_mA"])
    dv = np.diff(voltages)
    ramp = dv[voltages[1:] < np.float64(30.0) - limit_ma * 1e-3 / C_PL140 * dt]
    assert ramp.size >= 3
    np.testing.assert_allclose(C_PL140 * ramp / dt * 1e3, limit_ma, rtol=1e-12)
    assert all(limited[: ramp.size])
    # The charge-based current adds the motional part Gamma dtheta/dt, small against C dV/dt.
    np.testing.assert_allclose(currents[: ramp.size], limit_ma, rtol=0.15)
    env.reset(seed=0)
    slow = np.arange(1, 11) * 2.0  # 2 V/ms: within the limit
    for c in slow:
        *_, info = env.step(np.array([c]))
        assert info["voltage_V"] == c and info["command_V"] == c and not info["slew_limited"]


def test_amplifier_bandwidth_is_a_first_order_lag():
    f_a = 100.0
    env = _env(amplifier=Amplifier(current_limit_mA=1e6, bandwidth_Hz=f_a), hysteresis=None)
    p = math.exp(-2 * math.pi * f_a * env.config.dt)
    v = 0.0
    for _ in range(20):
        *_, info = env.step(np.array([1.0]))
        v = 1.0 + (v - 1.0) * p
        assert info["voltage_V"] == pytest.approx(v, rel=1e-14)


# -- sensor -----------------------------------------------------------------------------------


@pytest.mark.parametrize("delay", [1, 2])
def test_sensor_delay_shifts_the_measured_trace_by_exactly_d(delay):
    actions = 20.0 * np.sin(np.arange(60) * 0.3)
    traces = {}
    for d in (0, delay):
        env = _env(sensor=Sensor(delay=d, bandwidth_Hz=None))
        obs, _ = env.reset(seed=0)
        trace, truth = [obs[0]], []
        for a in actions:
            obs, _, _, _, info = env.step(np.array([a]))
            trace.append(obs[0])
            truth.append(info["deflection_um"])
        traces[d] = (np.array(trace), np.array(truth))
    measured, truth = traces[delay]
    np.testing.assert_array_equal(measured[delay:], traces[0][0][:-delay])
    np.testing.assert_array_equal(measured[:delay], traces[0][0][0])
    np.testing.assert_array_equal(truth, traces[0][1])  # the true deflection is untouched


def test_sensor_bandwidth_lags_a_ramp_by_tau():
    """First-order lag driven by a ramp: the output trails it by tau (continuous closed form),
    exactly at the samples for the first-order-hold discretisation."""
    f_s, dt = 300.0, 1e-3
    tau = 1 / (2 * math.pi * f_s)
    sensor = Sensor(bandwidth_Hz=f_s).state(dt)
    sensor.reset(0.0)
    slope = 5.0  # um per sample
    for t in range(1, 200):
        out = sensor.measure(slope * t)
    assert out == pytest.approx(slope * (199 - tau / dt), rel=1e-12)
    p, b0, b1 = Sensor(bandwidth_Hz=f_s).coefficients(dt)
    assert min(p, b0, b1) >= 0 and p + b0 + b1 == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("delay", [0, 1, 2])
def test_sensor_state_space_lags_a_ramp_by_tau_plus_its_delay(delay):
    """The sensor as a linear system (what an oracle predicts with) against the continuous
    closed form: a ramp comes out delayed by tau + delay samples, from rest (static gain 1)."""
    f_s, dt, slope = 300.0, 1e-3, 5.0
    tau = 1 / (2 * math.pi * f_s)
    a, b, c, d = Sensor(delay=delay, bandwidth_Hz=f_s).state_space(dt)
    assert float(c @ np.linalg.solve(np.eye(len(b)) - a, b)) + d == pytest.approx(1.0, rel=1e-12)
    q = np.zeros(len(b))
    for t in range(200):
        out = float(c @ q) + d * slope * t
        q = a @ q + b * slope * t
    assert out == pytest.approx(slope * (199 - tau / dt - delay), rel=1e-12)


@pytest.mark.parametrize(
    "sensor", [Sensor(0, None), Sensor(0, 20e3), Sensor(1, 300.0), Sensor(2, 2000.0)], ids=str
)
def test_sensor_state_space_steps_as_the_envs_sensor(sensor):
    """The state space against the stepping sensor the env runs, from rest at a deflection
    that is not zero (the state space's steady state there) on a random deflection."""
    dt = 1e-3
    a, b, c, d = sensor.state_space(dt)
    stepping = sensor.state(dt)
    rest = 37.0
    stepping.reset(rest)
    q = np.linalg.solve(np.eye(len(b)) - a, b * rest)
    for y in np.random.default_rng(5).uniform(-500.0, 500.0, 200):
        q, measured = a @ q + b * y, float(c @ q) + d * y
        assert measured == pytest.approx(stepping.measure(y), abs=1e-11)


@pytest.mark.parametrize("sensor", [Sensor(0, None), Sensor(0, 20e3), Sensor(2, 2000.0)], ids=str)
def test_oracle_predicts_what_the_sensor_measures(sensor):
    """The oracle's model (the plant in series with the env's sensor) against the env's own
    measured deflection, noise off: within the model reduction's budget (2 nm on the PL140)."""
    from controllers.prediction import PredictionModel

    env = _env(sensor=sensor)
    voltages = 30.0 * np.random.default_rng(3).uniform(-1.0, 1.0, 300)
    measured = np.array([env.step(np.array([v], np.float32))[0][0] for v in voltages])
    model = PredictionModel.from_plant(env.model, sensor=sensor)
    beam = PredictionModel.from_plant(env.model)
    assert model.n_states == beam.n_states + 1 + max(sensor.delay, 1)
    np.testing.assert_allclose(model.simulate(voltages.astype(np.float32)), measured, atol=5e-3)
    tip = model.simulate(voltages.astype(np.float32), tracked=True)
    np.testing.assert_allclose(tip, beam.simulate(voltages.astype(np.float32)), atol=1e-9)
    if sensor.delay or sensor.bandwidth_Hz:
        assert np.max(np.abs(tip - measured)) > 1.0  # the sensor is no rounding error


def test_sensor_reward_keeps_the_true_deflection():
    env = _env(sensor=Sensor(delay=2, bandwidth_Hz=500.0), reference=np.full(50, 100.0))
    for _ in range(10):
        obs, reward, _, _, info = env.step(np.array([10.0]))
    assert reward == pytest.approx(-(((info["deflection_um"] - 100.0) / 1000.0) ** 2))
    assert obs[0] != pytest.approx(info["deflection_um"], abs=1e-3)


# -- rate-dependent hysteresis ----------------------------------------------------------------


def _zero_crossing_widths(h, amplitude: float, period: int, cycles: int = 3) -> float:
    """u_eff at the rising minus at the falling zero crossing of a sampled sine (last cycle)."""
    state = h.initial_state(0.0)
    t = np.arange(cycles * period + 1)
    u = amplitude * np.sin(2 * np.pi * t / period)
    u[t % (period // 2) == 0] = 0.0
    u_eff = np.empty(u.size)
    for i, v in enumerate(u):
        state, u_eff[i] = h.step(state, v)
    rising, falling = (cycles - 1) * period, (cycles - 1) * period + period // 2
    return float(u_eff[falling] - u_eff[rising])


def test_loop_width_grows_with_frequency_as_the_closed_form():
    """Rate-dependent plays r_i + beta |u'| (Al Janaideh et al.): at a zero crossing each play
    trails the input by its current radius, so the loop width there is
    sum_i 2 w_i (r_i + beta rate) with the previous sample's rate, for plays away from
    saturation (r_i + beta rate < A - r_i)."""
    radii, weights, beta, dt, amplitude = (2.0, 5.0), (0.1, 0.2), 4e-4, 1e-3, 30.0
    h = RateDependentPrandtlIshlinskii(
        linear_weight=0.8, radii=radii, weights=weights, rate_time=beta, dt=dt
    )
    widths = []
    for period in (200, 100, 40, 20):  # 5, 10, 25, 50 Hz
        rate = amplitude * (np.sin(4 * np.pi / period) - np.sin(2 * np.pi / period)) / dt
        rate = abs(rate)
        expected = sum(2 * w * (r + beta * rate) for r, w in zip(radii, weights, strict=True))
        width = _zero_crossing_widths(h, amplitude, period)
        assert width == pytest.approx(expected, rel=1e-12)
        assert h.loop_width(amplitude, rate) == pytest.approx(expected, rel=1e-12)
        widths.append(width)
    assert np.all(np.diff(widths) > 0)
    # Quasi-static limit: the rate-independent Prandtl-Ishlinskii loop 2 sum w_i r_i.
    static = RateDependentPrandtlIshlinskii(
        linear_weight=0.8, radii=radii, weights=weights, rate_time=0.0, dt=dt
    )
    assert _zero_crossing_widths(static, amplitude, 200) == pytest.approx(2.4, rel=1e-12)


def test_default_rate_dependence_widens_the_full_stroke_loop_1_5x_at_50_hz():
    h = RateDependentPrandtlIshlinskii.for_voltage(30.0)
    quasi_static = h.loop_width(30.0, 0.0)
    assert quasi_static / 60.0 == pytest.approx(0.12, rel=1e-12)  # 12 % of peak to peak
    assert h.loop_width(30.0, 2 * np.pi * 50 * 30.0) / quasi_static == pytest.approx(1.5, 1e-3)


def test_sampled_full_stroke_loop_at_50_hz_approaches_the_closed_form_as_dt_shrinks():
    """The default map's widest play reaches A - r_i at a full-stroke 50 Hz sine, where the
    closed form assumes the rate is zero at the reversal; sampled, the previous sample's rate
    is not, and the loop is narrower: 1.33x the quasi-static loop at 1 ms, 1.49x at 0.1 ms
    (RATE_TIME), tending to 1.5x."""
    ratios = []
    for dt in (1e-3, 2.5e-4, 1e-4):
        h = RateDependentPrandtlIshlinskii.for_voltage(30.0, dt=dt)
        period = round(0.02 / dt)
        ratios.append(_zero_crossing_widths(h, 30.0, period) / h.loop_width(30.0, 0.0))
    assert ratios[0] == pytest.approx(1.33, abs=0.005)
    assert ratios[-1] == pytest.approx(1.49, abs=0.005)
    assert np.all(np.diff(ratios) > 0)


def test_rate_dependent_map_is_increasing_and_inverts():
    h = RateDependentPrandtlIshlinskii.for_voltage(30.0)
    rng = np.random.default_rng(3)
    state = h.initial_state(0.0)
    for u in rng.uniform(-30, 30, 40):
        state, _ = h.step(state, u)
        grid = np.linspace(-30, 30, 201)
        rows = np.broadcast_to(state, (grid.size, state.size))
        assert np.all(np.diff(h.step(rows, grid)[1]) > 0)
        target = float(h.step(state, 7.0)[1])
        assert h.inverse(target, state, (-30, 30)).u == pytest.approx(7.0, abs=1e-9)


def test_rate_dependent_output_holds_when_the_input_is_held():
    """A ramp that stops: while the input is held u_eff keeps its last value (the plays keep
    their rate-dependent lag), and the lag closes when the input next rises, not before."""
    h = RateDependentPrandtlIshlinskii.for_voltage(30.0)
    state = h.initial_state(0.0)
    for u in np.linspace(0.0, 15.0, 16):
        state, last = h.step(state, u)
    held = []
    for _ in range(5):
        state, u_eff = h.step(state, 15.0)
        held.append(float(u_eff))
    assert held == [float(last)] * 5
    # The lag left by the ramp: each play trails by its radius plus beta times the ramp rate.
    lag = 15.0 - state[2:]
    np.testing.assert_allclose(lag[:2], np.array(h.radii[:2]) + h.rate_time * 1.0 / h.dt)
    # Rising again closes it (rate 0 over the held sample): the plays sit at u - r_i.
    state, _ = h.step(state, 15.5)
    np.testing.assert_allclose(state[2:4], 15.5 - np.array(h.radii[:2]))


def test_rate_dependent_fast_paths_agree():
    """step (batch), step_inplace and casadi_step give the same outputs on a drive with ramps,
    holds and reversals."""
    import casadi

    h = RateDependentPrandtlIshlinskii.for_voltage(30.0)
    rng = np.random.default_rng(5)
    drive = np.repeat(rng.uniform(-30, 30, 60), rng.integers(1, 4, 60))
    u_sym, s_sym = casadi.MX.sym("u"), casadi.MX.sym("s", h.state_size)
    fun = casadi.Function("f", [u_sym, s_sym], list(h.casadi_step(u_sym, s_sym)))
    state, fast, sym = h.initial_state(0.0), h.initial_state(0.0), h.initial_state(0.0)
    for u in drive:
        state, u_eff = h.step(state, u)
        assert h.step_inplace(fast, float(u)) == pytest.approx(float(u_eff), abs=1e-12)
        z, sym = fun(u, sym)
        sym = np.asarray(sym).ravel()
        assert float(z) == pytest.approx(float(u_eff), abs=1e-12)
        np.testing.assert_allclose(fast, state, atol=1e-12)
        np.testing.assert_allclose(sym, state, atol=1e-12)


def test_rate_dependent_inverse_reports_a_target_inside_a_catch_up_jump():
    h = RateDependentPrandtlIshlinskii.for_voltage(30.0)
    state = h.initial_state(0.0)
    for u in [*np.linspace(0.0, 15.0, 16), 15.0, 15.0]:
        state, _ = h.step(state, u)
    rows = np.broadcast_to(state, (2, state.size))
    below, above = h.step(rows, np.array([15.0, np.nextafter(15.0, 16.0)]))[1]
    assert above - below > 0.1  # the plays' lag closes at once
    result = h.inverse(0.5 * (below + above), state, (-30.0, 30.0))
    assert result.status == "out-of-range" and result.u == pytest.approx(15.0, abs=1e-9)
    reachable = h.inverse(above + 0.2, state, (-30.0, 30.0))
    assert reachable.status == "ok" and reachable.z == pytest.approx(above + 0.2, abs=1e-9)


def test_rate_dependent_bound_holds_at_any_rate():
    h = RateDependentPrandtlIshlinskii.for_voltage(30.0, rate_time=5e-3)
    bound = h.max_effective_voltage(30.0)
    assert bound == PrandtlIshlinskii.for_voltage(30.0).max_effective_voltage(30.0)
    rng = np.random.default_rng(0)
    state = h.initial_state(0.0)
    peak = 0.0
    for u in rng.choice([-30.0, 30.0, 0.0], 3000):
        state, u_eff = h.step(state, u)
        peak = max(peak, abs(float(u_eff)))
    assert peak <= bound


# -- every option on --------------------------------------------------------------------------

ALL_ON = dict(
    amplifier=Amplifier(current_limit_mA=100.0, bandwidth_Hz=2000.0),
    sensor=Sensor(delay=2, bandwidth_Hz=2000.0),
    drift=Drift(piezo_coefficient=(0.9, 1.2), stiffness=(1.2, 0.8), duration=1.0),
    hysteresis="rate-dependent",
    noise_bound=1.0,
)


@pytest.mark.parametrize("period", [2, 6, 7, 40])
def test_observation_bound_holds_under_bang_bang_with_every_option_on(period):
    env = PiezoBenderEnv(**ALL_ON)
    obs, _ = env.reset(seed=1)
    space = env.observation_space
    peak = 0.0
    for t in range(1500):
        u = 30.0 if (t // (period // 2 or 1)) % 2 == 0 else -30.0
        obs, _, _, _, info = env.step(np.array([u]))
        assert space.contains(obs)
        peak = max(peak, abs(info["deflection_um"]))
    assert peak + env.noise_bound <= env.bound
    assert peak > 0.1 * env.model.stroke_um


def test_default_env_keeps_its_path_and_every_option_is_off():
    env = PiezoBenderEnv()
    assert "step" not in vars(env) and env.slew_limit is None
    config = TaskConfig()
    assert config.amplifier is None and config.sensor is None and config.drift is None
    assert not config.bench_options


def test_bench_env_pickles_and_copies_with_its_path():
    env = _env(**ALL_ON)
    for _ in range(5):
        env.step(np.array([10.0]))
    clones = [pickle.loads(pickle.dumps(env)), copy.deepcopy(env)]
    expected = env.step(np.array([-5.0]))
    for clone in clones:
        assert "step" in vars(clone)
        got = clone.step(np.array([-5.0]))
        np.testing.assert_array_equal(got[0], expected[0])
        assert got[4] == expected[4]


def test_options_are_validated():
    with pytest.raises(ValueError, match="amplifier must be"):
        TaskConfig(amplifier="fast")
    with pytest.raises(ValueError, match="current_limit_mA"):
        Amplifier(current_limit_mA=0.0)
    with pytest.raises(ValueError, match="0, 1 or 2"):
        Sensor(delay=3)
    with pytest.raises(ValueError, match="bandwidth_Hz"):
        Sensor(bandwidth_Hz=-1.0)
    with pytest.raises(ValueError, match="drift and randomize"):
        TaskConfig(drift=True, randomize=True)
    with pytest.raises(ValueError, match="unknown hysteresis"):
        TaskConfig(hysteresis="rate")


def test_vector_env_refuses_the_bench_options_and_runs_the_rate_dependent_map():
    with pytest.raises(ValueError, match="single envs"):
        gym.make_vec(
            "piezo_env:PiezoBender-v0",
            num_envs=2,
            vectorization_mode="vector_entry_point",
            amplifier=True,
        )
    vec = gym.make_vec(
        "piezo_env:PiezoBender-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        hysteresis="rate-dependent",
        noise_bound=0.0,
    )
    vec.reset(seed=0)
    single = _env(hysteresis="rate-dependent")
    for i in range(30):
        u = 20 * math.sin(i / 3)
        obs_v, *_ = vec.step(np.full((2, 1), u))
        obs_s, *_ = single.step(np.array([u]))
    np.testing.assert_allclose(obs_v[0], obs_s, rtol=1e-6)


# -- controllers: the amplifier's slew limit --------------------------------------------------


def _closed_loop(name: str, current_ma: float, reference: np.ndarray, **options):
    """Commands, slew flags and true deflections of ``name`` (plant model) on an env whose
    amplifier has ``current_ma``."""
    import controllers as ctl

    env = gym.make(
        "piezo_env:PiezoBender-v0",
        preview=20,
        amplifier=Amplifier(current_limit_mA=current_ma),
        reference=reference,
        max_episode_steps=reference.size - 21,
    )
    controller = ctl.make(name, "plant", env, **options)
    obs, _ = env.reset(seed=0)
    controller.reset(obs)
    commands, limited, deflection = [0.0], [], []
    done = False
    while not done:
        action = controller.act(obs)
        obs, _, terminated, truncated, info = env.step(action)
        commands.append(float(action[0]))
        limited.append(info["slew_limited"])
        deflection.append(info["deflection_um"])
        done = terminated or truncated
    step = env.unwrapped.slew_limit * env.unwrapped.config.dt
    return np.array(commands), np.array(limited), np.array(deflection), step, controller


STEP_REFERENCE = np.r_[np.zeros(30), np.full(300, 600.0)]
SINE_50HZ = 500.0 * np.sin(2 * np.pi * 50.0 * 1e-3 * np.arange(400))


@pytest.mark.parametrize("name", ["mpc", "nmpc"])
@pytest.mark.parametrize("reference", [STEP_REFERENCE, SINE_50HZ], ids=["step", "sine-50Hz"])
def test_mpc_voltages_respect_the_slew_limit(reference, name):
    """30 mA: S dt = 3.66 V per sample, below what both references ask (the 50 Hz sine needs
    4.7 V per sample at its zero crossings): the limit binds, both MPCs plan within it, and the
    amplifier never has to clip its command."""
    u, limited, _, step, mpc = _closed_loop(name, 30.0, reference)
    du = np.abs(np.diff(u))
    assert du.max() <= step
    assert du.max() >= step - 1e-3  # binding
    assert not limited.any()
    assert mpc.describe()["slew_limit_V_per_s"] == pytest.approx(30e-3 / C_PL140)


def _largest_planned_move(name: str):
    """The largest move between successive samples of any plan of ``name`` (plant model) over
    50 steps of a step reference at 30 mA, and the controller."""
    import controllers as ctl

    env = gym.make(
        "piezo_env:PiezoBender-v0",
        preview=20,
        amplifier=Amplifier(current_limit_mA=30.0),
        reference=STEP_REFERENCE[:80],
    )
    controller = ctl.make(name, "plant", env)
    obs, _ = env.reset(seed=0)
    controller.reset(obs)
    worst = 0.0
    for _ in range(50):
        obs, *_ = env.step(controller.act(obs))
        worst = max(worst, float(np.abs(np.diff(controller._plan)).max()))
    return worst, controller


def test_mpc_plans_later_moves_within_the_z_rate():
    worst, mpc = _largest_planned_move("mpc")
    assert worst <= mpc.z_rate * (1 + 1e-3) + 1e-6  # the QP meets the rows to its tolerance
    assert worst >= 0.9 * mpc.z_rate  # and they were active
    assert mpc.stats.status["solved"] > 0


@pytest.mark.parametrize("name", ["pid", "pid-ff"])
def test_pid_voltages_respect_the_slew_limit(name):
    current = 2.0 if name == "pid" else 20.0  # the plain PID moves gently: a tighter limit
    u, limited, _, step, pid = _closed_loop(name, current, STEP_REFERENCE)
    du = np.abs(np.diff(u))
    assert du.max() <= step and du.max() >= step - 1e-3
    assert not limited.any()
    assert pid.stats.status["slew-limited"] > 0


def test_pid_integrator_does_not_wind_up_against_the_slew_limit():
    """Back-calculation on the slew: with it the plain PID overshoots a step far less than with
    a back-calculation gain near zero (the integrator winding up while the voltage slews)."""
    overshoot = {}
    for gain in (1.0, 1e-3):
        *_, y, _, _ = _closed_loop("pid", 2.0, STEP_REFERENCE, antiwindup_gain=gain)
        overshoot[gain] = y.max() - 600.0
    assert overshoot[1.0] < 0.5 * overshoot[1e-3]


def test_nmpc_plans_every_move_within_the_slew_limit():
    """In the voltage the rate rows are exact: every move of every plan, not only the first."""
    worst, nmpc = _largest_planned_move("nmpc")
    step = nmpc.task.slew_step
    assert worst <= step + 1e-9  # DAQP meets the rows to rounding
    assert worst >= 0.99 * step  # and they were active
    assert nmpc.stats.status["solved"] > 0


def test_controllers_without_an_amplifier_keep_their_paths():
    import controllers as ctl
    from controllers.box_qp import BoxQP

    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    mpc = ctl.make("mpc", "plant", env)
    assert mpc.task.slew_limit is None and mpc.task.slew_step is None
    assert isinstance(mpc._qp, BoxQP) and "slew_limit_V_per_s" not in mpc.describe()
    assert "slew_limit_V_per_s" not in ctl.make("nmpc", "plant", env).describe()
    assert ctl.make("pid-ff", "plant", env)._slew_step is None


def test_smallest_slope_matches_the_hysteresis_closed_forms():
    """Bouc-Wen (beta = gamma): the slope just after a major-loop reversal is k (1 - alpha);
    Prandtl-Ishlinskii: the linear weight w_0 (every play inside its band after a reversal)."""
    from controllers.mpc import smallest_slope
    from controllers.prediction import PlantHysteresis
    from piezo_env.hysteresis import BoucWen

    bw = BoucWen.for_voltage(30.0)
    slope = smallest_slope(PlantHysteresis(bw, (-30.0, 30.0)), 0.05)
    assert slope == pytest.approx(bw.k * (1 - bw.alpha), rel=2e-3)
    pi = PrandtlIshlinskii.for_voltage(30.0)
    slope = smallest_slope(PlantHysteresis(pi, (-30.0, 30.0)), 2.0)
    assert slope == pytest.approx(pi.linear_weight, rel=1e-12)


def test_identification_data_record_the_voltage_the_amplifier_applied():
    """With a current-limited amplifier, ``collect`` returns the slew-limited voltage on the
    bender (the amplifier's monitor output), not the command."""
    from identification.experiment import collect

    env = gym.make(
        "piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, amplifier=True
    )
    command = np.where(np.arange(200) % 40 < 20, 30.0, -30.0)
    applied, _ = collect(env, command, seed=0)
    step = env.unwrapped.slew_limit * env.unwrapped.model.dt
    assert np.max(np.abs(np.diff(applied[:-1]))) <= step * (1 + 1e-6)
    assert not np.array_equal(applied, command)
