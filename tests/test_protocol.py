"""A controller of the user's own: the protocol, entry points, and the benchmark's rows."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import controllers
from benchmarks.runner import BenchmarkConfig
from piezo_cli.main import main

ROOT = Path(__file__).resolve().parents[1]
MODEL_DIR = str(ROOT / "docs" / "identify" / "model")
EXAMPLE = "examples.feedforward_pi:FeedforwardPI"


class Bare:
    """The protocol and nothing else: no stats, no describe."""

    def __init__(self, model, env, *, gain: float = 0.02) -> None:
        self.gain = gain

    def reset(self, observation):
        pass

    def act(self, observation):
        return np.array([self.gain * float(observation[2])], dtype=np.float32)


class NoAct:
    def __init__(self, model, env) -> None:
        pass

    def reset(self, observation):
        pass


@pytest.fixture(scope="module")
def env():
    return gym.make("piezo_env:PiezoBender-v0", preview=20)


@pytest.fixture(autouse=True)
def _project_folder(monkeypatch):
    monkeypatch.chdir(ROOT)  # entry points import from the current folder, as python -m does


def test_a_bare_protocol_object_runs_an_episode(env):
    controller = controllers.make("test_protocol:Bare", MODEL_DIR, env, gain=0.03)
    t = np.arange(1, 402) * 1e-3
    episode = controllers.run_episode(
        env, controller, seed=0, reference=300 * np.sin(2 * np.pi * 5 * t), max_steps=400
    )
    assert controller.gain == 0.03
    assert episode.compute_s.size == 400 and np.all(episode.compute_s > 0)
    assert episode.metrics["fallbacks"] == 0
    assert np.isfinite(episode.metrics["rmse_percent"])


class Offset(gym.ObservationWrapper):
    """A user's wrapper: the measured deflection read 5 um high."""

    def observation(self, observation):
        return observation + np.array([5.0] + [0.0] * (len(observation) - 1), np.float32)


def test_the_loop_steps_below_makes_wrappers_and_through_a_users():
    """The loop steps the env below ``gymnasium.make``'s pass-through wrappers and counts the
    time limit itself: the record is the one a step through every wrapper gives, bit for bit,
    and a user's wrapper anywhere in the stack is stepped through."""
    made = gym.make("piezo_env:PiezoBender-v0", preview=20, max_episode_steps=120)
    opaque = gym.Wrapper(made)  # no pass-through wrapper on top: every wrapper is stepped
    records = [  # max_steps beyond the time limit: a limit lost would run 500 steps
        controllers.run_episode(env, controllers.make("test_protocol:Bare", MODEL_DIR, made),
                                seed=3, reference=np.full(200, 100.0), max_steps=500)
        for env in (made, opaque)
    ]
    for field in ("deflection_um", "measured_um", "voltage_V", "reward"):
        np.testing.assert_array_equal(getattr(records[0], field), getattr(records[1], field))
    assert len(records[0].voltage_V) == 120
    # Stopped early, the time limit has counted the loop's steps: a step on truncates where
    # the whole stack would.
    controllers.run_episode(made, Bare(None, None), seed=3, max_steps=100)
    flags = [made.step(np.zeros(1, np.float32))[3] for _ in range(20)]
    assert flags == [False] * 19 + [True]
    shifted = gym.wrappers.TimeLimit(Offset(made.unwrapped), 50)
    episode = controllers.run_episode(
        shifted, Bare(None, None), seed=3, reference=np.full(200, 100.0), max_steps=500
    )
    assert len(episode.voltage_V) == 50
    np.testing.assert_allclose(
        episode.measured_um[:50] - 5.0, episode.deflection_um[:50], atol=4.0
    )


class WrongShape(Bare):
    """A controller whose action has the wrong shape from its third step on."""

    name = "wrong-shape"

    def __init__(self) -> None:
        super().__init__(None, None)
        self.calls = 0

    def act(self, observation):
        self.calls += 1
        action = super().act(observation)
        return action if self.calls <= 2 else np.repeat(action, 2)


