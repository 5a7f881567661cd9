"""The disturbances of a real bench: amplifier voltage noise, tip vibration, sensor quantisation.

Each one is off unless a :class:`Disturbance` is passed (``disturbance=Disturbance()`` gives
the typical bench values below; ``Disturbance.none()`` or zeros switch each off). Every random
draw comes from the env's ``np_random``, in blocks of ``NOISE_BLOCK`` samples as the sensor
noise is drawn, after the sensor noise of the same reset; a disturbance that is off draws
nothing.

Amplifier voltage noise. The amplifier's broadband output noise n_t sits on its output, so it
is added to the voltage the amplifier puts out (the clipped command, or the slew-limited voltage
with an :class:`~piezo_env.amplifier.Amplifier`), and the sum is held at the output rails
+-U_r (the drive range, where the action is clipped too): the bender gets
clip(v_t + n_t, -U_r, U_r). Inside the range the noise passes whole; at a rail only its inward
half does, as an amplifier's saturated output stage does. So |voltage| <= U_r still holds and
the deflection bounds (nominal, drifted, randomised) need no change. n_t is white over the
sample band and uniform, n_t ~ U(-sqrt(3) sigma_n, sqrt(3) sigma_n): the RMS sigma_n and the
flat spectrum (one-sided PSD 2 sigma_n^2 dt, V^2/Hz) a datasheet specifies, bounded at a crest
factor sqrt(3) like the project's sensor noise. ``info["voltage_noise_V"]`` is the noise that
reached the bender (after the rails).

Tip vibration. Floor and acoustic vibration move the tip relative to the sensor: the
displacement w_t is added to the bending deflection, so the sensor measures it AND the reward
is scored on it (the tracking error is what the sensor frame sees); ``info["deflection_um"]`` is
then bending plus vibration and ``info["vibration_um"]`` the vibration alone, so the bending is
their difference; the ``deflection_limit`` reads the sum too. w_t is white uniform noise
e_t ~ U(-b, b) through a fourth-order Butterworth band-pass (scipy.signal.butter, second-order
sections, run by sosfilt over each block with its state carried): RMS
sigma_w = b ||h||_2 / sqrt(3), so b = sqrt(3) sigma_w / ||h||_2, with h the filter's impulse
response. Being a sum of many bounded draws, w is close to Gaussian, yet provably bounded:
|w_t| <= b ||h||_1 (the ``peak_um`` of :func:`vibration_filter`), which the observation bound
adds (:class:`piezo_env.task.BenderTask`). That peak is reached only by the one adversarial
input sign(h) and grows with the sample rate (its crest factor sqrt(3) ||h||_1 / ||h||_2 is
about 12 for 8-80 Hz at 1 kHz, 37 at 10 kHz). At reset the filter first runs over a warm-up
of draws (until the impulse response's remaining energy is below 0.1 %), so an episode starts
in the stationary vibration rather than at rest.

Sensor quantisation. The sensor's ADC spans its measuring range [-R, R] with ``sensor_bits``
bits: the measured deflection (after the sensor dynamics and the sensor noise) is held within
[-R, R], as an out-of-range reading saturates, and rounded to a multiple of the LSB
q = 2 R / 2^bits, an error of at most q / 2 inside the range. R / q = 2^(bits - 1) is a whole
number of steps, so every reading lies in [-R, R]; the observation bound is raised to R if it
is below (:class:`piezo_env.task.BenderTask`). R is ``sensor_range_um``, by default twice the
datasheet stroke: a sensor chosen for the bender's travel (the static deflection at U_r, about
1.03 strokes with the hysteresis) with as much again for dynamic overshoot. The proven
observation bound B itself is no sensor range: it covers the worst resonant excitation (about
42 strokes for the PL140), and an ADC spread over it would step by 1.3 um at 16 bits.

Typical bench values (``Disturbance()``), each from a datasheet class:

- ``voltage_noise_mV_rms = 0.7``: a linear piezo amplifier of the PiezoDrive PD200 class on a
  10 uF load (the PL140's drive capacitance is 8.2 uF) has 0.71 mV RMS output noise from
  0.03 Hz to 1 MHz (PD200 manual, noise table; specified below 2 mV RMS); the load's capacitance
  filters the broadband part, so nearly all of it lies in the sample band.
- ``vibration_um_rms = 0.08`` in ``vibration_band_Hz = (8, 80)``: a lab floor at the VC-A
  vibration criterion (50 um/s RMS in each third-octave band from 8 to 80 Hz; Gordon's generic
  vibration criteria, IEST-RP-CC012) moves a cantilever's tip against its clamp by
  Gamma x_f r^2 / |1 - r^2 + 2 j zeta r| per band (x_f = v / (2 pi f) the floor displacement,
  r = f / f_1, Gamma = 1.566 the tip participation of a uniform cantilever's first mode):
  0.076 um RMS summed over the bands for the PL140 (f_1 = 160 Hz, zeta = 0.02), rounded up.
  The faster benders move less.
- ``sensor_bits = 16`` over ``sensor_range_um = None`` (+-2 strokes: q = 0.061 um on the
  PL140): PI's digital piezo controllers read their capacitive and strain sensors with 16- to
  20-bit A/D converters (PI, "Digital and Analog Interfaces"); 16 bits is the coarse end of
  that class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from piezo_env.checks import require_int, require_number

__all__ = [
    "FILTER_ORDER",
    "RANGE_STROKES",
    "Disturbance",
    "DisturbanceState",
    "VibrationFilter",
    "vibration_filter",
]

FILTER_ORDER = 4
"""Order of the vibration's Butterworth band-pass (per edge): about 90 % of its power lies
inside the band (a second-order one leaks about 20 % past the edges)."""

RANGE_STROKES = 2.0
"""Default sensor range in datasheet strokes (module docstring): the static travel (1.03 strokes
with the hysteresis) with as much again for dynamic overshoot."""

_DECAY = 1e-16
"""The impulse response is summed until its slowest pole has decayed by this factor; the rest
is bounded by the pole residues (:func:`vibration_filter`)."""

_MAX_SAMPLES = 1 << 22
"""Longest impulse response summed (samples): a band edge far below the sample rate needs more,
and is refused with a message."""

_WARMUP_ENERGY = 1e-3
"""The reset's warm-up runs the filter until the impulse response's remaining energy is below
this fraction: the first vibration sample's variance is then within 0.1 % of the stationary
one."""


@dataclass(frozen=True)
class Disturbance:
    """Bench disturbances (module docstring); the defaults are typical bench values.

    Parameters
    ----------
    voltage_noise_mV_rms : float
        RMS sigma_n (mV) of the amplifier's white output voltage noise, >= 0 (0: off).
    vibration_um_rms : float
        RMS sigma_w (um) of the tip's band-limited vibration relative to the sensor, >= 0
        (0: off).
    vibration_band_Hz : (float, float)
        Pass band (low, high) (Hz) of the vibration, 0 < low < high < 0.5 / dt (checked
        against the sample time when the env is made). Stored as a tuple of two floats.
    sensor_bits : int or None
        ADC bits over the sensor's range, 2 to 32; None: no quantisation.
    sensor_range_um : float or None
        The sensor's range R (um), > 0: readings are held within [-R, R]. None:
        :data:`RANGE_STROKES` times the bender's datasheet stroke. Only with ``sensor_bits``.
    """

    voltage_noise_mV_rms: float = 0.7
    vibration_um_rms: float = 0.08
    vibration_band_Hz: tuple[float, float] = (8.0, 80.0)
    sensor_bits: int | None = 16
    sensor_range_um: float | None = None

    def __post_init__(self) -> None:
        require_number("Disturbance.voltage_noise_mV_rms (mV)", self.voltage_noise_mV_rms, low=0.0)
        require_number("Disturbance.vibration_um_rms (um)", self.vibration_um_rms, low=0.0)
        object.__setattr__(self, "vibration_band_Hz", _check_band(self.vibration_band_Hz))
        if self.sensor_bits is not None:
            require_int("Disturbance.sensor_bits (bits, or None)", self.sensor_bits, minimum=2)
            if self.sensor_bits > 32:
                raise ValueError(
                    f"Disturbance.sensor_bits must be at most 32, got {self.sensor_bits}; "
                    "pass None for no quantisation"
                )
            object.__setattr__(self, "sensor_bits", int(self.sensor_bits))
        if self.sensor_range_um is not None:
            require_number(
                "Disturbance.sensor_range_um (um, or None for twice the stroke)",
                self.sensor_range_um,
                low=0.0,
                low_open=True,
            )
            if self.sensor_bits is None:
                raise ValueError(
                    "Disturbance.sensor_range_um is the ADC's range and needs sensor_bits; "
                    "pass sensor_bits or leave sensor_range_um None"
                )

    @classmethod
    def none(cls) -> Disturbance:
        """Every disturbance off: the env behaves as without one (same draws, same values)."""
        return cls(voltage_noise_mV_rms=0.0, vibration_um_rms=0.0, sensor_bits=None)

    def sensor_range(self, stroke_um: float) -> float | None:
        """The ADC's range R (um) on a bender of one-sided stroke ``stroke_um`` (um); None
        without quantisation."""
        if self.sensor_bits is None:
            return None
        if self.sensor_range_um is not None:
            return float(self.sensor_range_um)
        return RANGE_STROKES * stroke_um

    def check_sample_time(self, dt: float) -> None:
        """Raise ValueError if the vibration is on and its band does not fit below 0.5 / dt."""
        if self.vibration_um_rms == 0:
            return
        nyquist = 0.5 / dt
        low, high = self.vibration_band_Hz
        if not high < nyquist:
            raise ValueError(
                f"Disturbance.vibration_band_Hz = ({low:g}, {high:g}) Hz must lie below the "
                f"Nyquist frequency 0.5 / dt = {nyquist:g} Hz at dt = {dt:g} s; lower its "
                "high edge or use a shorter dt"
            )


def _check_band(band: object) -> tuple[float, float]:
    """``band`` as (low, high) floats with 0 < low < high."""
    name = "Disturbance.vibration_band_Hz"
    try:
        low, high = band  # type: ignore[misc]
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a pair (low, high) of frequencies in Hz, got {band!r}"
        ) from None
    low = require_number(f"{name} low edge (Hz)", low, low=0.0, low_open=True)
    high = require_number(f"{name} high edge (Hz)", high, low=low, low_open=True)
    return low, high


@dataclass(frozen=True)
class VibrationFilter:
    """The vibration's band-pass at one sample time (:func:`vibration_filter`).

    Attributes
    ----------
    sos : ndarray
        Second-order sections of the Butterworth band-pass.
    half_width_um : float
        b (um): the white input is U(-b, b).
    peak_um : float
        Proven bound of |w_t| (um): b ||h||_1.
    warmup : int
        Samples run at reset before the first one (the stationary start).
    """

    sos: np.ndarray
    half_width_um: float
    peak_um: float
    warmup: int


def vibration_filter(rms_um: float, band: tuple[float, float], dt: float) -> VibrationFilter:
    """The band-pass, input width, proven peak and warm-up of a vibration of RMS ``rms_um``.

    The impulse response h is computed by sosfilt over N samples, N the decay of the slowest
    pole to 1e-16; the tail beyond N is bounded by sum_j |rho_j| |lambda_j|^(N-1) / (1 - |lambda_j|)
    over the poles lambda_j and residues rho_j of the cascade's state space (as in
    :meth:`piezo_env.discrete.DiscreteBender.impulse_l1_bound`), and the L1 norm gets a 1e-9
    relative margin for the rounding of the sum.
    """
    from scipy import signal  # only with a vibration: scipy.signal is slow to import

    sos = signal.butter(FILTER_ORDER, band, btype="bandpass", fs=1.0 / dt, output="sos")
    a, b, c = _cascade_state_space(sos)
    lam, vec = np.linalg.eig(a)
    radius = np.abs(lam)
    n = math.ceil(math.log(_DECAY) / math.log(float(radius.max())))
    if n > _MAX_SAMPLES:
        raise ValueError(
            f"Disturbance.vibration_band_Hz low edge {band[0]:g} Hz is too low for dt = {dt:g} s: "
            f"its filter rings for more than {_MAX_SAMPLES} samples; raise the low edge"
        )
    impulse = np.zeros(n)
    impulse[0] = 1.0
    h = signal.sosfilt(sos, impulse)
    residues = (c @ vec) * np.linalg.solve(vec, b)
    tail = float(np.sum(np.abs(residues) * radius ** (n - 1) / (1.0 - radius)))
    l1 = (float(np.abs(h).sum()) + tail) * (1.0 + 1e-9)
    energy = np.cumsum((h * h)[::-1])[::-1]  # energy[k]: of h_k, h_k+1, ...
    l2 = math.sqrt(float(energy[0]))
    warmup = int(np.argmax(energy <= _WARMUP_ENERGY * energy[0]))
    half_width = math.sqrt(3.0) * rms_um / l2
    return VibrationFilter(sos, half_width, half_width * l1, warmup)


def _cascade_state_space(sos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C) of the sections in series, each in direct form (its poles are A's block
    eigenvalues, accurate where one high-order polynomial's roots would not be)."""
    m = len(sos)
    a = np.zeros((2 * m, 2 * m))
    b = np.zeros(2 * m)
    c = np.zeros(2 * m)
    # x_k of section s holds its last two inputs' contributions; the input of section s is the
    # output of section s - 1, y = c_s x + d_s u, x' = A_s x + B_s u.
    gain_in = np.zeros(2 * m)  # how the cascade's input enters the current section's input
    gain_in_d = 1.0
    for s, (b0, b1, b2, _, a1, a2) in enumerate(sos):
        i = slice(2 * s, 2 * s + 2)
        a_s = np.array([[-a1, -a2], [1.0, 0.0]])
        b_s = np.array([1.0, 0.0])
        c_s = np.array([b1 - b0 * a1, b2 - b0 * a2])
        # section input u_s = gain_in . x + gain_in_d u
        a[i, i] = a_s
        a[i, :] += np.outer(b_s, gain_in)
        b[i] = b_s * gain_in_d
        out = b0 * gain_in
        out[i] += c_s
        gain_in, gain_in_d = out, b0 * gain_in_d
    c[:] = gain_in
    return a, b, c


