"""The MPC at 10 kHz: the PL140 at 0.1 ms (model identified there, committed in
``tests/data/pl140-0.1ms-model``), on a reference far beyond what the bender can follow, so that
the QP solver runs at every step. Step counts and solver iterations, never wall-clock times
(``benchmarks/speed/controller_latency.py`` measures those)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import controllers

MODEL_10KHZ = str(Path(__file__).resolve().parent / "data" / "pl140-0.1ms-model")
DT = 1e-4


@pytest.fixture(scope="module")
def env():
    return gym.make("piezo_env:PiezoBender-v0", preview=20, dt=DT)


def test_the_committed_model_was_identified_at_10_khz(env):
    mpc = controllers.make("mpc", MODEL_10KHZ, env)
    assert mpc.model.dt == DT and mpc.task.dt == DT


@pytest.mark.parametrize("amplitude_um", [500.0, 1500.0])
def test_mpc_solves_a_qp_at_every_step_of_a_saturating_500_hz_sine(env, amplitude_um):
    """500 Hz, three times the first resonance: the drive saturates on 60 % of the steps and
    every step is a constrained QP. DAQP solves each one from the last active set (measured:
    at most 17 and 19 iterations; the cap asserted, 2 M = 40, is what adding and then dropping
    each of the M = 20 bounds once would take), and none falls back."""
    mpc = controllers.make("mpc", MODEL_10KHZ, env)
    t = np.arange(2021) * DT
    reference = amplitude_um * np.sin(2 * np.pi * 500.0 * t)
    episode = controllers.run_episode(env, mpc, seed=0, reference=reference, max_steps=2000)
    stats = episode.controller["stats"]
    assert stats["steps"] == 2000 and stats["status"] == {"solved": 2000}
    assert stats["fallbacks"] == 0 and 0 < stats["max_iterations"] <= 2 * 20
    assert episode.metrics["solver_iterations_max"] == stats["max_iterations"]
    assert episode.metrics["saturated_fraction"] > 0.5
    assert episode.controller["qp_solver"].startswith("daqp")


def test_mpc_at_10_khz_tracks_a_smooth_reference_at_the_noise_floor(env):
    """The 50 Hz benchmark sine at 0.1 ms: the same accuracy as at 1 ms (0.005 % there)."""
    from benchmarks.references import make_reference

    mpc = controllers.make("mpc", MODEL_10KHZ, env)
    reference = make_reference("sine-50Hz", 2021, dt=DT, seed=0)
    episode = controllers.run_episode(env, mpc, seed=0, reference=reference, max_steps=2000)
    assert episode.metrics["rmse_percent"] < 0.02  # measured 0.0052 % over these 0.2 s
    assert episode.controller["stats"]["fallbacks"] == 0


def test_piezo_benchmark_runs_at_the_models_sample_time(tmp_path, capsys):
    """``piezo benchmark --model`` of a 0.1 ms model steps every env at 0.1 ms (no --dt
    needed); a --dt the model was not identified at is refused in one line, nothing written."""
    import json

    from piezo_cli.main import main

    out = tmp_path / "b"
    common = ["--controllers", "mpc", "--plants", "nominal", "--references", "steps"]
    status = main(
        [
            "benchmark",
            "--model",
            MODEL_10KHZ,
            *common,
            "--steps",
            "300",
            "--policies",
            "none",
            "--out",
            str(out),
            "--quiet",
            "--jobs",
            "1",
        ]
    )
    assert status == 0
    data = json.loads((out / "benchmark.json").read_text())
    assert data["meta"]["dt"] == DT and data["results"]["config"]["dt"] == DT
    assert data["results"]["episodes"][0]["solver_iterations_max"] > 0
    capsys.readouterr()
    refused = tmp_path / "refused"
    status = main(
        [
            "benchmark",
            "--model",
            MODEL_10KHZ,
            "--dt",
            "1e-3",
            *common,
            "--policies",
            "none",
            "--out",
            str(refused),
        ]
    )
    assert status == 2 and not refused.exists()
    assert "identified at dt = 0.0001 s" in capsys.readouterr().err
