"""The closed-loop benchmark: reproducible for any jobs, metrics by hand, CLI refusals."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.machine import machine
from benchmarks.references import REFERENCES, make_reference
from benchmarks.report import deterministic_json, rewrite_report, tracking_tables, write_benchmark
from benchmarks.runner import BenchmarkConfig, run_benchmark
from controllers.metrics import tracking_metrics
from piezo_cli.main import main

MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "identify" / "model")


def test_metrics_match_hand_computed_values():
    metrics = tracking_metrics(
        deflection_um=np.array([1.0, 2.0, 6.0, -1.0]),
        reference_um=np.array([0.0, 2.0, 3.0, 0.0]),
        voltage_v=np.array([0.0, 30.0, -30.0, 10.0]),
        saturated=np.array([False, True, True, False]),
        compute_s=np.array([1e-6, 2e-6, 3e-6, 4e-6]),
        stroke_um=1000.0,
        fallbacks=2,
    )
    # errors 1, 0, 3, -1: RMSE sqrt(11 / 4); the full stroke is 2000 um.
    assert metrics["rmse_um"] == pytest.approx(np.sqrt(11 / 4))
    assert metrics["rmse_percent"] == pytest.approx(100 * np.sqrt(11 / 4) / 2000)
    assert metrics["max_error_um"] == 3.0
    assert metrics["rms_voltage_v"] == pytest.approx(np.sqrt((900 + 900 + 100) / 4))
    assert metrics["voltage_tv_v"] == pytest.approx(30 + 60 + 40)
    assert metrics["saturated_fraction"] == 0.5
    assert metrics["compute_median_us"] == pytest.approx(2.5)
    assert metrics["fallbacks"] == 2 and metrics["steps"] == 4


def test_metrics_refuse_mismatched_or_empty_input():
    good = dict(
        deflection_um=np.zeros(4),
        reference_um=np.zeros(4),
        voltage_v=np.zeros(4),
        saturated=np.zeros(4, bool),
        compute_s=np.zeros(4),
        stroke_um=1000.0,
    )
    with pytest.raises(ValueError, match="reference_um must be"):
        tracking_metrics(**{**good, "reference_um": np.zeros(1)})
    with pytest.raises(ValueError, match="deflection_um must be"):
        tracking_metrics(**{**good, "deflection_um": np.zeros(0)})
    with pytest.raises(ValueError, match="stroke_um"):
        tracking_metrics(**{**good, "stroke_um": -1.0})
    with pytest.raises(ValueError, match="non-finite"):
        tracking_metrics(**{**good, "voltage_v": np.array([0.0, np.nan, 0.0, 0.0])})


def test_references_are_seeded_named_and_start_at_rest():
    for name, reference in REFERENCES.items():
        a = make_reference(name, 500, dt=1e-3, seed=3)
        b = make_reference(name, 500, dt=1e-3, seed=3)
        np.testing.assert_array_equal(a, b)
        assert a.shape == (500,) and np.all(np.isfinite(a))
        if reference.smooth:
            assert abs(a[0]) < 1e-9, name
    with pytest.raises(ValueError, match="valid: sine-1Hz"):
        make_reference("sine-3Hz", 10, dt=1e-3, seed=0)


def test_small_benchmark_is_bitwise_equal_for_one_and_two_jobs(tmp_path):
    common = dict(
        controllers=("pid-ff", "mpc"),
        references=("sine-10Hz", "steps"),
        plants=("nominal", "damping-0.04"),
        steps=150,
    )
    one = run_benchmark(BenchmarkConfig(**common, jobs=1), MODEL_DIR)
    two = run_benchmark(BenchmarkConfig(**common, jobs=2), MODEL_DIR)
    assert tracking_tables(one) == tracking_tables(two)
    assert json.dumps(deterministic_json(one)) == json.dumps(deterministic_json(two))
    assert len(one.episodes) == 2 * 2 + 2 * 2
    meta = {
        "model": MODEL_DIR,
        "dt": 1e-3,
        "noise_bound_um": 1.0,
        "stroke_um": 1000.0,
        "machine": machine(),
    }
    paths = write_benchmark(one, tmp_path, meta, figures=False)
    text = (tmp_path / "benchmark.md").read_text()
    assert "| mpc |" in text and "damping-0.04" in text and "## Reference checks" in text
    assert text.index("## Verdict") < text.index("## Tracking")
    # The identified model is outside the damping-0.04 plant's class within a few steps, on
    # both references; pid-ff learns no gain and has no column.
    section = text.split("### Is the plant in the model class?")[1].split("##")[0]
    assert "| plant | mpc |" in section and "| damping-0.04 | 2 of 2, step " in section
    data = json.loads((tmp_path / "benchmark.json").read_text())
    assert data["meta"]["machine"]["cores"] >= 1
    assert data["schema"] == "piezo-testbed/benchmark" and data["schema_version"] == 2
    assert {e["reference"] for e in data["results"]["episodes"]} == {"sine-10Hz", "steps"}
    assert len(paths) == 2
    # The report rewritten from the run's own JSON is the report the run wrote, but for the
    # figures, which the JSON cannot redraw: they are named as absent.
    before = (tmp_path / "benchmark.md").read_text()
    rewrite_report(tmp_path)
    after = (tmp_path / "benchmark.md").read_text()
    assert after.split("## Figures")[0] == before.split("## Controllers")[0]
    assert "tracking.png: not drawn (not in the run's folder)" in after
    assert after.split("## Controllers")[1] == before.split("## Controllers")[1]
    assert json.loads((tmp_path / "benchmark.json").read_text()) == data
    with pytest.raises(ValueError, match=r"holds no benchmark\.json"):
        rewrite_report(tmp_path / "elsewhere")


def test_config_refuses_unknown_names():
    with pytest.raises(ValueError, match="unknown controller 'lqr'"):
        BenchmarkConfig(controllers=("lqr",))
    with pytest.raises(ValueError, match="unknown reference"):
        BenchmarkConfig(references=("sine-3Hz",))
    with pytest.raises(ValueError, match="unknown plant"):
        BenchmarkConfig(plants=("mars",))


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if the benchmark or the identification starts."""

    def refuse(*args, **kwargs):
        raise AssertionError("work started before the arguments were checked")

    monkeypatch.setattr("benchmarks.runner.run_benchmark", refuse)
    monkeypatch.setattr("identification.pipeline.identify", refuse)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--controllers", "mpc,lqr"], "unknown controller 'lqr'"),
        (["--references", "sine-3Hz"], "unknown reference 'sine-3Hz'"),
        (["--out", "/dev/null/x"], "cannot write to /dev/null/x"),
        (["--model", "/nonexistent/model"], "--model /nonexistent/model: cannot load the model"),
        (["--policies", "/nonexistent/ppo"], "/nonexistent/ppo/policy.json: missing"),
        (["--controllers", ",", "--policies", "none"], "no controller to run"),
        (["--controllers", "", "--policies", "none"], "no controller to run"),
        (["--plants", ","], "at least one reference and one plant"),
        (["--policies", "docs/policies/ppo-seed0", "--preview", "5"], "raise --preview"),
    ],
)
def test_cli_refuses_bad_calls_in_one_line_before_any_work(
    argv, message, no_work, tmp_path, capsys, monkeypatch
):
    monkeypatch.chdir(Path(MODEL_DIR).parents[2])  # the project folder: docs/policies
    if "--out" not in argv:
        argv = [*argv, "--out", str(tmp_path / "new" / "out")]
    assert main(["benchmark", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "new").exists()  # a refused call leaves no folder behind


def test_a_failure_after_the_folder_was_made_removes_it_only_when_empty(tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise ValueError("late failure")

    monkeypatch.setattr("benchmarks.runner.run_benchmark", fail)
    out = tmp_path / "a" / "b"
    argv = ["benchmark", "--model", MODEL_DIR, "--policies", "none", "--out", str(out)]
    assert main(argv) == 2
    assert not (tmp_path / "a").exists()
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "mine.txt").write_text("x")
    assert main([*argv[:-1], str(tmp_path / "keep")]) == 2
    assert (tmp_path / "keep" / "mine.txt").exists()


def test_monte_carlo_plants_differ_per_draw_and_the_oracle_runs_each_draws_own_model():
    from benchmarks.report import monte_carlo_table

    config = BenchmarkConfig(
        controllers=("mpc", "mpc-oracle"),
        references=("sine-50Hz",),
        plants=("random-plants",),
        steps=300,
        draws=3,
    )
    assert [g[1] for g in config.groups()] == ["mpc", "mpc-oracle"]
    result = run_benchmark(config, MODEL_DIR)
    assert len(result.episodes) == sum(config.episodes_of(p, r) for p, _, r, _ in config.runs())
    oracle = [e["rmse_percent"] for e in result.episodes if e["controller"] == "mpc-oracle"]
    result.episodes = [e for e in result.episodes if e["controller"] == "mpc"]
    rmse = [e["rmse_percent"] for e in result.episodes]
    # Knowing each drawn plant puts the oracle at the sensor-noise floor (uniform noise of
    # +-1 um: 0.58 um RMS, 0.029 % of the 2000 um stroke, filtered by the observer) on every
    # draw, far below the MPC that knows only the nominal model.
    assert max(oracle) < 0.029 and all(o < r / 10 for o, r in zip(oracle, rmse, strict=True))
    assert [e["draw"] for e in result.episodes] == [0, 1, 2]
    assert len(set(rmse)) == 3  # three different plants
    ranked = sorted(rmse)  # order statistics, not a "90th percentile" of three numbers
    expected = f"{np.median(rmse):.3f} / {ranked[-2]:.3f} / {ranked[-1]:.3f}"
    assert expected in monte_carlo_table(result)
    assert "2nd worst / worst of 3" in monte_carlo_table(result)
    assert tracking_tables(result) == ""  # the draws are not a plant table


def test_the_box_corners_run_each_vertex_of_the_datasheet_box():
    """One episode per vertex, on that vertex's bender (its datasheet deflection, resonance and
    damping), and their own table in the report."""
    from benchmarks.plants import VERTICES, vertex_options
    from benchmarks.report import monte_carlo_table
    from benchmarks.runner import _make_env

    config = BenchmarkConfig(
        controllers=("mpc", "mpc-oracle"),
        references=("sine-10Hz",),
        plants=("box-corners",),
        steps=60,
    )
    assert [g[1] for g in config.groups()] == ["mpc", "mpc-oracle"]
    result = run_benchmark(config, MODEL_DIR)
    assert len(result.episodes) == sum(config.episodes_of(p, r) for p, _, r, _ in config.runs())
    assert "Ratio to `mpc-oracle` on the same plant" in monte_carlo_table(result, "box-corners")
    result.episodes = [e for e in result.episodes if e["controller"] == "mpc"]
    assert [e["draw"] for e in result.episodes] == list(range(len(VERTICES)))
    assert len({e["rmse_percent"] for e in result.episodes}) == len(VERTICES)
    nominal = _make_env(config, "nominal").unwrapped.model.params
    for vertex in VERTICES:
        env = _make_env(config, "box-corners", **vertex_options(config.bender, vertex))
        sheet = env.unwrapped.model.params.datasheet
        assert sheet.free_deflection == pytest.approx(vertex[0] * nominal.datasheet.free_deflection)
        assert sheet.resonance == pytest.approx(vertex[1] * nominal.datasheet.resonance)
        assert env.unwrapped.config.damping_ratio == vertex[2]
        assert env.unwrapped.model.dt == config.dt
    table = monte_carlo_table(result, "box-corners")
    assert "Corners of the datasheet's tolerance box" in table and "worst of 8" in table
    assert tracking_tables(result) == ""


def test_another_bender_scales_references_and_plants_to_its_datasheet(tmp_path):
    from benchmarks.plants import PLANTS

    config = BenchmarkConfig(
        bender="PL127", controllers=("pid-ff", "mpc"), references=("sine-10Hz",),
        plants=("nominal", "stiffness+20%"), steps=120,
    )
    assert config.stroke_um == pytest.approx(450.0)
    pl140 = make_reference("sine-10Hz", 200, dt=1e-3, seed=0)
    np.testing.assert_allclose(
        make_reference("sine-10Hz", 200, dt=1e-3, seed=0, stroke_um=450.0), 0.45 * pl140
    )
    assert PLANTS["stiffness+20%"]("PL127")["bender"].name.startswith("PL127")
    model = str(Path(MODEL_DIR).parents[1] / "benchmark-PL127" / "model")
    result = run_benchmark(config, model)
    assert {e["plant"] for e in result.episodes} == {"nominal", "stiffness+20%"}
    assert all(e["rmse_percent"] < 1.0 for e in result.episodes if e["plant"] == "nominal")
    with pytest.raises(ValueError, match="unknown bender"):
        BenchmarkConfig(bender="PL999")


def test_several_noise_seeds_give_means_with_intervals_and_honest_ties(tmp_path):
    from benchmarks.cells import aggregate, different

    config = BenchmarkConfig(
        controllers=("mpc", "nmpc"), references=("sine-10Hz",), plants=("nominal",),
        steps=150, seeds=4,
    )
    result = run_benchmark(config, MODEL_DIR)
    assert len(result.episodes) == 2 * 4
    cells = {c["controller"]: c for c in aggregate(result.episodes)}
    mpc = cells["mpc"]
    runs = [e["rmse_percent"] for e in result.episodes if e["controller"] == "mpc"]
    assert mpc["seeds"] == 4 and mpc["rmse_percent"] == pytest.approx(np.mean(runs))
    # t(0.975, 3) = 3.182: the interval of the mean of four seeds.
    expected = 3.182446305 * np.std(runs, ddof=1) / 2.0
    assert mpc["rmse_ci95_percent"] == pytest.approx(expected, rel=1e-6)
    assert not different(mpc, cells["nmpc"])  # nmpc equals mpc within the noise: a tie
    meta = {"model": MODEL_DIR, "dt": 1e-3, "noise_bound_um": 1.0, "stroke_um": 1000.0,
            "machine": machine()}
    write_benchmark(result, tmp_path, meta, figures=False)
    text = (tmp_path / "benchmark.md").read_text()
    assert "mean over 4 seeds" in text and "tie between `mpc`, `nmpc`" in text
    assert f"{mpc['rmse_percent']:.3f} +- {mpc['rmse_ci95_percent']:.3f}" in text


def test_settling_time_is_the_end_of_the_first_window_that_stays_within_twice_the_floor():
    from controllers.metrics import window_settling_ms

    floor = np.ones(2000)
    assert window_settling_ms(floor, 1e-3) == 50.0
    late = floor.copy()
    late[120:130] = 30.0  # the window 100-150 ms is the last one above twice the floor
    assert window_settling_ms(late, 1e-3) == 200.0  # the next one (150-200 ms) and all after
    # Against another floor: a higher one is reached sooner; one below every window, never.
    assert window_settling_ms(late, 1e-3, floor=10.0) == 50.0  # that window's RMS, 13.4
    assert window_settling_ms(floor, 1e-3, floor=0.25) == 2050.0  # every window above 0.5
    # At another sample time the window is still 50 ms: 200 samples at 0.25 ms.
    quarter = np.ones(8000)
    quarter[480:520] = 30.0
    assert window_settling_ms(quarter, 0.25e-3) == 200.0
    # Nothing to judge: shorter than one window, or not finite.
    assert window_settling_ms(floor[:49], 1e-3) is None
    assert window_settling_ms(np.r_[floor, np.nan], 1e-3) is None


def test_the_committed_policies_run_when_asked_for_from_any_folder(tmp_path, monkeypatch):
    from piezo_cli.benchmark import _committed_policies, policies_line

    monkeypatch.chdir(tmp_path)  # not the project folder: found all the same
    assert _committed_policies(("mpc", "pid-ff"), "PL140") == ((), {})  # not asked for
    kept, left_out = _committed_policies(("mpc", "ppo"), "PL140")
    assert [Path(k).name for k in kept] == ["ppo-seed0", "ppo-seed1", "ppo-seed2"]
    assert not left_out and all(Path(k).is_dir() for k in kept)
    kept, left_out = _committed_policies(("ppo", "ppo-dr"), "PL122")
    line = policies_line(kept, left_out)
    assert kept == () and len(left_out) == 6 and "\n" not in line
    assert line.startswith("policies: left out ppo-dr-seed0, ppo-dr-seed1") and "PL122" in line
    monkeypatch.setattr("piezo_cli.benchmark.committed_policy_folder", lambda: tmp_path / "no")
    kept, left_out = _committed_policies(("ppo",), "PL140")
    assert kept == () and "not found in" in left_out["ppo"]


@pytest.mark.parametrize("bender", ["PL140", "PL127"])
def test_the_corners_study_previews_its_references_to_the_last_step(bender):
    """The last observation of an episode reads the reference's own future, not the value an
    array that ended early is held at (the env holds it; a controller would brake for it)."""
    from benchmarks.plants import EPISODE_S, sample_time
    from benchmarks.studies.corners import PREVIEW, vertex_env, vertex_reference

    reference = vertex_reference("sine-50Hz", bender)
    env = vertex_env((1.0, 1.0, 0.02), bender)
    steps = round(EPISODE_S / sample_time(bender))
    obs, _ = env.reset(seed=0, options={"reference": reference})
    for _ in range(steps):  # the observation after the last step previews the furthest
        obs, *_ = env.step(np.zeros(1))
    preview = obs[1:]
    assert preview.size == PREVIEW + 1
    np.testing.assert_array_equal(preview, reference[steps:].astype(np.float32))
    assert np.all(np.diff(preview[-3:]) != 0.0)  # a 50 Hz sine still moving: nothing held


def test_the_corners_study_scales_the_hysteresis_as_the_randomisation_does():
    """``--hysteresis`` runs the vertices at a hysteresis strength: the hysteretic share alpha
    times the scale at the same major-loop peak (:func:`scale_hysteresis`), the nominal
    strength being the env's own map; a strength outside (0, 2) is refused."""
    import gymnasium as gym

    from benchmarks.studies.corners import main as corners_main
    from benchmarks.studies.corners import vertex_env
    from piezo_env.randomization import major_loop_peak

    nominal = vertex_env((1.0, 1.0, 0.02)).unwrapped.model.hysteresis
    default = gym.make("piezo_env:PiezoBender-v0").unwrapped.model.hysteresis
    assert nominal == default
    weak = vertex_env((0.8, 1.2, 0.01), hysteresis_scale=0.7).unwrapped.model.hysteresis
    assert weak.alpha == pytest.approx(0.7 * nominal.alpha, rel=1e-12)
    assert major_loop_peak(weak, 30.0) == pytest.approx(major_loop_peak(nominal, 30.0))
    with pytest.raises(SystemExit):
        corners_main(["--hysteresis", "2.5"])


@pytest.mark.parametrize(
    ("controllers", "expected"),
    [
        (None, ["ppo-dr-seed0", "ppo-dr-seed1", "ppo-dr-seed2", "ppo-seed0", "ppo-seed1",
                "ppo-seed2"]),
        ("mpc,pid-ff", []),
        ("mpc,ppo", ["ppo-seed0", "ppo-seed1", "ppo-seed2"]),
    ],
)
def test_the_command_runs_the_policies_asked_for_and_says_so_in_one_line(
    controllers, expected, tmp_path, monkeypatch, capsys
):
    seen = {}

    def stop(config, *args, **kwargs):
        seen["config"] = config
        raise ValueError("stopped before the episodes")

    monkeypatch.setattr("benchmarks.runner.run_benchmark", stop)
    monkeypatch.chdir(tmp_path)  # another folder than the project's
    argv = ["benchmark", "--model", MODEL_DIR, "--out", str(tmp_path / "o")]
    argv += [] if controllers is None else ["--controllers", controllers]
    assert main(argv) == 2
    config = seen["config"]
    assert [Path(p).name for p in config.policies] == expected
    assert "ppo" not in config.controllers and "ppo-dr" not in config.controllers
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("policies:")]
    assert lines == ([f"policies: running {', '.join(expected)}"] if expected else [])


