"""Drift of the piezoelectric coefficient and the stiffness during an episode."""

from __future__ import annotations

import math

import numpy as np
import pytest

from piezo_env.drift import Drift, DriftPlan, drift_deflection_bound_um
from piezo_env.env import PiezoBenderEnv
from piezo_env.memo import ContentCache
from piezo_env.model import PiezoBenderModel
from piezo_env.parameters import cantilever_frequencies


def _run(env: PiezoBenderEnv, voltages) -> np.ndarray:
    env.reset(seed=0)
    return np.array([env.step(np.array([v]))[4]["deflection_um"] for v in voltages])


def test_a_drift_that_does_not_move_is_the_default_plant():
    voltages = 25 * np.sin(np.arange(400) * 0.05) * np.linspace(0.2, 1.2, 400)
    still = Drift(piezo_coefficient=(1.0, 1.0), stiffness=(1.0, 1.0))
    drifting = _run(PiezoBenderEnv(drift=still, noise_bound=0.0), voltages)
    nominal = _run(PiezoBenderEnv(noise_bound=0.0), voltages)
    np.testing.assert_allclose(drifting, nominal, rtol=0, atol=1e-9)


def test_static_gain_follows_piezo_over_stiffness():
    """After the drift, the static tip deflection under a held voltage is the closed form
    Gamma u L^2 / (2 EI) with Gamma and EI scaled by the end factors."""
    drift = Drift(piezo_coefficient=(0.95, 1.1), stiffness=(1.05, 0.9), duration=0.05)
    env = PiezoBenderEnv(drift=drift, hysteresis=None, noise_bound=0.0)
    env.reset(seed=0, options={"initial_voltage": 10.0})
    params = env.model.params
    plan = env.task.drift_plan  # the first segment: the ramp at its midpoint
    start = params.static_tip_deflection(10.0) * 1e6 * plan.piezo[0] / plan.stiffness[0]
    assert plan.piezo[0] == pytest.approx(0.95 + 0.15 * 0.1) and plan.stiffness[0] < 1.05
    assert env.unwrapped._plant.deflection * 1e6 == pytest.approx(start, rel=1e-9)
    for _ in range(3000):
        *_, info = env.step(np.array([10.0]))
    end = params.static_tip_deflection(10.0) * 1e6 * 1.1 / 0.9
    assert info["deflection_um"] == pytest.approx(end, rel=1e-6)


def test_resonance_follows_the_square_root_of_stiffness():
    model = PiezoBenderModel()
    plan = DriftPlan(model, Drift(piezo_coefficient=(1.0, 1.0), stiffness=(1.0, 0.8)))
    n = model.discrete.n_states
    z = np.linalg.eigvals(plan.square_matrices[-1][:n, :n])
    omega = np.abs(np.log(z[np.abs(z.imag) > 0])) / model.dt
    f1 = cantilever_frequencies(model.params)[0] * math.sqrt(0.8)
    assert omega.min() / (2 * math.pi) == pytest.approx(f1, rel=1e-3)


def test_segments_stay_within_the_stated_ramp_error():
    drift = Drift(piezo_coefficient=(1.0, 1.3), stiffness=(1.0, 0.7), segment_steps=25)
    plan = DriftPlan(PiezoBenderModel(), drift)
    dt = 1e-3
    err_g, err_s = drift.ramp_error(dt)
    for j in range(plan.n_segments - 1):
        times = (j * drift.segment_steps + np.arange(drift.segment_steps)) * dt
        g, s = drift.factors(times)
        assert np.abs(g - plan.piezo[j]).max() <= err_g + 1e-15
        assert np.abs(s - plan.stiffness[j]).max() <= err_s + 1e-15
    assert (plan.piezo[-1], plan.stiffness[-1]) == (1.3, 0.7)
    assert err_g == pytest.approx(0.3 * 25 * dt / (2 * drift.duration))


def test_the_drift_bounds_cover_the_time_invariant_worst_case():
    """Without drift both proven switched-plant bounds must not be below the exact L1 bound
    (the attainable worst case of a time-invariant plant), and the time-varying L1 sum must
    reproduce it."""
    model = PiezoBenderModel()
    still = DriftPlan(model, Drift(piezo_coefficient=(1.0, 1.0), stiffness=(1.0, 1.0)))
    nominal = model.deflection_bound_um()
    u_eff = model.hysteresis.max_effective_voltage(model.rated_voltage)
    assert still.energy_bound_m(u_eff) * 1e6 >= nominal
    assert still.l1_bound_m(u_eff) * 1e6 == pytest.approx(nominal, rel=1e-8)
    assert still.l1_bound_m(u_eff) * 1e6 >= nominal * (1 - 1e-12)
    assert drift_deflection_bound_um(model, still) == pytest.approx(nominal, rel=1e-8)


