"""The displacement sensor: a delay of whole samples and a first-order bandwidth.

Applied to the observed deflection only; the reward and ``info["deflection_um"]`` keep the true
tip deflection. The measured deflection at sample t is

    m_t = s_{t-d},   s_t = p s_{t-1} + b_0 y_t + b_1 y_{t-1}

with y the true deflection, d the delay (samples) and s the output of a first-order lag of
bandwidth f_s (tau = 1 / (2 pi f_s), p = exp(-dt / tau)) discretised exactly for a deflection
that is linear over each sample (first-order hold): b_0 = 1 - (tau / dt)(1 - p),
b_1 = (tau / dt)(1 - p) - p. Its low-frequency lag is tau, as the continuous sensor's (a
zero-order-hold discretisation would lag by about p / (1 - p) samples instead, far less than
tau when f_s is near the sample rate). p, b_0, b_1 are >= 0 and sum to 1, so |s_t| never exceeds
the largest |y| seen: the observation bound of the true deflection (plus noise) still holds.
Sensor noise is added after both. At reset the sensor holds the rest deflection.

What it costs: a sensor lag tau makes a loop that tracks the measurement lead the true
deflection by tau, an error of 2 pi f A tau at frequency f and amplitude A; a delay of d
samples likewise 2 pi f A d dt. At 50 Hz full stroke (1000 um) that is 0.25 % of the stroke
for a 20 kHz sensor and 31 % for a delay of one 1 ms sample, unless the controller knows it.
Typical values: capacitive and laser-triangulation displacement sensors' electronics are
specified with bandwidths of a few to tens of kHz (a documented choice here, not a quoted
datasheet value); the delay models a sensor read out one or two samples late (conversion
and transfer latency).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from piezo_env.checks import require_int, require_number

__all__ = ["MAX_DELAY", "Sensor", "SensorState"]

MAX_DELAY = 2
"""Largest accepted sensor delay (samples)."""


@dataclass(frozen=True)
class Sensor:
    """Displacement sensor dynamics (module docstring).

    Parameters
    ----------
    delay : int
        Measurement delay d in whole samples: 0, 1 or 2.
    bandwidth_Hz : float or None
        First-order bandwidth f_s (Hz), > 0 (default 20 kHz); None: none.
    """

    delay: int = 0
    bandwidth_Hz: float | None = 20e3

    def __post_init__(self) -> None:
        require_int("Sensor.delay (samples)", self.delay, minimum=0)
        if self.delay > MAX_DELAY:
            raise ValueError(
                f"Sensor.delay must be 0, 1 or 2 samples, got {self.delay}; a longer latency "
                "is a slower sample time, not a sensor"
            )
        if self.bandwidth_Hz is not None:
            require_number(
                "Sensor.bandwidth_Hz (Hz, or None)", self.bandwidth_Hz, low=0.0, low_open=True
            )

    def coefficients(self, dt: float) -> tuple[float, float, float]:
        """(p, b_0, b_1) of the first-order-hold lag at sample time ``dt`` (s); (0, 1, 0)
        without a bandwidth."""
        if self.bandwidth_Hz is None:
            return 0.0, 1.0, 0.0
        tau = 1.0 / (2.0 * math.pi * self.bandwidth_Hz)
        p = math.exp(-dt / tau)
        share = (tau / dt) * (-math.expm1(-dt / tau))
        return p, 1.0 - share, share - p

    def state_space(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The sensor as a discrete linear system from the true deflection y_t to the measured
        m_t (before noise), for a model that predicts what a controller measures.

        ``q_t+1 = a q_t + b y_t``, ``m_t = c q_t + d y_t``, with the state
        ``q_t = [s_t-1, y_t-1, s_t-2, ..., s_t-D]`` (D = max(delay, 1)): the filter's last
        output and input, then the delay line. ``d`` is b_0 without a delay and 0 with one. The
        static gain is 1 (p + b_0 + b_1 = 1), so a sensor at rest holds the deflection, as
        :class:`SensorState` starts.

        Parameters
        ----------
        dt : float
            Sample time (s).

        Returns
        -------
        a : numpy.ndarray
            (n, n), n = 1 + max(delay, 1).
        b, c : numpy.ndarray
            (n,) input and output vectors (dimensionless).
        d : float
            Feedthrough (dimensionless).
        """
        p, b0, b1 = self.coefficients(dt)
        n = 1 + max(self.delay, 1)
        a, b, c = np.zeros((n, n)), np.zeros(n), np.zeros(n)
        a[0, :2] = p, b1  # s_t = p s_t-1 + b_1 y_t-1 + b_0 y_t
        b[0] = b0
        b[1] = 1.0  # y_t-1 of the next sample
        if n > 2:
            a[2, 0] = 1.0  # s_t-2 of the next sample is this s_t-1
            a[3:, 2:-1] = np.eye(n - 3)  # and the rest of the line moves on by one
        if self.delay == 0:
            c[:2], d = (p, b1), b0
        else:
            c[0 if self.delay == 1 else self.delay], d = 1.0, 0.0
        return a, b, c, d

    def state(self, dt: float) -> SensorState:
        """A stepping state at sample time ``dt`` (s)."""
        return SensorState(self.delay, *self.coefficients(dt))


class SensorState:
    """Sensor filter and delay line, stepped per sample (um in, um out)."""

    def __init__(self, delay: int, p: float, b0: float, b1: float) -> None:
        self.delay = delay
        self.p, self.b0, self.b1 = p, b0, b1
        self._line: deque[float] = deque(maxlen=delay + 1)
        self._s = 0.0
        self._y = 0.0

    def reset(self, deflection_um: float) -> float:
        """At rest at ``deflection_um``; returns the measured value."""
        self._s = self._y = deflection_um
        self._line.clear()
        self._line.extend([deflection_um] * (self.delay + 1))
        return deflection_um

    def measure(self, deflection_um: float) -> float:
        """Measured deflection (um, before noise) after the true one became ``deflection_um``."""
        self._s = self.p * self._s + self.b0 * deflection_um + self.b1 * self._y
        self._y = deflection_um
        line = self._line
        line.append(self._s)
        return line[0]
