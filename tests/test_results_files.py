"""benchmark.json: its documented schema, and what piezo compare says about two runs."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest

from benchmarks.compare import compare_runs
from benchmarks.machine import machine
from benchmarks.report import write_benchmark
from benchmarks.runner import BenchmarkConfig, run_benchmark
from piezo_cli.main import main

ROOT = Path(__file__).resolve().parents[1]
MODEL_DIR = str(ROOT / "docs" / "identify" / "model")
SCHEMA = json.loads((ROOT / "benchmarks" / "benchmark.schema.json").read_text())


def _run(tmp_path: Path, name: str, **options) -> dict:
    config = BenchmarkConfig(
        controllers=("pid-ff", "mpc"), references=("sine-10Hz", "steps"),
        plants=("nominal",), steps=150, seeds=2, **options,
    )
    result = run_benchmark(config, MODEL_DIR)
    meta = {"model": MODEL_DIR, "dt": 1e-3, "noise_bound_um": 1.0, "stroke_um": 1000.0,
            "bender": "PL140", "jobs": 1, "machine": machine(), "timing": {}}
    write_benchmark(result, tmp_path / name, meta, figures=False)
    return json.loads((tmp_path / name / "benchmark.json").read_text())


@pytest.mark.parametrize("run", ["benchmark", "benchmark-PL127"])
def test_the_committed_runs_follow_the_schema(run):
    jsonschema.validate(json.loads((ROOT / "docs" / run / "benchmark.json").read_text()), SCHEMA)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    """The folder of a fresh small run (:func:`_run`), made once for the module's tests."""
    folder = tmp_path_factory.mktemp("runs")
    _run(folder, "fresh")
    return folder / "fresh"


def test_a_fresh_run_follows_the_schema_and_a_broken_one_does_not(fresh):
    data = json.loads((fresh / "benchmark.json").read_text())
    jsonschema.validate(data, SCHEMA)
    del data["results"]["episodes"][0]["rmse_percent"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(data, SCHEMA)


def test_compare_flags_a_change_made_on_purpose_and_nothing_else(fresh, tmp_path, capsys):
    old = json.loads((fresh / "benchmark.json").read_text())
    same = _run(tmp_path, "same")
    slower = _run(tmp_path, "slower", controller_options={"mpc": {"rate_weight": 30.0}})
    assert compare_runs(old, same)[1] == 0
    table, marked = compare_runs(old, slower)
    flagged = [line for line in table.splitlines() if "**yes**" in line]
    assert marked == len(flagged) >= 1
    assert all("| mpc |" in line for line in flagged)  # only the row that was changed
    status = main(["compare", str(fresh / "benchmark.json"),
                   str(tmp_path / "slower" / "benchmark.json"), "--strict"])
    assert status == 1 and "beyond the run-to-run noise" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("results", "fragment"),
    [
        (None, "no results.episodes"),
        ("episodes", "no results.episodes"),
        ({"episodes": [1]}, "results.episodes[0] is not an object"),
        ({"episodes": [{"plant": "a", "controller": "b"}]}, "has no reference"),
        ({"config": None, "episodes": []}, "results.config is not an object"),
        ({"config": {"seed": "0"}, "episodes": []}, "results.config.seed is not an integer"),
    ],
)
def test_compare_refuses_a_malformed_file_in_one_line(results, fragment, tmp_path, capsys):
    good = ROOT / "docs" / "benchmark" / "benchmark.json"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"results": results}))
    assert main(["compare", str(good), str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "bad.json" in err and fragment in err


def test_compare_refuses_an_episode_without_a_finite_rmse(tmp_path, capsys):
    data = json.loads((ROOT / "docs" / "benchmark" / "benchmark.json").read_text())
    data["results"]["episodes"][3]["rmse_percent"] = None
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(data))
    assert main(["compare", str(bad), str(ROOT / "docs" / "benchmark" / "benchmark.json")]) == 2
    assert "results.episodes[3].rmse_percent is not a finite number" in capsys.readouterr().err
