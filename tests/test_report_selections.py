"""Report and figures over any selection of controllers, references and plants.

A hand-made result (no episodes run) stands in for a benchmark, so that every selection a user
can ask for is drawn in a second; user warnings are errors here (an empty figure warns).
"""

from __future__ import annotations

import itertools
import json
import warnings

import numpy as np
import pytest

from benchmarks.figures import draw_figures
from benchmarks.report import TIE, missed_checks, verdict, write_benchmark
from benchmarks.rows import row_color
from benchmarks.runner import BenchmarkConfig, BenchmarkResult

META = {
    "model": "model",
    "dt": 1e-3,
    "noise_bound_um": 1.0,
    "stroke_um": 1000.0,
    "machine": {
        "date": "today",
        "platform": "test",
        "processor": "cpu",
        "cores": 2,
        "python": "3",
        "packages": {"numpy": "2"},
    },
}

_LOOP = {"num": [0.0, 0.02, 0.01], "den": [1.0, -1.5, 0.56], "dt": 1e-3}


def _episode(plant: str, controller: str, reference: str, rmse: float, **extra) -> dict:
    return {
        "plant": plant,
        "controller": controller,
        "reference": reference,
        "rmse_percent": rmse,
        "max_error_um": 20 * rmse,
        "rms_voltage_v": 10.0,
        "voltage_tv_v": 100.0,
        "saturated_fraction": 0.0,
        "compute_median_us": 5.0,
        "compute_p99_us": 9.0,
        "compute_max_us": 40.0,
        "deadline_misses": 0,
        "fallbacks": 0,
        "steps_settled": "3 of 3" if reference == "steps" else None,
        "rise_time_ms": 1.0 if reference == "steps" else None,
        "overshoot_percent": 2.0 if reference == "steps" else None,
        "settling_time_ms": 5.0 if reference == "steps" else None,
        **extra,
    }


def _result(controllers, references, plants) -> BenchmarkResult:
    config = BenchmarkConfig(
        controllers=controllers, references=references, plants=plants, draws=3
    )
    rng = np.random.default_rng(0)
    episodes = []
    for plant, controller, refs in config.groups():
        for ref in refs:
            draws = range(3) if plant == "random-plants" else [None]
            for draw in draws:
                extra = {} if draw is None else {"draw": draw}
                episodes.append(_episode(plant, controller, ref, float(rng.uniform(0.01, 2)),
                                         **extra))
    t = np.arange(2000)
    traces = {
        ref: {
            c: {
                "deflection_um": list(np.sin(t / 30.0) * 500 + rng.normal(size=t.size)),
                "reference_um": list(np.sin(t / 30.0) * 500),
                "voltage_V": list(np.zeros(t.size)),
            }
            for c in controllers
        }
        for ref in references
        if ref in ("sine-50Hz", "multisine", "steps") and "nominal" in plants
    }
    described = {
        c: {"name": c, "settings": {"horizon": 20}, "gain_margin_db": 8.0,
            "phase_margin_deg": 60.0, "ms": 1.8, "crossover_hz": 10.0,
            **({"loop": _LOOP} if c.startswith("pid") else {})}
        for c in controllers
    }
    return BenchmarkResult(config, episodes, described, traces, {"episodes_s": 1.0})


SELECTIONS = {
    "two slow sines (no trace reference)": (("pid", "mpc"), ("sine-1Hz", "sine-10Hz"),
                                            ("nominal",)),
    "nominal only": (("pid-ff", "mpc", "mpc-oracle"), ("sine-50Hz", "steps"), ("nominal",)),
    "one controller": (("mpc",), ("multisine",), ("nominal", "damping-0.01")),
    "robustness without nominal": (("mpc", "pid-ff"), ("sine-10Hz",), ("stiffness+20%",)),
    "monte carlo only": (("mpc",), ("sine-10Hz",), ("random-plants",)),
    "no pid": (("mpc", "nmpc"), ("steps",), ("nominal", "random-plants", "creep")),
    "everything small": (("pid", "pid-notch", "pid-ff", "mpc"), ("sine-50Hz", "steps"),
                         ("nominal", "damping-0.04", "random-plants")),
}


@pytest.mark.parametrize("selection", list(SELECTIONS))
def test_every_selection_gets_a_report_and_the_figures_it_can_show(selection, tmp_path):
    result = _result(*SELECTIONS[selection])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        # Old matplotlib calls old pyparsing names; that is not this figure code's warning.
        warnings.filterwarnings("ignore", message=".*deprecated", category=UserWarning)
        paths = write_benchmark(result, tmp_path, META)
    text = (tmp_path / "benchmark.md").read_text()
    assert text.startswith("# Closed-loop benchmark")
    for name in ("tracking.png", "summary.png", "robustness.png", "pid_loops.png"):
        drawn = (tmp_path / name).exists()
        assert drawn == (tmp_path / name in paths)
        assert drawn or f"{name}: not drawn (" in text  # a missing figure says why
    json.loads((tmp_path / "benchmark.json").read_text())


def test_figures_skip_what_has_nothing_to_show(tmp_path):
    result = _result(("pid", "mpc"), ("sine-1Hz", "sine-10Hz"), ("nominal",))
    drawn = draw_figures(result, tmp_path)
    assert isinstance(drawn["tracking.png"], str) and isinstance(drawn["robustness.png"], str)
    assert drawn["summary.png"] == tmp_path / "summary.png"
    assert drawn["pid_loops.png"] == tmp_path / "pid_loops.png"


def test_each_row_keeps_its_colour():
    names = ["pid", "pid-notch", "pid-ff", "mpc", "nmpc", "mpc-oracle", "nmpc-oracle"]
    colours = [row_color(n) for n in names]
    assert len(set(colours)) == len(colours)
    assert row_color("ppo-seed0") == row_color("ppo-seed2")  # one recipe, one colour
    assert row_color("mypkg.ctl:Mine") == row_color("mypkg.ctl:Mine")


def test_the_verdict_names_the_best_and_calls_near_ties_ties():
    result = _result(("pid-ff", "mpc", "mpc-oracle"), ("sine-50Hz", "steps"), ("nominal",))
    values = {("pid-ff", "sine-50Hz"): 0.2, ("mpc", "sine-50Hz"): 0.05,
              ("mpc-oracle", "sine-50Hz"): 0.01,
              ("pid-ff", "steps"): 0.90, ("mpc", "steps"): 0.90 * (1 + TIE / 2),
              ("mpc-oracle", "steps"): 0.5}
    for e in result.episodes:
        e["rmse_percent"] = values[(e["controller"], e["reference"])]
    lines = verdict(result)
    assert lines[0].startswith("- sine-50Hz: **`mpc`** (0.050 %), 4.0x better than `pid-ff`")
    assert "5.0x `mpc-oracle`" in lines[0]  # the oracle is a yardstick, not a winner
    assert lines[1].startswith("- steps: tie between `pid-ff`, `mpc`")


def test_missed_checks_are_what_strict_fails_on():
    checks = [{"holds": True}, {"holds": False}]
    assert missed_checks(checks) == [{"holds": False}]


def test_selections_cover_every_plant_kind():
    plants = set(itertools.chain.from_iterable(s[2] for s in SELECTIONS.values()))
    assert {"nominal", "random-plants"} <= plants and len(plants) >= 5
