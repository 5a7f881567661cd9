"""The env's argument checks go through piezo_env.checks: bools, NaN and inf are refused alike."""

from __future__ import annotations

import math

import numpy as np
import pytest

from piezo_env import BenderDatasheet, DomainRandomization, PiezoBenderModel, TaskConfig
from piezo_env.checks import require_number
from piezo_env.parameters import bender_parameters
from piezo_env.task import check_max_episode_steps, check_reset_options


def test_require_number_open_upper_bound():
    assert require_number("x", 0.999, low=0, high=1, high_open=True) == 0.999
    with pytest.raises(ValueError, match=r"x must be a finite number >= 0 and < 1, got 1"):
        require_number("x", 1, low=0, high=1, high_open=True)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("n_elements", True),
        ("n_elements", 2.0),
        ("dt", True),
        ("dt", math.inf),
        ("noise_bound", -1.0),
        ("noise_bound", math.nan),
        ("deflection_limit", 0.0),
        ("deflection_limit", math.inf),
        ("damping_ratio", 1.0),
    ],
)
def test_task_settings_name_the_field(field, value):
    with pytest.raises(ValueError, match=rf"^{field}\b"):
        TaskConfig(**{field: value})


def test_numpy_numbers_pass_like_python_numbers():
    config = TaskConfig(n_elements=np.int64(8), dt=np.float64(1e-3), noise_bound=np.float32(0.5))
    assert config.n_elements == 8
    assert check_max_episode_steps(np.int64(-1)) is None
    assert check_max_episode_steps(np.int32(7)) == 7
    assert check_reset_options({"initial_voltage": np.float32(12.5)}, 30.0) == 12.5


@pytest.mark.parametrize("voltage", [31.0, math.nan, "5", True])
def test_initial_voltage_outside_the_drive_range_is_refused(voltage):
    with pytest.raises(ValueError, match=r"initial_voltage \(V\) must be a finite number"):
        check_reset_options({"initial_voltage": voltage}, 30.0)


@pytest.mark.parametrize("half_width", [1.0, -0.1, math.nan, True])
def test_randomisation_half_widths_are_in_zero_one(half_width):
    with pytest.raises(ValueError, match=r"DomainRandomization\.resonance .* >= 0 and < 1"):
        DomainRandomization(resonance=half_width)


def test_datasheet_density_and_dt_refuse_non_numbers():
    sheet = PiezoBenderModel().params.datasheet
    fields = {f: getattr(sheet, f) for f in sheet.__dataclass_fields__}
    with pytest.raises(ValueError, match=r"BenderDatasheet\.resonance must be a finite number > 0"):
        BenderDatasheet(**{**fields, "resonance": True})
    with pytest.raises(ValueError, match=r"density \(kg/m\^3\) must be a finite number > 0"):
        bender_parameters("PL140", density=math.inf)
    with pytest.raises(ValueError, match="density must be 'calibrated', 'nominal' or a number"):
        bender_parameters("PL140", density="heavy")
    with pytest.raises(ValueError, match=r"dt \(s\) must be a finite number > 0"):
        PiezoBenderModel(dt=-1e-3)


@pytest.mark.parametrize("vector", [False, True])
def test_a_refused_reset_leaves_the_episode_as_it_was(vector):
    """A reference beyond reach (or a bad option) raises before the reset changes anything:
    the episode goes on from where it was, as if the call had not been made."""
    import gymnasium as gym

    kwargs = {"noise_bound": 0.0, "randomize": True}
    make = (
        (lambda: gym.make_vec("piezo_env:PiezoBender-v0", num_envs=2, **kwargs))
        if vector
        else (lambda: gym.make("piezo_env:PiezoBender-v0", **kwargs))
    )
    refused, untouched = make(), make()
    action = np.full((2, 1) if vector else (1,), 20.0, np.float32)
    for env in (refused, untouched):
        env.reset(seed=3)
        for _ in range(100):
            env.step(action)
    for bad in ({"reference": np.array([1e9])}, {"initial_voltage": 99.0}):
        with pytest.raises(ValueError):
            refused.reset(seed=7, options=bad)
    for _ in range(20):
        got, want = refused.step(action), untouched.step(action)
        np.testing.assert_array_equal(got[0], want[0])
