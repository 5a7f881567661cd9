"""Where the benchmark's episode groups run: in this process, a local process pool, or Ray.

A backend takes a picklable function and its argument tuples and returns the results in the
order of the arguments, whatever order the work finishes in; results therefore never depend on
the backend or the number of workers.

Backends
--------
``"local"`` (the default)
    ``jobs == 1`` runs in this process; ``jobs > 1`` in a pool of spawned worker processes.
``"ray"``
    Every task is a Ray task asking for one CPU. By default a private Ray instance with ``jobs``
    CPUs is started on this machine for the call and shut down after it; with an address (the
    ``address`` argument, else the ``RAY_ADDRESS`` environment variable, Ray's own convention,
    the default of ``ray.init``) the tasks go to that existing cluster, which keeps running, and
    its CPUs, not ``jobs``, decide how many run at once. A Ray connection the caller already
    opened (``ray.init`` or :func:`connect_ray`, as ``piezo benchmark --address`` does before
    any work) is used as it is and left open. Ray is the optional extra
    ``pip install "piezo-testbed[ray]"`` and is imported only here, only when asked for.

    Workers import ``function`` by its module, so every node needs this project (same version)
    installed, and a path passed in ``tasks`` (the benchmark's model folder) must exist on every
    node (a shared file system, or the same files copied). On the local instance both hold: the
    workers use this Python environment and working directory. Ray sets ``OMP_NUM_THREADS`` to
    the task's one CPU, and the benchmark limits BLAS to one thread itself, so the numbers are
    bitwise those of the local backend.

Faults
------
A task whose worker process dies (SIGKILL from the out-of-memory killer, a crash in native
code) runs again on a new worker, up to ``retries`` times (the local pool replaces the worker,
Ray retries the task); after that :class:`piezo_parallel.pool.WorkerLost` names the task and
how its worker ended. Whatever ends a call early (that error, a task's exception, an
interruption raised in this process by a signal handler), the workers are stopped before it
returns: the local pool's processes are terminated and reaped, unfinished Ray tasks are
cancelled and a private Ray instance is shut down.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from piezo_parallel.pool import DEFAULT_RETRIES, Prerequisite, WorkerLost, run_pool

__all__ = [
    "BACKENDS",
    "DEFAULT_RETRIES",
    "RAY_INSTALL_HINT",
    "Prerequisite",
    "WorkerLost",
    "check_backend",
    "connect_ray",
    "default_jobs",
    "run_tasks",
]

BACKENDS = ("local", "ray")
"""Names accepted by :func:`run_tasks`."""

RAY_INSTALL_HINT = 'the ray backend needs the optional extra: pip install "piezo-testbed[ray]"'
"""The message when the ``"ray"`` backend is asked for and Ray is not installed."""

Progress = Callable[[int, int, str], None]


def check_backend(backend: str) -> None:
    """Raise before any work if ``backend`` is unknown or its package is not installed.

    Parameters
    ----------
    backend : str
        One of :data:`BACKENDS`.

    Raises
    ------
    ValueError
        An unknown name (the message lists the valid ones).
    RuntimeError
        ``"ray"`` without Ray installed (the message says how to install it).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if backend == "ray" and not _ray_installed():
        raise RuntimeError(RAY_INSTALL_HINT)


def _ray_installed() -> bool:
    """Whether Ray can be imported (found without importing it: that takes a second)."""
    return importlib.util.find_spec("ray") is not None


