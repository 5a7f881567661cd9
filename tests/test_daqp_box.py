"""DAQP driven from C (:mod:`controllers.native.daqp_box`) against DAQP's own Python interface:
the same solutions to the bit, cold and warm, with and without the slew limit's rows, refusals
and failures included; the layout check; and the record when the wrapper is not used."""

from __future__ import annotations

import ctypes
import gc
import weakref
from importlib.metadata import version

import daqp
import gymnasium as gym
import numpy as np
import pytest

import controllers
from benchmarks.references import make_reference
from controllers.box_qp import DAQPBoxQP
from controllers.native import daqp_box, fused_step

MODEL_DIR = "docs/identify/model"


@pytest.fixture(scope="module")
def wrapper():
    if daqp_box.library() is None:
        pytest.skip(f"DAQP is not driven from C here: {daqp_box.build_record()}")
    return daqp_box.library()


def mpc_shaped(rng, n=20):
    """A dense P of the condensed tracking QP's form (decaying step responses plus a move
    penalty)."""
    responses = np.tril(rng.normal(0.0, 1.0, (n, n)) * np.exp(-0.2 * np.arange(n))[:, None])
    return responses.T @ responses + 1e-2 * (2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1))


@pytest.mark.parametrize("rate, limit", [(None, 15), (0.4, 40)])
def test_the_c_workspace_solves_as_daqps_python_interface_to_the_bit(wrapper, rate, limit):
    """A receding-horizon sequence of QPs (new q and bounds each time, warm from the last
    active set, cold after an unconstrained step or a failure), with crossed bounds and an
    iteration limit that some solves reach (chosen per case so that most solves end before
    it): solutions, multipliers, exit flags and iterations equal."""
    rng = np.random.default_rng(5)
    n = 20
    hessian = mpc_shaped(rng, n)
    lower, upper = np.full(n, -3.0), np.full(n, 3.0)
    native = DAQPBoxQP(lower.copy(), upper.copy(), hessian=hessian, max_iter=limit, rate=rate)
    assert native.native is not None
    rows = np.eye(n - 1, n, 1) - np.eye(n - 1, n) if rate is not None else np.zeros((0, n))
    rate_rows = np.full(n - 1, rate) if rate is not None else np.zeros(0)
    model = daqp.Model()
    high, low = np.r_[upper, rate_rows], np.r_[lower, -rate_rows]
    model.setup(hessian.copy(), np.zeros(n), rows, high, low)
    model.settings = {"iter_limit": limit}
    duals = np.zeros(lower.size + rate_rows.size)
    failed = False
    outcomes = set()
    for k in range(300):
        q = rng.normal(0.0, rng.uniform(0.5, 20.0), n)
        low, high = np.full(n, -3.0), np.full(n, 3.0)
        low[0], high[0] = rng.uniform(-3.0, 0.0), rng.uniform(0.0, 3.0)
        if k % 37 == 5:
            low, high = high.copy() + 1.0, low.copy()  # crossed: DAQP refuses the data
        if k % 11 == 0:
            duals = np.zeros_like(duals)  # as after an unconstrained step
        got = native.solve(q, np.zeros(n), duals, bounds=(low, high))
        data = {"f": q, "blower": np.r_[low, -rate_rows], "bupper": np.r_[high, rate_rows]}
        if not duals.any() or failed:
            data["sense"] = np.zeros(duals.size, dtype=np.intc)
        flag = int(model.update(**data))
        if flag < 0:
            assert got.x is None and got.iterations == 0
            assert got.status == daqp_box_status(flag)
            failed = True
            outcomes.add("refused")
            continue
        x, _, flag, info = model.solve()
        assert got.status == daqp_box_status(int(flag)) and got.iterations == info["iterations"]
        failed = flag <= 0
        if failed:
            assert got.x is None
            outcomes.add("failed")
            continue
        outcomes.add("solved")
        np.testing.assert_array_equal(got.x, np.clip(x, low, high))
        np.testing.assert_array_equal(got.duals, info["lam"])
        duals = got.duals
    assert outcomes == {"refused", "failed", "solved"}


def daqp_box_status(flag):
    from controllers.box_qp import DAQP_STATUS

    return DAQP_STATUS.get(flag, f"exit flag {flag}")


def test_the_layout_check_refuses_a_wrong_layout(wrapper):
    """The check that guards the wrapper: the recorded layout passes; a settings offset that
    is not DAQP's fails, and so does a workspace size too small by one word (DAQP's set-up
    writes into the slack past it), without a crash and without freeing what it did not
    allocate."""
    layout = daqp_box.LAYOUTS[version("daqp")]
    exported = ctypes.CDLL(daqp.__file__)
    names = daqp_box._FUNCTIONS
    table = (ctypes.c_void_p * len(names))(
        *[ctypes.cast(getattr(exported, name), ctypes.c_void_p).value for name in names]
    )
    check = wrapper.box_qp_layout
    size, offset = layout.workspace, layout.settings_offset
    assert check(table, size, offset) == 1
    assert check(table, size, offset - 8) == 0
    assert check(table, size, offset + 8) == 0
    assert check(table, size - 8, offset) == 0  # DAQP writes past it: the canary is hit
    assert check(table, offset, offset) == 0  # the slot would lie past the workspace


