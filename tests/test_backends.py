"""Backends of the benchmark: task order, refusals, and Ray bitwise equal to the local runs.

The Ray tests that need an open connection share the session's (``ray_connection`` in
tests/conftest.py), shut down when the session ends so that no Ray process outlives the test
run; the default path, a private instance started and shut down by the call itself, has its own
test. Ray is in the ``test`` extra, so these tests run in CI rather than skip.
"""

from __future__ import annotations

import json
import operator

import faulty
import pytest

from benchmarks.report import deterministic_json, tracking_tables
from benchmarks.runner import BenchmarkConfig, run_benchmark
from piezo_cli.main import main
from piezo_parallel.backends import BACKENDS, RAY_INSTALL_HINT, check_backend, run_tasks

MODEL_DIR = "docs/identify/model"

SMALL = dict(
    controllers=("pid-ff", "mpc"),
    references=("sine-10Hz", "steps"),
    plants=("nominal",),
    steps=100,
    jobs=2,
)


def _refuse(*args, **kwargs):
    raise AssertionError("work started before the arguments were checked")


@pytest.fixture
def no_ray_connection() -> None:
    """No Ray connection open in this process: the shared one of tests that ran earlier
    (``ray_connection``) is shut down (the next test that needs it opens it again)."""
    import sys

    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        ray.shutdown()


def test_backends_list_ray_and_refuse_unknown_names():
    assert BACKENDS == ("local", "ray")
    with pytest.raises(ValueError, match="unknown backend 'dask'; valid: local, ray"):
        run_tasks(operator.neg, [(1,)], backend="dask")
    with pytest.raises(ValueError, match="unknown backend"):
        BenchmarkConfig(backend="dask")
    check_backend("ray")  # installed through the test extra


def test_missing_ray_is_one_clear_error(monkeypatch):
    monkeypatch.setattr("piezo_parallel.backends._ray_installed", lambda: False)
    with pytest.raises(RuntimeError, match=r'pip install "piezo-testbed\[ray\]"'):
        run_tasks(operator.neg, [(1,)], backend="ray")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--backend", "dask"], "unknown backend 'dask'; valid: local, ray"),
        (["--backend", "ray", "--address", ""], "--address needs a Ray address"),
        (["--address", "auto"], "--address is for --backend ray"),
        (["--backend", "ray", "--address", "127.0.0.1:1"], "cannot connect to the Ray cluster"),
    ],
)
def test_cli_refuses_bad_backends_in_one_line_before_any_work(
    argv, message, monkeypatch, tmp_path, capsys, no_ray_connection
):
    monkeypatch.setattr("benchmarks.runner.run_benchmark", _refuse)
    monkeypatch.setattr("identification.pipeline.identify", _refuse)
    assert main(["benchmark", *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1


def test_cli_without_ray_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr("piezo_parallel.backends._ray_installed", lambda: False)
    monkeypatch.setattr("benchmarks.runner.run_benchmark", _refuse)
    monkeypatch.setattr("identification.pipeline.identify", _refuse)
    assert main(["benchmark", "--backend", "ray", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert RAY_INSTALL_HINT in err and len(err.splitlines()) == 1


def test_local_backend_keeps_task_order_with_a_pool():
    seen = []
    results = run_tasks(
        operator.mul,
        [(i, 3) for i in range(7)],
        jobs=2,
        labels=[f"t{i}" for i in range(7)],
        progress=lambda done, total, label: seen.append((done, total, label)),
    )
    assert results == [3 * i for i in range(7)]
    assert [d for d, _, _ in seen] == list(range(1, 8)) and {t for _, t, _ in seen} == {7}
    assert sorted(label for _, _, label in seen) == sorted(f"t{i}" for i in range(7))


def test_the_default_ray_path_starts_a_private_instance_and_shuts_it_down(no_ray_connection):
    """Without an open connection ``run_tasks`` starts a private Ray instance (the tasks see it
    running) and shuts it down after. Builtin tasks: the benchmark's own tasks on Ray are the
    next test's, on the shared connection, which :func:`connect_ray` opens as this path does."""
    import ray

    running = []
    results = run_tasks(
        operator.mul,
        [(i, 3) for i in range(4)],
        jobs=2,
        backend="ray",
        progress=lambda done, total, label: running.append(ray.is_initialized()),
    )
    assert results == [0, 3, 6, 9]
    assert running == [True] * 4
    assert not ray.is_initialized()


def test_small_benchmark_on_ray_is_bitwise_equal_to_local(ray_connection):
    """The reference runs in this process (``jobs=1``); tests/test_benchmark.py shows the local
    pool's results equal to those bit for bit."""
    local = run_benchmark(BenchmarkConfig(**{**SMALL, "jobs": 1}, backend="local"), MODEL_DIR)
    on_ray = run_benchmark(BenchmarkConfig(**SMALL, backend="ray"), MODEL_DIR)
    assert tracking_tables(on_ray) == tracking_tables(local)
    assert json.dumps(deterministic_json(on_ray)) == json.dumps(deterministic_json(local))
    assert json.dumps(on_ray.traces) == json.dumps(local.traces)
    assert len(on_ray.episodes) == 2 * 2
    assert ray_connection.is_initialized()


def test_ray_backend_keeps_task_order_and_reports_progress(ray_connection):
    seen = []
    results = run_tasks(
        operator.mul,
        [(i, 3) for i in range(9)],
        jobs=2,
        backend="ray",
        labels=[f"t{i}" for i in range(9)],
        progress=lambda done, total, label: seen.append((done, total, label)),
    )
    assert results == [3 * i for i in range(9)]
    assert [d for d, _, _ in seen] == list(range(1, 10)) and {t for _, t, _ in seen} == {9}
    assert sorted(label for _, _, label in seen) == sorted(f"t{i}" for i in range(9))
    assert ray_connection.is_initialized()  # a connection the caller opened stays open


def test_ray_backend_raises_the_task_error(ray_connection):
    # Workers import the function by its module, which a test file is not: use a builtin.
    with pytest.raises(ZeroDivisionError):
        run_tasks(operator.truediv, [(1, 1), (1, 0), (2, 1)], jobs=2, backend="ray")



def test_the_local_pool_raises_the_first_failure_without_running_the_rest(tmp_path):
    with pytest.raises(ValueError, match="task 0 broke"):
        run_tasks(faulty.fail_first, [(i, str(tmp_path)) for i in range(12)], jobs=2)
    # Raised as soon as task 0 failed: the tasks not yet started are cancelled, not run.
    assert len(list(tmp_path.iterdir())) <= 4