def run_tasks(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    *,
    jobs: int = 1,
    backend: str = "local",
    labels: Sequence[str] | None = None,
    progress: Progress | None = None,
    address: str | None = None,
    on_result: Callable[[int, Any], None] | None = None,
    retries: int = DEFAULT_RETRIES,
    prerequisite: Prerequisite | None = None,
    waits: Sequence[bool] | None = None,
) -> list[Any]:
    """``[function(*task) for task in tasks]``, possibly in parallel, in the tasks' order.

    Parameters
    ----------
    function : callable
        A module-level (picklable) function.
    tasks : sequence of tuple
        Positional arguments of each call.
    jobs : int
        Workers: processes of the local pool (1 runs in this process) or CPUs of the private
        Ray instance.
    backend : str
        ``"local"`` (a pool of ``jobs`` spawned workers, :mod:`piezo_parallel.pool`: no forked
        BLAS or torch thread state; a script using it needs the ``if __name__ ==
        "__main__":`` guard) or ``"ray"`` (see the module docstring).
    labels : sequence of str, optional
        One label per task for ``progress`` and for the error of a lost worker.
    progress : callable, optional
        ``progress(done, total, label)`` after each task.
    address : str, optional
        Ray only: the cluster to run on (``"auto"``, ``"HOST:PORT"`` or ``"ray://HOST:PORT"``);
        default ``RAY_ADDRESS`` from the environment, else a private local instance.
    on_result : callable, optional
        ``on_result(index, result)`` in this process as each task finishes (before
        ``progress``), so that a caller can keep finished work (a checkpoint) while the rest
        runs.
    retries : int
        Reruns of a task whose worker process died (killed by the out-of-memory killer, a
        crash in native code), each on a new worker: the local pool replaces the worker, Ray
        retries the task (``max_retries``). A task's own exception is never retried, and
        ``jobs == 1`` on the local backend runs in this process, with no worker to replace.
        Tasks must be deterministic functions of their arguments for a rerun to give the same
        result.
    prerequisite : piezo_parallel.pool.Prerequisite, optional
        A task the tasks flagged in ``waits`` need (the benchmark's identification). In the
        local pool it runs on one of the ``jobs`` workers beside the tasks that do not wait;
        in this process (``jobs == 1``) and on Ray it runs here, before every task.
    waits : sequence of bool, optional
        One flag per task: it starts only after ``prerequisite``'s ``then``.

    Raises
    ------
    ValueError
        An unknown backend.
    RuntimeError
        The ray backend without Ray installed.
    WorkerLost
        A task's worker died on its first attempt and on each retry.
    """
    check_backend(backend)
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    if retries < 0:
        raise ValueError(f"retries must be at least 0, got {retries}")
    labels = list(labels) if labels is not None else [str(i) for i in range(len(tasks))]
    if waits is not None and len(waits) != len(tasks):
        raise ValueError(f"waits has {len(waits)} flags for {len(tasks)} tasks; give one per task")
    results: list[Any] = [None] * len(tasks)
    done = 0

    def finished(index: int, result: Any) -> None:
        nonlocal done
        results[index] = result
        done += 1
        if on_result:
            on_result(index, result)
        if progress:
            progress(done, len(tasks), labels[index])

    pooled = backend == "local" and jobs > 1
    if prerequisite is not None and not pooled:
        prerequisite.then(prerequisite.function(*prerequisite.args))
    if backend == "ray":
        _run_ray(function, tasks, jobs, labels, finished, address, retries)
    elif jobs == 1:
        for i, task in enumerate(tasks):
            finished(i, function(*task))
    else:
        run_pool(
            function,
            tasks,
            jobs,
            finished,
            labels=labels,
            retries=retries,
            prerequisite=prerequisite,
            waits=waits,
        )
    return results