def test_no_collection_keeps_the_collector_off_inside_and_freezes_once(monkeypatch):
    import gc

    import benchmarks.runner as runner
    from benchmarks.runner import no_collection

    calls: list[int] = []
    monkeypatch.setattr(runner, "_base_frozen", False)
    monkeypatch.setattr(gc, "freeze", lambda original=gc.freeze: (original(), calls.append(1)))

    assert gc.isenabled()
    with no_collection():
        assert not gc.isenabled()
        frozen = gc.get_freeze_count()
    assert gc.isenabled() and frozen > 0
    with no_collection():
        assert not gc.isenabled()
        assert gc.get_freeze_count() <= frozen  # no second freeze: only new objects collected
    assert gc.isenabled() and calls == [1]
    gc.unfreeze()  # the rest of the session's heap stays collectable


def test_an_infinite_number_in_a_description_is_written_as_null(tmp_path):
    """A loop with no phase crossing has an infinite gain margin: the PID describes it as None,
    and any other controller's infinity or NaN becomes null in the JSON (which has neither)
    instead of failing the write after the run."""
    from identification.outputs import jsonable

    config = BenchmarkConfig(
        controllers=("pid",), references=("sine-10Hz",), plants=("nominal",), steps=50
    )
    result = run_benchmark(config, MODEL_DIR)
    result.controllers["pid"]["user_margin"] = math.inf
    result.controllers["pid"]["nested"] = {"values": (1.0, math.nan, -math.inf)}
    meta = {"model": MODEL_DIR, "dt": 1e-3, "noise_bound_um": 1.0, "stroke_um": 1000.0,
            "machine": machine()}
    write_benchmark(result, tmp_path, meta, figures=False)
    data = json.loads((tmp_path / "benchmark.json").read_text())
    assert data["controllers"]["pid"]["user_margin"] is None
    assert data["controllers"]["pid"]["nested"] == {"values": [1.0, None, None]}
    assert jsonable({"a": [2.0, math.inf], "b": "text", "c": 3}) == {
        "a": [2.0, None], "b": "text", "c": 3
    }


