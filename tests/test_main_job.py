"""The main commands' time report (:mod:`benchmarks.speed.main_job`): its scaling to the
reference machine, its verdicts, the README block made from it, and the CartPole sampler."""

import time

from benchmarks.readme import main_job as main_job_block
from benchmarks.speed.main_job import REFERENCE_CARTPOLE_US, CartPoleSampler, report


def _rows() -> dict:
    """Two rows on a machine half as fast as the reference: the quick start within its target
    there (110 s here is 55 s there), the identification not (20 s is 10 s, target 8 s)."""
    slow = 2.0 * REFERENCE_CARTPOLE_US
    return {
        "quick start": [{"wall_s": 110.0, "cpu_s": 200.0, "cartpole_us": slow}],
        "identify": [{"wall_s": 20.0, "cpu_s": 28.0, "cartpole_us": slow}],
    }


def test_times_are_scaled_by_the_cartpole_step_of_their_run_and_judged_there():
    lines = "\n".join(report(_rows())).splitlines()
    table = [line for line in lines if line.startswith(("| quick", "| identify"))]
    assert table[0].split(" | ")[4:] == ["55.0", "60", "yes |"]
    assert table[1].split(" | ")[4:] == ["10.0", "8", "no |"]


def test_the_readme_block_names_the_missed_target_only():
    data = {
        "date": "2026-01-01",
        "machine": "Linux, Some CPU, 2 cores, Python 3.11.7, numpy 2.4.6; BLAS: x",
        "reference_cartpole_us": REFERENCE_CARTPOLE_US,
        "targets_s": {"quick start": 60.0, "identify": 8.0},
        "rows": _rows(),
    }
    block = main_job_block(data)
    assert "`piezo benchmark` 110 s" in block and "`piezo identify` 20 s" in block
    assert "55 s (target 60 s)" in block and "10 s (target 8 s: missed)" in block
    assert block.count("missed") == 1 and "(Linux, Some CPU, 2 cores)" in block


def test_the_sampler_times_bursts_until_its_block_ends():
    with CartPoleSampler() as sampler:
        time.sleep(0.1)
    assert len(sampler.medians) >= 1 and sampler.step_us > 0.0
    count = len(sampler.medians)
    time.sleep(0.1)
    assert len(sampler.medians) == count  # stopped with the block