def _run_ray(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    jobs: int,
    labels: list[str],
    finished: Callable[[int, Any], None],
    address: str | None,
    retries: int,
) -> None:
    """Every task a Ray task; on any exit a private instance is shut down (its processes, the
    running tasks' workers among them, stopped) or, on a cluster that keeps running, the
    unfinished tasks are cancelled. (Cancelling tasks of a private instance just before its
    shutdown is not only needless: a task's reply racing the cancellation can abort the
    driver inside Ray's core, "Tried to complete task that was not pending".)"""
    import ray
    from ray.exceptions import NodeDiedError, OutOfMemoryError, WorkerCrashedError

    started = connect_ray(address, jobs=jobs)
    pending: list[Any] = []
    try:
        remote = ray.remote(_call).options(num_cpus=1, max_retries=retries)
        index = {}
        for i, task in enumerate(tasks):
            ref = remote.remote(function, *task)
            index[ref] = i
            pending.append(ref)
        while pending:
            # One at a time, so a failed task raises as soon as it ends.
            (ready,), pending = ray.wait(pending, num_returns=1)
            i = index[ready]
            try:
                result = ray.get(ready)
            except (WorkerCrashedError, OutOfMemoryError, NodeDiedError) as lost:
                cause = " ".join(str(lost).split())[:200]
                how = f"died ({type(lost).__name__}: {cause})"
                raise WorkerLost.of(labels[i], how, retries) from None
            finished(i, result)
    finally:
        if started:  # its processes, the tasks' workers among them, all stop with it
            ray.shutdown()
        else:  # a cluster that keeps running: the unfinished tasks are cancelled there
            for ref in pending:
                ray.cancel(ref, force=True)


def _call(function: Callable[..., Any], *args: Any) -> Any:
    """``function(*args)``: one Ray task (any picklable callable, builtins included)."""
    return function(*args)


def connect_ray(address: str | None = None, *, jobs: int = 1) -> bool:
    """Open this process's Ray connection unless one is open; True if this call opened it.

    Parameters
    ----------
    address : str, optional
        An existing cluster (``"auto"``, ``"HOST:PORT"``, ``"ray://HOST:PORT"``); default
        ``RAY_ADDRESS`` from the environment, else a private local instance started now.
    jobs : int
        CPUs of the private local instance (ignored for an existing cluster).

    Returns
    -------
    bool
        Whether the connection is new: who opened it closes it with ``ray.shutdown()``.
        :func:`run_tasks` leaves a connection opened before it open, so a command line can
        call this first to refuse an unreachable cluster before any work.

    Raises
    ------
    RuntimeError
        Ray is not installed.
    ConnectionError
        No cluster at ``address`` (a cluster with token authentication also needs
        ``RAY_AUTH_MODE=token`` and its token in this process's environment; see Ray's
        documentation).
    """
    check_backend("ray")
    import ray

    if ray.is_initialized():
        return False
    with _keeping_sigterm_handler():
        _init_ray(ray, address, jobs)
    return True


def _init_ray(ray: Any, address: str | None, jobs: int) -> None:
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        _probe(address)
        ray.init(address=address, log_to_driver=False)
        return
    # "local" starts a private instance even if `ray start` left one running on this machine.
    # Its processes inherit the environment at start: usage statistics stay off for them unless
    # the user asked for them, and this process's environment is left as it was.
    saved = os.environ.get("RAY_USAGE_STATS_ENABLED")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        # The workers import what this process can import, as spawned local workers do: its
        # sys.path (the current folder first), so a user's module is found by its entry point.
        folders = [os.getcwd(), *(p for p in sys.path if p and os.path.isdir(p))]
        path = os.pathsep.join(dict.fromkeys(folders))
        ray.init(
            address="local",
            num_cpus=jobs,
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
            runtime_env={"env_vars": {"PYTHONPATH": path}},
        )
    finally:
        if saved is None:
            del os.environ["RAY_USAGE_STATS_ENABLED"]


@contextmanager
def _keeping_sigterm_handler() -> Iterator[None]:
    """Put back this process's SIGTERM handler after ``ray.init``, which replaces it with one
    that exits at once: the caller's handler (``piezo`` stops its work and cleans up) stays."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = signal.getsignal(signal.SIGTERM)
    try:
        yield
    finally:
        if saved is not None:
            signal.signal(signal.SIGTERM, saved)


def _probe(address: str, timeout_s: float = 5.0) -> None:
    """Refuse a ``HOST:PORT`` nobody listens on: ``ray.init`` would retry it for many minutes."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        return  # "auto" and other forms Ray resolves itself
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as error:
        raise ConnectionError(f"nothing answers at {host}:{port} ({error})") from None


def default_jobs() -> int:
    """All cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover (not Linux)
        return os.cpu_count() or 1