def test_the_pid_describes_an_infinite_margin_as_none(monkeypatch):
    import gymnasium as gym

    from controllers.registry import make
    from identification.hammerstein import HammersteinModel

    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    pid = make("pid", HammersteinModel.load(MODEL_DIR), env)
    pid.report = {**pid.report, "gain_margin_db": math.inf, "crossover_hz": math.nan}
    info = pid.describe()
    assert info["gain_margin_db"] is None and info["crossover_hz"] is None
    json.dumps(info, allow_nan=False)


def test_a_reference_the_sample_time_cannot_carry_is_named_with_the_fix():
    with pytest.raises(ValueError, match=r"'sine-1Hz' cannot be sampled at dt = 0.7 s.*--ref"):
        make_reference("sine-1Hz", 10, dt=0.7, seed=0)


def test_the_robustness_plants_run_what_the_selection_names_and_refuse_to_run_nothing():
    """By default a robustness plant runs its subsets of the references and rows (the default
    run's budget); every_reference / every_controller (piezo benchmark: --references /
    --controllers given) run all of those selected on it. A plant that would run nothing is
    refused, with the subsets and the switches named."""
    subset = BenchmarkConfig(
        controllers=("pid", "mpc"), references=("chirp", "steps"), plants=("nominal", "creep")
    )
    assert ("creep", "mpc", ("steps",)) in subset.groups()
    assert all(c != "pid" for p, c, _ in subset.groups() if p == "creep")
    every = dataclasses.replace(subset, every_reference=True, every_controller=True)
    assert [g for g in every.groups() if g[0] == "creep"] == [
        ("creep", "pid", ("chirp", "steps")),
        ("creep", "mpc", ("chirp", "steps")),
    ]
    with pytest.raises(ValueError, match=r"box-corners plant would run nothing.*every_reference"):
        BenchmarkConfig(controllers=("mpc",), references=("chirp",), plants=("box-corners",))
    with pytest.raises(ValueError, match="would run nothing"):
        BenchmarkConfig(controllers=("pid",), references=("steps",), plants=("creep",))
    corners = BenchmarkConfig(
        controllers=("pid",),
        references=("chirp",),
        plants=("box-corners",),
        every_reference=True,
        every_controller=True,
    )
    assert corners.groups() == [("box-corners", "pid", ("chirp",))]
    with pytest.raises(ValueError, match="every_reference must be True or False"):
        dataclasses.replace(corners, every_reference="yes")


def test_the_command_line_names_make_every_plant_run_them(monkeypatch):
    """piezo benchmark: --references / --controllers given set every_reference /
    every_controller; left out, the subsets stand (the run stops once its config is made)."""
    from piezo_cli import benchmark as command
    from piezo_cli.main import main

    class Made(Exception):
        pass

    made, real = [], command._config

    def capture(args, policies):
        made.append(real(args, policies))
        raise Made

    monkeypatch.setattr(command, "_config", capture)
    for argv, expected in (
        ([], (False, False)),
        (["--references", "chirp"], (True, False)),
        (["--controllers", "pid"], (False, True)),
    ):
        with pytest.raises(Made):
            main(["benchmark", "--plants", "nominal,creep", *argv])
        assert (made[-1].every_reference, made[-1].every_controller) == expected
    assert made[0].references == made[2].references and len(made[0].references) > 1
    assert "ppo-seed0" in made[0].rows and made[1].controllers == made[0].controllers
