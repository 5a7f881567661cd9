"""Bench disturbances: amplifier voltage noise, tip vibration, sensor quantisation."""

from __future__ import annotations

import copy
import math
import pickle

import gymnasium as gym
import numpy as np
import pytest
from scipy import signal

from piezo_env import Disturbance, TaskConfig
from piezo_env.amplifier import Amplifier
from piezo_env.disturbance import vibration_filter
from piezo_env.env import PiezoBenderEnv
from piezo_env.sensor import Sensor

OFF = Disturbance.none()
STRONG = Disturbance(
    voltage_noise_mV_rms=300.0,
    vibration_um_rms=5.0,
    vibration_band_Hz=(50.0, 400.0),
    sensor_bits=10,
)


def _run(env: PiezoBenderEnv, voltages: np.ndarray, seed: int = 0):
    """Observations, rewards and infos of ``voltages`` from reset(seed)."""
    obs, info = env.reset(seed=seed)
    observations, rewards, infos = [obs], [], [info]
    for v in voltages:
        obs, reward, _, _, info = env.step(np.array([v]))
        observations.append(obs)
        rewards.append(reward)
        infos.append(info)
    return np.array(observations), np.array(rewards), infos


def _drive(n: int, seed: int = 5) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-30.0, 30.0, n)


# -- off: the default env is unchanged --------------------------------------------------------


@pytest.mark.parametrize("off", [None, False, OFF])
def test_an_env_without_a_disturbance_is_bitwise_the_default_env(off):
    """More than one noise block (1024 samples): the sensor noise is drawn as before."""
    voltages = _drive(1500)
    expected = _run(PiezoBenderEnv(), voltages, seed=11)
    actual = _run(PiezoBenderEnv(disturbance=off), voltages, seed=11)
    np.testing.assert_array_equal(actual[0], expected[0])
    np.testing.assert_array_equal(actual[1], expected[1])
    deflections = [info["deflection_um"] for info in actual[2]]
    assert deflections == [info["deflection_um"] for info in expected[2]]
    assert PiezoBenderEnv(disturbance=off).bound == PiezoBenderEnv().bound
    if off is not OFF:
        assert "step" not in vars(PiezoBenderEnv(disturbance=off))  # the default path


def test_quantisation_alone_leaves_the_sensor_noise_draws_alone():
    """Quantisation draws nothing: the readings stay within half an LSB of the default env's,
    whose sensor noise (1 um) is 250 LSBs wide (a slow drive, within the sensor's range)."""
    voltages = 25.0 * np.sin(2 * np.pi * 3e-3 * np.arange(1200))
    env = PiezoBenderEnv(disturbance=Disturbance(0.0, 0.0, sensor_bits=20))
    lsb = env.unwrapped._disturbance.lsb
    quantised = _run(env, voltages, seed=3)[0][:, 0]
    default = _run(PiezoBenderEnv(), voltages, seed=3)[0][:, 0]
    assert lsb < 0.005
    np.testing.assert_array_less(np.abs(quantised - default.astype(float)), 0.5 * lsb + 1e-3)


# -- seeding ----------------------------------------------------------------------------------


def test_same_seed_same_trajectory_and_another_seed_another():
    voltages = _drive(1300)
    first = _run(PiezoBenderEnv(disturbance=STRONG), voltages, seed=4)
    again = _run(PiezoBenderEnv(disturbance=STRONG), voltages, seed=4)
    other = _run(PiezoBenderEnv(disturbance=STRONG), voltages, seed=5)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    for key in ("voltage_noise_V", "vibration_um"):
        assert [i[key] for i in first[2]] == [i[key] for i in again[2]]
        assert [i[key] for i in first[2]][1:] != [i[key] for i in other[2]][1:]


def test_a_disturbed_env_pickles_and_copies_mid_episode():
    env = PiezoBenderEnv(disturbance=STRONG, amplifier=True, sensor=Sensor(delay=1))
    _run(env, _drive(700))
    clones = [pickle.loads(pickle.dumps(env)), copy.deepcopy(env)]
    expected = [env.step(np.array([v]))[0] for v in _drive(600, seed=8)]
    for clone in clones:
        got = [clone.step(np.array([v]))[0] for v in _drive(600, seed=8)]
        np.testing.assert_array_equal(got, expected)


