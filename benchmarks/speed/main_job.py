"""How long a user waits: the main commands' wall times, in seconds of this machine and of the
reference machine.

Each command runs as a user runs it, in a fresh process with a fresh output folder and an empty
native-code cache (``PIEZO_CACHE``; as on a fresh clone, its C kernels are compiled within the
command):

- ``piezo benchmark``: the quick start (identification included);
- ``piezo identify``: the default identification with its report and figures;
- ``piezo benchmark --bender PL127``: the PL127 at its rate (0.25 ms);

and the identification on the ``bench`` plant (amplifier, sensor, rate-dependent hysteresis),
``identification.identify(jobs=2)`` as ``piezo identify`` runs it, for identification seeds 0-4,
each in a fresh process that times the call alone (after its imports and first training).

Machines of one kind differ, and one machine differs from minute to minute: the same 2-core
virtual machine has measured a CartPole-v1 step at 5.2-13 us (``benchmarks/results/env_speed.md``,
``controller_latency.md`` and their history), and at 7.3-12.9 us within one run of this script.
So, as every speed figure of the project, the times are also given against a step of
CartPole-v1 measured while the command runs: a thread of this process (idle otherwise, waiting
for the command) times a burst of CartPole steps through ``gymnasium.make`` every
``SAMPLE_EVERY_S`` seconds, and the command's CartPole step is the median over its bursts of
each burst's median step. A burst that the command's processes crowd off a core loses whole
steps to the scheduler, not a part of each: its median still times the core, not its share
(1.2 % of the machine at most). Reference-machine seconds are ``wall x REFERENCE_CARTPOLE_US /
cartpole_us``, on the machine the time targets were set on. One number scales a command
that is Python and numpy small operations like CartPole's step, with a share of torch
training and C compilation; a machine faster at one than the other moves the figure by that
difference.

Run: ``python -m benchmarks.speed.main_job`` (about 10 minutes on 2 cores; ``--skip-pl127``
leaves out the PL127 run). Writes ``benchmarks/results/main_job.md`` and ``main_job.json``
(the README's block, :mod:`benchmarks.readme`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import (
    RESULTS,
    header,
    machine_line,
    markdown_table,
    single_env_step_times,
    write_result,
)

REFERENCE_CARTPOLE_US = 5.9
"""CartPole-v1 median step (us, through ``gymnasium.make``) on the 2-core machine the main job's
time targets were set on: 60 s for the quick start, 8 s for ``piezo identify``, 120 s for the
PL127 benchmark, 20 s for the bench identification (its controller latency run of the same
days measured 5.8 us, ``benchmarks/results/env_speed.md`` of 2026-11-24 5.80 us)."""

TARGETS_S = {
    "quick start": 60.0,
    "identify": 8.0,
    "PL127": 120.0,
    "bench identification": 20.0,
}
"""Time targets (s on the reference machine) of each row."""

COMMANDS = {
    "quick start": ["benchmark"],
    "identify": ["identify"],
    "PL127": ["benchmark", "--bender", "PL127"],
}
"""Row -> arguments of ``piezo`` (the output folder is added)."""

BENCH_SEEDS = (0, 1, 2, 3, 4)
"""Identification seeds of the bench plant's rows."""

BURST_STEPS = 2_000
"""CartPole-v1 steps of one burst (about 25 ms)."""

SAMPLE_EVERY_S = 2.0
"""Seconds between the starts of two bursts."""


class CartPoleSampler:
    """A thread that times a burst of CartPole-v1 steps every :data:`SAMPLE_EVERY_S` seconds
    while a command runs (``with`` block); :attr:`medians` holds each burst's median step (us)."""

    def __init__(self) -> None:
        self.medians: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while True:
            start = time.perf_counter()
            steps = single_env_step_times("CartPole-v1", BURST_STEPS)
            self.medians.append(float(np.median(steps)) * 1e6)
            if self._stop.wait(max(SAMPLE_EVERY_S - (time.perf_counter() - start), 0.0)):
                return

    def __enter__(self) -> CartPoleSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def step_us(self) -> float:
        """The median of the bursts' medians (us)."""
        return float(np.median(self.medians))


def run_command(command: list[str], env: dict[str, str]) -> dict[str, Any]:
    """Run ``command`` with ``env`` beside a :class:`CartPoleSampler`; its wall time (s), the
    CPU time of it and its processes (s), its standard output and the CartPole bursts (us)."""
    cpu = _children_cpu_s()
    with CartPoleSampler() as sampler:
        start = time.perf_counter()
        done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(command)} exited with {done.returncode}:\n{done.stderr[-3000:]}"
        )
    return {
        "wall_s": wall,
        "cpu_s": _children_cpu_s() - cpu,
        "stdout": done.stdout,
        "cartpole_us": sampler.step_us,
        "bursts": len(sampler.medians),
    }


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def bench_identification(seed: int) -> float:
    """Wall time (s) of ``identify(jobs=2)`` on the bench plant with identification ``seed``,
    after this process's imports and first training (the helper's are part of the call)."""
    from benchmarks.plants import PLANTS
    from identification.pipeline import IdentificationConfig, identify
    from identification.steps import warm_up

    warm_up()
    config = IdentificationConfig(seed=seed, env_kwargs=PLANTS["bench"]("PL140"))
    start = time.perf_counter()
    identify(config=config, jobs=2)
    return time.perf_counter() - start


