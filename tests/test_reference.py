"""Named references: drawn per episode, rendered in batches, checked against direct formulas."""

from __future__ import annotations

import hashlib

import gymnasium as gym
import numpy as np
import pytest
import scipy.signal

import piezo_env  # noqa: F401  (registers the ids)
from piezo_env.reference import (
    DEFAULT_BAND,
    REFERENCE_SHAPES,
    SEGMENT_S,
    ReferenceStream,
    check_reference_band,
    draw_reference,
    render_references,
    segment_samples,
)
from piezo_env.task import TaskConfig
from piezo_env.vector_env import PiezoBenderVectorEnv

DT = 1e-3
SEGMENT = segment_samples(DT)


def _signal_of(draw, n):
    """The same reference from np.sin / scipy.signal.sawtooth sample by sample."""
    if draw.shape == "steps":
        return np.repeat(draw.levels, draw.hold)[:n]
    angle = 2 * np.pi * draw.frequency * np.arange(n) * DT + draw.phase
    if draw.shape == "sine":
        return draw.amplitude * np.sin(angle)
    if draw.shape == "triangle":
        return draw.amplitude * scipy.signal.sawtooth(angle + np.pi / 2, width=0.5)
    tones = np.linspace(draw.low_frequency, draw.frequency, len(draw.tone_phases))
    x = np.sin(2 * np.pi * np.outer(np.arange(n) * DT, tones) + draw.tone_phases).sum(axis=1)
    return x * draw.amplitude / np.abs(x).max()


@pytest.mark.parametrize("shape", REFERENCE_SHAPES)
def test_rendered_shapes_match_the_signals(shape):
    for seed in range(10):
        draw = draw_reference(shape, 3000, dt=DT, stroke_um=1000.0, rng=np.random.default_rng(seed))
        rendered = render_references([draw], 3000, dt=DT)[0]
        np.testing.assert_allclose(rendered, _signal_of(draw, 3000), rtol=0, atol=1e-9)
        assert np.abs(rendered).max() <= 0.8 * 1000.0 + 1e-9


def test_batch_rendering_equals_single_rendering_bitwise():
    draws = [
        draw_reference("random", SEGMENT, dt=DT, stroke_um=310.0, rng=np.random.default_rng(s))
        for s in range(64)
    ]
    batch = render_references(draws, SEGMENT, dt=DT)
    single = np.array([render_references([d], SEGMENT, dt=DT)[0] for d in draws])
    assert np.array_equal(batch, single)
    assert {d.shape for d in draws} == set(REFERENCE_SHAPES)


@pytest.mark.parametrize("shape", REFERENCE_SHAPES)
def test_a_named_reference_is_a_function_of_time_whatever_the_sample_time(shape):
    """The same seed at 1 ms and at 0.25 ms (the PL127's rate) and 0.1 ms (the PL112's):
    the same reference at the shared instants over a whole 2 s episode, with no segment
    boundary inside it (segments and step holds are durations, not sample counts). The
    multisine is scaled to its peak over the samples, which a finer grid finds a little
    higher."""
    assert segment_samples(DT) * DT == pytest.approx(SEGMENT_S) and SEGMENT_S > 2.0
    coarse = ReferenceStream(shape, dt=DT, stroke_um=450.0, bound=5e4, rng=np.random.default_rng(9))
    coarse = coarse.ensure(2000)[:2000].astype(float)
    for factor in (4, 10):
        fine = ReferenceStream(
            shape, dt=DT / factor, stroke_um=450.0, bound=5e4, rng=np.random.default_rng(9)
        )
        fine = fine.ensure(2000 * factor)[: 2000 * factor : factor].astype(float)
        tolerance = 0.01 * np.abs(coarse).max() if shape == "multisine" else 1e-3
        np.testing.assert_allclose(fine, coarse, rtol=0, atol=tolerance, err_msg=f"x{factor}")


def test_stream_extends_by_fresh_segments_and_arrays_hold_their_last_value():
    stream = ReferenceStream(
        "sine", dt=DT, stroke_um=1000.0, bound=5e4, rng=np.random.default_rng(0)
    )
    values = stream.ensure(2 * SEGMENT + 1)
    assert len(values) == 3 * SEGMENT
    assert not np.allclose(values[:SEGMENT], values[SEGMENT : 2 * SEGMENT])
    fixed = ReferenceStream(np.array([1.0, 2.0]), dt=DT, stroke_um=1000.0, bound=10.0, rng=None)
    assert np.all(fixed.ensure(10)[1:] == 2.0)
    with pytest.raises(ValueError, match="one-dimensional"):
        ReferenceStream(np.ones((2, 2)), dt=DT, stroke_um=1000.0, bound=10.0, rng=None)


# Drawn with seed 11 before the band became an option: (frequency as float.hex, the first 16 hex
# digits of the SHA-256 of the rendered float64 samples rounded to 1e-6 um). The draw's numbers
# are compared bitwise; the samples to 1e-6 um, because numpy's vectorised sine differs in the
# last bit between numpy versions and CPUs (numpy 1.25 on an Intel Xeon), which is not a
# different draw (samples up to 280 um: a last-bit difference is about 6e-14 um).
_GOLDEN_DEFAULT_BAND = {
    "sine": ("0x1.93b1d8ba15d9cp+1", "10c209e224c37fff"),
    "triangle": ("0x1.93b1d8ba15d9cp+1", "5135dfd0fa78b3d4"),
    "multisine": ("0x1.4000000000000p+4", "9496130c9559ddc1"),
    "steps": ("0x1.93b1d8ba15d9cp+1", "39b3ec278dbc6ca8"),
}


