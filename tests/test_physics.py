"""The bender physics against closed-form results and independent computations."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

from piezo_env import CATALOGUE, PiezoBenderModel, bender_parameters
from piezo_env.discrete import Creep, discretize
from piezo_env.fem import assemble_beam
from piezo_env.hysteresis import BoucWen, PrandtlIshlinskii
from piezo_env.parameters import CANTILEVER_BETA_L, cantilever_frequencies

BENDERS = sorted(CATALOGUE)


@pytest.mark.parametrize("name", BENDERS)
@pytest.mark.parametrize("n_elements", [1, 3, 10])
def test_static_tip_deflection_matches_datasheet(name, n_elements):
    params = bender_parameters(name)
    beam = assemble_beam(params, n_elements)
    w_tip = beam.static_deflection(params.rated_voltage)[-2]
    # Exact for any n (Hermite elements carry a uniform moment exactly): only rounding remains.
    assert w_tip == pytest.approx(params.datasheet.free_deflection, rel=1e-10)


@pytest.mark.parametrize("name", BENDERS)
def test_blocking_force_matches_datasheet(name):
    params = bender_parameters(name)
    beam = assemble_beam(params, 6)
    k_inv = np.linalg.inv(beam.stiffness)
    e = beam.tip_force_input
    # Tip force that cancels the piezo deflection: e^T K^-1 (b U + e F) = 0.
    force = -(e @ k_inv @ beam.piezo_input) * params.rated_voltage / (e @ k_inv @ e)
    assert abs(force) == pytest.approx(params.datasheet.blocking_force, rel=1e-10)
    assert params.blocking_force(params.rated_voltage) == pytest.approx(
        params.datasheet.blocking_force
    )


@pytest.mark.parametrize("name", BENDERS)
def test_fe_frequencies_converge_to_cantilever_from_above(name):
    params = bender_parameters(name)
    analytic = np.array(cantilever_frequencies(params, 3))
    errors = []
    for n in (3, 4, 6, 8, 12):
        fe = assemble_beam(params, n).frequencies[:3]
        assert np.all(fe >= analytic * (1 - 1e-12)), (
            "FE frequencies must bound the continuum from above"
        )
        errors.append(fe / analytic - 1)
        if n >= 8:
            assert np.all(fe / analytic - 1 < 1e-3)
    assert np.all(np.diff(np.array(errors), axis=0) <= 1e-15), "errors must shrink with refinement"


@pytest.mark.parametrize("name", BENDERS)
def test_calibrated_first_mode_is_datasheet_resonance(name):
    model = PiezoBenderModel(name)
    # The density calibrates the continuum mode; 10 elements are within 1e-6 of it.
    assert model.beam.frequencies[0] == pytest.approx(model.params.datasheet.resonance, rel=1e-5)
    assert model.params.density_source.startswith("calibrated")


def test_nominal_density_gives_the_design_figure():
    params = bender_parameters("PL140", density="nominal")
    assert cantilever_frequencies(params, 1)[0] == pytest.approx(166.0, abs=1.0)


def test_mode_shape_matches_analytic_cantilever():
    params = bender_parameters("PL140")
    beam = assemble_beam(params, 12)
    x = beam.node_positions / params.length
    for k, bl in enumerate(CANTILEVER_BETA_L[:3]):
        sigma = (np.cosh(bl) + np.cos(bl)) / (np.sinh(bl) + np.sin(bl))
        phi = np.cosh(bl * x) - np.cos(bl * x) - sigma * (np.sinh(bl * x) - np.sin(bl * x))
        np.testing.assert_allclose(beam.mode_shape(k), phi / phi[-1], atol=2e-3)


def _physical_discretization(beam, dt):
    """Independent ZOH of the full physical-coordinate model [q, q'] (no modal step)."""
    n = beam.n_dofs
    m_inv = np.linalg.inv(beam.mass)
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-m_inv @ beam.stiffness, -m_inv @ beam.damping]])
    b = np.concatenate([np.zeros(n), m_inv @ beam.piezo_input])
    aug = np.zeros((2 * n + 1, 2 * n + 1))
    aug[: 2 * n, : 2 * n] = a
    aug[: 2 * n, -1] = b
    e = scipy.linalg.expm(aug * dt)
    return e[: 2 * n, : 2 * n], e[: 2 * n, -1]


