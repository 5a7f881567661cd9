"""The batched filter Riccati solver (controllers/riccati.py) against scipy's, one by one."""

from __future__ import annotations

from pathlib import Path

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


DATA = Path(__file__).parent / "data"


def _stored(name: str) -> tuple:
    """A bank's filter equations stored bit for bit (``tests/data/<name>.npz``): a
    three-state model with a lightly damped pair within 1e-6 of the unit circle, seen through a
    non-normal realization, with the output disturbance, at the bank's 12 noise levels."""
    data = np.load(DATA / f"{name}.npz")
    return data["a"], data["c"], data["q"], data["r"]


def test_equations_on_which_scipy_fails_to_reorder_are_solved_by_doubling():
    """The regression of ``ValueError: Reordering of (A, B) failed``, which scipy's Schur
    method raised from a filter Riccati solve in the middle of an episode (a model estimated
    online with a pole near the unit circle): scipy still raises it on one of these
    equations, the bank's doubling solves every one (checked here against the equation and for
    a stable filter, not against scipy), and no adaptive step solves a Riccati equation at all
    (tests/test_adaptive.py)."""
    aa, ca, q, r = _stored("riccati_near_unit_circle")
    failures = []
    for i in range(q.shape[0]):
        try:
            scipy.linalg.solve_discrete_are(aa.T, ca.T, q[i], np.array([[r[i]]]))
        except ValueError as error:
            failures.append(str(error))
    assert failures and all(f.startswith("Reordering of (A, B) failed") for f in failures)
    p, fallbacks = riccati.filter_riccati(aa, ca, q, r)
    assert fallbacks == 0
    for i in range(q.shape[0]):
        pc = p[i] @ ca.T
        innovation = (ca @ pc).item() + r[i]
        rhs = aa @ p[i] @ aa.T - aa @ pc @ pc.T @ aa.T / innovation + q[i]
        assert np.max(np.abs(rhs - p[i])) <= 1e-9 * np.max(np.abs(p[i]))
        assert np.all(np.linalg.eigvalsh(p[i]) >= -1e-9 * np.max(np.abs(p[i])))
        predictor = aa - aa @ pc @ ca / innovation  # the closed loop of the predicted estimate
        assert np.max(np.abs(np.linalg.eigvals(predictor))) < 1.0


def test_an_equation_neither_solver_solves_is_refused_with_the_reason_and_the_fix():
    aa, ca, q, r = _stored("riccati_ill_posed")
    reason = r"(?s)filter \d+ of 12 .*Reordering of \(A, B\) failed.*largest pole moduli "
    with pytest.raises(ValueError, match=reason + r".*Identify the model again") as caught:
        riccati.filter_riccati(aa, ca, q, r)
    assert isinstance(caught.value.__cause__, ValueError)  # scipy's own error, chained
