"""The main commands' time report (:mod:`benchmarks.speed.main_job`): its scaling to the
reference machine, its verdicts, the README block made from it, and the CartPole sampler."""

import pytest

from benchmarks.readme import main_job as main_job_block
from benchmarks.speed.main_job import (
    REFERENCE_CARTPOLE_US,
    TARGETS_S,
    CartPoleSampler,
    cartpole_step_us,
    report,
)


def _rows() -> dict:
    """Every row on a machine half as fast as the reference: the quick start within its target
    there (110 s here is 55 s there), the identification not (20 s is 10 s, target 8 s)."""
    slow = 2.0 * REFERENCE_CARTPOLE_US
    run = {"cpu_s": None, "cartpole_us": slow, "bursts_us": [slow]}
    return {
        "quick start": [{**run, "wall_s": 110.0, "cpu_s": 200.0}],
        "identify": [{**run, "wall_s": 20.0, "cpu_s": 28.0}],
        "PL127": [{**run, "wall_s": 200.0, "cpu_s": 380.0}],
        "bench identification": [{**run, "wall_s": 30.0}, {**run, "wall_s": 36.0}],
    }


def test_times_are_scaled_by_the_cartpole_step_of_their_run_and_judged_there():
    lines = "\n".join(report(_rows())).splitlines()
    table = {line.split(" | ")[0][2:]: line.split(" | ") for line in lines if "| " in line}
    assert table["quick start"][5:] == ["55.0", "60", "yes |"]
    assert table["identify"][5:] == ["10.0", "8", "no |"]
    assert table["bench identification"][5:] == ["15.0 / 18.0", "20", "yes |"]


def test_the_cartpole_step_is_the_harmonic_mean_of_the_bursts_in_the_window():
    """A machine at 8 us for half of the run and 12 us for the other half does the run's work
    at 9.6 us a step (1 / mean(1 / c)), not at either speed; bursts outside the window (a
    child's imports) do not count, and a window without a burst is refused."""
    bursts = [(0.5, 100.0), (1.0, 8.0), (2.0, 12.0), (3.0, 8.0), (4.0, 12.0), (9.0, 100.0)]
    assert cartpole_step_us(bursts, (0.9, 4.1)) == pytest.approx(9.6)
    with pytest.raises(RuntimeError, match="no CartPole burst"):
        cartpole_step_us(bursts, (5.0, 8.0))


def _data(rows: dict) -> dict:
    return {
        "date": "2026-01-01",
        "machine": "Linux, Some CPU, 2 cores, Python 3.11.7, numpy 2.4.6; BLAS: x",
        "reference_cartpole_us": REFERENCE_CARTPOLE_US,
        "targets_s": TARGETS_S,
        "rows": rows,
    }


def test_the_readme_block_names_the_missed_target_only_and_needs_every_row():
    block = main_job_block(_data(_rows()))
    assert "`piezo benchmark` 110 s" in block and "`piezo identify` 20 s" in block
    assert "`piezo benchmark` 55 s (target 60 s)" in block
    assert "`piezo identify` 10 s (target 8 s: missed)" in block
    assert block.count("missed") == 1 and "(Linux, Some CPU, 2 cores)" in block
    partial = {k: v for k, v in _rows().items() if k != "PL127"}
    with pytest.raises(ValueError, match="without --skip-pl127"):
        main_job_block(_data(partial))


def test_a_sampler_that_fails_raises_instead_of_reporting_no_burst(monkeypatch):
    import benchmarks.speed.main_job as main_job

    def broken(*args, **kwargs):
        raise OSError("no CartPole here")

    monkeypatch.setattr(main_job, "single_env_step_times", broken)
    with pytest.raises(RuntimeError, match="sampler failed"):
        with CartPoleSampler():
            pass


def test_the_sampler_times_bursts_while_its_block_runs():
    with CartPoleSampler() as sampler:
        pass
    assert len(sampler.bursts) == 1  # the first burst, then the block's end stopped it
    (mid, step), = sampler.bursts
    assert step > 0.0 and mid > 0.0
