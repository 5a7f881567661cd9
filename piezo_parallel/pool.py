"""A local pool of spawned worker processes that replaces a worker lost in the middle of a task.

Each worker is one :class:`multiprocessing.Process` (``spawn`` start method: no forked BLAS or
torch thread state) with its own :func:`multiprocessing.Pipe`, and runs one task at a time. The
pool waits on every worker's pipe and process sentinel at once
(:func:`multiprocessing.connection.wait`), so a worker that dies (the out-of-memory killer's
SIGKILL, a crash in native code) is known together with the task it was running and how it
ended. That worker alone is replaced and its task runs again, up to ``retries`` more times;
the other workers go on undisturbed. :class:`concurrent.futures.ProcessPoolExecutor` cannot do
this: one dead worker breaks the whole executor, every running task is lost with it, and which
task the dead worker held is not reported.

A run may have a *prerequisite*: one task (its own function) whose outcome some of the tasks
need, such as the model the benchmark identifies before the rows built on it can run. It runs on
one worker from the start while the other workers take the tasks that do not need it; when it
finishes, its ``then`` callback runs in this process, the tasks that waited join the queue and
its worker takes tasks as the others do. A worker that dies while running it is replaced as any
other.

Stopping is explicit. However the pool is left (results complete, a task's exception, an
interruption such as ``KeyboardInterrupt`` raised by a signal handler), every worker still
alive is sent SIGTERM, then SIGKILL after a grace period, and reaped; nothing is left running.
Workers ignore SIGINT (a Ctrl-C at a terminal reaches the whole process group; the parent
decides) and exit on their own within a second if their parent disappears without stopping
them (killed by SIGKILL).
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing import get_context
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any, NoReturn

__all__ = [
    "DEFAULT_RETRIES",
    "Prerequisite",
    "RemoteTraceback",
    "WorkerLost",
    "quick_exit",
    "run_pool",
]

DEFAULT_RETRIES = 2
"""Reruns of a task whose worker died, after its first attempt."""

STOP_GRACE_S = 3.0
"""How long stopped workers get to exit after SIGTERM before they are sent SIGKILL."""

_PARENT_POLL_S = 1.0


class WorkerLost(RuntimeError):
    """A task's worker died on every attempt: the first run and all its retries.

    The message is one line naming the task and how its worker ended (``killed by SIGKILL``).
    """

    @classmethod
    def of(cls, label: str, how: str, retries: int) -> WorkerLost:
        """The error for task ``label`` whose worker ``how`` (``"was killed by SIGKILL"``)."""
        if retries == 0:
            return cls(f"the worker running {label!r} {how} (no retries allowed)")
        times = "its one retry" if retries == 1 else f"each of its {retries} retries"
        return cls(f"the worker running {label!r} {how}, on its first attempt and on {times}")


class RemoteTraceback(Exception):
    """The traceback of a task's exception in its worker, chained as the ``__cause__``."""

    def __str__(self) -> str:
        return "\n" + str(self.args[0])


@dataclass(frozen=True)
class Prerequisite:
    """A task that others wait on (module docstring).

    Attributes
    ----------
    function : callable
        A module-level (picklable) function, run as ``function(*args)`` in a worker.
    args : tuple
        Its positional arguments.
    label : str
        Named when its worker is lost for good.
    then : callable
        ``then(result)``, called in this process when it finishes and before any task that
        waited on it starts; an exception it raises stops the run as a task's would.
    """

    function: Callable[..., Any]
    args: tuple
    label: str
    then: Callable[[Any], None]


_FIRST = -1
"""The task index of the prerequisite in the pool's bookkeeping."""


@dataclass(frozen=True)
class _Call:
    """A message to a worker: run this function instead of the pool's (the prerequisite)."""

    function: Callable[..., Any]
    args: tuple


@dataclass
class _Worker:
    process: BaseProcess
    conn: Connection
    task: int | None = None
    first: bool = False  # running the prerequisite


