"""Where independent tasks run: this process, a local pool of spawned workers, or Ray.

One home for distributed execution, used by the benchmark harness (episode groups), by RL
training (one seed per task) and by the identification (a helper process beside a run); it
imports nothing else of the project. See :mod:`piezo_parallel.backends`, for the local pool
that replaces a lost worker :mod:`piezo_parallel.pool`, and for the helper
:mod:`piezo_parallel.helper`.
"""

from piezo_parallel.backends import (
    BACKENDS,
    DEFAULT_RETRIES,
    RAY_INSTALL_HINT,
    Prerequisite,
    WorkerLost,
    check_backend,
    connect_ray,
    default_jobs,
    run_tasks,
)

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