def measure(skip_pl127: bool = False) -> dict[str, Any]:
    """Every run's wall time, CPU time and CartPole step: row name -> list of runs."""
    rows: dict[str, list[dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory(prefix="piezo-main-job-") as scratch:
        for name, arguments in COMMANDS.items():
            if name == "PL127" and skip_pl127:
                continue
            folder = Path(scratch) / name.replace(" ", "-")
            env = dict(os.environ, PIEZO_CACHE=str(folder / "cache"))
            command = [sys.executable, "-m", "piezo_cli.main", *arguments]
            run = run_command([*command, "--out", str(folder / "out")], env)
            rows[name] = [run]
            _say(name, run)
        runs = rows["bench identification"] = []
        for seed in BENCH_SEEDS:
            command = [sys.executable, "-m", __spec__.name, "--bench-seed", str(seed)]
            run = run_command(command, dict(os.environ, PIEZO_CACHE=str(Path(scratch) / "b")))
            run["wall_s"] = float(run["stdout"].split()[-1])  # the call alone
            run["cpu_s"] = None
            runs.append(run)
            _say(f"bench identification, seed {seed}", run)
    return rows


def _say(name: str, run: dict[str, Any]) -> None:
    print(f"{name}: {run['wall_s']:.1f} s, CartPole step {run['cartpole_us']:.2f} us", flush=True)


def report(rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    """The Markdown report of :func:`measure`'s figures."""
    table = []
    for name, runs in rows.items():
        scaled = [run["wall_s"] * REFERENCE_CARTPOLE_US / run["cartpole_us"] for run in runs]
        cpu = [run["cpu_s"] for run in runs if run["cpu_s"] is not None]
        target = TARGETS_S[name]
        table.append(
            [
                name,
                " / ".join(f"{run['wall_s']:.1f}" for run in runs),
                " / ".join(f"{c:.0f}" for c in cpu) or "-",
                " / ".join(f"{run['cartpole_us']:.2f}" for run in runs),
                " / ".join(f"{s:.1f}" for s in scaled),
                f"{target:.0f}",
                "yes" if max(scaled) <= target else "no",
            ]
        )
    return [
        *header("How long a user waits: the main commands", __spec__.name),
        "Wall time of each command run as a user runs it: a fresh process, a fresh output "
        "folder and an empty native-code cache (its C kernels compiled within the command). "
        "The bench identification is `identify(jobs=2)` on the `bench` plant (PL140), one "
        f"run per identification seed {', '.join(map(str, BENCH_SEEDS))}, each timed alone "
        "in a fresh process after its imports. CartPole step: the median of the medians of "
        f"{BURST_STEPS} CartPole-v1 steps timed every {SAMPLE_EVERY_S:g} s while the command "
        "ran. Reference-machine seconds: the wall time times "
        f"{REFERENCE_CARTPOLE_US} us (a CartPole step on the machine the targets were set on) "
        "over the command's CartPole step; `met` judges the worst run.",
        "",
        markdown_table(
            ["command", "wall (s)", "CPU (s)", "CartPole step (us)", "reference-machine (s)",
             "target (s)", "met"],
            table,
        ),
        "",
    ]


def write_json(rows: dict[str, list[dict[str, Any]]]) -> Path:
    """``benchmarks/results/main_job.json``: date, machine, reference, targets and every run
    (what the README's block is generated from)."""
    document = {
        "date": datetime.date.today().isoformat(),
        "machine": machine_line(),
        "reference_cartpole_us": REFERENCE_CARTPOLE_US,
        "targets_s": TARGETS_S,
        "rows": {
            name: [{k: v for k, v in run.items() if k != "stdout"} for run in runs]
            for name, runs in rows.items()
        },
    }
    path = RESULTS / "main_job.json"
    path.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    return path


def main(argv: list[str] | None = None) -> None:
    """Measure every row and write ``benchmarks/results/main_job.md``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-pl127", action="store_true", help="leave out the PL127 run")
    parser.add_argument("--bench-seed", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.bench_seed is not None:  # one bench row's run, in its own process
        print(f"{bench_identification(args.bench_seed):.3f}")
        return
    rows = measure(skip_pl127=args.skip_pl127)
    write_result("main_job", report(rows))
    write_json(rows)


if __name__ == "__main__":
    main()
