"""Discrete PID, optionally with a resonance notch and model-inverse feedforward.

Control law (parallel form, backward-Euler integral, filtered derivative), in z-transform::

    C(z) = kp + ki dt z / (z - 1) + kd (1 - a) / dt (z - 1) / (z - a),   a = exp(-dt / Tf)

The error is ``e_t = r_t+1 - y_t`` (um): the action a_t is scored against r_t+1, so the
reference sample the action aims at is compared with the latest measurement. The output goes
through the notch ``N(z)`` (identity without one) and is clipped to the drive range; the
integrator is protected by back-calculation (``I += g (u_sat - u)``), so it stays bounded
under saturation.

**Tuning rule** (MIGO-style, Astrom & Hagglund 2006, ch. 7): maximise the integral gain ki
(= the best rejection of low-frequency disturbances and model error) over (kp, ki, kd) subject
to the maximum sensitivity ``Ms = max_w |1 / (1 + L(e^jw dt))| <= Ms_max`` and a stable closed
loop, with ``L = C N P`` evaluated on a frequency grid up to the Nyquist frequency and ``P`` the
prediction model's linear part (z -> um; the identified nonlinearity has unit small-signal gain,
so z is volts for small signals). The search is scipy's SLSQP from several starts.

**Notch**: the model's lightly damped resonance is the complex pole pair of ``model.a`` with the
smallest damping ratio. The notch puts its zeros on those poles and its poles at the same
natural frequency with damping ``notch_damping`` (pole-zero placement, unit DC gain), so the
loop sees a well damped mode instead of a 26 dB peak, and the PID is re-tuned on ``N P``.

**Feedforward** (``feedforward=True``): stable inversion of the linear model on the reference
preview. A feedforward copy of the model ``x_f`` is driven by::

    z_ff,t = (r_t+1 - C A x_f,t) / (C B)   (clipped to the model's z range)
    x_f,t+1 = A x_f,t + B z_ff,t

so the model's output meets r_t+1 exactly whenever the reference is feasible; this is stable
when the model's zeros lie inside the unit circle (checked at construction; if they do not, the
inverse is regularised: ``z_ff`` minimises ``(y_f,t+1 - r_t+1)^2 + rho z_ff^2``). The feedback
then acts on the deviation from the feedforward model's output, ``e_t = C x_f,t - y_t`` (equal
to r_t - y_t when the reference is feasible, so the PID never fights an infeasible step), its
output is added in z, and the total z becomes volts through the nonlinearity's inverse, which
carries the memory state. Without feedforward the PID output is volts directly: no model
inverse is hidden in the plain PID.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import scipy.optimize

from controllers.base import Controller
from controllers.prediction import PredictionModel
from controllers.task import ControlTask

__all__ = [
    "PIDController",
    "PIDGains",
    "closed_loop_report",
    "notch_filter",
    "pid_transfer",
    "resonance",
    "tune_pid",
]


@dataclass(frozen=True)
class PIDGains:
    """Parallel-form PID gains (the plant input per um of error).

    Attributes
    ----------
    kp : float
        Proportional gain (V/um).
    ki : float
        Integral gain (V/(um s)).
    kd : float
        Derivative gain (V s/um).
    tf : float
        Derivative filter time constant (s).
    """

    kp: float
    ki: float
    kd: float
    tf: float


def pid_transfer(gains: PIDGains, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator (descending powers of z) of the discrete PID C(z).

    Parameters
    ----------
    gains : PIDGains
    dt : float
        Sample time (s).
    """
    a = math.exp(-dt / gains.tf)
    kdd = gains.kd * (1.0 - a) / dt
    den = np.polymul([1.0, -1.0], [1.0, -a])
    num = gains.kp * den + gains.ki * dt * np.polymul([1.0, 0.0], [1.0, -a])
    num = num + kdd * np.polymul([1.0, -1.0], [1.0, -1.0])
    return num, den


