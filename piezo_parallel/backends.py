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
"""

from __future__ import annotations

import importlib.util
import os
import socket
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any

__all__ = [
    "BACKENDS",
    "RAY_INSTALL_HINT",
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
        ``"local"`` (a process pool of ``jobs`` spawned workers: no forked BLAS or torch thread
        state; a script using it needs the ``if __name__ == "__main__":`` guard) or ``"ray"``
        (see the module docstring).
    labels : sequence of str, optional
        One label per task for ``progress``.
    progress : callable, optional
        ``progress(done, total, label)`` after each task.
    address : str, optional
        Ray only: the cluster to run on (``"auto"``, ``"HOST:PORT"`` or ``"ray://HOST:PORT"``);
        default ``RAY_ADDRESS`` from the environment, else a private local instance.

    Raises
    ------
    ValueError
        An unknown backend.
    RuntimeError
        The ray backend without Ray installed.
    """
    check_backend(backend)
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    labels = list(labels) if labels is not None else [str(i) for i in range(len(tasks))]
    if backend == "ray":
        return _run_ray(function, tasks, jobs, labels, progress, address)
    if jobs == 1:
        return _run_here(function, tasks, labels, progress)
    return _run_pool(function, tasks, jobs, labels, progress)


def _run_here(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    labels: list[str],
    progress: Progress | None,
) -> list[Any]:
    results: list[Any] = []
    for i, task in enumerate(tasks):
        results.append(function(*task))
        if progress:
            progress(i + 1, len(tasks), labels[i])
    return results


def _run_pool(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    jobs: int,
    labels: list[str],
    progress: Progress | None,
) -> list[Any]:
    results: list[Any] = [None] * len(tasks)
    pool = ProcessPoolExecutor(jobs, mp_context=get_context("spawn"))
    try:
        futures = {pool.submit(function, *task): i for i, task in enumerate(tasks)}
        for done, future in enumerate(as_completed(futures), start=1):
            i = futures[future]
            results[i] = future.result()  # the first failure raises here, at once
            if progress:
                progress(done, len(tasks), labels[i])
    except BaseException:
        # Cancel what has not started instead of waiting for every task before raising.
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return results


def _run_ray(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    jobs: int,
    labels: list[str],
    progress: Progress | None,
    address: str | None,
) -> list[Any]:
    import ray

    started = connect_ray(address, jobs=jobs)
    pending: list[Any] = []
    try:
        remote = ray.remote(_call).options(num_cpus=1, max_retries=0)
        index = {}
        for i, task in enumerate(tasks):
            ref = remote.remote(function, *task)
            index[ref] = i
            pending.append(ref)
        results: list[Any] = [None] * len(tasks)
        for done in range(1, len(tasks) + 1):
            # One at a time, so a failed task raises as soon as it ends.
            (ready,), pending = ray.wait(pending, num_returns=1)
            i = index[ready]
            results[i] = ray.get(ready)
            if progress:
                progress(done, len(tasks), labels[i])
        return results
    finally:
        if started:
            ray.shutdown()
        else:
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
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        _probe(address)
        ray.init(address=address, log_to_driver=False)
        return True
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
    return True


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
