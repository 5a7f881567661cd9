"""The default sample time follows the bender: the rule, the env, and everything downstream."""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from piezo_env import (
    CATALOGUE,
    DT_LADDER,
    DomainRandomization,
    TaskConfig,
    default_dt,
    get_datasheet,
)

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "piezo_env:PiezoBender-v0"
BENDERS = sorted(name.split(".")[0] for name in CATALOGUE)
EXPECTED_DT = {"PL112": 1e-4, "PL122": 2.5e-4, "PL127": 2.5e-4, "PL128": 5e-4, "PL140": 1e-3}


def _rule(bender: str, dt: float) -> float:
    """4 (1 + s) f_1 dt: at most 1 when the highest first resonance is well sampled."""
    s = DomainRandomization().resonance
    return 4.0 * (1.0 + s) * get_datasheet(bender).resonance * dt


@pytest.mark.parametrize("bender", BENDERS)
def test_the_default_is_the_largest_ladder_value_that_keeps_the_resonance_sampled(bender):
    dt = default_dt(bender)
    assert dt == EXPECTED_DT[bender]
    assert dt in DT_LADDER
    assert _rule(bender, dt) <= 1.0
    larger = [step for step in DT_LADDER if step > dt]
    if larger:
        assert _rule(bender, min(larger)) > 1.0
    else:
        assert dt == DT_LADDER[0] == 1e-3  # the PL140: the top of the ladder


def test_the_ladder_is_round_rates_that_divide_a_millisecond():
    assert list(DT_LADDER) == sorted(DT_LADDER, reverse=True)
    for dt in DT_LADDER:
        assert round(1e-3 / dt) * dt == pytest.approx(1e-3, rel=1e-12)
        assert 1e-3 / dt == pytest.approx(round(1e-3 / dt), rel=1e-12)
    assert max(a / b for a, b in itertools.pairwise(DT_LADDER)) <= 2.0


def test_the_pl140_keeps_exactly_1_ms():
    assert TaskConfig().dt == 1e-3
    assert TaskConfig(bender="PL140").dt == 1e-3
    env = gym.make(ENV_ID)
    assert env.unwrapped.model.dt == 1e-3
    assert env.unwrapped.config == TaskConfig(dt=1e-3)


def test_gym_make_follows_the_rule_for_another_bender():
    env = gym.make(ENV_ID, bender="PL127")
    assert env.unwrapped.config.dt == 2.5e-4
    assert env.unwrapped.model.dt == 2.5e-4


@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_an_explicit_dt_overrides_the_rule():
    assert TaskConfig(bender="PL127", dt=1e-3).dt == 1e-3
    env = gym.make(ENV_ID, bender="PL112", dt=5e-4)
    assert env.unwrapped.model.dt == 5e-4


@pytest.mark.parametrize("bender", BENDERS)
def test_an_explicit_dt_that_aliases_the_resonance_is_warned_about(bender):
    """Above the Nyquist frequency the first mode aliases: an explicit dt that puts the top of
    the resonance's tolerance there is kept, with a warning naming the default; the default
    dt and any dt that samples the resonance are silent."""
    f_top = (1.0 + DomainRandomization().resonance) * get_datasheet(bender).resonance
    aliasing = 1.01 / (2.0 * f_top)
    fix = rf"Nyquist.*default for the .* is dt = {default_dt(bender):g} s"
    with pytest.warns(UserWarning, match=fix) as caught:
        config = TaskConfig(bender=bender, dt=aliasing)
    assert config.dt == aliasing
    with pytest.warns(UserWarning, match=fix) as through_make:
        gym.make(ENV_ID, bender=bender, dt=aliasing)
    # The warning names the line that asked for the dt, not the library's.
    assert {w.filename for w in [*caught, *through_make]} == {__file__}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        TaskConfig(bender=bender)
        TaskConfig(bender=bender, dt=0.99 / (2.0 * f_top))


def test_dt_none_and_the_config_validation():
    assert TaskConfig(dt=None) == TaskConfig()
    for bad in (0.0, -1e-3, float("nan"), "1e-3", True):
        with pytest.raises(ValueError, match="dt"):
            TaskConfig(dt=bad)


@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_a_new_bender_gets_its_own_default_unless_dt_was_given():
    assert TaskConfig.from_kwargs(TaskConfig(), bender="PL127").dt == 2.5e-4
    assert TaskConfig.from_kwargs(TaskConfig(dt=1e-3), bender="PL127").dt == 1e-3
    assert TaskConfig.from_kwargs(TaskConfig(), bender="PL127", dt=5e-4).dt == 5e-4
    assert TaskConfig.from_kwargs(TaskConfig(bender="PL127"), noise_bound=0.5).dt == 2.5e-4


def test_a_resonance_beyond_the_ladder_asks_for_an_explicit_dt():
    sheet = dataclasses.replace(get_datasheet("PL112"), resonance=50e3)
    with pytest.raises(ValueError, match="pass dt explicitly"):
        default_dt(sheet)
    assert TaskConfig(bender=sheet, dt=1e-6).dt == 1e-6


# -- benchmark --------------------------------------------------------------------------------


def _benchmark_config(**options):
    from benchmarks.runner import BenchmarkConfig

    return BenchmarkConfig(
        controllers=("pid",), references=("sine-10Hz",), plants=("nominal",), **options
    )