def test_an_unknown_daqp_version_is_recorded_and_runs_the_python_interface(monkeypatch):
    """Nothing falls back silently: with a DAQP whose layout the wrapper does not know, the QP
    runs through DAQP's Python interface and the MPC's record says so."""
    daqp_box._bound_under.cache_clear()
    monkeypatch.setattr(daqp_box, "version", lambda name: "99.0.0")
    try:
        record = daqp_box.build_record()
        assert record.path == "numpy" and "daqp 99.0.0" in record.reason
        qp = DAQPBoxQP(np.full(3, -1.0), np.ones(3), hessian=np.eye(3), max_iter=10)
        assert qp.native is None
        env = gym.make("piezo_env:PiezoBender-v0", preview=20)
        mpc = controllers.make("mpc", MODEL_DIR, env)
        described = mpc.describe()["native"]["daqp_box_qp"]
        assert described["path"] == "numpy" and "99.0.0" in described["reason"]
    finally:
        monkeypatch.undo()
        daqp_box._bound_under.cache_clear()


def test_a_workspace_cannot_be_copied(wrapper):
    qp = DAQPBoxQP(np.full(3, -1.0), np.ones(3), hessian=np.eye(3), max_iter=10)
    import copy
    import pickle

    with pytest.raises(TypeError, match="cannot be copied"):
        copy.deepcopy(qp.native)
    with pytest.raises(TypeError, match="cannot be copied"):
        pickle.dumps(qp.native)


@pytest.mark.parametrize("max_iter", [1000, 3])
def test_the_compiled_step_solves_the_qp_as_python_does(wrapper, monkeypatch, max_iter):
    """``mpc`` with the QP inside the compiled step against the same step handing the QP to
    Python (``NEED_QP``), on steps that activate the box; with an iteration limit of 3 some
    solves fail and both take the shifted plan. Volts and plans equal to rounding, counts
    equal."""
    env = gym.make("piezo_env:PiezoBender-v0", preview=20, max_episode_steps=800)
    reference = make_reference("random-steps", 821, dt=1e-3, seed=3)

    def run(in_c):
        c = controllers.make("mpc", MODEL_DIR, env, max_iter=max_iter)
        if c._fused is None:
            pytest.skip(f"no compiled step here: {c._fused_build}")
        if not in_c:
            with monkeypatch.context() as patch:
                bind = fused_step.FusedStep.bind_qp
                patch.setattr(fused_step.FusedStep, "bind_qp", lambda self, qp: bind(self, None))
                return trace(c, env, reference)
        return trace(c, env, reference)

    in_c, in_python = run(True), run(False)
    # The compiled step sums q = G stacked left to right, numpy's BLAS in its own order: the
    # plans may differ in their last bits (measured: 2.8e-12 equivalent V), the volts by
    # rounding to float32 at most.
    np.testing.assert_array_max_ulp(in_c[0].astype(np.float32), in_python[0].astype(np.float32), 1)
    assert np.mean(in_c[0] == in_python[0]) > 0.99
    np.testing.assert_allclose(in_c[1], in_python[1], rtol=0.0, atol=1e-10)
    assert in_c[2] == in_python[2]
    assert in_c[2]["solved"] > 0
    if max_iter == 3:
        assert in_c[3] > 0  # failures took the shifted plan
    assert in_c[3] == in_python[3]
    # The iterations show the warm starts: each QP starts from the last active set unless the
    # last plan was unconstrained or the last solve failed (a cold start takes as many
    # iterations as active bounds).
    assert in_c[4] == in_python[4]


def trace(controller, env, reference):
    volts, plans = [], []
    act = controller.act

    def recorded(observation):
        action = act(observation)
        volts.append(float(action[0]))
        plans.append(controller._plan.copy())
        return action

    controller.act = recorded
    controllers.run_episode(env, controller, seed=0, reference=reference, max_steps=800)
    stats = controller.stats
    return np.array(volts), np.array(plans), dict(stats.status), stats.fallbacks, stats.iterations


def test_the_step_points_at_the_live_workspace_across_episodes_and_swaps(wrapper):
    """The compiled step's table holds the QP workspace in use after every reset and every
    swap of the adaptive MPC's member (whose workspaces are set up afresh each episode), and
    the workspaces of earlier episodes are freed."""
    from benchmarks.studies.corners import vertex_env

    plant = vertex_env((1.2, 0.8, 0.04))  # the adaptive MPC swaps members here
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    c = controllers.make("mpc-adaptive", MODEL_DIR, env)
    if c._fused is None:
        pytest.skip(f"no compiled step here: {c._fused_build}")
    reference = make_reference("steps", 621, dt=1e-3, seed=0)
    handles = []
    swapped = []
    use = c._use

    def checked_use(index):
        use(index)
        assert c._fused.table[fused_step.P_QP] == c._qp.native.handle
        swapped.append(index)

    c._use = checked_use
    for seed in range(3):
        controllers.run_episode(plant, c, seed=seed, reference=reference, max_steps=600)
        gc.collect()
        assert c._fused.table[fused_step.P_QP] == c._qp.native.handle
        handles.append([weakref.ref(m.qp.native) for m in c._members])
    assert len(swapped) > 3  # resets and swaps
    # Each episode set up its own workspaces; the first episode's are gone (freed).
    assert all(ref() is None for ref in handles[0])
    assert all(ref() is not None for ref in handles[2])


def test_piezo_native_off_switches_the_wrapper_off(monkeypatch):
    """``PIEZO_NATIVE=off`` compiles nothing: QPs set up under it run DAQP's Python interface
    (whatever ran before in the process), and the record says why."""
    monkeypatch.setenv("PIEZO_NATIVE", "off")
    record = daqp_box.build_record()
    assert record.path == "numpy" and "PIEZO_NATIVE=off" in record.reason
    assert DAQPBoxQP(np.full(3, -1.0), np.ones(3), hessian=np.eye(3), max_iter=10).native is None