def test_an_action_the_env_refuses_names_the_controller_and_the_step(env):
    with pytest.raises(ValueError, match=r"the env refused the action of 'wrong-shape' at step 2: "
                       r"action must have shape \(1,\)"):
        controllers.run_episode(env, WrongShape(), seed=0, max_steps=10)


class Scripted(Bare):
    """A controller whose every act takes a scripted time on an injected clock."""

    def __init__(self, clock: list[float], durations: np.ndarray) -> None:
        super().__init__(None, None)
        self.clock, self.durations, self.calls = clock, durations, 0

    def act(self, observation):
        self.clock[0] += self.durations[self.calls]
        self.calls += 1
        return super().act(observation)


def test_deadline_misses_count_the_steps_whose_compute_time_exceeds_dt(env, monkeypatch):
    """The miss accounting on an injected clock, so that the count is exact on any machine
    (a wall-clock count of zero misses would depend on the machine's load)."""
    clock = [0.0]
    monkeypatch.setattr(
        "controllers.episode.time", type("Clock", (), {"perf_counter": lambda: clock[0]})
    )
    dt = float(env.unwrapped.model.dt)
    durations = np.full(400, 0.1 * dt)
    durations[::10] = 2.0 * dt  # 40 misses
    durations[5] = 0.99 * dt  # just within the deadline: not a miss
    episode = controllers.run_episode(
        env, Scripted(clock, durations), seed=0, reference=np.zeros(421), max_steps=400
    )
    np.testing.assert_allclose(episode.compute_s, durations, rtol=1e-12)
    assert episode.metrics["deadline_misses"] == 40
    assert episode.metrics["compute_max_us"] == pytest.approx(2e6 * dt)


def test_the_example_controller_runs_through_make(env):
    controller = controllers.make(EXAMPLE, MODEL_DIR, env)
    # The saved ARX polynomials' static gain, B(1) / (1 - A(1)), read from the file itself.
    arx = json.loads((Path(MODEL_DIR) / "model.json").read_text(encoding="utf-8"))["arx"]
    static_gain = sum(arx["b"]) / (1.0 - sum(arx["a"]))
    assert controller.describe()["dc_gain_um_per_V"] == pytest.approx(static_gain, rel=1e-9)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("no_such_module:Thing", "module 'no_such_module' does not import"),
        ("examples.feedforward_pi:Nope", "has no attribute 'Nope'"),
        ("test_protocol:NoAct", "breaks the controller protocol: no callable act"),
        ("examples.feedforward_pi", "unknown controller"),
        ("a:b:c", "must read 'package.module:factory'"),
    ],
)
def test_broken_entry_points_are_refused_in_one_line(name, message, env):
    with pytest.raises(ValueError, match=message) as raised:
        controllers.make(name, MODEL_DIR, env)
    assert "\n" not in str(raised.value)


def test_an_option_the_factory_does_not_take_is_refused_before_it_is_called(env):
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['kk'\].*valid: ki$") as raised:
        controllers.make(EXAMPLE, MODEL_DIR, env, kk=1)
    assert "\n" not in str(raised.value)
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['kk'\]"):
        BenchmarkConfig(controllers=(EXAMPLE,), controller_options={"FeedforwardPI": {"kk": 1}})
    BenchmarkConfig(controllers=(EXAMPLE,), controller_options={"FeedforwardPI": {"ki": 0.3}})