# -- amplifier voltage noise ------------------------------------------------------------------


def test_voltage_noise_is_white_at_its_rms():
    """Welch PSD of the plant input minus the command against the closed form 2 sigma^2 dt
    (one-sided, V^2/Hz): the band average within 3 %, each half of the band within 10 % of it,
    every bin within 50 % (about 120 averaged segments: a bin's spread is about 10 %)."""
    sigma = 5e-3  # V
    env = PiezoBenderEnv(
        disturbance=Disturbance(voltage_noise_mV_rms=sigma * 1e3, vibration_um_rms=0.0),
        noise_bound=0.0,
    )
    n = 1 << 14
    _, _, infos = _run(env, np.full(n, 10.0))
    applied = np.array([i["voltage_V"] - i["command_V"] for i in infos[1:]])
    np.testing.assert_allclose(applied, [i["voltage_noise_V"] for i in infos[1:]], atol=1e-12)
    dt = env.config.dt
    assert np.abs(applied).max() <= math.sqrt(3.0) * sigma
    assert np.sqrt(np.mean(applied**2)) == pytest.approx(sigma, rel=0.02)
    _, psd = signal.welch(applied, fs=1.0 / dt, nperseg=256)
    psd = psd[1:-1]  # the one-sided DC and Nyquist bins hold half
    white = 2.0 * sigma**2 * dt
    assert psd.mean() == pytest.approx(white, rel=0.03)
    half = len(psd) // 2
    assert psd[:half].mean() == pytest.approx(white, rel=0.10)
    assert psd[half:].mean() == pytest.approx(white, rel=0.10)
    np.testing.assert_allclose(psd, white, rtol=0.5)


def test_voltage_noise_stays_within_the_rails():
    env = PiezoBenderEnv(disturbance=Disturbance(voltage_noise_mV_rms=200.0, vibration_um_rms=0))
    _, _, infos = _run(env, np.tile([30.0, -30.0, 40.0], 200))
    voltages = np.array([i["voltage_V"] for i in infos[1:]])
    assert np.abs(voltages).max() <= env.model.rated_voltage
    at_rail = np.abs(np.array([i["command_V"] for i in infos[1:]])) == env.model.rated_voltage
    noise = np.array([i["voltage_noise_V"] for i in infos[1:]])
    assert np.all(noise[at_rail] * np.sign(voltages[at_rail]) <= 0.0)  # only the inward half
    assert np.any(noise[at_rail] != 0.0)


# -- tip vibration ----------------------------------------------------------------------------


def test_vibration_has_its_rms_and_band_and_moves_the_scored_tip():
    """At rest under 0 V the bending stays 0, so the deflection is the vibration: the sensor
    reads it and the reward scores it. RMS within 5 % (about 5000 independent samples: a 1 %
    spread); the Welch share of power inside the band within 0.015 of the filter's own
    |H|^2 share (0.90 for a fourth-order Butterworth), and the spectrum peaks inside it."""
    rms, band = 0.5, (20.0, 100.0)
    env = PiezoBenderEnv(
        disturbance=Disturbance(
            voltage_noise_mV_rms=0.0, vibration_um_rms=rms, vibration_band_Hz=band, sensor_bits=None
        ),
        noise_bound=0.0,
        reference=None,
        preview=0,
    )
    n = 1 << 15
    observations, rewards, infos = _run(env, np.zeros(n))
    vibration = np.array([i["vibration_um"] for i in infos])
    np.testing.assert_allclose([i["deflection_um"] for i in infos], vibration, rtol=1e-12)
    np.testing.assert_allclose(observations[:, 0], vibration.astype(np.float32))
    np.testing.assert_allclose(rewards, -((vibration[1:] / env.model.stroke_um) ** 2))
    assert np.sqrt(np.mean(vibration**2)) == pytest.approx(rms, rel=0.05)

    fs = 1.0 / env.config.dt
    freqs, psd = signal.welch(vibration, fs=fs, nperseg=2048)
    inside = (freqs >= band[0]) & (freqs <= band[1])
    share = psd[inside].sum() / psd.sum()
    grid, response = signal.sosfreqz(env.task.vibration.sos, worN=1 << 16, fs=fs)
    power = np.abs(response) ** 2
    expected = power[(grid >= band[0]) & (grid <= band[1])].sum() / power.sum()
    assert expected > 0.85
    assert share == pytest.approx(expected, abs=0.015)
    assert band[0] <= freqs[np.argmax(psd)] <= band[1]


