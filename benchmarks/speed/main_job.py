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

Machines of one kind differ, and one machine differs from minute to minute: the committed
speed runs of one 2-core virtual machine have measured a CartPole-v1 step at 4.1-13.9 us
(``benchmarks/results/env_speed.md``, ``controller_latency.md`` and their history), and one
run of this script saw bursts from 7.5 to 13 us. So, as every speed figure of the project,
the times are also given against a step of CartPole-v1 measured while the command runs: a
thread of this process (idle otherwise, waiting for the command) times a burst of CartPole
steps through ``gymnasium.make`` every ``SAMPLE_EVERY_S`` seconds (25 ms in 2 s: 1.25 % of one
core). A burst that the command's processes crowd off a core loses whole steps to the
scheduler, not a part of each, so its median times the core, not its share of it. The run's
CartPole step is the harmonic mean of its bursts' medians (:func:`cartpole_step_us`), and
its time on the reference machine ``wall x REFERENCE_CARTPOLE_US / cartpole_us``. One number
scales a command that is Python and numpy small operations like CartPole's step, with a share
of torch training and C compilation; a machine faster at one than the other moves the figure
by that difference, and the report gives the bursts' range.

Run: ``python -m benchmarks.speed.main_job`` (about 10 minutes on 2 cores; ``--skip-pl127``
leaves out the PL127 run and writes nothing). Writes ``benchmarks/results/main_job.md`` and
``main_job.json`` (the README's block, :mod:`benchmarks.readme`).
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

REFERENCE_CARTPOLE_US = 5.8
"""CartPole-v1 median step (us, through ``gymnasium.make``) on the reference machine, the
2-core machine of ``benchmarks/results/env_speed.md`` of 2026-11-24 (5.80 us), on which the
time targets below hold."""

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

COMMAND_TIMEOUT_S = 3600.0
"""A command still running after this long is stopped and the script fails (the slowest,
the PL127 benchmark, takes about 3 minutes on 2 cores)."""

_WINDOW = "main-job window"
"""Tag of the line a bench row's process prints: its call's start and end (monotonic s)."""


class CartPoleSampler:
    """A thread that times a burst of CartPole-v1 steps every :data:`SAMPLE_EVERY_S` seconds
    while a command runs (``with`` block).

    Attributes
    ----------
    bursts : list of (float, float)
        Each burst's mid-time (``time.monotonic()``, s) and median step (us).
    """

    def __init__(self) -> None:
        self.bursts: list[tuple[float, float]] = []
        self._error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            while True:
                start = time.monotonic()
                steps = single_env_step_times("CartPole-v1", BURST_STEPS)
                end = time.monotonic()
                self.bursts.append((0.5 * (start + end), float(np.median(steps)) * 1e6))
                if self._stop.wait(max(SAMPLE_EVERY_S - (end - start), 0.0)):
                    return
        except BaseException as error:  # re-raised by __exit__: no silent NaN row
            self._error = error

    def __enter__(self) -> CartPoleSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        if self._error is not None:
            raise RuntimeError("the CartPole sampler failed") from self._error


def cartpole_step_us(bursts: list[tuple[float, float]], window: tuple[float, float]) -> float:
    """The CartPole step (us) that scales a run timed over ``window`` (monotonic s).

    Time on the reference machine is the run's time integrated at the reference's speed:
    ``integral REF / c(t) dt``. The bursts are evenly spaced, so over the bursts inside the
    window that is ``wall x REF x mean(1 / c_i)``: the harmonic mean of the bursts' steps,
    which a machine switching between two speeds does not snap to either of them (a median
    would).

    Parameters
    ----------
    bursts : list of (float, float)
        :attr:`CartPoleSampler.bursts`.
    window : (float, float)
        Start and end of the timed run.

    Returns
    -------
    float

    Raises
    ------
    RuntimeError
        When no burst lies inside the window (a run shorter than :data:`SAMPLE_EVERY_S`).
    """
    inside = [c for t, c in bursts if window[0] <= t <= window[1]]
    if not inside:
        raise RuntimeError(
            f"no CartPole burst inside the timed window of {window[1] - window[0]:.1f} s"
        )
    return float(len(inside) / np.sum(1.0 / np.asarray(inside)))


def run_command(command: list[str], env: dict[str, str]) -> dict[str, Any]:
    """Run ``command`` with ``env`` beside a :class:`CartPoleSampler`.

    Parameters
    ----------
    command : list of str
        The command line.
    env : dict
        Its environment.

    Returns
    -------
    dict
        ``wall_s`` (s), ``cpu_s`` (CPU s of the command and its processes), ``window``
        (monotonic start and end, s), ``stdout`` and ``bursts`` (:attr:`CartPoleSampler.bursts`).

    Raises
    ------
    RuntimeError
        When the command fails or runs past :data:`COMMAND_TIMEOUT_S`, with the end of its
        output.
    """
    cpu = _children_cpu_s()
    with CartPoleSampler() as sampler:
        start = time.monotonic()
        try:
            done = subprocess.run(
                command, env=env, capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S
            )
        except subprocess.TimeoutExpired as error:
            raise RuntimeError(f"{' '.join(command)} ran past {COMMAND_TIMEOUT_S:g} s") from error
        end = time.monotonic()
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(command)} exited with {done.returncode}:\n"
            f"{done.stdout[-1500:]}\n{done.stderr[-3000:]}"
        )
    return {
        "wall_s": end - start,
        "cpu_s": _children_cpu_s() - cpu,
        "window": (start, end),
        "stdout": done.stdout,
        "bursts": sampler.bursts,
    }


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def bench_identification(seed: int) -> tuple[float, float]:
    """Monotonic start and end (s) of ``identify(jobs=2)`` on the bench plant with
    identification ``seed``, after this process's imports and first training (the helper's
    are part of the call)."""
    from benchmarks.plants import PLANTS
    from identification.pipeline import IdentificationConfig, identify
    from identification.steps import warm_up

    warm_up()
    config = IdentificationConfig(seed=seed, env_kwargs=PLANTS["bench"]("PL140"))
    start = time.monotonic()
    identify(config=config, jobs=2)
    return start, time.monotonic()


