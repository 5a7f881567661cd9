"""Excitation signals: shapes, levels, determinism under a seed, argument errors."""

import numpy as np
import pytest

from piezo_env import signals
from piezo_env.signals import SIGNALS, make_signal

DT = 1e-3
PARAMS = {
    "prbs": {"amplitude": 2.0, "clock_period": 3},
    "random": {"amplitude": 2.0, "hold": 4},
    "sine": {"amplitude": 2.0, "frequency": 5.0},
    "triangle": {"amplitude": 2.0, "frequency": 5.0},
    "square": {"amplitude": 2.0, "frequency": 5.0},
    "step": {"amplitude": 2.0, "start": 10},
    "multisine": {"amplitude": 2.0, "f_min": 1.0, "f_max": 40.0, "n_tones": 8},
    "chirp": {"amplitude": 2.0, "f0": 1.0, "f1": 100.0},
    "decaying-multisine": {"amplitude": 2.0},
}


@pytest.mark.parametrize("name", sorted(SIGNALS))
def test_every_signal_is_float64_of_length_n_within_amplitude(name):
    x = make_signal(name, 1001, dt=DT, rng=np.random.default_rng(0), **PARAMS[name])
    assert x.dtype == np.float64
    assert x.shape == (1001,)
    assert np.all(np.abs(x) <= 2.0 + 1e-12)


@pytest.mark.parametrize("name", ["prbs", "random", "multisine"])
def test_random_signals_are_reproducible_under_a_seed(name):
    a = make_signal(name, 500, dt=DT, rng=np.random.default_rng(7), **PARAMS[name])
    b = make_signal(name, 500, dt=DT, rng=np.random.default_rng(7), **PARAMS[name])
    c = make_signal(name, 500, dt=DT, rng=np.random.default_rng(8), **PARAMS[name])
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("kind", ["telegraph", "mls"])
def test_prbs_is_two_level_and_held_for_the_clock_period(kind):
    x = signals.prbs(300, amplitude=1.5, clock_period=5, rng=np.random.default_rng(1), kind=kind)
    assert set(np.unique(x)) == {-1.5, 1.5}
    assert np.all(x.reshape(-1, 5) == x.reshape(-1, 5)[:, :1])


def test_random_hold_is_uniform_and_held():
    x = signals.random_hold(40_000, amplitude=3.0, hold=4, rng=np.random.default_rng(2))
    blocks = x.reshape(-1, 4)
    assert np.all(blocks == blocks[:, :1])
    assert abs(np.mean(x)) < 0.05
    assert np.var(blocks[:, 0]) == pytest.approx(3.0**2 / 3.0, rel=0.03)


def test_deterministic_waveforms_match_closed_forms():
    t = np.arange(400) * DT
    np.testing.assert_allclose(
        signals.sine(400, dt=DT, amplitude=2.0, frequency=5.0, phase=0.3),
        2.0 * np.sin(2 * np.pi * 5.0 * t + 0.3),
    )
    tri = signals.triangle(400, dt=DT, amplitude=2.0, frequency=5.0)
    assert tri[0] == pytest.approx(0.0, abs=1e-12)
    assert tri[50] == pytest.approx(2.0)  # quarter period: the peak
    assert tri[150] == pytest.approx(-2.0)
    sq = signals.square(400, dt=DT, amplitude=2.0, frequency=5.0)
    assert np.all(sq[:100] == 2.0) and np.all(sq[100:200] == -2.0)
    st = signals.step(20, amplitude=-1.0, start=5)
    assert np.all(st[:5] == 0.0) and np.all(st[5:] == -1.0)


def test_multisine_and_decaying_multisine_reach_their_peak_exactly():
    x = signals.multisine(
        2000, dt=DT, amplitude=3.0, f_min=1.0, f_max=50.0, n_tones=10, rng=np.random.default_rng(3)
    )
    assert np.max(np.abs(x)) == pytest.approx(3.0)
    d = signals.decaying_multisine(4000, dt=DT, amplitude=3.0)
    assert np.max(np.abs(d)) == pytest.approx(3.0)
    assert np.max(np.abs(d[-1000:])) < 0.5 * np.max(np.abs(d[:1000]))


def test_chirp_starts_at_f0():
    x = signals.chirp(1000, dt=DT, amplitude=1.0, f0=2.0, f1=50.0)
    assert x[0] == pytest.approx(1.0)


def test_make_signal_names_valid_signals_and_parameters():
    with pytest.raises(ValueError, match="valid names: prbs"):
        make_signal("noise", 10, dt=DT)
    with pytest.raises(ValueError, match="accepted parameters: amplitude, frequency, phase"):
        make_signal("sine", 10, dt=DT, amplitude=1.0, frequency=1.0, hold=3)
    with pytest.raises(ValueError, match="needs frequency"):
        make_signal("sine", 10, dt=DT, amplitude=1.0)
    with pytest.raises(ValueError, match="rng"):
        make_signal("prbs", 10, dt=DT, amplitude=1.0)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: signals.sine(0, dt=DT, amplitude=1.0, frequency=1.0), r"n \(samples\) must be"),
        (lambda: signals.sine(10, dt=-1.0, amplitude=1.0, frequency=1.0), "dt"),
        (lambda: signals.sine(10, dt=DT, amplitude=np.nan, frequency=1.0), "amplitude"),
        (lambda: signals.sine(10, dt=DT, amplitude=1.0, frequency=600.0), "Nyquist"),
        (lambda: signals.step(10, amplitude=1.0, start=11), "start"),
        (
            lambda: signals.multisine(
                10,
                dt=DT,
                amplitude=1.0,
                f_min=5.0,
                f_max=1.0,
                n_tones=3,
                rng=np.random.default_rng(0),
            ),
            "f_max",
        ),
        (
            lambda: signals.prbs(10, amplitude=1.0, clock_period=0, rng=np.random.default_rng(0)),
            "clock_period",
        ),
    ],
)
def test_bad_arguments_raise_clear_value_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_rng_must_be_a_generator():
    with pytest.raises(TypeError, match=r"numpy\.random\.Generator"):
        signals.prbs(10, amplitude=1.0, rng=np.random.RandomState(0))