@pytest.mark.parametrize("dt", [1e-3, 1e-4])
def test_vibration_peak_is_the_proven_bound_and_is_reached_by_the_worst_input(dt):
    """The adversarial input b sign(h_{N-k}) makes the output at N equal b sum|h|: within 1e-6
    of the peak, and the RMS matches Parseval on the filter's frequency response."""
    rms, band = 0.3, (8.0, 80.0)
    vib = vibration_filter(rms, band, dt)
    impulse = np.zeros(200_000)
    impulse[0] = 1.0
    h = signal.sosfilt(vib.sos, impulse)
    worst = signal.sosfilt(vib.sos, vib.half_width_um * np.sign(h[::-1]))[-1]
    assert worst <= vib.peak_um
    assert worst == pytest.approx(vib.peak_um, rel=1e-6)
    _, response = signal.sosfreqz(vib.sos, worN=1 << 20)
    variance = vib.half_width_um**2 / 3.0 * np.mean(np.abs(response) ** 2)
    assert math.sqrt(variance) == pytest.approx(rms, rel=1e-3)


def test_default_vibration_covers_a_vc_a_floor_under_the_pl140():
    """The module's derivation: VC-A (50 um/s RMS per third-octave band, 8-80 Hz) moves the
    tip of a cantilever with f_1 = 160 Hz, zeta = 0.02 by Gamma x_f r^2 / |1 - r^2 + 2 j zeta r|
    per band (Gamma = 1.566): 0.076 um RMS, below the default 0.08 um."""
    centres = np.array([8, 10, 12.5, 16, 20, 25, 31.5, 40, 50, 63, 80.0])
    r = centres / 160.0
    per_band = 1.566 * 50.0 / (2 * np.pi * centres) * r**2 / np.abs(1 - r**2 + 0.04j * r)
    relative = math.sqrt(np.sum(per_band**2))
    assert relative == pytest.approx(0.076, abs=0.001)
    assert Disturbance().vibration_um_rms >= relative
    assert Disturbance().vibration_band_Hz == (8.0, 80.0)


# -- sensor quantisation ----------------------------------------------------------------------


def test_readings_are_lsb_multiples_within_half_an_lsb_and_saturate_at_the_range():
    bits, span = 12, 300.0
    env = PiezoBenderEnv(
        disturbance=Disturbance(0.0, 0.0, sensor_bits=bits, sensor_range_um=span),
        noise_bound=0.0,
    )
    lsb = 2 * span / 2**bits
    voltages = 30.0 * np.sin(np.arange(3000) * 2 * np.pi * 5e-3)
    observations, _, infos = _run(env, voltages)
    readings = observations[:, 0].astype(float)
    deflections = np.array([i["deflection_um"] for i in infos])
    steps = readings / lsb
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-4)
    inside = np.abs(deflections) <= span
    assert inside.sum() > 500 and (~inside).sum() > 500
    error = readings[inside] - deflections[inside]
    assert np.abs(error).max() <= 0.5 * lsb * (1 + 1e-6)
    assert np.abs(error).max() > 0.4 * lsb  # the rounding is visible, not a no-op
    np.testing.assert_array_equal(np.abs(readings[~inside]), span)


def test_default_sensor_range_is_twice_the_stroke():
    env = PiezoBenderEnv(disturbance=True)
    assert env.task.sensor_range == 2.0 * env.model.stroke_um
    assert env.unwrapped._disturbance.lsb == pytest.approx(4000.0 / 2**16)


# -- the observation bound --------------------------------------------------------------------

BANG_BANG = {
    "amplifier": Amplifier(current_limit_mA=300.0),
    "sensor": Sensor(delay=1, bandwidth_Hz=5000.0),
    "noise_bound": 2.0,
}


