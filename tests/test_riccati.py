"""The batched filter Riccati solver (controllers/riccati.py) against scipy's, one by one."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

import controllers.riccati as riccati
from controllers.observer import augmented, noise_covariance, state_scale_of


def _bank_problem(pole: float, seed: int) -> tuple:
    """A lightly damped mode plus a fast real pole, with the output disturbance: the bank's
    augmented model, and noise levels spanning the bank's (process 0 .. 8, disturbance 1/27 .. 9
    times the sensor noise)."""
    rng = np.random.default_rng(seed)
    angle = 2 * np.pi * 160e-3 * rng.uniform(0.8, 1.2)
    a = np.zeros((3, 3))
    a[:2, :2] = pole * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    a[2, 2] = 0.3
    b = rng.normal(size=(3, 1))
    c = rng.normal(size=(1, 3))
    aa, _, ca = augmented(a, b, c, 1)
    scale = state_scale_of(a, b[:, 0])
    levels = [(px, dx) for px in (0.0, 0.1, 1.0, 8.0) for dx in (1 / 27, 1.0, 9.0)]
    q = np.array([noise_covariance(b, scale, px, dx) for px, dx in levels])
    return aa, ca, q, rng.uniform(0.1, 2.0, len(levels))


@pytest.mark.parametrize("pole", [0.9, 0.99, 0.999])
@pytest.mark.parametrize("seed", range(3))
def test_doubling_matches_scipy_filter_by_filter(pole, seed):
    aa, ca, q, r = _bank_problem(pole, seed)
    p, fallbacks = riccati.filter_riccati(aa, ca, q, r)
    assert fallbacks == 0
    for i in range(q.shape[0]):
        expected = scipy.linalg.solve_discrete_are(aa.T, ca.T, q[i], np.array([[r[i]]]))
        np.testing.assert_allclose(p[i], expected, rtol=1e-8, atol=1e-10 * np.abs(expected).max())


def test_an_unconverged_iterate_is_solved_by_scipy_and_counted(monkeypatch):
    aa, ca, q, r = _bank_problem(0.999, 0)
    monkeypatch.setattr(riccati, "MAX_ITERATIONS", 1)
    p, fallbacks = riccati.filter_riccati(aa, ca, q, r)
    assert fallbacks == q.shape[0]
    expected = scipy.linalg.solve_discrete_are(aa.T, ca.T, q[0], np.array([[r[0]]]))
    np.testing.assert_allclose(p[0], expected, rtol=1e-12)