def _pid_response(x: np.ndarray, zinv: np.ndarray, dt: float, a: float) -> np.ndarray:
    """C on the unit circle for x = (kp, ki, kd), with zinv = e^-jw dt."""
    one_minus = 1.0 - zinv
    return x[0] + x[1] * dt / one_minus + x[2] * (1.0 - a) / dt * one_minus / (1.0 - a * zinv)


def resonance(a: np.ndarray, dt: float) -> tuple[float, float, complex]:
    """The least damped complex pole pair of a discrete model.

    Parameters
    ----------
    a : numpy.ndarray
        State matrix (sample time ``dt``).
    dt : float
        Sample time (s).

    Returns
    -------
    frequency_hz, damping, pole
        Natural frequency (Hz), damping ratio and the pole with positive imaginary part.

    Raises
    ------
    ValueError
        If the model has no complex pole pair (nothing to notch).
    """
    poles = np.linalg.eigvals(a)
    poles = poles[(poles.imag > 1e-9) & (np.abs(poles) > 1e-9)]
    if poles.size == 0:
        raise ValueError("notch: the model has no complex pole pair (no resonance to notch)")
    s = np.log(poles) / dt
    damping = -s.real / np.abs(s)
    k = int(np.argmin(damping))
    return float(np.abs(s[k]) / (2 * np.pi)), float(damping[k]), complex(poles[k])


