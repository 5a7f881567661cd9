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
from controllers.nmpc import NonlinearMPC
from piezo_env.amplifier import Amplifier

MODEL_DIR = "docs/identify/model"
STEPS = 1500


@pytest.fixture(scope="module")
def env():
    environment = gym.make("piezo_env:PiezoBender-v0", preview=20)
    yield environment
    environment.close()


def build(env, *, compiled, fused=True, **options):
    if compiled and not fused:  # the compiled iteration between the estimators' Python calls
        with pytest.MonkeyPatch.context() as patch:
            off = nmpc_step.unavailable("switched off by the test", function="nmpc_fused")
            patch.setattr(NonlinearMPC, "_fused_record", lambda self: off)
            c = controllers.make("nmpc", MODEL_DIR, env, **options)
        assert c._kernel is None or not c._kernel.fused
        return c
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


def test_an_unconstrained_step_is_one_compiled_call(env):
    """The estimators' updates, the targets, offset and shifted plan, every SQP iteration of a
    step while the unconstrained optima meet the bounds (all steps of a half-stroke sine) and
    the memory step: one call. Without the fused step, three (the estimators in between)."""
    c = build(env, compiled=True)
    calls = kernel_calls(c, env, make_reference("sine-50Hz", 221, dt=1e-3, seed=0), 200)
    assert c.stats.status["unconstrained"] == 200
    assert calls == [1] * 200
    assert c.describe()["native"]["nmpc_fused"]["compiled"]
    c = build(env, compiled=True, fused=False)
    assert kernel_calls(c, env, make_reference("sine-50Hz", 221, dt=1e-3, seed=0), 200) == [3] * 200
    assert c.describe()["native"]["nmpc_fused"]["reason"] == "switched off by the test"


def test_a_step_with_a_qp_makes_one_call_per_iteration_after_it(env):
    """Beyond reach (the drive bound binds): the step up to the iteration that needs the QP is
    one call, each later iteration one more, and the step's end one (no early stop here:
    tolerance 0); without the fused step, the start and the memory step are calls of their
    own and the iterations up to the QP one more."""
    reference = np.r_[np.full(30, -1300.0), np.full(30, 1300.0)]
    for fused in (True, False):
        c = build(env, compiled=True, fused=fused, step_tolerance=0.0)
        most = c.settings.sqp_iterations + (1 if fused else 2)  # the QP at the first iteration
        calls = kernel_calls(c, env, reference, 40)
        assert c.stats.status["solved"] > 0
        # fused: 1 without a QP, else the step, the later iterations and the end; unfused:
        # prepare, run (up to the QP), one iterate per later iteration, the memory step
        allowed = {1, *range(2, most + 1)} if fused else set(range(3, most + 1))
        assert set(calls) <= allowed
        assert max(calls) == most


@pytest.mark.parametrize(
    "plant, reference_name, variant",
    [
        ("corner", "sine-100Hz", None),
        ("corner", "steps", None),
        ("corner", "sine-50Hz", "no gain"),
        ("nominal", "multisine", "fall back"),
        ("bench", "steps", None),
        ("bench", "sine-50Hz", None),
    ],
)
def test_the_fused_step_equals_the_unfused_one_in_closed_loop(
    env, plant, reference_name, variant
):
    """The whole step in one call against the compiled iteration between the estimators'
    Python calls: the same volts, plans, memory, learned gain, bank state and records (every
    step's QP iterations included) to the bit, on a box corner whose gain the NMPC learns (g
    away from 1: the bank's output estimates rescaled), on the bench plant with the NMPC
    built for its slew limit (the first move's window, the QP's rate rows), without a gain
    estimate (``gain_tolerance=0``), and with the bank's runaway guard made to fall back
    mid-episode (the step it happened recorded alike)."""
    from benchmarks.plants import _bench
    from benchmarks.studies.corners import vertex_env

    home = env
    if plant == "corner":
        target = vertex_env((1.2, 0.8, 0.04))
    elif plant == "bench":
        target = home = gym.make("piezo_env:PiezoBender-v0", preview=20, **_bench("PL140"))
    else:
        target = env
    options = {"gain_tolerance": 0.0} if variant == "no gain" else {}
    steps = 600
    reference = make_reference(reference_name, steps + 21, dt=1e-3, seed=0)
    runs, controllers_ = [], []
    for fused in (True, False):
        c = build(home, compiled=True, fused=fused, **options)
        assert (c.task.slew_step is not None) == (plant == "bench")

        def row(c):
            if variant == "fall back" and len(c.stats.compute_s) == 40:
                c.observer.fall_back()
            state = c.observer._state
            return np.r_[c._plan, c._memory, c._g, c._u_prev, state]

        runs.append(recorded_episode(c, target, reference, steps, row))
        controllers_.append(c)
        assert c._kernel.fused == fused
    if target is not env:
        target.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    for key in ("status", "fallbacks", "saturated", "observer_fallback_step"):
        assert runs[0][2][key] == runs[1][2][key], key
    assert controllers_[0].stats.iterations == controllers_[1].stats.iterations
    gain = runs[0][1][:, controllers_[0].settings.horizon + controllers_[0]._memory.size]
    if variant == "no gain":
        assert np.all(gain == 1.0)
    elif plant == "corner":
        assert np.any(gain != 1.0)  # the bank's output estimates were rescaled
    if variant == "fall back":
        assert runs[0][2]["observer_fallback_step"] == 40
    if reference_name == "steps":
        assert runs[0][2]["status"].get("solved", 0) > 0  # the QP path ran


def test_the_fused_step_refuses_a_non_finite_observation_before_any_update(env):
    """A NaN in the preview: the kernel finds it before the estimators move; the error names
    the entry, as the base class's check does, and the next good observation gives the volts
    of a controller that never saw the bad one."""
    reference = make_reference("sine-10Hz", 221, dt=1e-3, seed=0)
    good, bad = build(env, compiled=True), build(env, compiled=True)
    obs, _ = env.reset(seed=0, options={"reference": reference})
    good.reset(obs)
    bad.reset(obs)
    for _ in range(50):
        u = good.act(obs)
        assert bad.act(obs) == u
        obs, *_ = env.step(u)
    broken = obs.copy()
    broken[5] = np.nan
    with pytest.raises(ValueError, match=r"observation\[5\]"):
        bad.act(broken)
    assert bad.act(obs) == good.act(obs)


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


