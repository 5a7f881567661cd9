"""Statistics over what varies: identification seeds x noise seeds, one meaning of +-, and a
comparison of runs paired on the seeds they share."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.cells import aggregate, ci95_half_width
from benchmarks.compare import compare_runs
from benchmarks.report import deterministic_json
from benchmarks.runner import BenchmarkConfig, run_benchmark

ROOT = Path(__file__).resolve().parents[1]
MODELS = (str(ROOT / "docs" / "benchmark" / "model"), str(ROOT / "docs" / "benchmark" / "model-1"))
"""The committed run's models of identification seeds 0 and 1."""

# Student's t quantiles t_0.975 with 1, 2 and 5 degrees of freedom, from printed tables.
T_975 = {1: 12.706, 2: 4.303, 5: 2.571}


@pytest.mark.parametrize("values", [[1.0, 2.0], [1.0, 2.0, 3.0], [0.1, 0.4, 0.2, 0.3, 0.9, 0.5]])
def test_interval_half_width_is_students_t_closed_form(values):
    n = len(values)
    expected = T_975[n - 1] * float(np.std(values, ddof=1)) / math.sqrt(n)
    assert ci95_half_width(values) == pytest.approx(expected, rel=1e-3)
    assert ci95_half_width(values[:1]) is None


def test_a_cell_pools_identification_and_noise_seeds():
    episodes = [
        {"plant": "nominal", "controller": "mpc", "reference": "steps", "rmse_percent": r,
         "identification_seed": k, "seed_index": s}
        for k, row in enumerate([[1.0, 1.2], [1.4, 1.1], [0.9, 1.3]])
        for s, r in enumerate(row)
    ]
    (cell,) = aggregate(episodes)
    values = [e["rmse_percent"] for e in episodes]
    assert cell["seeds"] == 6 and cell["identification_seeds"] == 3
    assert cell["rmse_percent"] == pytest.approx(np.mean(values))
    expected = T_975[5] * float(np.std(values, ddof=1)) / math.sqrt(6)
    assert cell["rmse_ci95_percent"] == pytest.approx(expected, rel=1e-3)


def test_a_cell_of_one_episode_holds_its_numbers_to_the_bit():
    episode = {"plant": "nominal", "controller": "mpc", "reference": "steps",
               "rmse_percent": 0.1 + 0.2, "steps": 2000, "saturated": True, "note": "x",
               "observer_fallback_step": None, "worst": float("inf")}
    (cell,) = aggregate([episode])
    assert cell["rmse_percent"] == 0.1 + 0.2 and cell["steps"] == 2000.0
    assert isinstance(cell["steps"], float) and cell["worst"] == float("inf")
    assert cell["saturated"] is True and cell["note"] == "x" and cell["observer_fallbacks"] == 0
    assert cell["seeds"] == 1 and cell["rmse_ci95_percent"] is None


def test_rows_on_the_identified_model_run_once_per_model_and_the_oracle_once(one_seed):
    config = BenchmarkConfig(
        controllers=("mpc", "mpc-oracle"), references=("sine-10Hz",), plants=("nominal",),
        steps=60, identification_seeds=2,
    )
    result = run_benchmark(config, MODELS)
    mpc = [e for e in result.episodes if e["controller"] == "mpc"]
    oracle = [e for e in result.episodes if e["controller"] == "mpc-oracle"]
    assert [e["identification_seed"] for e in mpc] == [0, 1]
    assert len(oracle) == 1 and "identification_seed" not in oracle[0]
    assert mpc[0]["rmse_percent"] != mpc[1]["rmse_percent"]  # two models, two results
    # The first model's run is the one-model run's, bit for bit.
    assert one_seed["results"]["episodes"][0]["rmse_percent"] == mpc[0]["rmse_percent"]
    with pytest.raises(ValueError, match="one folder per identification seed"):
        run_benchmark(config, MODELS[0])


def _run_data(seeds: int) -> dict:
    """``mpc`` on the first model, nominal plant, sine-10Hz, 60 steps, ``seeds`` noise seeds."""
    config = BenchmarkConfig(
        controllers=("mpc",), references=("sine-10Hz",), plants=("nominal",), steps=60,
        seeds=seeds,
    )
    return {"results": deterministic_json(run_benchmark(config, MODELS[0]))}


@pytest.fixture(scope="module")
def one_seed() -> dict:
    """:func:`_run_data` with one noise seed, run once for the module's tests."""
    return _run_data(1)


