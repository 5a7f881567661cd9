"""The linear MPCs' compiled step (:mod:`controllers.native.fused_step`) against their numpy
and Python step: closed-loop episodes on a corner of the datasheet's box (the gain is learned
and the adaptive MPC swaps models), the work per step counted in native calls, and the records
of where the step does not run compiled."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from recorded import recorded_episode

import controllers
from benchmarks.references import make_reference
from benchmarks.studies.corners import vertex_env
from controllers.native import fused_step
from piezo_env.amplifier import Amplifier

MODEL_DIR = "docs/identify/model"


@pytest.fixture(scope="module")
def env():
    return gym.make("piezo_env:PiezoBender-v0", preview=20)


@pytest.fixture(scope="module")
def corner():
    """Gain 20 % up, resonance 20 % low, damping 0.04: the gain estimate moves g, the
    adaptive MPC swaps models, the steps activate the box."""
    return vertex_env((1.2, 0.8, 0.04))


def build(name, env, *, fused, **options):
    if not fused:
        with pytest.MonkeyPatch.context() as patch:
            off = fused_step.unavailable("switched off by the test")
            patch.setattr(fused_step, "compile_step", lambda inverse: (None, off))
            c = controllers.make(name, MODEL_DIR, env, **options)
        assert c._fused is None
        return c
    c = controllers.make(name, MODEL_DIR, env, **options)
    if c._fused is None:
        pytest.skip(f"no compiled step on this machine: {c._fused_build}")
    return c


def episode(controller, plant, reference):
    """Volts, after each step the z applied and the plan's first move (doubles), the stats'
    summary and the controller."""
    return (
        *recorded_episode(
            controller, plant, reference, 1500, lambda c: (c._z_applied, float(c._plan[0]))
        ),
        controller,
    )


@pytest.mark.parametrize("name", ["mpc", "mpc-adaptive"])
@pytest.mark.parametrize("reference_name", ["sine-50Hz", "steps", "random-steps"])
def test_compiled_step_equals_the_numpy_step_in_closed_loop(env, corner, name, reference_name):
    """The same voltages; the doubles inside differ only where the plan's product and the
    gain's rescaling sum in another order than numpy's BLAS (measured: at most 3.1e-12
    equivalent V in z over these episodes with the gain, 2.3e-11 in the first move with the
    adaptive MPC's learned drive, on the QP's samples; the float32 volts were bitwise
    equal)."""
    reference = make_reference(reference_name, 1521, dt=1e-3, seed=0)
    fused = episode(build(name, env, fused=True), corner, reference)
    numpy_step = episode(build(name, env, fused=False), corner, reference)
    np.testing.assert_array_max_ulp(fused[0], numpy_step[0], maxulp=1)
    assert np.mean(fused[0] == numpy_step[0]) > 0.999
    tolerance = 1e-10 if name == "mpc-adaptive" else 1e-11
    np.testing.assert_allclose(fused[1], numpy_step[1], rtol=0.0, atol=tolerance)
    for key in ("status", "inverse", "fallbacks", "saturated", "observer_fallback_step"):
        assert fused[2][key] == numpy_step[2][key], key
    # The same warm starts: a QP starts from the last active set unless the last plan was
    # unconstrained or the last solve failed, in C as in Python.
    assert fused[3].stats.iterations == numpy_step[3].stats.iterations
    if name == "mpc-adaptive":
        assert fused[2]["adaptation"] == numpy_step[2]["adaptation"]
        assert fused[2]["adaptation"].get("swaps", 0) >= 1  # the swap path ran
    if reference_name != "sine-50Hz":
        assert fused[2]["status"].get("solved", 0) > 0  # the QP path ran


@pytest.fixture(scope="module")
def slewing():
    """The nominal bender behind an amplifier whose current limit makes the slew limit bind on
    steps (77 mA: 2.9 V per sample at 1 ms)."""
    return gym.make("piezo_env:PiezoBender-v0", preview=20, amplifier=Amplifier(77.0))


@pytest.mark.parametrize(
    ("name", "reference_name", "plant"),
    [
        ("mpc", "steps", "nominal"),
        ("mpc", "sine-100Hz", "nominal"),
        ("mpc-adaptive", "steps", "nominal"),
        ("mpc-adaptive", "random-steps", "corner"),  # the gain moves, the set swaps models
    ],
)
def test_compiled_step_with_a_slew_limit_equals_the_numpy_step(
    slewing, name, reference_name, plant
):
    """With a slew limit the compiled step takes the first move's z bounds over the slew
    window, tests the plan's rates, gives the QP (DAQP) its rate rows and hands a move that
    leaves the window to Python: the same volts, plans, statuses (QPs, window clips) and warm
    starts as the numpy step's, also where the learned gain changes the rate rows' bound and
    the adaptive MPC swaps models."""
    reference = make_reference(reference_name, 1521, dt=1e-3, seed=0)
    env = slewing if plant == "nominal" else vertex_env((1.2, 0.8, 0.04), amplifier=Amplifier(77.0))
    fused = episode(build(name, slewing, fused=True), env, reference)
    numpy_step = episode(build(name, slewing, fused=False), env, reference)
    np.testing.assert_array_max_ulp(fused[0], numpy_step[0], maxulp=1)
    np.testing.assert_allclose(fused[1], numpy_step[1], rtol=0.0, atol=1e-10)
    for key in ("status", "inverse", "fallbacks", "saturated", "observer_fallback_step"):
        assert fused[2][key] == numpy_step[2][key], key
    assert fused[3].stats.iterations == numpy_step[3].stats.iterations
    assert fused[2]["status"].get("solved", 0) > 0  # the QP with its rate rows ran
    if reference_name != "sine-100Hz":
        assert fused[2]["inverse"].get("slew-window", 0) > 0  # Python clipped a move
    volts = np.r_[0.0, fused[0]]
    step = fused[3].task.slew_step
    assert np.all(np.abs(np.diff(volts)) <= step * (1 + 1e-6))  # the amplifier's limit held
    if plant == "corner":
        assert fused[2]["adaptation"] == numpy_step[2]["adaptation"]
        assert fused[2]["adaptation"].get("swaps", 0) >= 1


def counted(controller, monkeypatch):
    """Count the compiled step's calls and those of the separate kernels it replaces."""
    calls = {"step": 0, "solve": 0, "finish": 0, "separate": 0}
    fused = controller._fused
    for key in ("step", "solve", "finish"):
        original = getattr(fused, key)

        def wrapper(original=original, key=key):
            calls[key] += 1
            return original()

        monkeypatch.setattr(fused, key, wrapper)

    def separate(*args, **kwargs):
        calls["separate"] += 1
        raise AssertionError("a separate kernel ran on the compiled step's path")

    inverse = controller.model.nonlinearity._inverse
    monkeypatch.setattr(inverse._function, "run", separate)
    monkeypatch.setattr(inverse._reachable, "run", separate)
    return calls