def notch_filter(pole: complex, dt: float, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Notch with zeros on ``pole`` (and its conjugate), poles at ``damping``, unit DC gain.

    Parameters
    ----------
    pole : complex
        Discrete resonant pole to cancel.
    dt : float
        Sample time (s).
    damping : float
        Damping ratio of the notch's own poles (same natural frequency).

    Returns
    -------
    num, den : numpy.ndarray
        Biquad coefficients in descending powers of z (den monic).
    """
    wn = abs(np.log(pole)) / dt
    s = wn * complex(-damping, math.sqrt(max(1.0 - damping**2, 0.0)))
    q = np.exp(s * dt)
    num = np.real(np.poly([pole, np.conj(pole)]))
    den = np.real(np.poly([q, np.conj(q)]))
    return num * (den.sum() / num.sum()), den


def _frequency_grid(dt: float, f_res: float | None) -> np.ndarray:
    """Frequencies (Hz) from 0.1 Hz to just below Nyquist, dense around the resonance."""
    nyquist = 0.5 / dt
    grid = np.geomspace(0.1, 0.999 * nyquist, 1500)
    if f_res is not None:
        grid = np.union1d(grid, np.linspace(0.8 * f_res, 1.25 * f_res, 400))
    return grid


def _closed_loop_stable(x: np.ndarray, plant: tuple, notch: tuple, dt: float, a: float) -> bool:
    """Whether 1 + C N P has all its roots inside the unit circle."""
    c_num, c_den = pid_transfer(PIDGains(x[0], x[1], x[2], -dt / math.log(a)), dt)
    num = np.polymul(np.polymul(c_num, notch[0]), plant[0])
    den = np.polymul(np.polymul(c_den, notch[1]), plant[1])
    char = np.polyadd(den, num)
    return bool(np.abs(np.roots(char)).max() < 1.0 - 1e-9)


def tune_pid(
    model: PredictionModel,
    *,
    notch: tuple[np.ndarray, np.ndarray] | None,
    ms_max: float,
    derivative_filter_s: float,
    use_derivative: bool = True,
) -> PIDGains:
    """Maximise ki subject to Ms <= ``ms_max`` and closed-loop stability (MIGO-style).

    Parameters
    ----------
    model : PredictionModel
        Its linear part (z -> um) is the plant.
    notch : (num, den) or None
        Notch in series with the PID.
    ms_max : float
        Bound on the maximum sensitivity.
    derivative_filter_s : float
        Derivative filter time constant Tf (s), fixed during the search.
    use_derivative : bool
        Search kd too (else kd = 0: PI).

    Returns
    -------
    PIDGains
    """
    dt = model.dt
    plant, notch, freqs, loop0 = _loop_data(model, notch)
    k0 = 1.0 / abs(float(np.real(loop0[0])))  # 1 / DC gain: the natural gain scale
    zinv, loop0 = np.exp(-2j * np.pi * freqs[1:] * dt), loop0[1:]
    a = math.exp(-dt / derivative_filter_s)
    scale = np.array([k0, k0 / dt, k0 * dt])

    def inverse_sensitivity(x: np.ndarray) -> np.ndarray:
        gains = x * scale
        return np.abs(1.0 + _pid_response(gains, zinv, dt, a) * loop0)

    def margin(x: np.ndarray) -> float:
        return float(inverse_sensitivity(x).min() - 1.0 / ms_max)

    bounds = [(0.0, 5.0), (1e-6, 3.0), (0.0, 5.0 if use_derivative else 0.0)]
    best = None
    for start in _starts(use_derivative):
        res = scipy.optimize.minimize(
            lambda x: -x[1],
            start,
            method="SLSQP",
            bounds=bounds,
            constraints=[{"type": "ineq", "fun": margin}],
            options={"maxiter": 300, "ftol": 1e-10},
        )
        x = np.clip(res.x, [b[0] for b in bounds], [b[1] for b in bounds])
        if margin(x) < -1e-6 or not _closed_loop_stable(x * scale, plant, notch, dt, a):
            continue
        if best is None or x[1] > best[1]:
            best = x
    if best is None:
        raise ValueError(f"ms_max: no stabilising PID found with Ms <= {ms_max}")
    kp, ki, kd = (float(v) for v in best * scale)
    return PIDGains(kp, ki, kd, derivative_filter_s)


def _starts(use_derivative: bool) -> list[np.ndarray]:
    """SLSQP starting points (scaled kp, ki, kd): small, stabilising gains of several shapes."""
    shapes = [(0.0, 0.0), (0.1, 0.0), (0.3, 0.0)]
    if use_derivative:
        shapes += [(0.1, 0.1), (0.3, 0.3)]
    return [np.array([kp, ki, kd]) for ki in (1e-3, 1e-2) for kp, kd in shapes]


def _loop_data(
    model: PredictionModel, notch: tuple[np.ndarray, np.ndarray] | None
) -> tuple[tuple, tuple, np.ndarray, np.ndarray]:
    """Plant polynomials, notch polynomials, frequency grid (Hz) and N P on that grid."""
    import control

    tf = control.ss2tf(model.to_control())
    plant = (np.atleast_1d(np.squeeze(tf.num[0][0])), np.atleast_1d(np.squeeze(tf.den[0][0])))
    notch = notch if notch is not None else (np.array([1.0]), np.array([1.0]))
    try:
        f_res = resonance(model.a, model.dt)[0]
    except ValueError:
        f_res = None
    freqs = np.concatenate([[0.0], _frequency_grid(model.dt, f_res)])
    z = np.exp(2j * np.pi * freqs * model.dt)
    response = np.polyval(plant[0], z) / np.polyval(plant[1], z)
    response = response * np.polyval(notch[0], z) / np.polyval(notch[1], z)
    return plant, notch, freqs, response


def closed_loop_report(
    model: PredictionModel, gains: PIDGains, notch: tuple[np.ndarray, np.ndarray] | None
) -> dict[str, float]:
    """Margins, Ms and closed-loop bandwidth of ``L = C N P`` on a dense frequency grid.

    The loop is python-control's product of the PID, notch and model transfer functions,
    evaluated at 20,000 frequencies up to Nyquist. (``control.stability_margins`` solves
    polynomial equations in z and reports spurious crossings where the notch cancels the
    resonant poles, so the margins are read off the grid instead.)

    Returns
    -------
    dict
        ``gain_margin_db``, ``phase_margin_deg``, ``crossover_hz`` (first |L| = 1), ``ms``,
        ``mt`` (peak |T|), ``bandwidth_hz`` (first frequency where |T| drops below -3 dB),
        ``resonance_loop_gain_db`` (|L| at the model's resonance, dB).
    """
    import control

    dt = model.dt
    loop = control.tf(*pid_transfer(gains, dt), dt) * control.ss2tf(model.to_control())
    if notch is not None:
        loop = loop * control.tf(notch[0], notch[1], dt)
    freqs = np.union1d(np.geomspace(0.01, 10.0, 2000), np.linspace(10.0, 0.4999 / dt, 20000))
    resp = np.asarray(loop(np.exp(2j * np.pi * freqs * dt)))
    gain_cross = np.flatnonzero(np.diff(np.sign(np.abs(resp) - 1.0)))
    phase_cross = np.flatnonzero((np.diff(np.sign(resp.imag)) != 0) & (resp.real[:-1] < 0))
    phase = np.degrees(np.angle(resp[gain_cross]))
    pm = np.where(phase <= 0.0, 180.0 + phase, phase - 180.0)
    gm = [-20 * np.log10(np.abs(resp[i])) for i in phase_cross]
    comp = np.abs(resp / (1.0 + resp))
    below = np.flatnonzero(comp < 1.0 / math.sqrt(2.0))
    try:
        f_res = resonance(model.a, dt)[0]
        peak = float(np.abs(loop(np.exp(2j * np.pi * f_res * dt))))
    except ValueError:
        peak = math.nan
    return {
        "gain_margin_db": float(min(gm)) if gm else math.inf,
        "phase_margin_deg": float(pm.min()) if pm.size else math.inf,
        "crossover_hz": float(freqs[gain_cross[0]]) if gain_cross.size else math.nan,
        "ms": float(np.abs(1.0 / (1.0 + resp)).max()),
        "mt": float(comp.max()),
        "bandwidth_hz": float(freqs[below[0]]) if below.size else 0.5 / dt,
        "resonance_loop_gain_db": float(20 * np.log10(peak)) if peak > 0 else math.nan,
    }


class PIDController(Controller):
    """Discrete PID with optional notch and model-inverse feedforward (module docstring).

    Parameters
    ----------
    model : PredictionModel
        Tuning model (its linear part) and, with feedforward, the inverse model.
    task : ControlTask
    settings : PIDController.Settings
    name : str
        Registry name, for reports.
    """

    @dataclass(frozen=True)
    class Settings:
        """PID settings; the registry presets set ``notch`` and ``feedforward``."""

        notch: bool = False
        """Notch the model's least damped resonance and tune the PID on the notched loop."""
        feedforward: bool = False
        """Add model-inverse feedforward (linear inverse on the preview, then the NLS inverse)."""
        ms_max: float = 1.8
        """Bound on the maximum sensitivity Ms of the tuning rule (1.2 .. 3)."""
        notch_damping: float | None = None
        """Damping ratio of the notch's poles (0.05 .. 1; its zeros sit on the model's poles).

        None: 0.7 (a wide notch: the feedback carries the tracking) without feedforward, 0.1 with
        it (a narrow notch and a gentle loop: the feedback only corrects model error, and a wide
        notch leaves |S| > 1 around the resonance, where the hysteresis model's odd harmonics
        fall, e.g. 150 Hz on a 50 Hz sine)."""
        derivative_filter_s: float = 1e-3
        """Derivative filter time constant Tf (s), > 0."""
        derivative: bool = True
        """Search a derivative gain (False: PI)."""
        antiwindup_gain: float = 1.0
        """Back-calculation gain g in (0, 1]: the integrator absorbs g (u_sat - u) per step."""
        inverse_regularization: float = 1e-6
        """rho >= 0 of the regularised inverse, used only when the model is non-minimum phase."""

        def __post_init__(self) -> None:
            for name in ("notch", "feedforward", "derivative"):
                if not isinstance(getattr(self, name), bool):
                    raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
            checks = {
                "ms_max": lambda v: 1.2 <= v <= 3.0,
                "notch_damping": lambda v: 0.05 <= v <= 1.0,
                "derivative_filter_s": lambda v: v > 0,
                "antiwindup_gain": lambda v: 0 < v <= 1.0,
                "inverse_regularization": lambda v: v >= 0,
            }
            for name, ok in checks.items():
                value = getattr(self, name)
                if value is None and name == "notch_damping":
                    continue
                valid = isinstance(value, (int, float)) and not isinstance(value, bool)
                if not (valid and math.isfinite(value) and ok(value)):
                    raise ValueError(f"{name} out of range or not a number: {value!r}")

    def __init__(
        self,
        model: PredictionModel,
        task: ControlTask,
        settings: Settings | None = None,
        *,
        name: str = "pid",
    ) -> None:
        super().__init__(task)
        self.name = name
        self.settings = settings = settings or self.Settings()
        self.model = model
        self.notch = None
        self.resonance_hz = math.nan
        if settings.notch:
            self.resonance_hz, _, pole = resonance(model.a, model.dt)
            self.notch_damping = settings.notch_damping
            if self.notch_damping is None:
                self.notch_damping = 0.1 if settings.feedforward else 0.7
            self.notch = notch_filter(pole, model.dt, self.notch_damping)
        self.gains = tune_pid(
            model,
            notch=self.notch,
            ms_max=settings.ms_max,
            derivative_filter_s=settings.derivative_filter_s,
            use_derivative=settings.derivative,
        )
        self.report = closed_loop_report(model, self.gains, self.notch)
        self._setup_coefficients()
        if settings.feedforward:
            self._setup_feedforward()
        self._reset(np.zeros(task.observation_size))

    def _setup_coefficients(self) -> None:
        """Per-step scalars: integral, derivative and notch (biquad) coefficients."""
        g, dt = self.gains, self.model.dt
        self._a_d = math.exp(-dt / g.tf)
        self._k_d = g.kd * (1.0 - self._a_d) / dt
        self._k_i = g.ki * dt
        num, den = self.notch if self.notch is not None else (np.array([1.0, 0, 0]), np.ones(1))
        num = np.pad(num, (0, 3 - num.size)) / den[0]
        den = np.pad(den, (0, 3 - den.size)) / den[0]
        self._b0, self._b1, self._b2 = (float(v) for v in num)
        self._a1, self._a2 = float(den[1]), float(den[2])
        self._g_aw = self.settings.antiwindup_gain

    def _setup_feedforward(self) -> None:
        """Stable (or regularised) one-step inverse of the linear model."""
        m = self.model
        self._ca = (m.c @ m.a).ravel()
        cb = float((m.c @ m.b).item())
        zeros = _transmission_zeros(m)
        self.minimum_phase = bool(zeros.size == 0 or np.abs(zeros).max() < 1.0)
        rho = 0.0 if self.minimum_phase else self.settings.inverse_regularization
        if cb == 0.0 and rho == 0.0:
            raise ValueError("feedforward: the model has C B = 0 (relative degree > 1)")
        self._ff_gain = cb / (cb * cb + rho)
        self._z_lo, self._z_hi = (float(v) for v in m.z_bounds)
        self.max_zero_magnitude = float(np.abs(zeros).max()) if zeros.size else 0.0

    def _reset(self, observation: np.ndarray) -> None:
        self._integral = 0.0
        self._deriv = 0.0
        self._s1 = self._s2 = 0.0
        if self.settings.feedforward:
            self._x_ff = np.zeros(self.model.n_states)
            self._nl_state = self.model.nonlinearity.initial_state()
            self._e_prev = 0.0 - float(observation[0])
        else:
            self._e_prev = float(observation[2]) - float(observation[0])

    def _pid(self, error: float, low: float, high: float) -> float:
        """PID on one error sample (um), limited to [low, high] before the notch, then notch.

        Back-calculation on the limit keeps the integrator bounded; the notch has unit DC gain,
        so the limit is the drive range (or the z headroom left by the feedforward).
        """
        integral = self._integral + self._k_i * error
        self._deriv = self._a_d * self._deriv + self._k_d * (error - self._e_prev)
        self._e_prev = error
        v = self.gains.kp * error + integral + self._deriv
        v_sat = min(max(v, low), high)
        self._integral = integral + self._g_aw * (v_sat - v)
        out = self._b0 * v_sat + self._s1
        self._s1 = self._b1 * v_sat - self._a1 * out + self._s2
        self._s2 = self._b2 * v_sat - self._a2 * out
        return out

    def _act(self, observation: np.ndarray) -> float:
        y, r_next = float(observation[0]), float(observation[2])
        if self.settings.feedforward:
            return self._act_feedforward(y, r_next)
        u = self._pid(r_next - y, -self._u_max, self._u_max)
        self.stats.status["ok"] += 1
        return min(max(u, -self._u_max), self._u_max)  # the notch may overshoot the limit

    def _act_feedforward(self, y: float, r_next: float) -> float:
        """Linear inverse on r_t+1, PID on the deviation from the model, NLS inverse to volts."""
        x = self._x_ff
        y_model = float(self.model.c[0] @ x)
        z_ff = (r_next - float(self._ca @ x)) * self._ff_gain
        z_ff = min(max(z_ff, self._z_lo), self._z_hi)
        self._x_ff = self.model.a @ x + self.model.b[:, 0] * z_ff
        z_cmd = z_ff + self._pid(y_model - y, self._z_lo - z_ff, self._z_hi - z_ff)
        result = self.model.nonlinearity.inverse(z_cmd, self._nl_state)
        self._nl_state = result.state
        # Whatever the memory state could not reach is taken off the integrator too.
        self._integral += self._g_aw * (result.z - z_cmd)
        self.stats.status[result.status] += 1
        return result.u

    def describe(self) -> dict[str, Any]:
        """Settings, gains, notch, loop margins, Ms, bandwidth and the tuning rule (JSON-safe)."""
        info: dict[str, Any] = {
            "name": self.name,
            "settings": asdict(self.settings),
            "tuning_rule": (
                f"maximise ki subject to Ms <= {self.settings.ms_max} and a stable closed loop "
                "(MIGO-style, SLSQP over kp, ki, kd on a frequency grid up to Nyquist)"
            ),
            "gains": asdict(self.gains),
            **self.report,
        }
        if self.notch is not None:
            info["notch_hz"] = self.resonance_hz
            info["notch_damping"] = self.notch_damping
            info["notch_depth_db"] = _notch_depth_db(self.notch, self.resonance_hz, self.model.dt)
        if self.settings.feedforward:
            info["feedforward"] = {
                "minimum_phase": self.minimum_phase,
                "max_zero_magnitude": self.max_zero_magnitude,
            }
        return info


def _notch_depth_db(notch: tuple[np.ndarray, np.ndarray], f_hz: float, dt: float) -> float:
    """|N| at ``f_hz`` (dB)."""
    z = np.exp(2j * np.pi * f_hz * dt)
    gain = abs(np.polyval(notch[0], z) / np.polyval(notch[1], z))
    return float(20 * np.log10(max(gain, 1e-300)))


def _transmission_zeros(model: PredictionModel) -> np.ndarray:
    """Finite nonzero zeros of C (zI - A)^-1 B, from the numerator polynomial (np.roots)."""
    import scipy.signal

    num, _ = scipy.signal.ss2tf(model.a, model.b, model.c, np.zeros((1, 1)))
    num = np.trim_zeros(np.real_if_close(num[0]), "f")
    zeros = np.roots(num) if num.size > 1 else np.zeros(0)
    return zeros[np.abs(zeros) > 1e-9]
