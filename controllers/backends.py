"""Where the benchmark's episode groups run: in this process or in a local process pool.

A backend takes a picklable function and its argument tuples and returns the results in the
order of the arguments, whatever order the work finishes in; results therefore never depend on
the backend or the number of workers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any

__all__ = ["BACKENDS", "run_tasks"]

BACKENDS = ("local",)
"""Names accepted by :func:`run_tasks`."""

Progress = Callable[[int, int, str], None]


def run_tasks(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    *,
    jobs: int = 1,
    backend: str = "local",
    labels: Sequence[str] | None = None,
    progress: Progress | None = None,
) -> list[Any]:
    """``[function(*task) for task in tasks]``, possibly in parallel, in the tasks' order.

    Parameters
    ----------
    function : callable
        A module-level (picklable) function.
    tasks : sequence of tuple
        Positional arguments of each call.
    jobs : int
        Worker processes; 1 runs in this process.
    backend : str
        ``"local"`` (a process pool of ``jobs`` spawned workers: no forked BLAS or torch thread
        state; a script using it needs the ``if __name__ == "__main__":`` guard).
    labels : sequence of str, optional
        One label per task for ``progress``.
    progress : callable, optional
        ``progress(done, total, label)`` after each task.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    labels = list(labels) if labels is not None else [str(i) for i in range(len(tasks))]
    results: list[Any] = [None] * len(tasks)
    if jobs == 1:
        for i, task in enumerate(tasks):
            results[i] = function(*task)
            if progress:
                progress(i + 1, len(tasks), labels[i])
        return results
    with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(function, *task): i for i, task in enumerate(tasks)}
        for done, future in enumerate(as_completed(futures), start=1):
            i = futures[future]
            results[i] = future.result()
            if progress:
                progress(done, len(tasks), labels[i])
    return results