@pytest.mark.parametrize(
    "drift",
    [
        Drift(piezo_coefficient=(1.0, 1.05), stiffness=(1.0, 0.95)),
        Drift(piezo_coefficient=(0.8, 1.25), stiffness=(0.6, 1.6), duration=0.5),
        Drift(piezo_coefficient=(1.25, 0.8), stiffness=(1.6, 0.6), duration=0.5),
    ],
)
def test_the_drift_bound_holds_under_worst_case_drives(drift):
    """The frozen end plant's worst-case drive (the sign of its reversed impulse response)
    and a drive that chases the drifting resonance stay inside the proven bound."""
    env = PiezoBenderEnv(drift=drift, hysteresis=None, noise_bound=0.0)
    model = env.model
    bound = drift_deflection_bound_um(model, env.task.drift_plan)
    plan = env.task.drift_plan
    n = model.discrete.n_states
    a, b = plan.square_matrices[-1][:n, :n], plan.square_matrices[-1][:n, n]
    c = model.discrete.output_matrix[0]
    h = np.empty(1500)
    x = b.copy()
    for k in range(h.size):
        h[k] = c @ x
        x = a @ x
    steps = int(drift.duration / model.dt) + 200
    worst = np.zeros(steps + h.size)
    worst[steps:] = 30.0 * np.sign(h[::-1])
    peak = np.abs(_run(env, worst)).max()
    assert peak <= bound
    assert peak >= 0.5 * np.abs(h).sum() * 30.0 * 1e6  # the drive is near-worst for this plant
    f = cantilever_frequencies(model.params)[0]
    phase = np.cumsum(
        2 * np.pi * f * np.sqrt(drift.factors(np.arange(steps) * model.dt)[1]) * model.dt
    )
    chase = 30.0 * np.sign(np.sin(phase))
    assert np.abs(_run(env, chase)).max() <= bound


def test_reset_starts_the_drift_again():
    env = PiezoBenderEnv(drift=Drift(duration=0.05), noise_bound=0.0)
    first = _run(env, np.full(120, 12.0))
    second = _run(env, np.full(120, 12.0))
    np.testing.assert_array_equal(first, second)


def test_drift_is_validated():
    with pytest.raises(ValueError, match="piezo_coefficient"):
        Drift(piezo_coefficient=(1.0, 3.0))
    with pytest.raises(ValueError, match="stiffness must be a pair"):
        Drift(stiffness=1.0)
    with pytest.raises(ValueError, match="duration"):
        Drift(duration=0.0)
    with pytest.raises(ValueError, match="segment_steps"):
        Drift(segment_steps=0)


def _kept(task, env):
    """The bound the process keeps for ``env``'s settings (fails if none is kept)."""
    parts = task._drift_parts(env.config)
    return task._drift_bounds.get(parts, lambda: pytest.fail("no bound kept for the settings"))


def test_the_drift_bound_is_computed_once_per_setting_and_kept_apart_per_setting(monkeypatch):
    """A second env with the same settings reuses the proven bound; another drift or damping
    computes its own, equal to the bound computed afresh."""
    import piezo_env.task as task

    calls = []
    real = task.drift_deflection_bound_um

    def counted(model, plan):
        calls.append(plan)
        return real(model, plan)

    monkeypatch.setattr(task, "drift_deflection_bound_um", counted)
    monkeypatch.setattr(task, "_drift_bounds", ContentCache(task.DRIFT_BOUNDS_KEPT))
    first = PiezoBenderEnv(drift=Drift(), dt=1e-3)
    again = PiezoBenderEnv(drift=Drift(), dt=1e-3)
    assert len(calls) == 1 and again.task.bound == first.task.bound
    for other in (
        {"drift": Drift(stiffness=(1.0, 0.8)), "dt": 1e-3},
        {"drift": Drift(), "dt": 1e-3, "damping_ratio": 0.03},
    ):
        env = PiezoBenderEnv(**other)
        fresh = drift_deflection_bound_um(env.task.model, env.task.drift_plan)
        assert _kept(task, env) == fresh
    assert len(calls) == 3


def test_a_drifting_plant_with_creep_given_as_lists_is_built_and_its_bound_kept():
    """Creep's settings become tuples (values, not objects that could change), so a drifting
    env with creep given as lists builds, and its bound is kept like any other."""
    from piezo_env.discrete import Creep

    creep = Creep(time_constants=[0.01, 0.1], weights=np.array([0.015, 0.015]))
    assert creep.time_constants == (0.01, 0.1) and creep.weights == (0.015, 0.015)
    env = PiezoBenderEnv(drift=True, creep=creep, dt=1e-3)
    fresh = drift_deflection_bound_um(env.task.model, env.task.drift_plan)
    import piezo_env.task as task

    assert _kept(task, env) == fresh
    with pytest.raises(ValueError, match="sequence of numbers"):
        Creep(time_constants=[0.01, "slow"], weights=[0.015, 0.015])
