"""The NMPC's compiled iteration (:mod:`controllers.native.nmpc_step`) against its numpy path:
closed-loop episodes on the benchmark's references, the linearization against the structured
horizon's, the work per step counted in compiled calls, and the record of the fallback."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from recorded import recorded_episode

import controllers
from benchmarks.references import make_reference
from controllers.native import nmpc_step
from controllers.native.codegen import NativeCodeError
from controllers.native.nmpc_horizon import StructuredHorizon
from piezo_env.amplifier import Amplifier

MODEL_DIR = "docs/identify/model"
STEPS = 1500


@pytest.fixture(scope="module")
def env():
    environment = gym.make("piezo_env:PiezoBender-v0", preview=20)
    yield environment
    environment.close()


def build(env, *, compiled, **options):
    if not compiled:
        with pytest.MonkeyPatch.context() as patch:
            off = nmpc_step.unavailable("switched off by the test")
            patch.setattr(nmpc_step, "compile_kernel", lambda partials: (None, off))
            c = controllers.make("nmpc", MODEL_DIR, env, **options)
        assert c._kernel is None
        return c
    c = controllers.make("nmpc", MODEL_DIR, env, **options)
    if c._kernel is None:
        pytest.skip(f"no compiled iteration on this machine: {c._kernel_build}")
    return c


def episode(controller, env, reference):
    """Volts, and after each step the plan's first move and the memory state (doubles)."""
    return recorded_episode(
        controller, env, reference, STEPS, lambda c: np.r_[c._plan[0], c._memory]
    )


@pytest.mark.parametrize("reference_name", ["sine-50Hz", "steps", "random-steps"])
def test_compiled_iteration_equals_the_numpy_path_in_closed_loop(env, reference_name):
    """The same float32 volts. The doubles inside differ in their last bits only (summation
    order, Cholesky against LU, the chain rule against casadi's forward sweep, casadi's memory
    step against numpy's: :mod:`controllers.native.nmpc_step`). Measured: volts bitwise equal
    on all three; plan's first move at most 2.0e-12 V apart, memory 1.3e-13 V."""
    reference = make_reference(reference_name, STEPS + 21, dt=1e-3, seed=0)
    compiled = episode(build(env, compiled=True), env, reference)
    numpy_path = episode(build(env, compiled=False), env, reference)
    np.testing.assert_array_max_ulp(compiled[0], numpy_path[0], maxulp=1)
    assert np.mean(compiled[0] == numpy_path[0]) > 0.999
    np.testing.assert_allclose(compiled[1], numpy_path[1], rtol=0.0, atol=1e-10)
    for key in ("status", "fallbacks", "saturated", "observer_fallback_step"):
        assert compiled[2][key] == numpy_path[2][key], key
    if reference_name != "sine-50Hz":
        assert compiled[2]["status"].get("solved", 0) > 0  # the QP path ran


@pytest.fixture(scope="module")
def slewing():
    """An amplifier whose current limit binds (77 mA): a slew limit of 9.39 V per sample."""
    environment = gym.make("piezo_env:PiezoBender-v0", preview=20, amplifier=Amplifier(77.0))
    yield environment
    environment.close()


def test_prepare_equals_the_numpy_step_start_under_a_slew_limit(slewing):
    """Targets, offset and the shifted plan made feasible (slew window, rate limit) against
    the numpy path's expressions: the plan exactly (min and max only), the offset to the
    last bits (a dot product)."""
    c = build(slewing, compiled=True)
    kernel, n = c._kernel, c.model.n_states
    assert c.task.slew_step is not None
    rng = np.random.default_rng(5)
    for _ in range(20):
        c._u_prev = float(rng.uniform(-30.0, 30.0))
        c._plan = rng.uniform(-40.0, 40.0, c.settings.horizon)
        observation = rng.uniform(-900.0, 900.0, c.task.observation_size)
        estimate = rng.normal(0.0, 10.0, kernel.estimate.size)
        c._lower[0], c._upper[0] = c._slew_window()
        kernel.observation[:], kernel.estimate[:], kernel.plan[:] = observation, estimate, c._plan
        kernel.scalars[nmpc_step.S_U_PREV] = c._u_prev
        kernel.prepare()
        shifted = c._feasible(np.concatenate((c._plan[1:], c._plan[-1:])))
        np.testing.assert_array_equal(kernel.u, shifted)
        targets = c.task.targets(observation, c.settings.horizon)
        offset = c._phi @ estimate[:n] + (estimate[n] - targets)
        np.testing.assert_allclose(kernel.offset, offset, rtol=1e-13, atol=1e-12)