@pytest.mark.parametrize("name, selects", [("mpc", 0), ("mpc-adaptive", 1)])
def test_a_step_without_active_constraint_is_one_native_call(env, monkeypatch, name, selects):
    """On the nominal plant and the 50 Hz sine no bound is active: every step is one call of
    the compiled step, none of the compiled inverse's own, and (the adaptive MPC) Python
    selects only on the samples where the set of plausible models may change."""
    controller = build(name, env, fused=True)
    calls = counted(controller, monkeypatch)
    reference = make_reference("sine-50Hz", 521, dt=1e-3, seed=0)
    run = controllers.run_episode(env, controller, seed=0, reference=reference, max_steps=500)
    assert run.controller["stats"]["status"] == {"unconstrained": 500}
    assert calls["step"] == 500 and calls["finish"] == 0 and calls["separate"] == 0
    if selects:
        assert calls["solve"] < 100  # measured: the set changes on a few samples only
    else:
        assert calls["solve"] == 0


def test_a_constrained_step_is_one_native_call_with_the_qp_inside(env, monkeypatch):
    """With DAQP driven from C (the default), a step whose plan leaves the box solves its QP
    inside the same call: no Python QP, no second call. With the QP handed to Python (DAQP's
    Python interface here), it is two calls around the QP."""
    from controllers.native import daqp_box

    if daqp_box.library() is None:
        pytest.skip(f"DAQP is not driven from C here: {daqp_box.build_record()}")
    controller = build("mpc", env, fused=True)
    calls = counted(controller, monkeypatch)
    python_qp = {"solves": 0}
    solve = controller._solve_constrained

    def counted_solve(*args):
        python_qp["solves"] += 1
        return solve(*args)

    monkeypatch.setattr(controller, "_solve_constrained", counted_solve)
    reference = make_reference("steps", 521, dt=1e-3, seed=0)
    run = controllers.run_episode(env, controller, seed=0, reference=reference, max_steps=500)
    solved = run.controller["stats"]["status"].get("solved", 0)
    assert solved > 0 and calls["step"] == 500 and calls["finish"] == 0
    assert python_qp["solves"] == 0
    monkeypatch.setattr(daqp_box, "library", lambda: None)  # QPs set up now use Python
    run = controllers.run_episode(env, controller, seed=0, reference=reference, max_steps=500)
    solved = run.controller["stats"]["status"].get("solved", 0)
    assert solved > 0 and calls["finish"] == python_qp["solves"] == solved