def _window(stdout: str) -> tuple[float, float]:
    """The call's window from a bench row's output (the line :func:`main` prints)."""
    for line in stdout.splitlines():
        if line.startswith(_WINDOW + " "):
            start, end = (float(x) for x in line.split()[-2:])
            return start, end
    raise RuntimeError(f"a bench row's process printed no '{_WINDOW}' line:\n{stdout[-1500:]}")


def measure(skip_pl127: bool = False) -> dict[str, list[dict[str, Any]]]:
    """Every run's wall time, CPU time and CartPole step.

    Parameters
    ----------
    skip_pl127 : bool
        Leave out the PL127 benchmark.

    Returns
    -------
    dict
        Row name -> list of runs, each with ``wall_s``, ``cpu_s`` (None for the bench rows),
        ``cartpole_us`` (:func:`cartpole_step_us`) and ``bursts_us`` (every burst's median
        inside the timed window).
    """
    rows: dict[str, list[dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory(prefix="piezo-main-job-") as scratch:
        for name, arguments in COMMANDS.items():
            if name == "PL127" and skip_pl127:
                continue
            folder = Path(scratch) / name.replace(" ", "-")
            env = dict(os.environ, PIEZO_CACHE=str(folder / "cache"))
            command = [sys.executable, "-m", "piezo_cli.main", *arguments]
            run = run_command([*command, "--out", str(folder / "out")], env)
            rows[name] = [_summary(run, run["window"], run["cpu_s"])]
            _say(name, rows[name][-1])
        runs = rows["bench identification"] = []
        for seed in BENCH_SEEDS:
            command = [sys.executable, "-m", __spec__.name, "--bench-seed", str(seed)]
            run = run_command(command, dict(os.environ, PIEZO_CACHE=str(Path(scratch) / "b")))
            runs.append(_summary(run, _window(run["stdout"]), None))
            _say(f"bench identification, seed {seed}", runs[-1])
    return rows


def _summary(run: dict[str, Any], window: tuple[float, float], cpu: float | None) -> dict:
    bursts = [c for t, c in run["bursts"] if window[0] <= t <= window[1]]
    return {
        "wall_s": window[1] - window[0],
        "cpu_s": cpu,
        "cartpole_us": cartpole_step_us(run["bursts"], window),
        "bursts_us": bursts,
    }


def _say(name: str, run: dict[str, Any]) -> None:
    print(f"{name}: {run['wall_s']:.1f} s, CartPole step {run['cartpole_us']:.2f} us", flush=True)


def report(rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    """The Markdown report of :func:`measure`'s rows.

    Parameters
    ----------
    rows : dict
        :func:`measure`'s result.

    Returns
    -------
    list of str
        The report's lines.
    """
    table = []
    for name, runs in rows.items():
        scaled = [run["wall_s"] * REFERENCE_CARTPOLE_US / run["cartpole_us"] for run in runs]
        cpu = [run["cpu_s"] for run in runs if run["cpu_s"] is not None]
        bursts = [c for run in runs for c in run.get("bursts_us", [])]
        target = TARGETS_S[name]
        table.append(
            [
                name,
                " / ".join(f"{run['wall_s']:.1f}" for run in runs),
                " / ".join(f"{c:.0f}" for c in cpu) or "-",
                " / ".join(f"{run['cartpole_us']:.2f}" for run in runs),
                f"{min(bursts):.1f}-{max(bursts):.1f}" if bursts else "-",
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
        "in a fresh process after its imports. CartPole step: the harmonic mean of the "
        f"medians of {BURST_STEPS} CartPole-v1 steps timed every {SAMPLE_EVERY_S:g} s while "
        "the timed run went on (the range of those medians beside it). Reference-machine "
        "seconds: the wall time times "
        f"{REFERENCE_CARTPOLE_US} us (a CartPole step on the reference machine, "
        "`env_speed.md` of 2026-11-24) over the run's CartPole step; `met` judges the worst "
        "run.",
        "",
        markdown_table(
            ["command", "wall (s)", "CPU (s)", "CartPole step (us)", "bursts (us)",
             "reference-machine (s)", "target (s)", "met"],
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
        "rows": rows,
    }
    path = RESULTS / "main_job.json"
    path.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    return path


def main(argv: list[str] | None = None) -> None:
    """Measure every row and write ``benchmarks/results/main_job.md``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--skip-pl127",
        action="store_true",
        help="leave out the PL127 run (the report is printed, the results files kept)",
    )
    parser.add_argument("--bench-seed", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.bench_seed is not None:  # one bench row's run, in its own process
        start, end = bench_identification(args.bench_seed)
        print(f"{_WINDOW} {start!r} {end!r}")
        return
    rows = measure(skip_pl127=args.skip_pl127)
    if args.skip_pl127:  # a partial run: printed, the committed results left as they are
        print("\n".join(report(rows)))
        return
    write_result("main_job", report(rows))
    write_json(rows)


if __name__ == "__main__":
    main()
