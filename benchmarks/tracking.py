"""Closed-loop tracking benchmark: ``piezo benchmark`` run as committed with the code.

Identifies the default PL140 (seed 0), runs, in one worker process (so the compute times
are free of waits for a core), every default controller on every reference and
robustness plant, writes the full report and figures to ``docs/benchmark/`` and the tables, with
the machine and the date, to ``benchmarks/results/tracking.md``.

Run: ``python -m benchmarks.tracking`` (a few minutes on 2 cores).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from benchmarks._common import RESULTS

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    os.chdir(ROOT)  # relative paths in the committed report; finds docs/policies
    out = Path("docs") / "benchmark"
    # One worker on two cores: the compute times are the controllers', not waits for a core.
    command = [
        sys.executable, "-m", "piezo_cli.main", "benchmark", "--out", str(out), "--quiet",
        "--jobs", "1",
    ]
    status = subprocess.run([*command, *sys.argv[1:]], check=False).returncode
    if status == 0:
        RESULTS.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "benchmark.md", RESULTS / "tracking.md")
        print(f"copied the report to {RESULTS / 'tracking.md'}")
    return status


if __name__ == "__main__":
    raise SystemExit(main())
