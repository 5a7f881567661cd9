"""Discrete PID, optionally with a resonance notch and model-inverse feedforward.

Control law (parallel form, backward-Euler integral, filtered derivative), in z-transform::

    C(z) = kp + ki dt z / (z - 1) + kd (1 - a) / dt (z - 1) / (z - a),   a = exp(-dt / Tf)

The error is ``e_t = r_t+1 - y_t`` (um): the action a_t is scored against r_t+1, so the
reference sample the action aims at is compared with the latest measurement. The output goes
through the notch ``N(z)`` (identity without one) and is clipped to the drive range; the
integrator is protected by back-calculation (``I += g (u_sat - u)``), so it stays bounded
under saturation.

**Tuning** (:mod:`controllers.pid_tuning`): maximise the integral gain ki subject to the
maximum sensitivity ``Ms <= Ms_max`` and a stable closed loop on the prediction model's linear
part (z -> um; the identified nonlinearity has unit small-signal gain, so z is volts for small
signals), solved in closed form per (kp, kd) so that the gains do not depend on rounding.

**Over the datasheet's tolerance box** (the default): the bound and the stability must hold on
the nominal model and on every vertex of free deflection (static gain) x first resonance x its
damping (``gain_tolerance``, ``resonance_tolerance``, ``damping_range``: +-20 %, +-20 %,
0.01 .. 0.04 for the PI PICMA benders), each vertex built from the model itself by the modal
correction of its first bending mode (:mod:`controllers.tolerance_box`). A fixed loop cannot know
where in a +-20 % band a resonance with 0.01 damping sits, so it must keep its gain below
``1 - 1/Ms`` across the whole band whatever the phase: the price is bandwidth. Tuned on the
nominal model alone, the notched loop crosses over far higher and diverges on the benders with
a resonance 20 % low; tuned over the box it holds every vertex (its crossover: the Controllers
table of ``benchmarks/results/tracking.md``; the nominal tuning's on the PL140:
``benchmarks/results/design_measurements.md``). ``gain_tolerance=0, resonance_tolerance=0,
damping_range=None`` tunes on the nominal model alone. A resonance above the Nyquist frequency
(PL112, PL122 at 1 kHz) is seen as its alias, and the box moves the alias, not the mode: a
+-20 % band of such a mode aliases to a far wider one (the sample rate must follow the bender).

**Notch**: the model's lightly damped resonance is the complex pole pair of ``model.a`` with the
smallest damping ratio. On a bender whose first resonance lies above the Nyquist frequency (the
PL112's 1800 Hz and the PL122's 600 Hz at 1 kHz sampling) that is the aliased mode the samples
see (about 200 and 400 Hz), and the notch sits there: it is the peak the sampled loop has. The
notch puts its zeros on those poles and its poles at the same natural frequency with damping
``notch_damping`` (pole-zero placement, unit DC gain), so the loop sees a well damped mode
instead of a 26 dB peak, and the PID is re-tuned on ``N P``. Over the box the notch must
reach the whole band: its pole damping is the one that lets the largest integral gain meet
the bound on every vertex (:func:`controllers.pid_tuning.robust_notch_damping`; on the PL140
above 1, i.e. two real poles, a notch and a low-pass near ``wn / (2 zeta)``: ``notch_damping``
in the ``pid-notch`` table of ``benchmarks/results/tracking.md``). ``pid-ff``'s feedback is
then the same loop as ``pid-notch``'s; its feedforward stays the nominal model's inverse (open
loop, it cannot destabilise; on the vertices it leaves an error at the reference's frequency,
not at the resonance).

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

**Slew limit** (``task.slew_limit`` = S, V/s, the amplifier's datasheet value read from the env):
the voltage is kept within u_t-1 +- S dt (less 1e-5 V for the float32 action), and the integrator
does not wind up against that limit: the part the limit takes off goes back into it by the
same back-calculation as the drive-range saturation, ``I += g (u_limited - u)`` in volts without
feedforward, and with feedforward in z, ``I += g (z_applied - z_cmd)`` with z_applied the
nonlinearity's output at the limited voltage (as for a z the memory state cannot reach). The
feedforward model itself is not moved: letting it follow the limited z instead reduces the
overshoot of a step the amplifier slows, but makes the loop unstable on a reference the
amplifier cannot follow (``benchmarks/results/design_measurements.md``). Without a slew limit
nothing changes (bitwise).

**The design is kept.** Notch, gains and loop reports are a pure function of the model's linear
part, the tolerance box and the settings of the tuning rule, and the box tuning is most of a
PID's construction. The last :data:`DESIGNS_KEPT` designs are kept by content
(:mod:`piezo_env.memo`), so a benchmark that builds the same PID for every plant, or a test
suite that builds it in many tests, tunes it once; every controller gets its own copies.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controllers.base import Controller
from controllers.pid_tuning import (
    NOTCH_DAMPING_RANGE,
    PIDGains,
    TuningError,
    closed_loop_report,
    loop_transfer,
    notch_filter,
    resonance,
    robust_notch_damping,
    tune_pid,
)
from controllers.prediction import PredictionModel
from controllers.settings import (
    GAIN_TOLERANCE,
    check_initial_voltage,
    damping_pair,
    python_numbers,
)
from controllers.task import ControlTask
from controllers.tolerance_box import (
    DAMPING_RANGE,
    RESONANCE_TOLERANCE,
    ToleranceBox,
    vertex_models,
)
from piezo_env.checks import require_number
from piezo_env.memo import ContentCache

__all__ = ["DESIGNS_KEPT", "PIDController", "PIDGains", "TuningError"]

DESIGNS_KEPT = 16
"""PID designs kept by content (:func:`_design`). A benchmark worker meets two box designs per
identified model (``pid``'s, and the notched one ``pid-notch`` and ``pid-ff`` share) on up to
six models (three identification seeds, on the nominal bender and on the bench): 12."""

_designs = ContentCache(DESIGNS_KEPT)


def _design(model: PredictionModel, settings: Any, box: ToleranceBox) -> dict[str, Any]:
    """Notch, gains and loop reports of a PID with ``settings`` on ``model``'s linear part and
    the vertices of ``box`` around it (module docstring: kept by content, returned as fresh
    copies). The key holds what the design reads: the linear part, the box, and the settings
    of the notch and the tuning rule (``feedforward`` only where it picks the notch's default
    damping, so ``pid-ff`` shares ``pid-notch``'s box design)."""

    def compute() -> dict[str, Any]:
        design: dict[str, Any] = {"notch": None, "resonance_hz": math.nan}
        vertices = vertex_models(model, box)
        plants = [vertex_model for _, vertex_model in vertices]
        if settings.notch:
            design["resonance_hz"], _, pole = resonance(model.a, model.dt)
            damping = settings.notch_damping
            if damping is None and plants:
                damping = robust_notch_damping(model, pole, plants, ms_max=settings.ms_max)
            elif damping is None:
                damping = 0.1 if settings.feedforward else 0.7
            design["notch_damping"] = damping
            design["notch"] = notch_filter(pole, model.dt, damping)
        design["gains"] = gains = tune_pid(
            model,
            notch=design["notch"],
            ms_max=settings.ms_max,
            derivative_filter_s=settings.derivative_filter_s,
            use_derivative=settings.derivative,
            box=plants,
        )
        design["report"] = closed_loop_report(model, gains, design["notch"])
        design["vertex_reports"] = [
            (vertex, closed_loop_report(vertex_model, gains, design["notch"]))
            for vertex, vertex_model in vertices
        ]
        return design

    default_damping = settings.notch and settings.notch_damping is None and box.is_nominal
    parts = (
        model.a,
        model.b,
        model.c,
        float(model.dt),
        box,
        settings.notch,
        settings.notch_damping,
        settings.feedforward if default_damping else None,
        settings.ms_max,
        settings.derivative_filter_s,
        settings.derivative,
    )
    return _designs.get(parts, compute)


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
        """Damping ratio of the notch's poles (0.05 .. 10; its zeros sit on the model's poles;
        from 1 on, two real poles: a notch and a low-pass).

        None, tuned over a box (the default): the damping that lets the largest integral gain
        meet ``ms_max`` on every vertex (:func:`controllers.pid_tuning.robust_notch_damping`).
        None, tuned on the nominal model alone: 0.7 (a wide notch: the feedback carries the
        tracking) without feedforward, 0.1 with it (a narrow notch and a gentle loop: the
        feedback only corrects model error, and a wide notch leaves |S| > 1 around the
        resonance, where the hysteresis model's odd harmonics fall, e.g. 150 Hz on a 50 Hz
        sine)."""
        derivative_filter_s: float = 1e-3
        """Derivative filter time constant Tf (s), > 0."""
        derivative: bool = True
        """Search a derivative gain (False: PI)."""
        antiwindup_gain: float = 1.0
        """Back-calculation gain g in (0, 1]: the integrator absorbs g (u_sat - u) per step."""
        inverse_regularization: float = 1e-6
        """rho >= 0 of the regularised inverse, used only when the model is non-minimum phase."""
        gain_tolerance: float = GAIN_TOLERANCE
        """Relative half-width of the bender's static gain the loop must hold (-), in [0, 1):
        the datasheet's free-deflection tolerance, +-20 %."""
        resonance_tolerance: float = RESONANCE_TOLERANCE
        """Relative half-width of the first resonance the loop must hold (-), in [0, 1): the
        datasheet's +-20 %."""
        damping_range: tuple[float, float] | None = DAMPING_RANGE
        """(low, high) first-mode damping ratio the loop must hold (-), or None for the model's
        own: 0.01 .. 0.04 (the range :class:`piezo_env.DomainRandomization` draws from).

        With ``gain_tolerance=0``, ``resonance_tolerance=0`` and ``damping_range=None`` the loop
        is tuned on the nominal model alone (the faster loop that diverges on benders at the
        edges of the datasheet's tolerances)."""
        initial_voltage: float | None = None
        """Voltage (V) the bender rests under at each reset, when it is known (an env reset
        with ``initial_voltage``; within the drive range): the loop starts from it, so that the
        first move's slew window is the amplifier's. None: estimated from the first
        measurement (:meth:`controllers.prediction.PredictionModel.steady_start`)."""

        def __post_init__(self) -> None:
            python_numbers(self)
            for name in ("notch", "feedforward", "derivative"):
                if not isinstance(getattr(self, name), bool):
                    raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
            require_number("ms_max", self.ms_max, low=1.2, high=3.0)
            if self.notch_damping is not None:
                low, high = NOTCH_DAMPING_RANGE
                require_number("notch_damping", self.notch_damping, low=low, high=high)
            require_number("gain_tolerance", self.gain_tolerance, low=0, high=1, high_open=True)
            require_number(
                "resonance_tolerance", self.resonance_tolerance, low=0, high=1, high_open=True
            )
            if self.damping_range is not None:
                pair = damping_pair("damping_range (or None)", self.damping_range)
                object.__setattr__(self, "damping_range", pair)
            require_number("derivative_filter_s", self.derivative_filter_s, low=0, low_open=True)
            require_number("antiwindup_gain", self.antiwindup_gain, low=0, high=1, low_open=True)
            require_number("inverse_regularization", self.inverse_regularization, low=0)
            if self.initial_voltage is not None:
                require_number("initial_voltage (or None)", self.initial_voltage)

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
        check_initial_voltage(settings, task.u_max)
        self.model = model
        self.box = ToleranceBox(
            settings.gain_tolerance, settings.resonance_tolerance, settings.damping_range
        )
        self.vertices = vertex_models(model, self.box)
        design = _design(model, settings, self.box)
        self.notch, self.resonance_hz = design["notch"], design["resonance_hz"]
        self.gains = design["gains"]
        if settings.notch:
            self.notch_damping = design["notch_damping"]
        self.report, self.vertex_reports = design["report"], design["vertex_reports"]
        self._slew_step = task.slew_step
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
        """Stable (or regularised) one-step inverse of the linear model, from z to the output
        the model steers (:attr:`PredictionModel.c_tracked`: the tip of an oracle behind a
        sensor); the feedback compares the model's measured output with the measurement."""
        m = self.model
        self._ca = (m.c_tracked @ m.a).ravel()
        cb = float((m.c_tracked @ m.b).item())
        zeros = _transmission_zeros(m)
        self.minimum_phase = bool(zeros.size == 0 or np.abs(zeros).max() < 1.0)
        rho = 0.0 if self.minimum_phase else self.settings.inverse_regularization
        if cb == 0.0 and rho == 0.0:
            raise ValueError("feedforward: the model has C B = 0 (relative degree > 1)")
        self._ff_gain = cb / (cb * cb + rho)
        self._z_lo, self._z_hi = (float(v) for v in m.z_bounds)
        self.max_zero_magnitude = float(np.abs(zeros).max()) if zeros.size else 0.0

    def _reset(self, observation: np.ndarray) -> None:
        """Start from the model's steady state that holds the first measurement (rest at 0 V
        within the noise bound; see :meth:`PredictionModel.steady_start`): a bumpless start
        after an env reset with ``initial_voltage``."""
        start = self.model.steady_start(
            float(observation[0]), self.task.noise_bound_um, self.settings.initial_voltage
        )
        self._u_prev = float(np.float32(start.u))
        self._deriv = 0.0
        if self.settings.feedforward:
            self._x_ff = start.x
            self._nl_state = start.memory
            self._integral = 0.0
            self._e_prev = float(self.model.c[0] @ self._x_ff) - float(observation[0])
        else:
            self._integral = start.u  # the PID's output is the voltage that holds y0
            self._e_prev = float(observation[2]) - float(observation[0])
        self._hold_notch(self._integral)

    def _hold_notch(self, v: float) -> None:
        """Notch states at steady state for a constant input ``v`` (the notch has unit DC gain)."""
        self._s2 = (self._b2 - self._a2) * v
        self._s1 = (self._b1 - self._a1) * v + self._s2

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
        u = min(max(u, -self._u_max), self._u_max)  # the notch may overshoot the limit
        if self._slew_step is None:
            return u
        low, high = self._slew_window()
        limited = min(max(u, low), high)
        if limited != u:
            self._integral += self._g_aw * (limited - u)  # no windup against the slew limit
            self.stats.status["slew-limited"] += 1
        self._u_prev = min(max(float(np.float32(limited)), low), high)
        return self._u_prev

    def _slew_window(self) -> tuple[float, float]:
        """Voltages (V) reachable this sample: u_t-1 +- S dt within the drive range."""
        step = self._slew_step
        return max(self._u_prev - step, -self._u_max), min(self._u_prev + step, self._u_max)

    def _act_feedforward(self, y: float, r_next: float) -> float:
        """Linear inverse on r_t+1, PID on the deviation from the model, NLS inverse to volts."""
        x = self._x_ff
        y_model = float(self.model.c[0] @ x)
        z_ff = (r_next - float(self._ca @ x)) * self._ff_gain
        z_ff = min(max(z_ff, self._z_lo), self._z_hi)
        self._x_ff = self.model.a @ x + self.model.b[:, 0] * z_ff
        z_cmd = z_ff + self._pid(y_model - y, self._z_lo - z_ff, self._z_hi - z_ff)
        result = self.model.nonlinearity.inverse(z_cmd, self._nl_state)
        if self._slew_step is not None:
            return self._slew_feedforward(result, z_cmd)
        self._nl_state = result.state
        # Whatever the memory state could not reach is taken off the integrator too.
        self._integral += self._g_aw * (result.z - z_cmd)
        self.stats.status[result.status] += 1
        return result.u

    def _slew_feedforward(self, result: Any, z_cmd: float) -> float:
        """The inverse's voltage kept in the slew window; the z it misses off the integrator."""
        low, high = self._slew_window()
        u = float(np.float32(result.u))
        if low <= u <= high:
            z, self._nl_state = result.z, result.state
            self.stats.status[result.status] += 1
        else:
            u = min(max(float(np.float32(min(max(u, low), high))), low), high)
            z, self._nl_state = self.model.nonlinearity.step(u, self._nl_state)
            self.stats.status["slew-limited"] += 1
        self._integral += self._g_aw * (z - z_cmd)
        self._u_prev = u
        return u

    def loop_polynomials(self) -> dict[str, Any]:
        """The open loop L = C N P as polynomials in z (descending powers) and its dt (s).

        For Bode and Nyquist plots (python-control: ``control.tf(num, den, dt)``); JSON-safe.
        """
        import control

        loop = control.ss2tf(loop_transfer(self.model, self.gains, self.notch))
        num, den = (np.atleast_1d(np.squeeze(p)) for p in (loop.num[0][0], loop.den[0][0]))
        return {"num": num.tolist(), "den": den.tolist(), "dt": self.model.dt}

    def describe(self) -> dict[str, Any]:
        """Settings, gains, notch, loop margins, Ms, bandwidth and the tuning rule (JSON-safe).

        The loop figures at the top level are the nominal model's (None: no crossing, an
        infinite margin); under ``"box"``, the tolerances tuned over and each vertex's Ms,
        margins (None likewise), crossover and bandwidth, with the worst vertex (largest Ms)
        and the smallest margins.
        """
        where = "the nominal model" if self.box.is_nominal else (
            f"the nominal model and each of the {len(self.vertices)} vertices of the tolerance box"
        )
        info: dict[str, Any] = {
            "name": self.name,
            "settings": asdict(self.settings),
            "tuning_rule": (
                f"maximise ki subject to Ms <= {self.settings.ms_max} and a stable closed loop "
                f"on {where} (MIGO-style; the largest ki in closed form per (kp, kd) on a "
                "frequency grid up to Nyquist, maximised over a grid of (kp, kd) and refined)"
            ),
            "gains": asdict(self.gains),
            **{key: _finite_or_none(value) for key, value in self.report.items()},
            "box": self._describe_box(),
            "loop": self.loop_polynomials(),
            "native": self.native_code() if self.settings.feedforward else {},
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

    def _describe_box(self) -> dict[str, Any]:
        """The tolerance box the loop was tuned over and its margins on each vertex."""
        vertices = [
            {
                "vertex": vertex.label(),
                "gain": vertex.gain,
                "resonance": vertex.resonance,
                "damping": vertex.damping,
                **{key: _finite_or_none(report[key]) for key in _VERTEX_KEYS},
            }
            for vertex, report in self.vertex_reports
        ]
        out: dict[str, Any] = {"tolerances": asdict(self.box), "vertices": vertices}
        if vertices:
            worst = max(vertices, key=lambda v: v["ms"])
            out["worst_vertex"] = worst["vertex"]
            out["worst_ms"] = worst["ms"]
            for key in ("gain_margin_db", "phase_margin_deg"):
                values = [v[key] for v in vertices if v[key] is not None]
                out[f"worst_{key}"] = min(values) if values else None
        return out


_VERTEX_KEYS = ("ms", "gain_margin_db", "phase_margin_deg", "crossover_hz", "bandwidth_hz")
"""The loop figures reported per vertex of the box."""


def _finite_or_none(value: float) -> float | None:
    """``value``, or None where it is not finite (no crossing: an infinite margin)."""
    return float(value) if math.isfinite(value) else None


def _notch_depth_db(notch: tuple[np.ndarray, np.ndarray], f_hz: float, dt: float) -> float:
    """|N| at ``f_hz`` (dB)."""
    z = np.exp(2j * np.pi * f_hz * dt)
    gain = abs(np.polyval(notch[0], z) / np.polyval(notch[1], z))
    return float(20 * np.log10(max(gain, 1e-300)))


def _transmission_zeros(model: PredictionModel) -> np.ndarray:
    """Finite nonzero zeros of C (zI - A)^-1 B, C the steered output
    (:attr:`PredictionModel.c_tracked`), from the numerator polynomial (np.roots)."""
    import scipy.signal

    num, _ = scipy.signal.ss2tf(model.a, model.b, model.c_tracked, np.zeros((1, 1)))
    num = np.trim_zeros(np.real_if_close(num[0]), "f")
    zeros = np.roots(num) if num.size > 1 else np.zeros(0)
    return zeros[np.abs(zeros) > 1e-9]
