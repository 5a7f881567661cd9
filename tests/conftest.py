"""Test-wide settings and shared fixtures.

Property-based tests draw the same examples on every run and machine: Hypothesis explores at
random by default, so a suite could pass on one run and fail on the next; derandomized, its
search is a fixed function of the test, like every other random draw here (seeded generators).
Explore more widely on purpose with ``HYPOTHESIS_PROFILE=explore``.

The suite runs on one process per core (pytest-xdist); a session fixture below is made once
per test process that uses it.

The short identification of the PL140 (:func:`fast_pl140_identification`) is made once: the
records tests compare the identification from files against it, the pipeline tests a second run
of the same settings.

The PID presets tuned on the committed identified model (:func:`identified_pid_presets`) are
built once: tuning over the datasheet's tolerance box takes seconds per controller, and every
test that uses them starts an episode with ``reset``, which restarts a controller's state and
its statistics.

The adaptive MPC on the committed benchmark model (:func:`benchmark_adaptive_mpc`) is built
once for the same reason (its set's members take seconds); ``reset`` starts it afresh from the
identified model, and the fixture resets it before each test.

The tests that need an open Ray connection share one (:func:`ray_connection`): a local Ray
instance takes seconds to start and its workers seconds more to import the project, and what
those tests check (task order, errors, a user's controller on Ray workers) does not depend on
whose connection it is. The path that starts and stops a private instance is tested on its
own (tests/test_backends.py).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

ROOT = Path(__file__).resolve().parents[1]
IDENTIFIED_MODEL = ROOT / "docs" / "identify" / "model"
"""The committed model of ``piezo identify`` (PL140)."""
BENCHMARK_MODEL = ROOT / "docs" / "benchmark" / "model"
"""The committed benchmark run's model (PL140, identification seed 0)."""

settings.register_profile("repeatable", derandomize=True, database=None)
settings.register_profile("explore", max_examples=2000, database=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))


@pytest.fixture(scope="session")
def fast_pl140_identification():
    """``identify`` of the PL140 with the short settings :data:`short_runs.FAST` and seed
    :data:`short_runs.FAST_SEED`, from the environment."""
    from short_runs import FAST, FAST_SEED

    from identification.config import IdentificationConfig
    from identification.pipeline import identify

    return identify(
        config=IdentificationConfig(seed=FAST_SEED, env_kwargs={"bender": "PL140"}, **FAST)
    )


@pytest.fixture(scope="session")
def identified_pid_presets() -> dict:
    """``pid``, ``pid-notch`` and ``pid-ff`` tuned on :data:`IDENTIFIED_MODEL` for the nominal
    PL140 with a preview of 20 samples, by name."""
    import gymnasium as gym

    import controllers

    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    model = controllers.prediction_model(str(IDENTIFIED_MODEL), env)
    return {name: controllers.make(name, model, env) for name in ("pid", "pid-notch", "pid-ff")}


@pytest.fixture(scope="session")
def _benchmark_adaptive_mpc_built():
    import gymnasium as gym

    import controllers

    env = gym.make("piezo_env:PiezoBender-v0", preview=20, bender="PL140")
    return controllers.make("mpc-adaptive", str(BENCHMARK_MODEL), env)


@pytest.fixture
def benchmark_adaptive_mpc(_benchmark_adaptive_mpc_built):
    """``mpc-adaptive`` on :data:`BENCHMARK_MODEL` for the nominal PL140 with a preview of 20
    samples, reset to rest (on the identified model, whatever an earlier test did with it)."""
    controller = _benchmark_adaptive_mpc_built
    controller.reset(np.zeros(controller.task.observation_size))
    return controller


@pytest.fixture(scope="session")
def _ray_closed_at_exit() -> Iterator[None]:
    """Shut down a Ray connection the tests left open when the session ends, so that no Ray
    process outlives the test run."""
    yield
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        ray.shutdown()


@pytest.fixture
def ray_connection(_ray_closed_at_exit: None, monkeypatch: pytest.MonkeyPatch):
    """An open local Ray connection with two CPUs, opened the way a user's script opens one
    (:func:`piezo_parallel.backends.connect_ray`, from the project folder, so that the workers
    import the project, its examples and the test modules) and kept open for the tests after
    this one; returns the ``ray`` module."""
    import ray

    from piezo_parallel.backends import connect_ray

    with monkeypatch.context() as patch:
        patch.chdir(ROOT)  # the workers' import path starts at the current folder
        connect_ray(jobs=2)
    return ray
