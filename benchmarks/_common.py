"""Shared pieces of the benchmark scripts: machine description, Markdown tables, result files."""

from __future__ import annotations

import datetime
import os
import platform
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import threadpoolctl

from benchmarks.machine import cpu_name

RESULTS = Path(__file__).parent / "results"


def machine_line() -> str:
    """One line naming the machine, Python, numpy and the BLAS threading in force."""
    blas = ", ".join(
        f"{info['internal_api']} {info['num_threads']} thread(s)"
        for info in threadpoolctl.threadpool_info()
        if info.get("user_api") == "blas"
    )
    return (
        f"{platform.platform()}, {cpu_name()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, numpy {np.__version__}; BLAS: {blas or 'unknown'}"
    )


def header(title: str, module: str, args: str = "") -> list[str]:
    """Title, date, machine and the command that produced the file.

    Parameters
    ----------
    title : str
        The file's title.
    module : str
        Dotted name of the script's module (``__spec__.name`` when run with ``python -m``, e.g.
        ``benchmarks.speed.env_speed``), so the file names the command that reproduces it.
    args : str
        The command's arguments, if any (e.g. ``--bender PL127 --model DIR``).
    """
    if not module.startswith("benchmarks.") or module.endswith(".py"):
        raise ValueError(
            f"module must be a dotted module name such as 'benchmarks.speed.env_speed', "
            f"got {module!r}"
        )
    command = f"python -m {module}" + (f" {args}" if args else "")
    return [
        f"# {title}",
        "",
        f"Date: {datetime.date.today().isoformat()}  ",
        f"Machine: {machine_line()}  ",
        f"Produced by `{command}`.",
        "",
    ]


def markdown_table(head: list[str], rows: list[list[str]]) -> str:
    """A Markdown table from a header and string rows."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def write_result(name: str, lines: list[str]) -> Path:
    """Print the report and write it to benchmarks/results/<name>.md."""
    text = "\n".join(lines) + "\n"
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.md"
    path.write_text(text, encoding="utf-8")
    return path


def single_env_step_times(
    env_id: str, steps: int, seed: int = 0, **settings: Any
) -> np.ndarray:
    """Per-step wall times (s) of ``steps`` random-action steps through gym.make (with the
    env's keyword ``settings``), with resets."""
    env = gym.make(env_id, **settings)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    times = np.empty(steps)
    clock = time.perf_counter
    for i, action in enumerate(actions):
        start = clock()
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
        times[i] = clock() - start
    env.close()
    return times


def same_model(a: Any, b: Any) -> bool:
    """Whether two Hammerstein models hold the same features, network and linear part, to
    the bit."""
    arrays_a, arrays_b = a.nls.arrays(), b.nls.arrays()
    return (
        a.nls.feature_map == b.nls.feature_map
        and arrays_a.keys() == arrays_b.keys()
        and all(np.array_equal(arrays_a[k], arrays_b[k]) for k in arrays_a)
        and np.array_equal(a.arx.a, b.arx.a)
        and np.array_equal(a.arx.b, b.arx.b)
        and a.arx.noise_bound == b.arx.noise_bound
    )