def test_rows_are_named_after_the_attribute_or_the_label():
    config = BenchmarkConfig(
        controllers=("mpc", EXAMPLE, f"mine={EXAMPLE}"),
        references=("sine-10Hz",),
        plants=("nominal", "damping-0.01"),
        controller_options={"mine": {"ki": 0.3}},
    )
    assert config.rows == ("mpc", "FeedforwardPI", "mine")
    assert config.entry_points == {"FeedforwardPI": EXAMPLE, "mine": EXAMPLE}
    # A user's controller gets the robustness plants too.
    assert ("damping-0.01", "mine", ("sine-10Hz",)) in config.groups()
    with pytest.raises(ValueError, match="distinct names"):
        BenchmarkConfig(controllers=(EXAMPLE, EXAMPLE))
    with pytest.raises(ValueError, match=r"label=package\.module:Factory"):
        BenchmarkConfig(controllers=("mine=mpc",))


def _run(tmp_path, backend: str, jobs: int) -> dict:
    out = tmp_path / f"{backend}-{jobs}"
    argv = [
        "benchmark", "--model", MODEL_DIR, "--policies", "none", "--quiet",
        "--controllers", f"pid,{EXAMPLE},slow={EXAMPLE},test_protocol:Bare",
        "--option", "slow.ki=0.2", "--option", "Bare.gain=0.025",
        "--references", "sine-10Hz", "--plants", "nominal,damping-0.04", "--steps", "150",
        "--backend", backend, "--jobs", str(jobs), "--out", str(out),
    ]
    assert main(argv) == 0
    return json.loads((out / "benchmark.json").read_text())


def test_the_example_runs_through_piezo_benchmark_on_both_backends(tmp_path, ray_connection):
    """The user's controllers (the example, found from the project folder, and one defined in
    this module) give the same episodes in this process and on Ray workers, which import them
    by their entry points. (Spawned local workers import a test module's controller the same
    way: tests/test_faults.py, with the local pool's results bitwise equal to this process's.)"""
    local, on_ray = _run(tmp_path, "local", 1), _run(tmp_path, "ray", 2)
    rows = {e["controller"] for e in local["results"]["episodes"]}
    assert rows == {"pid", "FeedforwardPI", "slow", "Bare"}  # Bare: defined in this module
    assert local["controllers"]["slow"]["ki"] == 0.2
    assert on_ray["results"]["episodes"] == local["results"]["episodes"]


def test_a_broken_entry_point_stops_the_benchmark_before_any_work(tmp_path, monkeypatch, capsys):
    def refuse(*args, **kwargs):
        raise AssertionError("work started before the controllers were checked")

    monkeypatch.setattr("identification.pipeline.identify", refuse)
    monkeypatch.setattr("piezo_parallel.backends.run_tasks", refuse)
    argv = ["benchmark", "--controllers", "mpc,no_such_module:Thing", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "does not import" in err and len(err.splitlines()) == 1
    argv = ["benchmark", "--model", MODEL_DIR, "--policies", "none",
            "--controllers", "mpc,test_protocol:NoAct", "--out", str(tmp_path / "p")]
    assert main(argv) == 2
    assert "breaks the controller protocol" in capsys.readouterr().err


def _model_of(tmp_path, bender: str) -> str:
    """The shipped model's files, relabelled as identified on ``bender``."""
    import dataclasses
    import shutil

    from piezo_env import get_datasheet

    folder = tmp_path / f"model-{bender}"
    shutil.copytree(MODEL_DIR, folder)
    document = json.loads((folder / "model.json").read_text())
    sheet = get_datasheet(bender)
    document.setdefault("metadata", {}).update(
        bender=sheet.name, datasheet=dataclasses.asdict(sheet)
    )
    (folder / "model.json").write_text(json.dumps(document))
    return str(folder)


def test_a_model_of_another_bender_is_refused(tmp_path, env, capsys):
    pl127 = _model_of(tmp_path, "PL127")
    with pytest.raises(ValueError, match=r"identified on PL127\.10 but the env is a PL140\.10"):
        controllers.make("mpc", pl127, env)
    controllers.make("mpc", _model_of(tmp_path, "PL140"), env)  # its own bender is fine
    argv = ["benchmark", "--model", pl127, "--policies", "none", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "identified on PL127.10" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()