@pytest.mark.parametrize(
    "disturbance",
    [
        Disturbance(300.0, 5.0, (50.0, 400.0), sensor_bits=None),
        Disturbance(300.0, 5.0, (5.0, 480.0), sensor_bits=6, sensor_range_um=1e6),
        STRONG,
    ],
    ids=["unquantised", "range-above-the-bound", "two-stroke-range"],
)
@pytest.mark.parametrize("period", [2, 6, 40])
def test_observation_bound_holds_under_bang_bang_with_every_disturbance_on(disturbance, period):
    env = PiezoBenderEnv(disturbance=disturbance, **BANG_BANG)
    task = env.task
    assert env.bound >= task.model.deflection_bound_um() + env.noise_bound + (
        0.0 if task.vibration is None else task.vibration.peak_um
    )
    if task.sensor_range is not None:
        assert env.bound >= task.sensor_range
    obs, _ = env.reset(seed=2)
    space = env.observation_space
    assert space.contains(obs)
    peak = 0.0
    for t in range(1500):
        u = 30.0 if (t // (period // 2)) % 2 == 0 else -30.0
        obs, _, _, _, info = env.step(np.array([u]))
        assert space.contains(obs), (t, obs)
        peak = max(peak, abs(info["deflection_um"]))
    assert peak > 0.1 * env.model.stroke_um


# -- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"voltage_noise_mV_rms": -1.0}, "voltage_noise_mV_rms"),
        ({"voltage_noise_mV_rms": float("nan")}, "voltage_noise_mV_rms"),
        ({"vibration_um_rms": -0.1}, "vibration_um_rms"),
        ({"vibration_um_rms": float("inf")}, "vibration_um_rms"),
        ({"vibration_band_Hz": (0.0, 80.0)}, "vibration_band_Hz low edge"),
        ({"vibration_band_Hz": (-5.0, 80.0)}, "vibration_band_Hz low edge"),
        ({"vibration_band_Hz": (80.0, 8.0)}, "vibration_band_Hz high edge"),
        ({"vibration_band_Hz": (8.0, float("nan"))}, "vibration_band_Hz high edge"),
        ({"vibration_band_Hz": 80.0}, r"pair \(low, high\)"),
        ({"sensor_bits": 1}, "sensor_bits"),
        ({"sensor_bits": 12.0}, "sensor_bits"),
        ({"sensor_bits": 40}, "at most 32"),
        ({"sensor_range_um": 0.0}, "sensor_range_um"),
        ({"sensor_bits": None, "sensor_range_um": 100.0}, "needs sensor_bits"),
    ],
)
def test_bad_settings_raise_naming_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Disturbance(**kwargs)


@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_band_is_checked_against_the_sample_time():
    with pytest.raises(ValueError, match=r"Nyquist frequency 0.5 / dt = 500 Hz"):
        gym.make("piezo_env:PiezoBender-v0", disturbance=Disturbance(vibration_band_Hz=(8, 500)))
    with pytest.raises(ValueError, match="vibration_band_Hz"):
        TaskConfig(dt=1e-2, disturbance=True)  # 8-80 Hz above 50 Hz
    TaskConfig(dt=1e-2, disturbance=Disturbance(vibration_um_rms=0.0))  # no vibration: no band
    PiezoBenderEnv(dt=1e-4, disturbance=Disturbance(vibration_band_Hz=(8, 4000)))
    with pytest.raises(ValueError, match="disturbance must be"):
        TaskConfig(disturbance="bench")


def test_vector_env_refuses_a_disturbance():
    with pytest.raises(ValueError, match=r"disturbance.*single envs"):
        gym.make_vec(
            "piezo_env:PiezoBender-v0",
            num_envs=2,
            vectorization_mode="vector_entry_point",
            disturbance=True,
        )


def test_gymnasium_make_takes_a_disturbance_and_passes_the_checker():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("piezo_env:PiezoBender-v0", disturbance=Disturbance())
    check_env(env.unwrapped, skip_render_check=True)
    assert env.unwrapped.config.disturbance == Disturbance()