@pytest.mark.parametrize("shape", REFERENCE_SHAPES)
@pytest.mark.parametrize("band", [None, DEFAULT_BAND])
def test_default_band_draws_are_bitwise_those_made_before_the_option(shape, band):
    kwargs = {} if band is None else {"band": band}
    draw = draw_reference(
        shape, SEGMENT, dt=DT, stroke_um=1000.0, rng=np.random.default_rng(11), **kwargs
    )
    samples = render_references([draw], SEGMENT, dt=DT)[0]
    digest = hashlib.sha256(np.round(samples, 6).tobytes()).hexdigest()[:16]
    assert (draw.frequency.hex(), digest) == _GOLDEN_DEFAULT_BAND[shape]


@pytest.mark.parametrize("band", [(40.0, 100.0), (0.5, 250.0), (75.0, 75.0)])
def test_draws_stay_in_the_band_and_take_as_many_numbers_as_the_default(band):
    low, high = band
    for seed in range(200):
        rng, default_rng = np.random.default_rng(seed), np.random.default_rng(seed)
        draw = draw_reference("random", 3000, dt=DT, stroke_um=1000.0, rng=rng, band=band)
        draw_reference("random", 3000, dt=DT, stroke_um=1000.0, rng=default_rng)
        assert rng.bit_generator.state == default_rng.bit_generator.state
        if draw.shape in ("sine", "triangle"):
            assert low * (1 - 1e-12) <= draw.frequency <= high * (1 + 1e-12)
        elif draw.shape == "multisine":
            assert (draw.low_frequency, draw.frequency) == (low, high)
        rendered = render_references([draw], 3000, dt=DT)[0]
        np.testing.assert_allclose(rendered, _signal_of(draw, 3000), rtol=0, atol=1e-9)


@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_band_is_validated_and_stored_as_floats():
    assert TaskConfig().reference_band == DEFAULT_BAND
    assert TaskConfig(reference_band=[1, 100]).reference_band == (1.0, 100.0)
    assert check_reference_band(DEFAULT_BAND, 0.05) == DEFAULT_BAND  # cut to 5 Hz when drawn
    for bad in [(0.0, 10.0), (-1.0, 10.0), (20.0, 10.0), (0.5, 251.0), (0.5,), "0.5-20", None]:
        with pytest.raises(ValueError, match="reference_band"):
            TaskConfig(reference_band=bad)
    with pytest.raises(ValueError, match=r"0\.25/dt = 25 Hz"):
        TaskConfig(reference_band=(0.5, 30.0), dt=1e-2)


def test_single_env_equals_vector_env_with_a_band():
    """Sub-env i is the single env seeded seed + i, second segments and autoresets included."""
    n, seed, steps, horizon, band = 3, 5, 2 * SEGMENT + 100, SEGMENT + 500, (40.0, 100.0)
    vec = PiezoBenderVectorEnv(n, max_episode_steps=horizon, preview=4, reference_band=band)
    singles = [
        gym.make(
            "piezo_env:PiezoBender-v0", max_episode_steps=horizon, preview=4, reference_band=band
        )
        for _ in range(n)
    ]
    actions = np.random.default_rng(3).uniform(-5, 5, (steps, n, 1)).astype(np.float32)
    obs_v = [vec.reset(seed=seed)[0]]
    obs_s = [np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(singles)])]
    done = False
    for a in actions:
        obs_v.append(vec.step(a)[0])
        if done:  # the vector env autoresets on the step after the episode ends
            rows = [env.reset()[0] for env in singles]
            done = False
        else:
            results = [env.step(a[i]) for i, env in enumerate(singles)]
            rows = [r[0] for r in results]
            done = results[0][3] or results[0][2]
        obs_s.append(np.stack(rows))
    np.testing.assert_array_equal(np.array(obs_v), np.array(obs_s))
    default = gym.make("piezo_env:PiezoBender-v0", preview=4)
    assert not np.array_equal(default.reset(seed=seed)[0][1:], obs_s[0][0][1:])


@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
@pytest.mark.parametrize("reference", ["random", "sine", "steps"])
def test_a_sample_time_too_coarse_for_the_default_band_is_refused_with_the_fix(reference):
    """At dt = 1 s the default band's top, cut to 0.25/dt = 0.25 Hz, falls below its 0.5 Hz
    bottom: the reset says so and what to change, not a numpy error. Steps use no frequency
    and run at any dt."""
    env = gym.make("piezo_env:PiezoBender-v0", dt=1.0, reference=reference)
    if reference == "steps":
        env.reset(seed=0)
    else:
        with pytest.raises(ValueError, match=r"is empty: use dt <= 0\.5 s"):
            env.reset(seed=0)
    ok = gym.make("piezo_env:PiezoBender-v0", dt=0.5, reference=reference)
    ok.reset(seed=0)