def test_closed_loop_under_a_slew_limit_until_a_kink(slewing):
    """With the slew limit the plans chatter at the rate bound; a plan with two neighbouring
    voltages equal in one path and 1e-14 V apart in the other sits on the features' kink at
    du = 0, where dz/du jumps (measured at step 183 of this episode: plans 2.5e-11 V apart,
    their Jacobians 0.22 apart), and the paths part there. Before it: the same volts."""
    reference = make_reference("steps", STEPS + 21, dt=1e-3, seed=0)
    compiled = episode(build(slewing, compiled=True), slewing, reference)
    numpy_path = episode(build(slewing, compiled=False), slewing, reference)
    np.testing.assert_array_equal(compiled[0][:150], numpy_path[0][:150])
    step = build(slewing, compiled=True).task.slew_step
    for volts in (compiled[0], numpy_path[0]):
        assert np.all(np.abs(np.diff(volts)) <= step * (1 + 1e-6))
    assert compiled[2]["fallbacks"] == numpy_path[2]["fallbacks"] == 0


def test_linearization_equals_the_structured_horizon(env):
    """z and dz/du of one iteration against the numpy path's (the structured horizon), from a
    memory state inside a loop, along a plan with no repeated voltage; and the QP's Hessian
    and vector against the numpy expressions."""
    c = build(env, compiled=True)
    kernel, horizon = c._kernel, c.horizon
    memory = c.model.nonlinearity.initial_state()
    for v in 20.0 * np.sin(np.linspace(0.0, 7.0, 40)):
        _, memory = c.model.nonlinearity.step(float(v), memory)
    u = np.random.default_rng(2).uniform(-25.0, 25.0, c.settings.horizon)
    offset = np.random.default_rng(3).normal(0.0, 50.0, u.size)
    kernel.u[:], kernel.memory[:], kernel.offset[:] = u, memory, offset
    kernel.scalars[nmpc_step.S_U_PREV] = 1.5
    kernel.iterate()
    z, jac = horizon.linearize(u, memory)
    # Measured: 3.6e-15 (z, up to 30 equivalent V) and 4.4e-16 (dz/du, entries up to 1.3).
    np.testing.assert_allclose(kernel.z, z, rtol=0, atol=2e-14)
    np.testing.assert_allclose(kernel.jac, jac, rtol=0, atol=2e-15)
    assert np.all(np.triu(kernel.jac, 1) == 0.0)
    jac_y = c._gamma @ jac
    constant = offset + c._gamma @ z - jac_y @ u
    w, rate = c.settings.tracking_weight, c.settings.rate_weight
    hessian = w * (jac_y.T @ jac_y) + c._rate_hessian
    q = w * (jac_y.T @ constant)
    q[0] -= rate * 1.5
    np.testing.assert_allclose(kernel.hessian, hessian, rtol=1e-12, atol=0)
    np.testing.assert_allclose(kernel.q, q, rtol=1e-11, atol=1e-9 * np.max(np.abs(q)))


def kernel_calls(controller, env, reference, steps):
    """The compiled kernel's calls in each of ``steps`` closed-loop steps on ``reference``."""
    obs, _ = env.reset(seed=0, options={"reference": reference})
    controller.reset(obs)
    calls = []
    for _ in range(steps):
        before = controller._kernel.calls
        obs, *_ = env.step(controller.act(obs))
        calls.append(controller._kernel.calls - before)
    return calls


def test_an_unconstrained_step_is_three_compiled_calls(env):
    """The targets, offset and shifted plan in one call, every SQP iteration of a step in one
    while the unconstrained optima meet the bounds (all steps of a half-stroke sine), and one
    for the memory step."""
    c = build(env, compiled=True)
    calls = kernel_calls(c, env, make_reference("sine-50Hz", 221, dt=1e-3, seed=0), 200)
    assert c.stats.status["unconstrained"] == 200
    assert calls == [3] * 200


