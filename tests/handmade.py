"""Small hand-made models the tests share."""

from __future__ import annotations

import numpy as np
import scipy.signal

from controllers import PredictionModel
from controllers.prediction import InverseResult
from identification.arx import ARXModel
from identification.features import PastInputFeatures
from identification.nls import NLS


def handmade_nls(out_weight: float) -> NLS:
    """z = u + out_weight * tanh(u) on +-5 V with identity normalization (past-input features).

    Monotone in u for out_weight > -1, not monotone below.
    """
    params = {
        "feature_mean": np.zeros(2),
        "feature_scale": np.ones(2),
        "z_mean": np.array(0.0),
        "z_scale": np.array(1.0),
        "layer0_weight": np.array([[1.0, 0.0]]),
        "layer0_bias": np.zeros(1),
        "out_weight": np.array([out_weight]),
        "out_bias": np.array(0.0),
        "skip_weight": np.array([1.0, 0.0]),
        "skip_bias": np.array(0.0),
    }
    return NLS(PastInputFeatures(n_past=1), params, u_range=(-5.0, 5.0))


class AffineNonlinearity:
    """z = 2 u + 1 with a memory-free state: its exact inverse is u = (z - 1) / 2."""

    u_range = (-30.0, 30.0)

    def initial_state(self) -> np.ndarray:
        return np.zeros(1)

    def step(self, u: float, state: np.ndarray) -> tuple[float, np.ndarray]:
        return 2.0 * u + 1.0, np.array([u])

    def inverse(self, z_target: float, state: np.ndarray) -> InverseResult:
        u = min(max((z_target - 1.0) / 2.0, -30.0), 30.0)
        status = "ok" if u == (z_target - 1.0) / 2.0 else "out-of-range"
        return InverseResult(u, 2.0 * u + 1.0, status, np.array([u]))

    def reachable(self, state: np.ndarray) -> tuple[float, float]:
        return -59.0, 61.0


def synthetic_model() -> PredictionModel:
    arx = ARXModel([1.2, -0.5], [2.0, 1.0], dt=1e-3)  # poles 0.6 +- 0.37j, zero at -0.5
    a, b, c, _ = arx.state_space_matrices()
    return PredictionModel(a, b, c, 1e-3, AffineNonlinearity(), "identified", (-59.0, 61.0))


def first_mode(dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bender-like first mode: 160 Hz, damping 0.02, 16 um/V static, exact ZOH at ``dt``
    (s): ``(a, b, c)`` of ``x_t+1 = a x_t + b z_t, y_t = c x_t``."""
    w, zeta, gain = 2 * np.pi * 160.0, 0.02, 16.0
    a_c = np.array([[0.0, 1.0], [-(w**2), -2 * zeta * w]])
    b_c = np.array([[0.0], [gain * w**2]])
    c_c = np.array([[1.0, 0.0]])
    a, b, c, _, _ = scipy.signal.cont2discrete((a_c, b_c, c_c, np.zeros((1, 1))), dt)
    return a, b, c


def run_observer(
    observer, z: np.ndarray, y: np.ndarray, *, guard: list | None = None
) -> np.ndarray:
    """Run an observer (or bank) on (z, y); the innovations of the estimate it read at each
    sample (um). ``guard``: a list to which a bank's ``guard_statistics`` after each
    measurement update are appended."""
    innovations = np.empty(z.size)
    for t in range(z.size):
        innovations[t] = y[t] - observer.c_aug @ observer.estimate
        observer.correct(y[t])
        if guard is not None:
            guard.append(observer.guard_statistics)
        observer.predict(z[t])
    return innovations
