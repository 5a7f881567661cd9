"""Offset-free state estimation: a steady-state Kalman filter with an output-disturbance state.

The prediction model ``x_t+1 = A x_t + B z_t``, ``y_t = C x_t`` is augmented with a constant
output disturbance d (a random walk)::

    [x; d]_t+1 = [[A, 0], [0, 1]] [x; d]_t + [B; 0] z_t + w_t,   y_meas,t = C x_t + d_t + v_t

d absorbs whatever the model gets wrong at low frequency (gain error, hysteresis mismatch, creep),
and because the controller predicts with the estimated d, a constant model error leaves no
steady-state tracking error (offset-free MPC: Muske & Badgwell 2002, Pannocchia & Rawlings 2003).

Tuning is one trade-off. The disturbance's random-walk standard deviation ``disturbance_std``
(um per sample) against the sensor's ``measurement_std`` (um) sets how fast d follows the
measurement: fast rejects model error quickly (a plant whose hysteresis differs from the
model's) but passes sensor noise into the control (amplified near the model's zeros close to
-1, i.e. near the Nyquist frequency); slow smooths noise but leaves model error uncorrected for
longer. ``process_std`` (equivalent V) is input-referred model noise on x.

The gain is the steady-state one (``scipy.linalg.solve_discrete_are``), so a step is two small
matrix-vector products.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["DisturbanceObserver"]


class DisturbanceObserver:
    """Steady-state Kalman filter of ``[x; d]`` (see the module docstring).

    Parameters
    ----------
    a, b, c : numpy.ndarray
        Linear model ``x_t+1 = a x_t + b z_t``, ``y_t = c x_t`` (um).
    measurement_std : float
        Sensor noise standard deviation (um), > 0.
    disturbance_std : float
        Random-walk step of the output disturbance (um per sample), > 0.
    process_std : float
        Input-referred process noise (equivalent V), >= 0.
    """

    def __init__(
        self,
        a: np.ndarray,
        b: np.ndarray,
        c: np.ndarray,
        *,
        measurement_std: float,
        disturbance_std: float,
        process_std: float = 0.0,
    ) -> None:
        if not (measurement_std > 0 and disturbance_std > 0 and process_std >= 0):
            raise ValueError(
                "observer needs measurement_std > 0, disturbance_std > 0, process_std >= 0; got "
                f"{measurement_std}, {disturbance_std}, {process_std}"
            )
        n = a.shape[0]
        self.n = n
        aa = np.zeros((n + 1, n + 1))
        aa[:n, :n] = a
        aa[n, n] = 1.0
        ba = np.zeros(n + 1)
        ba[:n] = b[:, 0]
        ca = np.zeros((1, n + 1))
        ca[0, :n] = c[0]
        ca[0, n] = 1.0
        q = np.zeros((n + 1, n + 1))
        q[:n, :n] = process_std**2 * np.outer(b[:, 0], b[:, 0])
        q[n, n] = disturbance_std**2
        q += 1e-12 * np.eye(n + 1)  # keeps the Riccati equation well posed for delay states
        r = np.array([[measurement_std**2]])
        p = scipy.linalg.solve_discrete_are(aa.T, ca.T, q, r)
        # Filter (current-estimate) gain: L = P C^T (C P C^T + R)^-1 on the predicted P.
        self.gain = (p @ ca.T / (ca @ p @ ca.T + r)).ravel()
        self.a_aug, self.b_aug, self.c_aug = aa, ba, ca[0]
        self.estimate = np.zeros(n + 1)

    def reset(self, estimate: np.ndarray | None = None) -> None:
        """Set the prior ``[x; d]`` (default: rest, no disturbance)."""
        self.estimate = np.zeros(self.n + 1) if estimate is None else np.array(estimate, float)

    def correct(self, y_measured: float) -> np.ndarray:
        """Measurement update with y (um); returns the filtered ``[x; d]`` (a view, not a copy)."""
        innovation = y_measured - float(self.c_aug @ self.estimate)
        self.estimate += self.gain * innovation
        return self.estimate

    def predict(self, z: float) -> None:
        """Time update with the hidden input z actually applied (equivalent V)."""
        self.estimate = self.a_aug @ self.estimate + self.b_aug * z

    def slowest_pole_hz(self, dt: float) -> float:
        """Decay rate of the slowest observer pole, -ln|p| / (2 pi dt) (Hz), for reports.

        Parameters
        ----------
        dt : float
            Sample time (s).
        """
        closed = self.a_aug - np.outer(self.a_aug @ self.gain, self.c_aug)
        radius = np.abs(np.linalg.eigvals(closed)).max()
        return float(-np.log(max(radius, 1e-300)) / (2 * np.pi * dt))