def test_a_non_finite_observation_raises_before_any_state_changes(env):
    controller = build("mpc", env, fused=True)
    observation, _ = env.reset(seed=0)
    controller.reset(observation)
    controller.act(observation)
    state = controller.observer._state.copy(), controller._gain._state.copy()
    bad = observation.copy()
    bad[5] = np.nan
    with pytest.raises(ValueError, match=r"observation\[5\] = nan is not finite"):
        controller.act(bad)
    with pytest.raises(ValueError, match="shape"):
        controller.act(observation[:-1])
    np.testing.assert_array_equal(controller.observer._state, state[0])
    np.testing.assert_array_equal(controller._gain._state, state[1])
    action = controller.act(observation.astype(np.float64))  # float64 takes the same path
    assert action.dtype == np.float32 and action.shape == (1,)


def test_the_step_records_where_it_runs_numpy(env, monkeypatch):
    """Nothing falls back silently: ``describe()["native"]["mpc_step"]`` says which path runs
    the step, and why not the compiled one."""
    compiled = build("mpc", env, fused=True).describe()["native"]["mpc_step"]
    assert compiled["path"] == "compiled" and compiled["sha256"]
    fixed = controllers.make("mpc", MODEL_DIR, env, observer="fixed")
    record = fixed.describe()["native"]["mpc_step"]
    assert record["path"] == "numpy" and "not a bank" in record["reason"]
    amplifier = Amplifier(current_limit_mA=77.0)
    slewing = gym.make("piezo_env:PiezoBender-v0", preview=20, amplifier=amplifier)
    record = controllers.make("mpc", MODEL_DIR, slewing).describe()["native"]["mpc_step"]
    assert record["path"] == "compiled"  # a slew limit runs in the compiled step too
    rate = gym.make("piezo_env:PiezoBender-v0", preview=20, hysteresis="rate-dependent")
    oracle = controllers.make("mpc", "plant", rate).describe()["native"]["mpc_step"]
    assert oracle["path"] == "numpy" and "no compiled inverse" in oracle["reason"]
    monkeypatch.setenv("PIEZO_NATIVE", "off")
    off = controllers.make("mpc", MODEL_DIR, env)
    assert off._fused is None
    assert off.describe()["native"]["mpc_step"]["path"] == "numpy"