@pytest.mark.parametrize("bender", BENDERS)
def test_a_benchmark_episode_lasts_2_s_at_the_bender_s_sample_time(bender):
    config = _benchmark_config(bender=bender)
    assert config.dt == EXPECTED_DT[bender]
    assert config.steps == round(2.0 / config.dt)
    assert config.steps * config.dt == pytest.approx(2.0)
    assert _benchmark_config(bender=bender, steps=150).steps == 150


def test_every_benchmark_plant_steps_at_the_nominal_bender_s_sample_time():
    from benchmarks.runner import _make_env

    config = _benchmark_config(bender="PL128")
    # +20 % resonance alone would ask the rule for 0.25 ms; the plant keeps the nominal 0.5 ms.
    for plant in ("nominal", "stiffness+20%"):
        env = _make_env(config, plant)
        assert env.unwrapped.model.dt == 5e-4
        assert env.spec.max_episode_steps == 4000


def test_random_steps_hold_a_tenth_of_a_second_at_any_sample_time():
    from benchmarks.references import make_reference

    for dt in (1e-3, 2.5e-4):
        r = make_reference("random-steps", round(1.0 / dt), dt=dt, seed=0)
        changes = np.flatnonzero(np.diff(r)) + 1
        assert changes.size > 0
        assert np.all(changes % round(0.1 / dt) == 0)


def test_a_policy_trained_at_1_ms_is_refused_or_left_out_on_the_pl127(monkeypatch):
    from piezo_cli.benchmark import _committed_policies

    folder = str(ROOT / "docs" / "policies" / "ppo-seed0")
    with pytest.raises(ValueError, match=r"trained at dt = 0.001 s .* steps at dt = 0.00025 s"):
        _benchmark_config(bender="PL127", policies=(folder,))
    monkeypatch.chdir(ROOT)
    kept, left_out = _committed_policies(("ppo", "ppo-dr"), "PL127")
    assert kept == () and len(left_out) == 6
    assert all("PL127" in reason for reason in left_out.values())
    kept, left_out = _committed_policies(("ppo", "ppo-dr"), "PL140")
    assert len(kept) == 6 and not left_out


def test_the_benchmark_command_defaults_to_2_s_episodes():
    from piezo_cli.benchmark import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args(["--bender", "PL127"]).steps is None


# -- identification ---------------------------------------------------------------------------


@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_identification_records_follow_the_env_s_sample_time():
    from identification.config import IdentificationConfig, env_sample_time

    pl140 = IdentificationConfig().at_sample_time(1e-3)
    assert (pl140.rich_samples, pl140.validation_samples, pl140.validation_hold) == (
        12000,
        6000,
        10,
    )
    assert pl140.rich_params == {"hold": 10} and pl140.prbs_samples == 8000
    config = IdentificationConfig(env_kwargs={"bender": "PL127"})
    dt = env_sample_time(config.env_kwargs)
    assert dt == 2.5e-4
    pl127 = config.at_sample_time(dt)
    assert (pl127.rich_samples, pl127.validation_samples, pl127.validation_hold) == (
        48000,
        24000,
        40,
    )
    assert pl127.rich_params == {"hold": 40}
    assert pl127.prbs_samples == 8000 and pl127.prbs_clock == 1  # white at any dt
    given = IdentificationConfig(rich_samples=500, validation_hold=7).at_sample_time(dt)
    assert (given.rich_samples, given.validation_hold) == (500, 7)
    assert env_sample_time({"bender": "PL127", "dt": 1e-3}) == 1e-3
    with pytest.raises(ValueError, match="give validation_samples"):
        IdentificationConfig().at_sample_time(0.05)


def test_the_rich_record_holds_10_ms_on_the_env_it_runs_on():
    from identification.config import IdentificationConfig
    from identification.steps import excite_rich, step_seeds

    env = gym.make(ENV_ID, bender="PL127", reference=None, max_episode_steps=-1)
    u, _ = excite_rich(env, IdentificationConfig(rich_samples=400), step_seeds(0))
    levels = u.reshape(-1, 40)
    assert np.all(levels == levels[:, :1])
    assert np.unique(levels[:, 0]).size == 10


def test_the_command_line_leaves_dt_to_the_bender_unless_given():
    from piezo_cli.arguments import add_env_arguments, env_kwargs, sample_time

    parser = argparse.ArgumentParser()
    add_env_arguments(parser)
    args = parser.parse_args(["--bender", "PL127"])
    assert "dt" not in env_kwargs(args) and sample_time(args) == 2.5e-4
    args = parser.parse_args(["--bender", "PL127", "--dt", "1e-3"])
    assert env_kwargs(args)["dt"] == 1e-3 and sample_time(args) == 1e-3


@pytest.mark.parametrize(
    ("dt", "message"),
    [
        (1e-7, r"more than the 1,000,000 an identification takes: use a dt of at least 1\.2e-05 s"),
        (0.1, r"fewer than 200: use a dt of at most 0\.03 s \(--dt on the command line\)"),
    ],
)
@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_a_dt_too_fine_or_too_coarse_for_the_records_is_refused_before_work(
    dt, message, tmp_path, capsys
):
    """Default record durations at a dt that makes them a billion samples or a handful: refused
    with the dt that works, by the library and by ``piezo excite`` / ``piezo identify``."""
    from identification.config import IdentificationConfig
    from piezo_cli.main import main

    with pytest.raises(ValueError, match=message):
        IdentificationConfig().at_sample_time(dt)
    for command in ("excite", "identify"):
        assert main([command, "--dt", str(dt), "--out", str(tmp_path / command)]) == 2
        assert "use a dt of" in capsys.readouterr().err
        assert not (tmp_path / command).exists()
