"""Rate-aware identification: the default identification on plants whose hysteresis it was and
was not designed around, over identification seeds.

For each plant (the nominal PL140, the Prandtl-Ishlinskii plant, the rate-dependent plant
without an amplifier, and the ``bench`` plant with its amplifier, sensor and disturbances) and
each identification seed, identifies the model on that plant with the default configuration
(``features="auto"``, learned play radii, ``rate="auto"``), then runs ``mpc`` on that model and
``mpc-oracle`` (the same MPC on the plant's own model) on the same plant, seed 0, whole 2 s
episodes. Reports, per plant and seed: the features chosen, whether the rate model was kept and
its rate constant, the validation fit, the time of the identification, and ``mpc``'s RMSE (% of
the full stroke) and its ratio to the oracle at 10, 50 and 100 Hz and on the multisine.

Writes ``benchmarks/results/rate_aware_identification.md``. Run:
``python -m benchmarks.studies.rate_aware_identification`` (about half an hour on 2 cores).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks._common import header, markdown_table, same_model, write_result
from benchmarks.plants import PLANTS
from benchmarks.runner import BenchmarkConfig, run_benchmark
from identification.pipeline import IdentificationConfig, identify

BENDER = "PL140"
SEEDS = (0, 1, 2, 3, 4)
"""Identification seeds."""
STUDY_PLANTS = {
    "nominal": "nominal",
    "prandtl-ishlinskii": "prandtl-ishlinskii",
    "rate-dependent": None,
    "bench": "bench",
}
"""Row label -> benchmark plant (None: the rate-dependent hysteresis alone, no bench options)."""
REFERENCES = ("sine-10Hz", "sine-50Hz", "sine-100Hz", "multisine")
JOBS = (1, 2)
"""Processes each identification runs with: alone, then with one helper."""


def _env(label: str) -> dict[str, Any]:
    plant = STUDY_PLANTS[label]
    if plant is None:
        return {"bender": BENDER, "hysteresis": "rate-dependent"}
    return PLANTS[plant](BENDER)


def _one(label: str, seed: int, folder: Path) -> dict[str, Any]:
    """Identify on the plant with ``seed`` in one process and with a helper (``jobs=2``,
    :mod:`identification.runner`), check that both give the same model, then run ``mpc`` and
    ``mpc-oracle`` on it."""
    config = IdentificationConfig(seed=seed, env_kwargs=_env(label))
    took = {}
    for jobs in JOBS:
        start = time.perf_counter()
        result = identify(config=config, jobs=jobs)
        took[jobs] = time.perf_counter() - start
        if jobs == JOBS[0]:
            first = result.model
        elif not same_model(first, result.model):
            raise AssertionError(f"{label}, seed {seed}: jobs={jobs} gave another model")
    result.model.save(folder)
    report = result.report
    rate = (report["nls"].get("output_error") or {}).get("rate_choice") or {}
    plant = STUDY_PLANTS[label]
    rmse: dict[tuple[str, str], float] = {}
    if plant is not None:
        config = BenchmarkConfig(
            controllers=("mpc", "mpc-oracle"), references=REFERENCES, plants=(plant,)
        )
        run = run_benchmark(config, str(folder))
        rmse = {(e["controller"], e["reference"]): e["rmse_percent"] for e in run.episodes}
    return {
        "features": report["nls"]["features"],
        "rate_kept": rate.get("kept"),
        "rate_time_s": getattr(result.model.nls.feature_map, "rate_time", None),
        "fit": report["validation"]["hammerstein"]["fit_percent"],
        "time_s": took,
        "rmse": rmse,
    }


def main() -> None:
    """Identify every plant with every seed, run the MPCs, write the report."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label in STUDY_PLANTS:
            for seed in SEEDS:
                out = _one(label, seed, Path(tmp) / f"{label}-{seed}")
                cells = []
                for ref in REFERENCES:
                    mine = out["rmse"].get(("mpc", ref))
                    oracle = out["rmse"].get(("mpc-oracle", ref))
                    cells.append("-" if mine is None else f"{mine:.3f} ({mine / oracle:.2g}x)")
                rate = {True: "kept", False: "not kept", None: "-"}[out["rate_kept"]]
                if out["rate_kept"] and out["rate_time_s"] is not None:
                    rate += f", c = {out['rate_time_s'] * 1e3:.3g} ms"
                times = " / ".join(f"{out['time_s'][jobs]:.0f}" for jobs in JOBS)
                rows.append(
                    [label, str(seed), out["features"], rate, f"{out['fit']:.2f}", times, *cells]
                )
                print(rows[-1], flush=True)
    lines = [
        *header("Rate-aware identification over identification seeds", __spec__.name),
        "Each plant identified with each seed by the default configuration (features chosen "
        "on the held-out selection record, learned play radii, `rate=\"auto\"`), then `mpc` "
        "on that model and `mpc-oracle` on the plant's own, seed 0, whole 2 s episodes: RMSE "
        "in % of the full stroke (ratio to the oracle). The rate-dependent plant without an "
        "amplifier is identified but not a benchmark plant, so it has no MPC cells. Each "
        "identification runs twice, in one process and with a helper process (`jobs=2`, what "
        "`piezo identify` does on 2 cores: step e's candidates and step e''s independent "
        "refinements beside each other), and the two models are checked equal to the bit; "
        "the times are wall seconds of both, on a machine that may be shared.",
        "",
        markdown_table(
            ["plant", "seed", "features", "rate model", "validation fit %",
             "identification s (jobs 1 / 2)", *REFERENCES],
            rows,
        ),
        "",
    ]
    write_result("rate_aware_identification", lines)


if __name__ == "__main__":
    main()
