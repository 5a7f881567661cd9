"""Long runs that survive: SIGTERM stops a benchmark cleanly, a lost worker is replaced and its
task rerun, and an interrupted benchmark resumes to the bits of an uninterrupted one.

Processes are watched through /proc (Linux): the run's descendants are listed before the
signal and must all be gone (or zombies awaiting their reaper: no longer running) after it.
"""

from __future__ import annotations

import errno
import json
import multiprocessing
import operator
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import faulty
import pytest

from benchmarks.checkpoint import Checkpoint, CheckpointMismatch, run_identity
from benchmarks.report import deterministic_json, tracking_tables
from benchmarks.runner import BenchmarkConfig, run_benchmark
from piezo_cli.main import main
from piezo_cli.signals import Interrupted, signals_interrupt
from piezo_parallel.backends import WorkerLost, run_tasks

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")

MODEL_DIR = "docs/benchmark/model"
PROJECT = Path(__file__).resolve().parents[1]

SMALL = dict(
    controllers=("mpc",),
    references=("sine-10Hz", "steps"),
    plants=("nominal", "damping-0.01", "damping-0.04", "stiffness+20%"),
    steps=120,
)
"""Four groups of two short episodes each: the cheapest controller to build."""

ARGV = [
    "benchmark",
    "--model",
    MODEL_DIR,
    "--policies",
    "none",
    "--controllers",
    "mpc",
    "--references",
    "sine-10Hz,steps",
    "--plants",
    "nominal,damping-0.01,damping-0.04,stiffness+20%",
    "--quiet",
    "--steps",
    "120",
]


def _described(result) -> str:
    """The controllers' descriptions, each native library named by what ran (its path, key
    and digest), not by whether this process built it or found it in the cache."""
    described = json.loads(json.dumps(result.controllers))
    for description in described.values():
        for record in description.get("native", {}).values():
            record.pop("reason", None)
            record.pop("compiler_output", None)
    return json.dumps(described, sort_keys=True)


def _same(a, b) -> bool:
    """Bitwise equal tracking results, traces and controller descriptions."""
    return (
        json.dumps(deterministic_json(a)) == json.dumps(deterministic_json(b))
        and json.dumps(a.traces) == json.dumps(b.traces)
        and _described(a) == _described(b)
        and tracking_tables(a) == tracking_tables(b)
    )


@pytest.fixture(scope="module")
def uninterrupted():
    """The small benchmark run in one go, in this process."""
    return run_benchmark(BenchmarkConfig(**SMALL, jobs=1), MODEL_DIR)