def test_a_step_with_a_qp_makes_one_call_per_iteration_after_it(env):
    """Beyond reach (the drive bound binds): the iterations up to the one that needs the QP
    are one call, each later iteration one more (no early stop here: tolerance 0)."""
    c = build(env, compiled=True, step_tolerance=0.0)
    calls = kernel_calls(c, env, np.r_[np.full(30, -1300.0), np.full(30, 1300.0)], 40)
    assert c.stats.status["solved"] > 0
    # prepare, run (up to the QP), one iterate per later iteration, the memory step
    assert all(3 <= n <= c.settings.sqp_iterations + 2 for n in calls)
    assert max(calls) == c.settings.sqp_iterations + 2


def test_the_numpy_path_is_recorded_and_the_ipopt_reference_keeps_it(env):
    c = build(env, compiled=False)
    record = c.describe()["native"]["nmpc_step"]
    assert record["path"] == "numpy" and not record["compiled"]
    assert record["reason"] == "switched off by the test"
    ipopt = controllers.make("nmpc", MODEL_DIR, env, solver="ipopt", horizon=5)
    assert ipopt._kernel is None
    assert "solver='ipopt'" in ipopt.describe()["native"]["nmpc_step"]["reason"]


def test_native_off_records_the_numpy_path(env, monkeypatch):
    monkeypatch.setenv("PIEZO_NATIVE", "off")
    c = controllers.make("nmpc", MODEL_DIR, env, horizon=5)
    assert c._kernel is None
    native = c.describe()["native"]
    assert "PIEZO_NATIVE=off" in native["nmpc_step"]["reason"]
    # The numpy path's iterations run the horizon's feature recursion, so it was asked for.
    assert native["nmpc_features"]["path"] == "casadi-vm"
    assert "PIEZO_NATIVE=off" in native["nmpc_features"]["reason"]


def test_the_compiled_iteration_leaves_the_feature_recursion_uncompiled(env):
    """The compiled iteration computes the features itself: the unrolled horizon's generated
    C (the largest the NMPC has) is built at its first use, not with the controller, and the
    description says so until then; so is its casadi graph."""
    c = controllers.make("nmpc", MODEL_DIR, env, horizon=5)
    if c._kernel is None:
        pytest.skip(f"no compiled iteration here: {c.describe()['native']['nmpc_step']}")
    described = c.describe()
    assert c.horizon._function is None
    assert "nmpc_features" not in described["native"]
    assert "deferred: generated C built on first use" in described["jacobian"]
    u = np.linspace(-5.0, 5.0, 5)
    state = c.model.nonlinearity.initial_state()
    first_use = c.horizon.evaluate(u, state)  # builds, then evaluates as built
    assert c.describe()["native"]["nmpc_features"]["path"] == "compiled"
    vm = StructuredHorizon(c.model.nonlinearity.nls, 5, compiled=False).evaluate(u, state)
    np.testing.assert_allclose(first_use, vm, rtol=0, atol=1e-13)


def test_a_deferred_horizon_falls_back_visibly_or_raises_at_its_first_use(
    env, monkeypatch, tmp_path
):
    fake = tmp_path / "broken-cc"
    fake.write_text(
        '#!/bin/sh\nif [ "$1" = --version ]; then echo broken 1.0; exit 0; fi\nexit 1\n'
    )
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    monkeypatch.setenv("PIEZO_CACHE", str(tmp_path / "cache"))
    nls = controllers.make("nmpc", MODEL_DIR, env, horizon=5).model.nonlinearity.nls
    u, state = np.zeros(5), np.zeros(nls.n_state)
    horizon = StructuredHorizon(nls, 5, defer=True)
    horizon.evaluate(u, state)
    assert horizon.native[0].path == "casadi-vm" and "compiler failed" in horizon.backend
    monkeypatch.setenv("PIEZO_NATIVE", "require")
    horizon = StructuredHorizon(nls, 5, defer=True)  # nothing is built yet: nothing to raise
    with pytest.raises(NativeCodeError, match="nmpc_features"):
        horizon.evaluate(u, state)