class DisturbanceState:
    """The drawn noise and vibration blocks and the quantiser, stepped per sample.

    Parameters
    ----------
    disturbance : Disturbance
        The settings.
    vibration : VibrationFilter or None
        The vibration's filter at the env's dt (None: no vibration).
    u_max : float
        Output rails (V): the noisy voltage is held within +-u_max.
    sensor_range : float or None
        The ADC's range R (um; :meth:`Disturbance.sensor_range`), None without quantisation.
    block : int
        Samples drawn at a time.
    """

    def __init__(
        self,
        disturbance: Disturbance,
        vibration: VibrationFilter | None,
        u_max: float,
        sensor_range: float | None,
        block: int,
    ) -> None:
        self.u_max = u_max
        self.block = block
        self.noise_half_width = math.sqrt(3.0) * disturbance.voltage_noise_mV_rms * 1e-3
        self.vibration = vibration
        self.sensor_range = sensor_range
        bits = disturbance.sensor_bits
        self.lsb = None if sensor_range is None else 2.0 * sensor_range / 2.0**bits
        self._noise = np.zeros(block)
        self._noise_index = block
        self._vib = np.zeros(block)
        self._vib_index = block
        self._zi = None if vibration is None else np.zeros((len(vibration.sos), 2))
        if vibration is not None:
            from scipy.signal import sosfilt

            self._sosfilt = sosfilt

    def reset(self, rng: np.random.Generator) -> float:
        """New episode: the first blocks (voltage noise, then the vibration's warm-up and
        first block) from ``rng``; returns the vibration at t = 0 (um)."""
        if self.noise_half_width > 0:
            self._draw_noise(rng)
        if self.vibration is None:
            return 0.0
        self._zi[:] = 0.0
        b = self.vibration.half_width_um
        _, self._zi = self._sosfilt(
            self.vibration.sos, rng.uniform(-b, b, self.vibration.warmup), zi=self._zi
        )
        self._draw_vibration(rng)
        return self.next_vibration(rng)

    def drive(self, voltage: float, rng: np.random.Generator) -> tuple[float, float]:
        """(voltage on the bender, the noise that reached it) (V) for the amplifier output
        ``voltage`` (V): plus the noise, held within the rails."""
        if self.noise_half_width == 0:
            return voltage, 0.0
        if self._noise_index == self.block:
            self._draw_noise(rng)
        noisy = voltage + self._noise.item(self._noise_index)
        self._noise_index += 1
        u_max = self.u_max
        noisy = u_max if noisy > u_max else -u_max if noisy < -u_max else noisy
        return noisy, noisy - voltage

    def next_vibration(self, rng: np.random.Generator) -> float:
        """The tip's vibration (um) at the next sample; 0 without one."""
        if self.vibration is None:
            return 0.0
        if self._vib_index == self.block:
            self._draw_vibration(rng)
        value = self._vib.item(self._vib_index)
        self._vib_index += 1
        return value

    def quantise(self, measured_um: float) -> float:
        """``measured_um`` held within the ADC's range and rounded to its LSB (um; unchanged
        without quantisation)."""
        lsb = self.lsb
        if lsb is None:
            return measured_um
        limit = self.sensor_range
        held = limit if measured_um > limit else -limit if measured_um < -limit else measured_um
        return round(held / lsb) * lsb

    def _draw_noise(self, rng: np.random.Generator) -> None:
        r = self.noise_half_width
        self._noise = rng.uniform(-r, r, self.block)
        self._noise_index = 0

    def _draw_vibration(self, rng: np.random.Generator) -> None:
        b = self.vibration.half_width_um
        self._vib, self._zi = self._sosfilt(
            self.vibration.sos, rng.uniform(-b, b, self.block), zi=self._zi
        )
        self._vib_index = 0
