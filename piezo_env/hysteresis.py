"""Rate-independent input hysteresis u -> u_eff of the piezo ceramic.

The hysteresis sits at the input of the linear beam. Being rate-independent, its output only
changes when the input changes, so under a zero-order-hold drive it is updated once per step,
exactly, from the voltage jump u_prev -> u. The operators themselves (closed-form Bouc-Wen jump,
play) live in :mod:`piezo_env.operators`, shared with the identified model's features.

Bouc-Wen (default), exponent n = 1::

    u_eff = k u - h,   dh = alpha k du - beta |du| h - gamma du |h|

Prandtl-Ishlinskii: u_eff = w_0 u + sum_i w_i P_{r_i}[u], play operators
P_r: p <- max(u - r, min(u + r, p)).

Both default calibrations give a loop ~12 % of the peak-to-peak output wide at full stroke
(+-U_r) while the effective voltage still reaches +-U_r at the ends of the major loop, so the
full-stroke deflection matches the datasheet.

Prediction-model interface (what a controller needs, the same for every model here and for the
identified NLS): ``step(state, u) -> (state, u_eff)``, ``inverse(u_eff_target, state, u_range)
-> InverseResult(u, z, status, state)`` and ``casadi_step(u, state) -> (u_eff, next_state)``.
Every accepted parameter set makes u -> u_eff strictly increasing from every state reachable
from rest, so the inverse is unique (see each class for the proof).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from piezo_env.inverse import InverseResult, solve_increasing
from piezo_env.operators import (
    BoucWenBatch,
    bouc_wen_bound,
    bouc_wen_casadi,
    bouc_wen_jump,
    check_bouc_wen,
    play,
    play_casadi,
)

__all__ = [
    "BoucWen",
    "Hysteresis",
    "InverseResult",
    "NoHysteresis",
    "PrandtlIshlinskii",
    "RateDependentPrandtlIshlinskii",
    "bouc_wen_rows",
    "make_hysteresis",
]

_INVERSE_GRID = 9
"""Grid points of the bracketing pass of :meth:`Hysteresis.inverse` (the map is monotone)."""


def _check_range(u_range: Sequence[float]) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in u_range)
    except (TypeError, ValueError):
        raise ValueError(f"u_range must be a pair (low, high) in V; got {u_range!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"u_range must be finite with low < high (V); got {u_range!r}")
    return low, high


class Hysteresis:
    """Interface of an input hysteresis model (stateless: the state is passed in and out).

    The state is a float64 array of length ``state_size`` whose first entry is the previous
    input voltage (V). ``step`` works on one state (1-D) or a batch (2-D, one row per env).
    """

    state_size: int = 1
    name: str = "none"
    kinks_anywhere: ClassVar[bool] = True
    """Whether u -> u_eff may kink anywhere in the range (play operators), not only at the
    previous input; a generated inverse then never stops on its curvature estimate."""

    def initial_state(self, voltage: float = 0.0) -> np.ndarray:
        """State after a slow monotone approach from 0 V to ``voltage`` (V)."""
        state = np.zeros(self.state_size)
        return self.step(state, voltage)[0] if voltage != 0.0 else state

    def step(
        self, state: np.ndarray, u: float | np.ndarray
    ) -> tuple[np.ndarray, float | np.ndarray]:
        """Advance over the jump to ``u`` (V); returns (new state, effective voltage u_eff in V)."""
        raise NotImplementedError

    def max_effective_voltage(self, u_max: float) -> float:
        """A proven bound on |u_eff| (V) for |u| <= u_max from any state reached from rest."""
        raise NotImplementedError

    def inverse_parameters(self) -> np.ndarray | None:
        """The numbers of this model that a generated inverse
        (:mod:`controllers.native.compiled_inverse`) takes as an input instead of as
        constants, so that one compiled function serves every strength of one loop shape (the
        Monte Carlo's draws); None for a model without a generated inverse."""
        return None

    def casadi_step_with(self, u: Any, state: Any, parameters: Any) -> tuple[Any, Any]:
        """:meth:`casadi_step` with the casadi symbols ``parameters`` standing for
        :meth:`inverse_parameters`."""
        raise NotImplementedError

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        """casadi expressions ``(u_eff, next_state)`` of one step (u in V, state as in step)."""
        raise NotImplementedError

    def inverse(
        self, u_eff_target: float, state: np.ndarray, u_range: Sequence[float]
    ) -> InverseResult:
        """Voltage whose step from ``state`` gives ``u_eff_target`` (V), inside ``u_range`` (V).

        Exact (safeguarded Newton on the closed-form step until the correction is below
        1e-12 V; ``z`` evaluated at ``u``): u -> u_eff is strictly increasing.
        A target outside the reachable range [u_eff(low), u_eff(high)] gives the nearer range
        end and status ``"out-of-range"``.

        Returns
        -------
        InverseResult
            ``(u, u_eff achieved, status, state after u)``; unpacks as a 4-tuple.
        """
        low, high = _check_range(u_range)
        s = np.asarray(state, dtype=np.float64)
        if s.shape != (self.state_size,) or not np.isfinite(s).all():
            raise ValueError(f"state must be {self.state_size} finite values; got {state!r}")
        target = float(u_eff_target)
        if not math.isfinite(target):
            raise ValueError(f"u_eff_target must be a finite voltage; got {u_eff_target!r}")

        def evaluate(rows: np.ndarray) -> np.ndarray:
            return self.step(np.broadcast_to(s, (rows.size, s.size)), rows)[1]

        grid = np.linspace(low, high, _INVERSE_GRID)
        u_prev = float(s[0])
        sol = solve_increasing(
            evaluate, target, grid, u_prev, u_ref=u_prev, xtol=1e-12, extrapolate=False
        )
        new_state, u_eff = self.step(s, sol.u)
        return InverseResult(sol.u, float(u_eff), sol.status, new_state)

    solve_inverse = inverse


@dataclass(frozen=True)
class NoHysteresis(Hysteresis):
    """Identity: u_eff = u."""

    name: str = "none"

    def step(self, state, u):
        new = state.copy()
        new[..., 0] = u
        return new, u

    def max_effective_voltage(self, u_max: float) -> float:
        return u_max

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        import casadi

        return u, casadi.vertcat(u)

    def inverse(self, u_eff_target, state, u_range):
        low, high = _check_range(u_range)
        target = float(u_eff_target)
        if not math.isfinite(target):
            raise ValueError(f"u_eff_target must be a finite voltage; got {u_eff_target!r}")
        u = min(max(target, low), high)
        status = "ok" if u == target else "out-of-range"
        return InverseResult(u, u, status, np.array([u]))

    solve_inverse = inverse


@dataclass(frozen=True)
class BoucWen(Hysteresis):
    """Bouc-Wen hysteresis (exponent 1), integrated exactly over each voltage jump.

    Accepted parameters (each violation raises a ValueError that names it):

    - k > 0, alpha > 0;
    - beta + gamma > 0 and beta >= gamma: the loop is bounded for every bounded input and every
      initial state (Ikhouane & Rodellar's condition, see :mod:`piezo_env.operators`), with
      |h| <= h_max = alpha k / (beta + gamma) from rest, so
      |u_eff| <= k u_max + h_max (:meth:`max_effective_voltage`) is a proven bound;
    - 2 alpha beta / (beta + gamma) < 1: u -> u_eff is strictly increasing. Its slope is
      k - dh/du with dh/du = alpha k - beta sign(du) h - gamma |h|, largest just after a
      reversal at |h| = h_max, where it is 2 alpha k beta / (beta + gamma).

    Parameters
    ----------
    k : float
        Linear gain (-).
    alpha : float
        Hysteretic share (-); h_max = alpha k / (beta + gamma).
    beta, gamma : float
        Loop shape parameters (1/V).
    """

    k: float = 1.245
    alpha: float = 0.32
    beta: float = 0.0233
    gamma: float = 0.0233
    name: str = "bouc-wen"
    state_size: int = field(default=2, init=False)
    kinks_anywhere: ClassVar[bool] = False  # only at the previous input (the jump's start)

    def __post_init__(self) -> None:
        if not (self.k > 0 and self.alpha > 0):
            raise ValueError(
                f"Bouc-Wen needs k > 0 and alpha > 0, got k={self.k}, alpha={self.alpha}"
            )
        check_bouc_wen(self.alpha * self.k, self.beta, self.gamma)
        peak_slope = 2.0 * self.alpha * self.beta / (self.beta + self.gamma)
        if not peak_slope < 1.0:
            raise ValueError(
                f"Bouc-Wen with 2 alpha beta / (beta + gamma) = {peak_slope:.4g} >= 1 makes "
                "u_eff fall while u rises after a reversal; lower alpha or bring beta closer "
                "to gamma"
            )
        object.__setattr__(self, "_ak", self.alpha * self.k)
        object.__setattr__(self, "_batch", BoucWenBatch(self._ak, self.beta, self.gamma))

    @classmethod
    def for_voltage(cls, rated_voltage: float) -> BoucWen:
        """Default calibration (12 % loop at +-30 V) rescaled to another rated voltage (V)."""
        scale = 30.0 / rated_voltage
        return cls(beta=0.0233 * scale, gamma=0.0233 * scale)

    @property
    def h_max(self) -> float:
        """Upper bound of |h| (V)."""
        return bouc_wen_bound(self.alpha * self.k, self.beta, self.gamma)

    def max_effective_voltage(self, u_max: float) -> float:
        return self.k * u_max + self.h_max

    def step(self, state, u):
        if state.ndim == 1:
            h = bouc_wen_jump(
                float(state[1]), float(u) - float(state[0]), self._ak, self.beta, self.gamma
            )
            return np.array([u, h]), self.k * u - h
        return bouc_wen_rows(self._batch, self.k, state, np.asarray(u, dtype=float))

    def step_scalar(self, u_prev: float, h: float, u: float) -> tuple[float, float]:
        """Scalar fast path: returns (h_new, u_eff) for the jump u_prev -> u (V)."""
        h = bouc_wen_jump(h, u - u_prev, self._ak, self.beta, self.gamma)
        return h, self.k * u - h

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        import casadi

        h = bouc_wen_casadi(state[1], u - state[0], self._ak, self.beta, self.gamma)
        return self.k * u - h, casadi.vertcat(u, h)

    def inverse_parameters(self) -> np.ndarray:
        """``[k, alpha k]``: the strength (what :func:`piezo_env.randomization.
        scale_hysteresis` scales); beta and gamma fix the loop's shape and stay constants."""
        return np.array([self.k, self._ak])

    def casadi_step_with(self, u: Any, state: Any, parameters: Any) -> tuple[Any, Any]:
        import casadi

        h = bouc_wen_casadi(state[1], u - state[0], parameters[1], self.beta, self.gamma)
        return parameters[0] * u - h, casadi.vertcat(u, h)


def bouc_wen_rows(
    batch: BoucWenBatch, k: float | np.ndarray, state: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bouc-Wen states of many rows over their jumps to ``u`` (V): (new states, u_eff in V).

    ``state`` has shape (N, 2), rows [previous u (V), h (V)]; ``batch`` holds the rows'
    A = alpha k, beta and gamma, and the linear gain ``k`` is one number or one per row.
    """
    h = batch(state[:, 1], u - state[:, 0])
    new_state = np.empty_like(state)
    new_state[:, 0] = u
    new_state[:, 1] = h
    u_eff = k * u
    u_eff -= h
    return new_state, u_eff


@dataclass(frozen=True)
class PrandtlIshlinskii(Hysteresis):
    """Prandtl-Ishlinskii hysteresis: a linear term plus weighted play operators.

    Accepted parameters: linear weight w_0 > 0, play weights w_i >= 0, radii r_i >= 0, all
    finite. Then u -> u_eff is strictly increasing (each play output is a non-decreasing
    function of u, so the slope is at least w_0), and from rest with |u| <= u_max each play
    output stays in [-(u_max - r_i)+, (u_max - r_i)+] (a play clips its output to
    [u - r, u + r], which keeps it there), so :meth:`max_effective_voltage`
    w_0 u_max + sum w_i (u_max - r_i)+ is a proven (and attained) bound. A negative weight can
    make u_eff fall while u rises, and w_0 <= 0 leaves flat stretches with no unique inverse.

    Parameters
    ----------
    linear_weight : float
        w_0 (-), positive.
    radii : tuple of float
        Play radii r_i (V), non-negative.
    weights : tuple of float
        Play weights w_i (-), non-negative.
    """

    linear_weight: float = 0.72
    radii: tuple[float, ...] = (3.0, 9.0, 15.0)
    weights: tuple[float, ...] = (0.13333333333333333,) * 3
    name: str = "prandtl-ishlinskii"

    def __post_init__(self) -> None:
        if len(self.radii) != len(self.weights) or not self.radii:
            raise ValueError("radii and weights must be non-empty and of equal length")
        r = np.asarray(self.radii, dtype=float)
        w = np.asarray(self.weights, dtype=float)
        if not (np.isfinite(r).all() and np.isfinite(w).all()):
            raise ValueError(f"radii and weights must be finite, got {self.radii}, {self.weights}")
        if min(self.radii) < 0:
            raise ValueError(f"play radii must be >= 0 V, got {self.radii}")
        if min(self.weights) < 0:
            raise ValueError(
                f"play weights must be >= 0 (a negative weight makes u_eff fall while u rises "
                f"and breaks the bound), got {self.weights}"
            )
        if not (math.isfinite(self.linear_weight) and self.linear_weight > 0):
            raise ValueError(
                f"linear_weight must be > 0 (u -> u_eff strictly increasing), got "
                f"{self.linear_weight}"
            )
        object.__setattr__(self, "_r", r)
        object.__setattr__(self, "_w", w)

    @property
    def state_size(self) -> int:  # type: ignore[override]
        return 1 + len(self.radii)

    @classmethod
    def for_voltage(cls, rated_voltage: float, loop_width: float = 0.12) -> PrandtlIshlinskii:
        """Three plays at 0.1, 0.3, 0.5 U_r with equal weights: loop width ``loop_width`` of the
        peak-to-peak output at +-U_r, and u_eff(+-U_r) = +-U_r on the major loop."""
        radii = tuple(rated_voltage * f for f in (0.1, 0.3, 0.5))
        # Branch gap at u = 0 is 2 sum(w r); relative to the 2 U_r peak-to-peak output.
        w = loop_width * rated_voltage / sum(radii)
        linear = (rated_voltage - w * sum(rated_voltage - r for r in radii)) / rated_voltage
        return cls(linear_weight=linear, radii=radii, weights=(w,) * len(radii))

    def max_effective_voltage(self, u_max: float) -> float:
        reach = np.maximum(u_max - self._r, 0.0)
        return self.linear_weight * u_max + float(self._w @ reach)

    def step(self, state, u):
        plays = play(state[..., 1:], np.asarray(u)[..., None], self._r)
        new = np.concatenate([np.asarray(u, dtype=float)[..., None], plays], axis=-1)
        return new, self.linear_weight * u + plays @ self._w

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        import casadi

        plays = play_casadi(state[1:], u, self.radii)
        u_eff = self.linear_weight * u + casadi.dot(casadi.DM(self._w), plays)
        return u_eff, casadi.vertcat(u, plays)

    def inverse_parameters(self) -> np.ndarray:
        """``[w_0, r_1 .. r_n, w_1 .. w_n]``; the number of plays is the structure."""
        return np.concatenate([[self.linear_weight], self._r, self._w])

    def casadi_step_with(self, u: Any, state: Any, parameters: Any) -> tuple[Any, Any]:
        import casadi

        n = len(self.radii)
        radii = [parameters[1 + i] for i in range(n)]
        plays = play_casadi(state[1:], u, radii)
        u_eff = parameters[0] * u + casadi.dot(parameters[1 + n : 1 + 2 * n], plays)
        return u_eff, casadi.vertcat(u, plays)


HYSTERESIS_NAMES = ("bouc-wen", "prandtl-ishlinskii", "rate-dependent")
"""The hysteresis models a task can name (None: a linear bender)."""


def make_hysteresis(
    kind: str | Hysteresis | None, rated_voltage: float, *, dt: float = 1e-3
) -> Hysteresis:
    """Hysteresis model from a name (:data:`HYSTERESIS_NAMES` or None) or object.

    ``dt`` (s) is the sample time, which only the rate-dependent model needs (it measures the
    drive's rate over a sample).
    """
    if isinstance(kind, Hysteresis):
        return kind
    if kind is None or kind == "none":
        return NoHysteresis()
    if kind == "bouc-wen":
        return BoucWen.for_voltage(rated_voltage)
    if kind == "prandtl-ishlinskii":
        return PrandtlIshlinskii.for_voltage(rated_voltage)
    if kind == "rate-dependent":
        return RateDependentPrandtlIshlinskii.for_voltage(rated_voltage, dt=dt)
    raise ValueError(
        f"unknown hysteresis {kind!r}; use one of {HYSTERESIS_NAMES}, None or a Hysteresis"
    )


_JUMP_TOLERANCE = 1e-9
"""Relative miss of the target (-) above which an inverse landed on a jump of the map, not a
root: the Newton iteration stops at a correction of 1e-12 V, so a root misses by about
slope x 1e-12 V (slope <= w_0 + sum w_i)."""

RATE_TIME = 7.16e-4
"""Default rate constant beta (s) of :class:`RateDependentPrandtlIshlinskii`: at a full-stroke
(+-U_r) 50 Hz sine the loop is 1.5 times as wide as the quasi-static one in continuous time
(closed form in the class docstring: the two narrower plays widen by beta omega U_r = 6.75 V at
U_r = 30 V). Sampled, the loop is narrower, since the rate the radii use is the previous
sample's, not zero at a reversal, so a play starts its branch short of -A + r_i: 1.33 times at
1 ms (20 samples per period), 1.43 at 0.5 ms, 1.47 at 0.25 ms, 1.49 at 0.1 ms."""


@dataclass(frozen=True)
class RateDependentPrandtlIshlinskii(Hysteresis):
    """Prandtl-Ishlinskii hysteresis whose play radii grow with the drive's rate.

    The rate-dependent Prandtl-Ishlinskii model of Al Janaideh, Rakheja and Su (IEEE/ASME
    Trans. Mechatronics 16(4), 2011, "An analytical generalized Prandtl-Ishlinskii model
    inversion for hysteresis compensation in micropositioning control") and Al Janaideh and
    Krejci (IEEE/ASME Trans. Mechatronics 18(5), 2013, "Inverse rate-dependent
    Prandtl-Ishlinskii model for feedforward compensation of hysteresis in a
    piezomicropositioning actuator"): dynamic thresholds r_i(t) = r_i + beta |u'(t)|, so that
    the loop of a periodic drive widens with its frequency, as measured on piezo actuators.
    Sampled at ``dt``, the rate is the drive's rate over the previous sample,
    |u_{t-1} - u_{t-2}| / dt (carried in the state), so within one sample the radii are fixed,
    and the play is directional: a rising input only raises its output, a falling input only
    lowers it, and a held input leaves it::

        rho_t = r_i + beta |u_{t-1} - u_{t-2}| / dt
        p_i <- max(p_i, u_t - rho_t)   if u_t > u_{t-1}
        p_i <- min(p_i, u_t + rho_t)   if u_t < u_{t-1}
        p_i unchanged                  if u_t = u_{t-1}
        u_eff = w_0 u_t + sum_i w_i p_i

    State: [previous voltage (V), previous rate |du| / dt (V/s), play outputs (V)].

    Why directional. With a fixed radius the directional play equals the symmetric clip
    max(u - r, min(u + r, p)) (the output stays within r of the input). With a radius that
    shrinks when the drive slows down, the symmetric clip drags the output by the rate's
    share of the lag as soon as the rate drops, also when the drive stops and is held: u_eff
    then moves with no change of its input. The directional play keeps the lag through a hold
    and closes it when the input next moves the way the lag points (the radius shrinks while
    the input moves, as in the continuous model). Why the previous sample's rate and not the
    current sample's (u_t - u_{t-1}) / dt: with the current rate the radius grows by
    k = beta / dt per volt of the step, so a play that catches up moves with slope 1 - k in
    u_t and u_eff falls while u_t rises once (k - 1) sum w_i > w_0 (at the default beta that is
    dt <= 2.5e-4 s, the default sample time of the PL122, PL127 and PL112); with the previous
    sample's rate the radii are fixed within a sample and the map is increasing at every dt.

    Loop width (closed form). Under u = A sin(omega t) with the rate taken continuously, a play
    of base radius r < A / 2 reaches p = -A + r at the lower reversal (rate 0 there) and on the
    rising branch is dragged along u - rho(t); at the zero crossing the rate is omega A and
    d rho / dt = 0, so p(u = 0) = max(-(r + beta omega A), -A + r): the branch gap of that play at
    u = 0 is 2 min(r + beta omega A, A - r) (the falling branch by symmetry; between the top
    and the crossing u + rho(t) = A cos(phi) + r + beta omega A sin(phi) has no minimum below its
    end values while beta omega < 1). The loop width of u_eff at u = 0 is therefore
    sum_i 2 w_i min(r_i + beta omega A, A - r_i): linear in the frequency until a play's
    radius reaches A - r_i. Sampled, omega A is replaced by the previous sample's rate, exactly
    for the plays that stay below A - r_i; the others start their branch short of -A + r_i,
    since the previous sample's rate is not zero at a reversal, and the loop is narrower
    (:data:`RATE_TIME`). The drive moves one way between its reversals, so the directional play
    gives the same branch as the symmetric clip there.

    Accepted parameters: those of :class:`PrandtlIshlinskii` (w_0 > 0, w_i >= 0, r_i >= 0) and
    beta >= 0 (s), dt > 0 (s). Within a sample the radii are fixed, so each play output is a
    non-decreasing function of u_t (max(p, u - rho) above u_{t-1}, min(p, u + rho) below,
    p at u_{t-1}), u -> u_eff is strictly increasing (slope >= w_0) and the inverse is unique.
    The map jumps at u_{t-1} when a play holds a lag larger than its radius (after a hold or a
    slow-down); a target inside such a jump is not reachable and :meth:`inverse` says so
    (status ``"out-of-range"``, ``u`` at the jump). Observation bound: a play of radius
    rho >= r_i keeps its output in [-(u_max - r_i)+, (u_max - r_i)+] when |u| <= u_max. Proof:
    if |p| <= M = (u_max - r_i)+ and the input rises, the new output is p or u - rho with
    p < u - rho <= u_max - r_i <= M (likewise when it falls); a held input keeps p. From rest
    (p = 0) this holds at every sample, so :meth:`max_effective_voltage` is the
    rate-independent map's bound w_0 u_max + sum w_i (u_max - r_i)+ for every drive, at every
    rate.

    Parameters
    ----------
    linear_weight : float
        w_0 (-), positive.
    radii : tuple of float
        Base (zero-rate) play radii r_i (V), non-negative.
    weights : tuple of float
        Play weights w_i (-), non-negative.
    rate_time : float
        beta (s), >= 0: radius growth per unit drive rate (V per V/s).
    dt : float
        Sample time (s), > 0, over which the rate is measured.
    """

    linear_weight: float = 0.72
    radii: tuple[float, ...] = (3.0, 9.0, 15.0)
    weights: tuple[float, ...] = (0.13333333333333333,) * 3
    rate_time: float = RATE_TIME
    dt: float = 1e-3
    name: str = "rate-dependent"

    def __post_init__(self) -> None:
        base = PrandtlIshlinskii(
            linear_weight=self.linear_weight, radii=self.radii, weights=self.weights
        )
        if not (math.isfinite(self.rate_time) and self.rate_time >= 0):
            raise ValueError(f"rate_time must be a finite number >= 0 s, got {self.rate_time!r}")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be a finite number > 0 s, got {self.dt!r}")
        object.__setattr__(self, "_base", base)
        object.__setattr__(self, "_r", np.asarray(self.radii, dtype=float))
        object.__setattr__(self, "_w", np.asarray(self.weights, dtype=float))
        object.__setattr__(self, "_beta", float(self.rate_time))
        object.__setattr__(
            self,
            "_pairs",
            tuple(zip(map(float, self.radii), map(float, self.weights), strict=True)),
        )

    @property
    def state_size(self) -> int:  # type: ignore[override]
        return 2 + len(self.radii)

    @classmethod
    def for_voltage(
        cls, rated_voltage: float, *, dt: float = 1e-3, rate_time: float | None = None
    ) -> RateDependentPrandtlIshlinskii:
        """The default Prandtl-Ishlinskii calibration (12 % loop at +-U_r, quasi-static) with
        rate constant ``rate_time`` (s; default :data:`RATE_TIME` scaled to keep the loop growth
        at 50 Hz full stroke for any U_r: the radii scale with U_r and so does the rate)."""
        base = PrandtlIshlinskii.for_voltage(rated_voltage)
        return cls(
            linear_weight=base.linear_weight,
            radii=base.radii,
            weights=base.weights,
            rate_time=RATE_TIME if rate_time is None else rate_time,
            dt=dt,
        )

    def initial_state(self, voltage: float = 0.0) -> np.ndarray:
        """State after a slow monotone approach from 0 V to ``voltage`` (V): rate 0."""
        state = np.zeros(self.state_size)
        state[2:] = play(state[2:], voltage, self._r)
        state[0] = voltage
        return state

    def max_effective_voltage(self, u_max: float) -> float:
        return self._base.max_effective_voltage(u_max)

    def loop_width(self, amplitude: float, rate: float) -> float:
        """Closed-form loop width (V) of u_eff at u = 0 for a symmetric periodic drive.

        ``amplitude`` (V) is the drive's peak, ``rate`` (V/s) the rate at its zero crossing
        (omega A for a sine; sampled, the previous sample's rate there): sum_i 2 w_i
        min(r_i + beta rate, A - r_i) over the plays with r_i < A (class docstring). Sampled,
        it is exact for the plays with r_i + beta rate < A - r_i; a play beyond starts its
        branch short of -A + r_i, since the sampled rate is not zero at a reversal, and the
        loop is narrower than this (:data:`RATE_TIME` gives the default map's widths).
        """
        rho = self._r + self.rate_time * abs(rate)
        gap = np.minimum(rho, amplitude - self._r)
        return float(2.0 * self._w @ np.maximum(gap, 0.0))

    def inverse(
        self, u_eff_target: float, state: np.ndarray, u_range: Sequence[float]
    ) -> InverseResult:
        """As :meth:`Hysteresis.inverse`; a target inside the map's jump at the previous input
        (a play catching up its lag, class docstring) gives the jump's voltage and status
        ``"out-of-range"``: no voltage reaches it."""
        result = super().inverse(u_eff_target, state, u_range)
        missed = abs(result.z - float(u_eff_target)) > _JUMP_TOLERANCE * (1.0 + abs(result.z))
        if result.status == "ok" and missed:
            return InverseResult(result.u, result.z, "out-of-range", result.state)
        return result

    def step(self, state, u):
        u_arr = np.asarray(u, dtype=float)
        u_prev = state[..., 0]
        rho = self._r + self._beta * state[..., 1:2]
        # Directional play: a rising input only raises the output to u - rho, a falling one
        # only lowers it to u + rho, a held input leaves it (class docstring).
        lower = np.where(u_arr > u_prev, u_arr, -np.inf)[..., None] - rho
        upper = np.where(u_arr < u_prev, u_arr, np.inf)[..., None] + rho
        plays = np.maximum(lower, np.minimum(upper, state[..., 2:]))
        rate = np.abs(u_arr - u_prev) / self.dt
        new = np.concatenate([u_arr[..., None], rate[..., None], plays], axis=-1)
        return new, self.linear_weight * u_arr + plays @ self._w

    def step_inplace(self, state: np.ndarray, u: float) -> float:
        """Scalar fast path of :meth:`step`: advances ``state`` (1-D) in place; returns u_eff (V).

        Equal to :meth:`step` to rounding (the weighted sum is added in order)."""
        u_prev = state.item(0)
        extra = self._beta * state.item(1)
        rising, falling = u > u_prev, u < u_prev
        total = 0.0
        for i, (r, w) in enumerate(self._pairs, start=2):
            rho = r + extra
            p = state.item(i)
            if rising:
                low = u - rho
                if p < low:
                    p = low
            elif falling:
                high = u + rho
                if p > high:
                    p = high
            state[i] = p
            total += w * p
        state[0] = u
        state[1] = abs(u - u_prev) / self.dt
        return self.linear_weight * u + total

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        import casadi

        rho = [r + self._beta * state[1] for r in self.radii]
        rising, falling = u > state[0], u < state[0]
        plays = casadi.vertcat(
            *[
                casadi.if_else(
                    rising,
                    casadi.fmax(u - rho[i], state[2 + i]),
                    casadi.if_else(falling, casadi.fmin(u + rho[i], state[2 + i]), state[2 + i]),
                )
                for i in range(len(self.radii))
            ]
        )
        u_eff = self.linear_weight * u + casadi.dot(casadi.DM(self._w), plays)
        return u_eff, casadi.vertcat(u, casadi.fabs(u - state[0]) / self.dt, plays)
