"""Hysteresis operators: the scalar, numpy and casadi backends agree with each other and the ODE."""

from __future__ import annotations

import casadi
import numpy as np
import pytest
import scipy.integrate
from hypothesis import given, settings
from hypothesis import strategies as st

from identification.features import bouc_wen_update
from piezo_env.operators import (
    BoucWenBatch,
    bouc_wen_bound,
    bouc_wen_casadi,
    bouc_wen_jump,
    bouc_wen_slope,
    check_bouc_wen,
    clamp_sequence,
    normalized_bouc_wen,
    play,
    play_casadi,
    play_sequence,
)

PARAMS = [(0.4, 0.0233, 0.0233), (0.4, 0.03, 0.01), (1.0, 0.05, 0.0), (2.0, 0.1, -0.05)]


@pytest.mark.parametrize(("ak", "beta", "gamma"), PARAMS)
def test_bouc_wen_backends_agree(ak, beta, gamma):
    rng = np.random.default_rng(0)
    bound = bouc_wen_bound(ak, beta, gamma)
    h = rng.uniform(-bound, bound, 300)
    du = np.r_[rng.uniform(-40.0, 40.0, 299), 0.0]
    batch = BoucWenBatch(ak, beta, gamma)(h, du)
    scalar = np.array(
        [bouc_wen_jump(float(a), float(b), ak, beta, gamma) for a, b in zip(h, du, strict=True)]
    )
    np.testing.assert_allclose(batch, scalar, rtol=0, atol=1e-12)
    hs, ds = casadi.SX.sym("h"), casadi.SX.sym("du")
    f = casadi.Function("f", [hs, ds], [bouc_wen_casadi(hs, ds, ak, beta, gamma)])
    np.testing.assert_allclose(np.array(f(h, du)).ravel(), scalar, rtol=0, atol=1e-12)
    assert np.all(np.abs(batch) <= bound * (1 + 1e-12))


@settings(deadline=None, max_examples=50)
@given(
    h0=st.floats(-1.0, 1.0),
    du=st.floats(-50.0, 50.0).filter(lambda x: abs(x) > 1e-3),
    index=st.integers(0, len(PARAMS) - 1),
)
def test_bouc_wen_jump_and_slope_match_the_ode(h0, du, index):
    ak, beta, gamma = PARAMS[index]
    h0 *= bouc_wen_bound(ak, beta, gamma)
    s = np.sign(du)
    ode = scipy.integrate.solve_ivp(
        lambda u, h: [ak - beta * s * h[0] - gamma * abs(h[0])],
        (0.0, du),
        [h0],
        rtol=1e-11,
        atol=1e-12,
    )
    h1 = bouc_wen_jump(h0, du, ak, beta, gamma)
    assert h1 == pytest.approx(ode.y[0, -1], abs=1e-7)
    step = 1e-6 * s
    slope = (bouc_wen_jump(h0, du + step, ak, beta, gamma) - h1) / step
    assert bouc_wen_slope(h1, du, ak, beta, gamma) == pytest.approx(slope, abs=1e-4)


def test_normalized_operator_is_the_special_case():
    levels = np.array([3.0, 10.0, 40.0])
    ak, b, g = normalized_bouc_wen(levels)
    assert ak == 1.0 and np.array_equal(b, 0.5 / levels) and b is g
    np.testing.assert_allclose(bouc_wen_bound(ak, b, g), levels)
    rng = np.random.default_rng(1)
    h = rng.uniform(-3.0, 3.0, (50, 3))
    du = rng.uniform(-30.0, 30.0, (50, 1))
    expected = [
        [bouc_wen_jump(h[i, j], du[i, 0], 1.0, b[j], b[j]) for j in range(3)] for i in range(50)
    ]
    np.testing.assert_allclose(bouc_wen_update(h, du, levels), expected, atol=1e-12)


def test_check_bouc_wen_names_the_failed_condition():
    check_bouc_wen(0.4, 0.02, 0.02)
    with pytest.raises(ValueError, match="beta >= gamma"):
        check_bouc_wen(0.4, -0.01, 0.05)
    with pytest.raises(ValueError, match="beta \\+ gamma > 0"):
        check_bouc_wen(0.4, -0.05, 0.01)
    with pytest.raises(ValueError, match="alpha k > 0"):
        check_bouc_wen(0.0, 0.02, 0.02)


def test_play_backends_agree():
    rng = np.random.default_rng(2)
    radii = np.array([0.0, 2.0, 7.0])
    u = np.repeat(rng.uniform(-20.0, 20.0, 40), 2)
    seq, final = play_sequence(u, radii, np.zeros(3))
    p = np.zeros(3)
    ps, us_ = casadi.SX.sym("p", 3), casadi.SX.sym("u")
    f = casadi.Function("f", [ps, us_], [play_casadi(ps, us_, radii)])
    for t, v in enumerate(u):
        cas = np.array(f(p, v)).ravel()
        p = play(p, v, radii)
        np.testing.assert_array_equal(p, seq[t])
        np.testing.assert_array_equal(cas, p)
    np.testing.assert_array_equal(final, p)
    np.testing.assert_array_equal(seq[:, 0], u)  # radius 0 is the identity


def _clamp_case(length: int, width: int, seed: int):
    """Bounds with open sides (+-inf), held samples (both infinite), equal bounds and repeated
    values (rounded to 0.1 V), a start, and the recursion run sample by sample."""
    rng = np.random.default_rng(seed)
    centre = np.round(rng.uniform(-5.0, 5.0, (length, width)), 1)
    half = np.round(rng.uniform(0.0, 2.0, (length, width)), 1)
    lower, upper = centre - half, centre + half
    kind = rng.integers(0, 4, (length, width))
    lower[kind == 1] = -np.inf  # a falling directional play: only the upper bound
    upper[kind == 2] = np.inf  # a rising one
    lower[kind == 3], upper[kind == 3] = -np.inf, np.inf  # a held input
    start = np.round(rng.uniform(-5.0, 5.0, width), 1)
    expected = np.empty((length, width))
    p = start.copy()
    for t in range(length):
        p = np.maximum(lower[t], np.minimum(upper[t], p))
        expected[t] = p
    return lower, upper, start, expected


@pytest.mark.parametrize("length", [0, 1, 7, 8, 9, 16, 17, 63, 64, 65, 513])
def test_clamp_sequence_is_the_recursion_across_chunk_boundaries(length):
    lower, upper, start, expected = _clamp_case(length, 3, seed=length)
    got = clamp_sequence(lower, upper, start)
    assert got.shape == (length, 3)
    np.testing.assert_array_equal(got, expected)


@settings(max_examples=60, deadline=None)
@given(
    length=st.integers(min_value=0, max_value=300),
    width=st.integers(min_value=1, max_value=5),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_clamp_sequence_is_the_recursion(length, width, seed):
    """The scan gives the values of p_t = max(lo_t, min(hi_t, p_t-1)) run sample by sample."""
    lower, upper, start, expected = _clamp_case(length, width, seed)
    np.testing.assert_array_equal(clamp_sequence(lower, upper, start), expected)


def test_clamp_sequence_refuses_other_shapes():
    with pytest.raises(ValueError, match="samples, outputs"):
        clamp_sequence(np.zeros(5), np.ones(5), 0.0)
    with pytest.raises(ValueError, match="one shape"):
        clamp_sequence(np.zeros((5, 2)), np.ones((5, 3)), 0.0)