def run_pool(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    jobs: int,
    on_result: Callable[[int, Any], None],
    *,
    labels: Sequence[str],
    retries: int = DEFAULT_RETRIES,
    prerequisite: Prerequisite | None = None,
    waits: Sequence[bool] | None = None,
) -> None:
    """Run ``function(*task)`` for every task on ``jobs`` spawned workers.

    Parameters
    ----------
    function : callable
        A module-level (picklable) function; the workers import it by its module.
    tasks : sequence of tuple
        Positional arguments of each call.
    jobs : int
        Worker processes (at most one per task is started).
    on_result : callable
        ``on_result(index, result)``, called in this process as each task finishes, in the
        order they finish.
    labels : sequence of str
        One label per task, named when its worker is lost for good.
    retries : int
        Reruns of a task whose worker died, each on a new worker.
    prerequisite : Prerequisite, optional
        Started first, on one of the ``jobs`` workers (module docstring).
    waits : sequence of bool, optional
        With ``prerequisite``: which tasks wait for it (default: none). The others start in
        their order at once; the waiting ones, in their order, after its ``then``.

    Raises
    ------
    WorkerLost
        A task's worker (or the prerequisite's) died ``retries + 1`` times; the tasks still
        running are stopped.
    Exception
        The first exception a task raised (its worker's traceback chained as the cause); the
        tasks still running are stopped and the rest not started.
    """
    context = get_context("spawn")
    held = prerequisite is not None and waits is not None
    waiting = [i for i in range(len(tasks)) if held and waits[i]]  # type: ignore[index]
    queue = deque(i for i in range(len(tasks)) if not (held and waits[i]))  # type: ignore[index]
    attempts = [0] * len(tasks)
    first_attempts = 0
    workers: list[_Worker] = []
    pending_first = prerequisite is not None
    try:
        while pending_first or queue or any(w.task is not None for w in workers):
            if pending_first:  # (re)start the prerequisite on a new worker
                assert prerequisite is not None
                first = _start(context, function)
                first.first, first.task = True, _FIRST
                first_attempts += 1
                pending_first = False
                workers.append(first)
                _send(first, _Call(prerequisite.function, prerequisite.args))
            idle = sum(w.task is None for w in workers)
            while len(queue) > idle and len(workers) < jobs:  # a worker per task waiting
                workers.append(_start(context, function))
                idle += 1
            for worker in workers:
                if worker.task is None and queue:
                    index = queue.popleft()
                    attempts[index] += 1
                    worker.task = index
                    _send(worker, tasks[index])
            busy = [w for w in workers if w.task is not None]
            ready = set(wait([x for w in busy for x in (w.conn, w.process.sentinel)]))
            for worker in busy:
                if worker.conn not in ready and worker.process.sentinel not in ready:
                    continue
                index = worker.task
                outcome = _receive(worker)
                if outcome is None:  # the worker died
                    workers.remove(worker)
                    how = _ending(worker)
                    if worker.first:
                        assert prerequisite is not None
                        if first_attempts > retries:
                            raise WorkerLost.of(prerequisite.label, how, retries)
                        pending_first = True
                    elif attempts[index] > retries:
                        raise WorkerLost.of(labels[index], how, retries)
                    else:
                        queue.appendleft(index)
                    continue
                worker.task = None
                kind, value, text = outcome
                if kind == "error":
                    raise value from RemoteTraceback(text)
                if worker.first:  # its worker now takes tasks as the others do
                    assert prerequisite is not None
                    worker.first = False
                    prerequisite.then(value)
                    queue.extend(waiting)
                    continue
                on_result(index, value)
    finally:
        _stop(workers)


def _send(worker: _Worker, task: tuple | _Call) -> None:
    try:
        worker.conn.send(task)
    except (BrokenPipeError, ConnectionResetError):
        pass  # the worker is gone: its sentinel says so when the pool next waits


def _start(context: Any, function: Callable[..., Any]) -> _Worker:
    here, there = context.Pipe()
    process = context.Process(target=_serve, args=(there, function, os.getpid()), daemon=False)
    process.start()
    there.close()
    return _Worker(process, here)


def _receive(worker: _Worker) -> tuple[str, Any, str] | None:
    """The worker's answer, or None when it died (its pipe closed before an answer came)."""
    try:
        if worker.conn.poll():
            return worker.conn.recv()
    except (EOFError, OSError):
        return None
    return None


def _ending(worker: _Worker) -> str:
    """How a dead worker ended: ``was killed by SIGKILL`` or ``exited with status 1``."""
    worker.process.join()
    worker.conn.close()
    code = worker.process.exitcode
    if code is not None and code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with status {code}"


def _stop(workers: list[_Worker]) -> None:
    """Stop every worker: idle ones are told to exit, busy ones sent SIGTERM, and any still
    alive after :data:`STOP_GRACE_S` sent SIGKILL; all are reaped and their pipes closed."""
    for worker in workers:
        try:
            if worker.task is None:
                worker.conn.send(None)
            else:
                worker.process.terminate()
        except OSError:
            worker.process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for worker in workers:
        worker.process.join(max(0.0, deadline - time.monotonic()))
        if worker.process.is_alive():
            worker.process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for worker in workers:
        worker.process.join(max(0.0, deadline - time.monotonic()))
        if worker.process.is_alive():
            worker.process.kill()
            worker.process.join()
        worker.conn.close()
    workers.clear()


def _serve(conn: Connection, function: Callable[..., Any], parent: int) -> None:
    """A worker's loop: run each task received (``function(*task)``, or a :class:`_Call`'s
    own function), send back ("ok", result, "") or ("error", exception, traceback); exit on
    None or when the parent's end of the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for number in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(number, signal.SIG_DFL)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            quick_exit(0)
        if task is None:
            quick_exit(0)
        try:
            if isinstance(task, _Call):
                answer: tuple[str, Any, str] = ("ok", task.function(*task.args), "")
            else:
                answer = ("ok", function(*task), "")
        except Exception as error:
            answer = ("error", error, traceback.format_exc())
        try:
            conn.send(answer)
        except (BrokenPipeError, ConnectionResetError):
            quick_exit(0)
        except Exception as error:  # an unpicklable result or exception
            failure = RuntimeError(f"cannot send the task's outcome back: {error}")
            conn.send(("error", failure, traceback.format_exc()))


def quick_exit(status: int = 0) -> NoReturn:
    """End this process now with ``status``, after its exit handlers (:mod:`atexit`: the
    logging flush, ``weakref.finalize`` clean-ups) and a flush of stdout and stderr, but
    without the interpreter's finalization, which with torch loaded tears down thousands of
    modules and runs C++ destructors, slowly, and does nothing a finished process needs. Used
    where a process has done its work: a worker told to stop and the ``piezo`` command line.
    What finalization alone would do is lost: non-daemon threads are ended, not joined, with
    the hooks ``threading`` runs before joining them (the project starts no thread that outlives
    its work), and objects' ``__del__`` clean-ups do not run (files are closed by their
    ``with`` blocks, results are sent or written)."""
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing left to say
            pass
    os._exit(status)


def _exit_with_parent(parent: int) -> None:
    """End this worker at once when its parent is gone (it was killed without stopping us)."""
    while os.getppid() == parent:
        time.sleep(_PARENT_POLL_S)
    os._exit(1)
