"""Closed-loop tracking benchmark: ``piezo benchmark`` run as committed with the code.

Identifies the default PL140 with three identification seeds (0, 1, 2) on the nominal plant
and three on the bench (the bench identified on the bench, as a user meets it), runs, in one
worker process (so the compute times are free of waits for a core) and over three noise seeds,
every default controller on every reference and robustness plant (each cell a mean over 3 x 3
seeds with its 95 % interval), writes the full report and figures to ``docs/benchmark/`` and
the tables, with the machine and the date, to ``benchmarks/results/tracking.md``.

Run: ``python -m benchmarks.tracking`` (about an hour on 2 cores: the report's ``Time:`` line
gives the last run's); ``python -m benchmarks.tracking --bender PL127`` commits the PL127's run
to ``docs/benchmark-PL127/`` and ``benchmarks/results/tracking-PL127.md``. Another bender steps
at its own sample time (the PL127 at 0.25 ms: four times the PL140's steps per episode), so its
committed run holds one identification seed and two noise seeds (:data:`OTHER_BENDER_SEEDS`),
which keeps it within the PL140's run time. ``--rewrite-report`` runs no episode: it rewrites the
committed run's report with this version's report code from the run's own ``benchmark.json``
(:func:`benchmarks.report.rewrite_report`; the figures stay as the run drew them).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from benchmarks._common import RESULTS

ROOT = Path(__file__).resolve().parents[1]

OTHER_BENDER_SEEDS = ("--identification-seeds", "1", "--seeds", "2")
"""Seeds of a committed run of a bender other than the PL140 (module docstring)."""


def main() -> int:
    """Run the committed benchmark; ``--bender NAME`` commits another bender's run beside it."""
    os.chdir(ROOT)  # relative paths in the committed report; finds docs/policies
    args = sys.argv[1:]
    bender = args[args.index("--bender") + 1].upper() if "--bender" in args else "PL140"
    suffix = "" if bender.startswith("PL140") else f"-{bender.split('.')[0]}"
    out = Path("docs") / f"benchmark{suffix}"
    if "--rewrite-report" in args:
        from benchmarks.report import rewrite_report

        report = rewrite_report(out)
        target = RESULTS / f"tracking{suffix}.md"
        shutil.copyfile(report, target)
        print(f"rewrote {report} from {out / 'benchmark.json'} and copied it to {target}")
        return 0
    # One worker on two cores: the compute times are the controllers', not waits for a core;
    # 3 identification seeds x 3 noise seeds: every cell a mean with its 95 % interval over
    # what varies; the bench identified on the bench; 50 random plants.
    command = [
        sys.executable, "-m", "piezo_cli.main", "benchmark", "--out", str(out), "--quiet",
        "--jobs", "1", "--seeds", "3", "--identification-seeds", "3",
        "--identify-on", "nominal,bench", "--draws", "50",
    ]
    if suffix:
        command += OTHER_BENDER_SEEDS
    status = subprocess.run([*command, *args], check=False).returncode
    if status == 0:
        # The checkpoint serves --resume of this run only; the committed folder holds results.
        (out / "checkpoint.jsonl").unlink(missing_ok=True)
        RESULTS.mkdir(parents=True, exist_ok=True)
        target = RESULTS / f"tracking{suffix}.md"
        shutil.copyfile(out / "benchmark.md", target)
        print(f"copied the report to {target}")
    return status


if __name__ == "__main__":
    raise SystemExit(main())
