"""The high-voltage amplifier that drives the bender: current (slew) limit and bandwidth.

A PICMA bender is a capacitor to its amplifier: the env's charge equation is
Q = C_p u + Gamma theta_tip (C_p = 2 x 4.1 uF on a PL140). The amplifier's output current is
limited, and so is the rate of the voltage it can put on that capacitance:
|du/dt| <= S = I_max / C_p (the slew limit, V/s). A sine u = U sin(2 pi f t) needs a peak
current C_p 2 pi f U: full stroke (U = 30 V) at 50 Hz on a PL140 needs 77 mA, and a current
limit I_max allows full-stroke sines up to f_max = I_max / (2 pi C_p U_r) (64.7 Hz at the
default 100 mA on a PL140; 19.4 Hz at 30 mA). The motional part Gamma dtheta/dt of the
current (the beam's reaction, about 10 % of the capacitive part below the resonance of a
PL140) is reported but not limited: the limit acts on the capacitive current C_p du/dt that a
datasheet's slew rate is quoted for (slew rate = current / capacitance, as in the Thorlabs
piezo-driver bandwidth tutorial, thorlabs.com NewGroupPage9.cfm?ObjectGroup_ID=1191, and the PI
E-617 manual: peak current for about 5 ms, then the average current).

Discrete model, at the env's sample rate: the voltage held on the bender over sample t is

    v_t = v_{t-1} + (1 - p) clip(c_t - v_{t-1}, -S dt, S dt),   p = exp(-2 pi f_a dt)

with c_t the (clipped) command: a rate limiter followed, if a small-signal bandwidth f_a is
given, by the exact ZOH of a first-order lag (p = 0 without one). A command whose increments
stay within S dt passes unchanged (without a bandwidth), so a controller that respects the
slew limit sees no amplifier at all; |v_t - v_{t-1}| <= S dt always, so C_p |dv/dt| <= I_max.
``info["slew_limited"]`` says when the clip was active.

Default values: 100 mA, no small-signal bandwidth (the sample rate is the bandwidth). These are
a typical bender amplifier's class of output current (tens to a few hundred mA at 60 V); the
E-650 / E-651 datasheet values could not be retrieved here, so the figure is a documented
choice, not a quoted one. What it implies on a PL140: S = 12.2 V/ms, full-stroke sines up to
64.7 Hz; a full-stroke 50 Hz sine needs 77 % of it (less by the beam's 1.08 gain there), so the
limit binds in transients. The benchmark's ``bench`` plant uses 50 mA for its half-stroke references
(:mod:`benchmarks.plants`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from piezo_env.checks import require_number

__all__ = ["Amplifier", "AmplifierState"]


@dataclass(frozen=True)
class Amplifier:
    """Current-limited amplifier (module docstring).

    Parameters
    ----------
    current_limit_mA : float
        Output current limit I_max (mA), > 0.
    bandwidth_Hz : float or None
        Small-signal (first-order) bandwidth f_a (Hz), > 0; None: none (instantaneous within the
        slew limit).
    """

    current_limit_mA: float = 100.0
    bandwidth_Hz: float | None = None

    def __post_init__(self) -> None:
        require_number(
            "Amplifier.current_limit_mA (mA)", self.current_limit_mA, low=0.0, low_open=True
        )
        if self.bandwidth_Hz is not None:
            require_number(
                "Amplifier.bandwidth_Hz (Hz, or None)", self.bandwidth_Hz, low=0.0, low_open=True
            )

    def slew_limit(self, capacitance: float) -> float:
        """Slew limit S = I_max / C_p (V/s) on a drive capacitance ``capacitance`` (F)."""
        return self.current_limit_mA * 1e-3 / capacitance

    def full_stroke_frequency(self, capacitance: float, amplitude: float) -> float:
        """Highest sine frequency (Hz) of amplitude ``amplitude`` (V) within the slew limit."""
        return self.slew_limit(capacitance) / (2.0 * math.pi * amplitude)

    def state(self, capacitance: float, dt: float) -> AmplifierState:
        """A stepping state for a drive capacitance (F) at sample time ``dt`` (s)."""
        pole = (
            0.0 if self.bandwidth_Hz is None else math.exp(-2.0 * math.pi * self.bandwidth_Hz * dt)
        )
        return AmplifierState(self.slew_limit(capacitance) * dt, 1.0 - pole)


class AmplifierState:
    """The amplifier's output voltage, stepped per sample (module docstring).

    Parameters
    ----------
    max_step : float
        S dt (V): the largest voltage change in one sample.
    gain : float
        1 - p of the small-signal lag (1 without a bandwidth).
    """

    def __init__(self, max_step: float, gain: float) -> None:
        self.max_step = max_step
        self.gain = gain
        self.voltage = 0.0

    def reset(self, voltage: float) -> None:
        """At rest at ``voltage`` (V)."""
        self.voltage = voltage

    def apply(self, command: float) -> tuple[float, bool]:
        """Voltage (V) held on the bender over this sample for ``command`` (V); whether the
        slew limit clipped it."""
        change = command - self.voltage
        limit = self.max_step
        limited = change > limit or change < -limit
        if limited:
            change = limit if change > 0 else -limit
        self.voltage += self.gain * change
        return self.voltage, limited
