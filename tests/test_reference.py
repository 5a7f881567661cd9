"""Named references: drawn per episode, rendered in batches, checked against direct formulas."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from piezo_env.reference import (
    REFERENCE_SHAPES,
    SEGMENT,
    ReferenceStream,
    draw_reference,
    render_references,
)

DT = 1e-3


def _signal_of(draw, n):
    """The same reference from np.sin / scipy.signal.sawtooth sample by sample."""
    if draw.shape == "steps":
        return np.repeat(draw.levels, draw.hold)[:n]
    angle = 2 * np.pi * draw.frequency * np.arange(n) * DT + draw.phase
    if draw.shape == "sine":
        return draw.amplitude * np.sin(angle)
    if draw.shape == "triangle":
        return draw.amplitude * scipy.signal.sawtooth(angle + np.pi / 2, width=0.5)
    tones = np.linspace(0.5, draw.frequency, len(draw.tone_phases))
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