@pytest.mark.parametrize("damping", ["rayleigh", "modal"])
def test_reduced_discrete_model_equals_full_physical_model(damping):
    params = bender_parameters("PL140")
    beam = assemble_beam(params, 6, damping=damping)
    dt = 1e-3
    reduced = discretize(beam, dt)
    ad, bd = _physical_discretization(beam, dt)
    u = np.random.default_rng(0).uniform(-30, 30, 400)
    x = np.zeros(2 * beam.n_dofs // 1)
    y_full = np.empty(len(u))
    for i, ui in enumerate(u):
        x = ad @ x + bd * ui
        y_full[i] = x[beam.n_dofs - 2]
    y_red = reduced.simulate(u)
    # The stiff physical-coordinate exponential carries its own ~1e-8 relative rounding.
    np.testing.assert_allclose(y_red, y_full, rtol=0, atol=1e-7 * np.abs(y_full).max())
    if damping == "rayleigh":
        assert reduced.n_states < 2 * beam.n_dofs


def test_step_is_exact_across_sample_times():
    coarse = PiezoBenderModel(hysteresis=None, dt=1e-3)
    fine = PiezoBenderModel(hysteresis=None, dt=1e-4)
    y_coarse = coarse.simulate(np.full(200, 20.0)).deflection_um
    y_fine = fine.simulate(np.full(2000, 20.0)).deflection_um
    np.testing.assert_allclose(y_coarse, y_fine[9::10], rtol=0, atol=1e-7 * np.abs(y_fine).max())


def test_linear_without_hysteresis():
    model = PiezoBenderModel(hysteresis=None)
    u = np.random.default_rng(1).uniform(-10, 10, 500)
    y1 = model.simulate(u).deflection_um
    y2 = model.simulate(2 * u).deflection_um
    np.testing.assert_allclose(y2, 2 * y1, rtol=1e-12, atol=1e-9)


def test_deflection_bound_is_tight_and_never_exceeded():
    model = PiezoBenderModel(hysteresis=None)
    u_max = model.rated_voltage
    impulse = model.discrete.simulate(np.r_[1.0, np.zeros(5999)])
    worst = u_max * np.sign(impulse[::-1])  # the input that maximises y at the last sample
    y = model.simulate(worst).deflection_um
    bound = model.deflection_bound_um()
    assert np.abs(y).max() <= bound
    assert abs(y[-1]) >= 0.99 * bound


def _loop_width(model, cycles=3):
    n = round(cycles / model.dt)
    t = np.arange(n) * model.dt
    u = model.rated_voltage * np.sin(2 * np.pi * 1.0 * t)
    y = model.simulate(u).deflection_um
    last = slice(n - round(1 / model.dt), n)
    u_c, y_c = u[last], y[last]
    rising = np.gradient(u_c) > 0
    grid = np.linspace(-0.9, 0.9, 37) * model.rated_voltage
    up = np.interp(grid, *_sorted(u_c[rising], y_c[rising]))
    down = np.interp(grid, *_sorted(u_c[~rising], y_c[~rising]))
    return np.max(np.abs(down - up)) / (y_c.max() - y_c.min()), y_c.max()


def _sorted(x, y):
    order = np.argsort(x)
    return x[order], y[order]


@pytest.mark.parametrize("hysteresis", ["bouc-wen", "prandtl-ishlinskii"])
@pytest.mark.parametrize("name", ["PL140", "PL122"])
def test_hysteresis_loop_width_and_full_stroke(hysteresis, name):
    model = PiezoBenderModel(name, hysteresis=hysteresis)
    width, peak = _loop_width(model)
    assert 0.08 <= width <= 0.16
    assert peak == pytest.approx(model.stroke_um, rel=0.03)


@pytest.mark.parametrize("hysteresis", ["bouc-wen", "prandtl-ishlinskii"])
def test_hysteresis_loop_closes_on_periodic_input(hysteresis):
    hyst = PiezoBenderModel(hysteresis=hysteresis).hysteresis
    cycles = 8
    u = np.tile(25 * np.sin(2 * np.pi * np.arange(200) / 200), cycles)
    state = hyst.initial_state(0.0)
    out = []
    for v in u:
        state, u_eff = hyst.step(state, float(v))
        out.append(float(u_eff))
    gaps = np.abs(np.diff(np.array(out).reshape(cycles, 200), axis=0)).max(axis=1)
    # Play operators close after one cycle; Bouc-Wen converges geometrically to its limit cycle.
    assert gaps[-1] < 1e-4
    assert np.all(np.diff(gaps) <= 1e-12)


@pytest.mark.parametrize(
    "params", [{}, {"beta": 0.03, "gamma": 0.01}, {"beta": 0.046, "gamma": 0.0}]
)
def test_bouc_wen_jump_matches_ode_integration(params):
    """Closed-form jumps against dh/du = alpha k - beta sign(du) h - gamma |h| (solve_ivp)."""
    bw = BoucWen(**params)
    state = bw.initial_state(0.0)
    for target in np.random.default_rng(2).uniform(-30, 30, 25):
        u0, h0 = float(state[0]), float(state[1])
        s = 1.0 if target > u0 else -1.0
        ode = scipy.integrate.solve_ivp(
            lambda u, h, s=s: [bw.alpha * bw.k - bw.beta * s * h[0] - bw.gamma * abs(h[0])],
            (u0, float(target)),
            [h0],
            rtol=1e-11,
            atol=1e-12,
        )
        state, u_eff = bw.step(state, float(target))
        assert float(state[1]) == pytest.approx(ode.y[0, -1], abs=1e-7)
        assert u_eff == pytest.approx(bw.k * target - ode.y[0, -1], abs=1e-7)
        assert abs(state[1]) <= bw.h_max


def test_prandtl_ishlinskii_play_operator():
    pi = PrandtlIshlinskii(linear_weight=1e-3, radii=(2.0,), weights=(1.0,))
    state = pi.initial_state(0.0)
    outputs = []
    inputs = [0.0, 5.0, 3.0, 1.0, -4.0, 0.0]
    for u in inputs:
        state, z = pi.step(state, u)
        outputs.append(float(z) - 1e-3 * u)
    np.testing.assert_allclose(outputs, [0.0, 3.0, 3.0, 3.0, -2.0, -2.0], atol=1e-15)


def test_creep_grows_about_one_to_two_percent_per_decade():
    model = PiezoBenderModel(hysteresis=None, creep=True, dt=1e-2)
    y = model.simulate(np.full(5001, 20.0)).deflection_um
    t = model.dt * np.arange(1, len(y) + 1)
    at = lambda s: y[np.searchsorted(t, s)]  # noqa: E731
    per_decade = (at(50.0) / at(0.5) - 1) / 2  # after the first mode has rung out
    assert 0.01 <= per_decade <= 0.02
    assert Creep().size == 5


def test_parameters_reject_bad_input():
    with pytest.raises(ValueError, match="unknown bender"):
        bender_parameters("PL999")
    with pytest.raises(ValueError, match="density"):
        bender_parameters("PL140", density=-1.0)
    with pytest.raises(ValueError, match="n_elements"):
        assemble_beam(bender_parameters("PL140"), 0)
    with pytest.raises(ValueError, match="dt"):
        PiezoBenderModel(dt=0.0)
    with pytest.raises(ValueError, match="hysteresis"):
        PiezoBenderModel(hysteresis="preisach")


def test_undamped_bender_is_rejected_because_it_has_no_deflection_bound():
    with pytest.raises(ValueError, match="damping_ratio"):
        PiezoBenderModel(damping_ratio=0.0)


def test_deflection_bound_covers_creep():
    plain = PiezoBenderModel(hysteresis=None)
    creeping = PiezoBenderModel(hysteresis=None, creep=True)
    u_max = creeping.rated_voltage
    # Charge the creep states for 200 s, then drive the beam's worst-case sequence.
    impulse = plain.discrete.simulate(np.r_[1.0, np.zeros(5999)])
    drive = np.r_[np.full(200_000, u_max), u_max * np.sign(impulse[::-1])]
    peak = np.abs(creeping.simulate(drive).deflection_um).max()
    assert peak > plain.deflection_bound_um()  # creep really adds to the worst case
    assert peak <= creeping.deflection_bound_um()


def _dropped_error_l1(discrete, drop, samples):
    """Exact l1 norm (m / V) of the impulse response of the tip-deflection error that
    carrying the kept modes ``drop`` as their one-step response makes: the error the worst
    input of amplitude 1 V reaches."""
    impulse = np.r_[1.0, np.zeros(samples - 1)]
    difference = discrete.simulate(impulse) - discrete.without_modes(drop).simulate(impulse)
    return float(np.abs(difference).sum())


@pytest.mark.parametrize(("bender", "dt"), [("PL127", 2.5e-4), ("PL140", 1e-3)])
def test_mode_error_bound_is_the_worst_input_error(bender, dt):
    """Without creep the bound is the exact l1 norm of the error's impulse response (to its
    0.1 % tail allowance), checked by simulating the full and the reduced model."""
    discrete = PiezoBenderModel(bender, hysteresis=None, dt=dt, damping_ratio=0.04).discrete
    bounds = discrete.mode_error_bounds()
    high = list(range(2, len(bounds)))
    assert len(high) >= 2
    for i in [0, 1, *high[:3]]:
        exact = _dropped_error_l1(discrete, [i], 20_000)
        assert exact <= bounds[i] <= 1.01 * exact
    together = _dropped_error_l1(discrete, high, 4000)
    assert together <= bounds[high].sum() <= 1.01 * together * len(high)


def test_mode_error_bound_covers_creep():
    """Creep states feed every mode: after a drive that charges them for 10 s and then
    reverses, dropping the high modes errs by no more than their bounds."""
    discrete = PiezoBenderModel(
        "PL127", hysteresis=None, dt=2.5e-4, damping_ratio=0.04, creep=True
    ).discrete
    high = list(range(2, len(discrete.kept_modes)))
    assert len(high) >= 2
    drive = np.r_[np.full(40_000, 1.0), -np.ones(2000)]
    error = discrete.simulate(drive) - discrete.without_modes(high).simulate(drive)
    assert 0.0 < np.abs(error).max() <= discrete.mode_error_bounds()[high].sum()


def test_dropping_modes_equals_discretizing_with_a_larger_tolerance():
    params = bender_parameters("PL127")
    beam = assemble_beam(params, 10, damping_ratio=0.04)
    dt = 2.5e-4
    full = discretize(beam, dt)
    radii = np.array(
        [
            np.abs(np.linalg.eigvals(full.a[2 * i : 2 * i + 2, 2 * i : 2 * i + 2])).max()
            for i in range(len(full.kept_modes))
        ]
    )
    tolerance = float(np.sqrt(np.sort(radii)[2] * np.sort(radii)[3]))  # between two radii
    coarse = discretize(beam, dt, tolerance=tolerance)
    dropped = full.without_modes(np.flatnonzero(radii < tolerance))
    assert 2 < dropped.n_states < full.n_states
    np.testing.assert_array_equal(dropped.kept_modes, coarse.kept_modes)
    scale = np.abs(coarse.step_matrix).max(axis=1, keepdims=True)
    np.testing.assert_allclose(dropped.step_matrix / scale, coarse.step_matrix / scale, atol=1e-14)
    np.testing.assert_allclose(dropped.output_matrix, coarse.output_matrix, rtol=0, atol=0)
