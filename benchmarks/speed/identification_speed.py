"""Identification time in one process and with a helper process (``identify(jobs=...)``).

For each plant (the nominal PL140, the Prandtl-Ishlinskii plant and the ``bench`` plant, on which
step e' also learns a rate constant), :func:`identification.identify` with the default
configuration runs with ``jobs=1`` (everything in this process) and ``jobs=2`` (step e's
candidates and step e''s independent refinements beside each other on a helper process,
:mod:`identification.runner`), in alternating order over the rounds so that a drift of the
machine's speed falls on both; every model is checked equal to the bit to the first. Reports
the median wall time of the whole call and of steps e and e' (the report's ``timings_s``).
This process's imports and first training are made before the first run; the helper's are
part of each run with ``jobs=2``.

Run: ``python -m benchmarks.speed.identification_speed`` (about five minutes on 2 cores).
Writes ``benchmarks/results/identification_speed.md``.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from benchmarks._common import header, markdown_table, same_model, write_result
from benchmarks.plants import PLANTS
from identification.pipeline import IdentificationConfig, identify
from identification.steps import warm_up

BENDER = "PL140"
PLANT_NAMES = ("nominal", "prandtl-ishlinskii", "bench")
ROUNDS = 2
"""Runs per plant and jobs setting; round k runs jobs 1 first when k is even, else jobs 2."""


def _run(plant: str, jobs: int) -> tuple[float, dict[str, float], Any]:
    config = IdentificationConfig(seed=0, env_kwargs=PLANTS[plant](BENDER))
    start = time.perf_counter()
    result = identify(config=config, jobs=jobs)
    return time.perf_counter() - start, result.report["timings_s"], result.model


def main() -> None:
    """Time every plant with both settings, check the models, write the report."""
    warm_up()  # this process's first training, as the helper's warm-up does for it
    rows = []
    for plant in PLANT_NAMES:
        times: dict[int, list[tuple[float, dict[str, float]]]] = {1: [], 2: []}
        first = None
        for k in range(ROUNDS):
            for jobs in (1, 2) if k % 2 == 0 else (2, 1):
                wall, steps, model = _run(plant, jobs)
                times[jobs].append((wall, steps))
                if first is None:
                    first = model
                elif not same_model(first, model):
                    raise AssertionError(f"{plant}: jobs={jobs} gave another model")
                print(plant, jobs, f"{wall:.1f} s", flush=True)

        def median(jobs: int, key: str | None = None, times: dict = times) -> float:
            return statistics.median(
                wall if key is None else steps[key] for wall, steps in times[jobs]
            )

        rows.append(
            [
                plant,
                f"{median(1):.1f}",
                f"{median(2):.1f}",
                f"{median(1) / median(2):.2f}",
                f"{median(1, 'e_nls_training'):.1f} / {median(2, 'e_nls_training'):.1f}",
                f"{median(1, 'e2_nls_output_error'):.1f} / "
                f"{median(2, 'e2_nls_output_error'):.1f}",
                "yes",
            ]
        )
    lines = [
        *header("Identification time: one process and a helper process", __spec__.name),
        f"`identify()` with the default configuration, seed 0, on the {BENDER}, "
        f"{ROUNDS} runs per plant and setting in alternating order; medians of the wall time "
        "(s). `jobs=2` runs step e's candidate networks and step e''s rate-dependent "
        "refinement (and, without a sensor bound, the play rival) beside the main line on a "
        "helper process started with the "
        "run (`identification/runner.py`; `piezo identify` does so on a machine with 2 cores "
        "or more). Same model: every run's model equals the first's to the bit.",
        "",
        markdown_table(
            ["plant", "jobs 1 (s)", "jobs 2 (s)", "speed-up", "step e (s, 1 / 2)",
             "step e' (s, 1 / 2)", "same model"],
            rows,
        ),
        "",
    ]
    write_result("identification_speed", lines)


if __name__ == "__main__":
    main()