def test_compare_pairs_runs_on_their_shared_seeds(one_seed):
    three = _run_data(3)
    one = copy.deepcopy(one_seed)
    table, marked = compare_runs(one, three)
    assert marked == 0, table  # seed 0 agrees; the other seeds are not a change
    assert "seeds differ" in table and "1 shared" in table
    # A change on one shared seed is flagged.
    changed = copy.deepcopy(three)
    changed["results"]["episodes"][0]["rmse_percent"] *= 1.5
    assert compare_runs(one, changed)[1] == 1
    # Several shared seeds: a consistent shift is flagged, a reshuffle within noise is not.
    shifted = copy.deepcopy(three)
    for e in shifted["results"]["episodes"]:
        e["rmse_percent"] *= 1.3
    assert compare_runs(three, shifted)[1] == 1
    assert compare_runs(three, copy.deepcopy(three))[1] == 0


@pytest.mark.parametrize(("key", "value"), [("bender", "PL122"), ("dt", 2e-4), ("steps", 61)])
def test_compare_refuses_runs_of_another_task(one_seed, key, value):
    """Another bender, sample time or episode length: no cell is the same experiment."""
    other = copy.deepcopy(one_seed)
    assert key in other["results"]["config"]
    other["results"]["config"][key] = value
    with pytest.raises(ValueError, match=f"different tasks \\({key} "):
        compare_runs(one_seed, other)


def test_identification_plants_are_the_bender_itself():
    from piezo_cli.benchmark import identification_plants

    plants = identification_plants("PL140")
    assert "nominal" in plants and "bench" in plants
    assert not {"stiffness+20%", "stiffness-20%", "random-plants", "box-corners"} & set(plants)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--identify-on", "stiffness+20%"], "not a plant a model of the PL140"),
        (["--identify-on", "nominal,bench", "--plants", "nominal"], "bench plant is not run"),
        (["--identify-on", "bench,bench", "--plants", "bench"], "names a plant twice"),
        (["--identify-on", "bench", "--model", MODELS[0]], "drop one of the two"),
        (["--identification-seeds", "2", "--model", MODELS[0]], "drop one of the two"),
        (["--identification-seeds", "0"], "identification-seeds"),
    ],
)
def test_identification_options_that_cannot_be_honoured_are_refused_before_work(
    tmp_path, capsys, options, message
):
    from piezo_cli.main import main

    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        status = main(["benchmark", "--out", str(out), "--policies", "none", *options])
        raise SystemExit(status)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_plant_with_its_own_model_runs_it_and_the_others_run_the_first():
    config = BenchmarkConfig(
        controllers=("mpc",), references=("sine-10Hz",), plants=("nominal", "bench"), steps=60,
    )
    mixed = run_benchmark(config, {"nominal": MODELS[0], "bench": MODELS[1]})
    first = run_benchmark(config, MODELS[0])
    second = run_benchmark(config, MODELS[1])
    mixed, first, second = (
        {e["plant"]: e["rmse_percent"] for e in r.episodes} for r in (mixed, first, second)
    )
    assert mixed["nominal"] == first["nominal"]
    assert mixed["bench"] == second["bench"] != first["bench"]
    with pytest.raises(ValueError, match="not run"):
        run_benchmark(config, {"nominal": MODELS[0], "creep": MODELS[1]})


def test_the_report_opens_with_the_clean_plant_and_the_bench_identified_on_it(tmp_path):
    from benchmarks.machine import machine
    from benchmarks.report import write_benchmark
    from benchmarks.verdict import verdict

    config = BenchmarkConfig(
        controllers=("mpc", "pid-ff", "mpc-oracle"), references=("sine-10Hz",),
        plants=("nominal", "creep", "bench"), steps=60,
    )
    result = run_benchmark(config, {"nominal": MODELS[0], "bench": MODELS[1]})
    meta = {"model": MODELS[0], "dt": 1e-3, "noise_bound_um": 1.0, "stroke_um": 1000.0,
            "machine": machine(), "identify_on": ["nominal", "bench"]}
    lines = verdict(result, meta)
    assert lines[0].startswith("- sine-10Hz:")
    assert lines[1] == "- on the plant `bench`, with the model identified on it:"
    assert lines[2].startswith("  - sine-10Hz:")
    write_benchmark(result, tmp_path, meta, figures=False)
    text = (tmp_path / "benchmark.md").read_text()
    headline = text[text.index("## Headline"):text.index("## Verdict")]
    assert "### Nominal PL140: RMSE" in headline
    assert "### Plant: bench, model identified on it: RMSE" in headline
    assert "creep" not in headline  # the other plants come under Tracking, once
    assert text.count("### Plant: bench, model identified on it: RMSE") == 1
    assert "### Plant: creep: RMSE" in text[text.index("## Tracking"):]