# -- processes, as a test sees them ------------------------------------------------------------


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            children.setdefault(int(stat.rpartition(")")[2].split()[1]), []).append(int(entry))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def _running(pid: int) -> bool:
    """Alive and not a zombie (a zombie has ended; only its exit status waits for a reaper)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0] != "Z"
    except OSError:
        return False


def _wait_for(condition, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


# -- SIGTERM -----------------------------------------------------------------------------------


def _terminate_benchmark(out: Path, backend: str) -> tuple[int, str, list[int]]:
    """Start ``piezo benchmark`` (two workers), send it SIGTERM once a group has finished;
    its exit status, its stderr (read to the end) and the processes it had started."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(PROJECT), *sys.path]))}
    command = [sys.executable, "-m", "piezo_cli.main", *ARGV, "--jobs", "2", "--out", str(out)]
    command += ["--backend", backend]
    run = subprocess.Popen(
        command, cwd=PROJECT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    checkpoint = out / "checkpoint.jsonl"
    try:
        started = _wait_for(
            lambda: checkpoint.exists() and checkpoint.read_text().count("\n") >= 2, 120
        )
        assert started, "no group finished"
        processes = _descendants(run.pid)
        assert len(processes) >= 2  # the workers (and multiprocessing's resource tracker)
        run.send_signal(signal.SIGTERM)
        _, err = run.communicate(timeout=60)  # read to the end: nothing holds the pipes
    finally:
        run.kill()
    return run.returncode, err, processes


def _assert_stopped_cleanly(status: int, err: str, processes: list[int], out: Path) -> int:
    """Exit 143 with one line, every process gone, what finished kept and marked incomplete;
    the number of groups kept."""
    assert status == 128 + signal.SIGTERM, err[-2000:]
    assert err.splitlines()[-1] == "piezo benchmark: interrupted by SIGTERM"
    assert "Traceback" not in err and "leaked" not in err
    assert _wait_for(lambda: not any(_running(p) for p in processes), 10)
    names = {p.name for p in out.iterdir()}
    assert "benchmark.json" not in names and "benchmark.md" not in names
    marker = (out / "INCOMPLETE.txt").read_text()
    assert "was interrupted" in marker and "--resume" in marker
    kept = (out / "checkpoint.jsonl").read_text().count("\n") - 1
    assert 1 <= kept < 4
    return kept


def test_sigterm_stops_a_benchmark_leaves_no_process_and_resume_finishes_it(
    tmp_path, uninterrupted
):
    out = tmp_path / "out"
    kept = _assert_stopped_cleanly(*_terminate_benchmark(out, "local"), out)
    assert "interrupted by SIGTERM" in (out / "INCOMPLETE.txt").read_text()

    # Resumed with the same --out: only the missing groups run, and the result is the
    # uninterrupted run's, bit for bit.
    assert main([*ARGV, "--jobs", "1", "--out", str(out), "--resume"]) == 0
    data = json.loads((out / "benchmark.json").read_text())
    assert data["meta"]["resumed_groups"] == kept
    assert json.dumps(data["results"]) == json.dumps(deterministic_json(uninterrupted))
    assert not (out / "INCOMPLETE.txt").exists()


@pytest.mark.slow
def test_sigterm_on_ray_cancels_the_tasks_and_shuts_the_private_instance_down(tmp_path):
    out = tmp_path / "out"
    _assert_stopped_cleanly(*_terminate_benchmark(out, "ray"), out)


@pytest.mark.slow
def test_ray_retries_a_task_whose_worker_was_killed(tmp_path):
    results = run_tasks(
        faulty.die_once, [(i, str(tmp_path)) for i in range(4)], jobs=2, backend="ray"
    )
    assert results == [0, 3, 6, 9] and [p.name for p in tmp_path.iterdir()] == ["died-2"]
    with pytest.raises(WorkerLost, match=r"'b' died .*on its first attempt and on its one retry"):
        run_tasks(faulty.always_die, [(0,), (1,)], jobs=2, backend="ray", retries=1, labels="ab")


def test_signals_raise_interrupted_once_and_handlers_come_back():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as stopped:
        with signals_interrupt() as caught:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(1)
    assert (stopped.value.status, stopped.value.name, caught.signum) == (129, "SIGHUP", 1)
    assert signal.getsignal(signal.SIGTERM) == before


# -- a lost worker -----------------------------------------------------------------------------


def test_the_local_pool_replaces_a_killed_worker_and_reruns_its_task(tmp_path):
    results = run_tasks(faulty.die_once, [(i, str(tmp_path)) for i in range(6)], jobs=2)
    assert results == [3 * i for i in range(6)]
    assert [p.name for p in tmp_path.iterdir()] == ["died-2"]
    message = "'t1' was killed by SIGKILL, on its first attempt and on its one retry"
    with pytest.raises(WorkerLost, match=message):
        run_tasks(
            faulty.always_die, [(i,) for i in range(4)], jobs=2, retries=1, labels=["t0", "t1"] * 2
        )
    assert multiprocessing.active_children() == []
    with pytest.raises(ValueError, match="retries must be at least 0"):
        run_tasks(operator.neg, [(1,)], retries=-1)


def test_a_worker_killed_mid_episode_is_replaced_and_the_results_are_unchanged(tmp_path):
    config = dict(SMALL, controllers=("killed=faulty:KilledWorker",), plants=("nominal",))
    options = {"killed": {"marker": str(tmp_path)}}
    disturbed = run_benchmark(
        BenchmarkConfig(**config, jobs=2, controller_options=options), MODEL_DIR
    )
    assert [p.name for p in tmp_path.iterdir()] == ["killed-0"]  # one worker died
    undisturbed = run_benchmark(  # the marker is there: nobody dies
        BenchmarkConfig(**config, jobs=1, controller_options=options), MODEL_DIR
    )
    assert _same(disturbed, undisturbed)


def test_a_worker_lost_for_good_stops_the_run_in_one_line(tmp_path, capsys):
    out, marker = tmp_path / "out", tmp_path / "marker"
    marker.mkdir()
    argv = [*ARGV, "--controllers", "killed=faulty:KilledWorker", "--plants", "nominal"]
    argv += ["--option", f"killed.marker={marker}", "--retries", "0", "--jobs", "2"]
    assert main([*argv, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.splitlines() == [
        "piezo benchmark: the worker running 'killed on nominal' was killed by SIGKILL (no "
        "retries allowed)"
    ]
    assert [p.name for p in marker.iterdir()] == ["killed-0"]
    assert not out.exists()  # nothing had finished: nothing is left
    assert multiprocessing.active_children() == []


@pytest.mark.parametrize(
    ("fault", "line"),
    [
        ("act", "the row 'broken' failed on the nominal plant: RuntimeError: boom at step 30"),
        (
            "nan-action",
            "the row 'broken' failed on the nominal plant: ValueError: the env refused the "
            "action of 'Broken' at step",
        ),
        ("build", "the row 'broken' failed on the nominal plant: RuntimeError: cannot build"),
        ("describe", "broken: describe() cannot be written as JSON: object"),
    ],
)
def test_a_users_faulty_row_stops_the_run_in_one_line_naming_it(fault, line, tmp_path, capsys):
    out = tmp_path / "out"
    argv = [*ARGV, "--controllers", "broken=faulty:Broken", "--plants", "nominal"]
    assert main([*argv, "--option", f"broken.fault={fault}", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"piezo benchmark: {line}"), err


def test_an_earlier_runs_figures_do_not_stay_in_the_output_folder(tmp_path):
    """A figure this run does not draw must not be left from an earlier run in the same
    folder: the report would link it as this run's."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "adaptation.png").write_bytes(b"an earlier run's figure")
    (out / "notes.txt").write_text("the user's own file")
    argv = [*ARGV, "--controllers", "pid-ff", "--plants", "nominal", "--out", str(out)]
    assert main(argv) == 0
    assert not (out / "adaptation.png").exists()
    assert (out / "notes.txt").read_text() == "the user's own file"


def test_numpy_values_in_a_users_description_are_written_as_numbers(tmp_path):
    out = tmp_path / "out"
    argv = [*ARGV, "--controllers", "broken=faulty:Broken", "--plants", "nominal"]
    assert main([*argv, "--option", "broken.fault=none", "--out", str(out)]) == 0
    described = json.loads((out / "benchmark.json").read_text())["controllers"]["broken"]
    assert described["gains"] == [0, 1, 2] and described["ms"] == 1.5


# -- resume ------------------------------------------------------------------------------------


def test_interrupted_twice_then_resumed_equals_the_uninterrupted_run(tmp_path, uninterrupted):
    config = BenchmarkConfig(**SMALL, jobs=1)
    identity = run_identity(config, MODEL_DIR)
    path = tmp_path / "checkpoint.jsonl"

    def stop_at(group: int):
        def progress(done: int, total: int, label: str) -> None:
            if done == group:
                raise KeyboardInterrupt

        return progress

    checkpoint = Checkpoint.start(tmp_path, identity)
    for group in (1, 3):  # interrupted after the first group, then resumed and interrupted again
        with pytest.raises(KeyboardInterrupt):
            run_benchmark(config, MODEL_DIR, progress=stop_at(group), checkpoint=checkpoint)
        checkpoint = Checkpoint.resume(tmp_path, identity)
        assert len(checkpoint.finished) == group
    with path.open("ab") as file:  # a write cut short by a crash: dropped on resume
        file.write(b'{"digest": "')
    checkpoint = Checkpoint.resume(tmp_path, identity)
    seen = []
    resumed = run_benchmark(
        config, MODEL_DIR, checkpoint=checkpoint, progress=lambda *a: seen.append(a)
    )
    assert seen == [(4, 4, "mpc on stiffness+20%")]  # only the missing group ran
    assert _same(resumed, uninterrupted)
    assert path.read_text().count("\n") == 1 + 4


def test_a_checkpoint_of_another_run_is_refused_saying_what_changed(tmp_path, capsys):
    config = BenchmarkConfig(**SMALL, jobs=1)
    identity = run_identity(config, MODEL_DIR)
    Checkpoint.start(tmp_path, identity)
    changed = json.loads(json.dumps(identity))
    changed["code"]["controllers/predictive.py"] = "0" * 64
    changed["native"]["compiler"] = "/usr/bin/cc: other 1.0"
    with pytest.raises(CheckpointMismatch) as refused:
        Checkpoint.resume(tmp_path, changed)
    message = str(refused.value)
    assert "the code (controllers/predictive.py)" in message
    assert "native-code identity (compiler:" in message and "\n" not in message
    argv = [*ARGV[:-1], "200", "--out", str(tmp_path), "--resume"]  # --steps 200, not 120
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "the configuration (steps: 120 -> 200) changed" in err[0]


def test_an_output_folder_unwritable_mid_run_is_one_clean_error(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    append = Checkpoint.append

    def lose_the_folder(self, group, output):
        if self.finished:  # the second group: the folder has become read-only
            out.chmod(0o500)
            self.path.chmod(0o400)
            if os.geteuid() == 0:  # root writes anyway: fail as the file system would
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self.path))
        return append(self, group, output)

    monkeypatch.setattr(Checkpoint, "append", lose_the_folder)
    try:
        status = main([*ARGV, "--plants", "nominal,damping-0.04", "--jobs", "1", "--out", str(out)])
    finally:
        out.chmod(0o755)
        (out / "checkpoint.jsonl").chmod(0o644)
    assert status == 1
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"piezo benchmark: cannot write {out / 'checkpoint.jsonl'}: Permission denied"
    ]
    assert (out / "checkpoint.jsonl").read_text().count("\n") == 2  # the first group is kept
    assert not (out / "benchmark.json").exists()
    assert multiprocessing.active_children() == []


# -- a prerequisite (the identification) beside the tasks that do not need it ---------------


def _prerequisite_run(tmp_path, function, jobs, retries=2):
    from piezo_parallel import Prerequisite

    waits = [False, True, False, True, True]
    called = []
    prerequisite = Prerequisite(
        function, (str(tmp_path),), label="first", then=lambda result: called.append(result)
    )
    results = run_tasks(
        faulty.beside_or_after,
        [(i, str(tmp_path), w) for i, w in enumerate(waits)],
        jobs=jobs,
        prerequisite=prerequisite,
        waits=waits,
        retries=retries,
    )
    return waits, called, results


def test_tasks_that_wait_for_a_prerequisite_start_after_it_and_the_others_beside_it(tmp_path):
    # after_beside finishes only once a task that does not wait has run: the pool ran the two
    # at once (a pool that ran it first and alone would time out)
    waits, called, results = _prerequisite_run(tmp_path, faulty.after_beside, jobs=2)
    assert called == ["ready"]
    assert [i for i, _ in results] == list(range(len(waits)))
    assert all(after for (_, after), w in zip(results, waits, strict=True) if w)
    assert multiprocessing.active_children() == []


def test_a_prerequisite_whose_worker_dies_runs_again_on_a_new_one(tmp_path):
    waits, called, results = _prerequisite_run(tmp_path, faulty.prerequisite_dies_once, jobs=2)
    assert called == ["ready"] and (tmp_path / "died-first").exists()
    assert all(after for (_, after), w in zip(results, waits, strict=True) if w)
    (tmp_path / "died-first").unlink()
    with pytest.raises(WorkerLost, match="'first' was killed by SIGKILL"):
        _prerequisite_run(tmp_path, faulty.always_die_first, jobs=2, retries=0)
    assert multiprocessing.active_children() == []


def test_without_a_pool_the_prerequisite_runs_first_in_this_process(tmp_path):
    _, called, results = _prerequisite_run(tmp_path, faulty.mark_ready, jobs=1)
    assert called == ["ready"] and all(after for _, after in results)


def test_a_prerequisite_that_fails_stops_the_run_before_the_tasks_that_wait(tmp_path):
    with pytest.raises(ValueError, match="the prerequisite broke"):
        _prerequisite_run(tmp_path, faulty.prerequisite_fails, jobs=2)
    started = {p.name for p in tmp_path.iterdir() if p.name.startswith("started-")}
    assert started <= {"started-0", "started-2"}  # no task that waits
    assert multiprocessing.active_children() == []
    with pytest.raises(ValueError, match="one per task"):
        run_tasks(operator.neg, [(1,)], waits=[True, False])


def test_a_benchmark_identifying_its_model_runs_the_oracles_beside_it_to_the_same_bits(tmp_path):
    from piezo_parallel import Prerequisite

    config = BenchmarkConfig(**{**SMALL, "controllers": ("mpc", "mpc-oracle")}, jobs=2)
    model = str(tmp_path / "model")
    opened = []

    def open_checkpoint(timing):
        opened.append(Checkpoint.start(tmp_path, run_identity(config, model)))
        return opened[-1]

    identification = Prerequisite(
        faulty.copy_model, (str(PROJECT / MODEL_DIR), model), "copy", then=open_checkpoint
    )
    in_process = BenchmarkConfig(**{**SMALL, "controllers": ("mpc", "mpc-oracle")})
    beside = run_benchmark(config, model, identification=identification)
    given = run_benchmark(in_process, model)
    # the results, as test_benchmark holds one and two jobs to them (the descriptions can name
    # another state of the native cache in a worker)
    assert json.dumps(deterministic_json(beside)) == json.dumps(deterministic_json(given))
    assert json.dumps(beside.traces) == json.dumps(given.traces)
    assert tracking_tables(beside) == tracking_tables(given)
    resumed = Checkpoint.resume(tmp_path, run_identity(config, model))
    assert len(opened) == 1 and len(resumed.finished) == len(config.runs())
    with pytest.raises(ValueError, match="identification's then"):
        run_benchmark(config, model, identification=identification, checkpoint=opened[0])


def test_runs_that_finish_before_the_models_exist_reach_the_checkpoint_once_it_opens(
    tmp_path, monkeypatch
):
    """The pool's order made certain: every task that does not wait finishes before the
    identification ends (on a machine where it is slow), then the rest."""
    import benchmarks.runner as runner
    from piezo_parallel import Prerequisite

    def beside_first(function, tasks, *, prerequisite, waits, on_result, progress, **_):
        order = [i for i, w in enumerate(waits) if not w] + [i for i, w in enumerate(waits) if w]
        for n, i in enumerate(order):
            if n == waits.count(False):
                prerequisite.then(prerequisite.function(*prerequisite.args))
            on_result(i, function(*tasks[i]))
            progress(n + 1, len(tasks), str(i))

    config = BenchmarkConfig(**{**SMALL, "controllers": ("mpc-oracle", "mpc")})
    model = str(tmp_path / "model")
    shown = []
    identification = Prerequisite(
        faulty.copy_model,
        (str(PROJECT / MODEL_DIR), model),
        "copy",
        then=lambda timing: Checkpoint.start(tmp_path, run_identity(config, model)),
    )
    monkeypatch.setattr(runner, "run_tasks", beside_first)
    beside = run_benchmark(
        config, model, identification=identification, progress=lambda *a: shown.append(a[0])
    )
    monkeypatch.undo()
    assert _same(beside, run_benchmark(config, model))
    # the progress is held while the models are identified, then shown from where it is
    assert shown == list(range(len(SMALL["plants"]), len(config.runs()) + 1))
    kept = Checkpoint.resume(tmp_path, run_identity(config, model)).finished
    assert len(kept) == len(config.runs())


def test_the_prerequisites_worker_takes_the_tasks_after_it():
    from piezo_parallel.pool import Prerequisite, run_pool

    ran: dict[int, int] = {}
    first: list[int] = []
    prerequisite = Prerequisite(faulty.process_id, (), "first", then=first.append)
    run_pool(
        faulty.process_id,
        [(i,) for i in range(3)],
        1,
        ran.__setitem__,
        labels=["a", "b", "c"],
        prerequisite=prerequisite,
        waits=[True, True, True],
    )
    assert set(ran.values()) == set(first) and first[0] != os.getpid()  # one spawned worker


def test_the_pool_starts_no_more_workers_than_tasks_to_run(monkeypatch):
    import piezo_parallel.pool as pool

    started = []
    original = pool._start

    def counted(context, function):
        started.append(1)
        return original(context, function)

    monkeypatch.setattr(pool, "_start", counted)
    first: list[int] = []
    prerequisite = pool.Prerequisite(faulty.process_id, (), "first", then=first.append)
    ran: dict[int, int] = {}
    pool.run_pool(
        faulty.process_id, [(0,), (1,)], 4, ran.__setitem__, labels=["a", "b"],
        prerequisite=prerequisite, waits=[False, True],
    )
    assert len(ran) == 2 and len(started) == 2  # the prerequisite's and one for task a
    started.clear()
    pool.run_pool(faulty.process_id, [(0,), (1,)], 4, ran.__setitem__, labels=["a", "b"])
    assert len(started) == 2
