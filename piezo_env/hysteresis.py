"""Rate-independent input hysteresis u -> u_eff of the piezo ceramic.

The hysteresis sits at the input of the linear beam. Being rate-independent, its output only
changes when the input changes, so under a zero-order-hold drive it is updated once per step,
exactly, from the voltage jump u_prev -> u.

Bouc-Wen (default), exponent n = 1::

    u_eff = k u - h,   dh = alpha k du - beta |du| h - gamma du |h|

Along a monotone jump of size d = |du| with s = sign(du) and g = s h, this is the linear ODE
dg/dd = alpha k - (beta + gamma) g while g >= 0 and dg/dd = alpha k - (beta - gamma) g while
g < 0, so the jump is integrated in closed form (piecewise exponential, switching once at
g = 0): exact and cheaper than Runge-Kutta sub-steps. h stays inside
[-h_max, h_max], h_max = alpha k / (beta + gamma).

Prandtl-Ishlinskii: u_eff = w_0 u + sum_i w_i P_{r_i}[u], play operators
P_r: p <- max(u - r, min(u + r, p)).

Both default calibrations give a loop ~12 % of the peak-to-peak output wide at full stroke
(+-U_r) while the effective voltage still reaches +-U_r at the ends of the major loop, so the
full-stroke deflection matches the datasheet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["BoucWen", "Hysteresis", "NoHysteresis", "PrandtlIshlinskii", "make_hysteresis"]


class Hysteresis:
    """Interface of an input hysteresis model (stateless: the state is passed in and out).

    The state is a float64 array of length ``state_size`` whose first entry is the previous
    input voltage (V). ``step`` works on one state (1-D) or a batch (2-D, one row per env).
    """

    state_size: int = 1
    name: str = "none"

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


@dataclass(frozen=True)
class BoucWen(Hysteresis):
    """Bouc-Wen hysteresis (exponent 1), integrated exactly over each voltage jump.

    Parameters
    ----------
    k : float
        Linear gain (-).
    alpha : float
        Hysteretic share (-); h_max = alpha k / (beta + gamma).
    beta, gamma : float
        Loop shape parameters (1/V); beta + gamma > 0 keeps h bounded.
    """

    k: float = 1.245
    alpha: float = 0.32
    beta: float = 0.0233
    gamma: float = 0.0233
    name: str = "bouc-wen"
    state_size: int = field(default=2, init=False)

    def __post_init__(self) -> None:
        if not (self.k > 0 and self.alpha > 0 and self.beta + self.gamma > 0):
            raise ValueError(
                f"Bouc-Wen needs k > 0, alpha > 0 and beta + gamma > 0 (bounded loop), got "
                f"k={self.k}, alpha={self.alpha}, beta={self.beta}, gamma={self.gamma}"
            )

    @classmethod
    def for_voltage(cls, rated_voltage: float) -> BoucWen:
        """Default calibration (12 % loop at +-30 V) rescaled to another rated voltage (V)."""
        scale = 30.0 / rated_voltage
        return cls(beta=0.0233 * scale, gamma=0.0233 * scale)

    @property
    def h_max(self) -> float:
        """Upper bound of |h| (V)."""
        return self.alpha * self.k / (self.beta + self.gamma)

    def max_effective_voltage(self, u_max: float) -> float:
        return self.k * u_max + self.h_max

    def step(self, state, u):
        if state.ndim == 1:
            h = _bouc_wen_jump(
                float(state[1]),
                float(u) - float(state[0]),
                self.alpha * self.k,
                self.beta,
                self.gamma,
            )
            return np.array([u, h]), self.k * u - h
        return self._step_batch(state, np.asarray(u, dtype=float))

    def step_scalar(self, u_prev: float, h: float, u: float) -> tuple[float, float]:
        """Scalar fast path: returns (h_new, u_eff) for the jump u_prev -> u (V)."""
        h = _bouc_wen_jump(h, u - u_prev, self.alpha * self.k, self.beta, self.gamma)
        return h, self.k * u - h

    def _step_batch(self, state: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batched closed-form jump; the same algebra as :func:`_bouc_wen_jump`.

        In g = sign(du) h: a negative g first climbs linearly (beta = gamma) or exponentially
        towards 0 over the distance d0, then the rest of the jump relaxes g towards g_inf.
        """
        ak, rate, lam = self.alpha * self.k, self.beta + self.gamma, self.beta - self.gamma
        g_inf = ak / rate
        du = u - state[:, 0]
        s = np.copysign(1.0, du)
        d = np.abs(du, out=du)
        g = state[:, 1] * s
        if abs(lam) < 1e-12:
            # climb = min(d, d0) with d0 = max(-g, 0) / ak; g1 = g + ak climb is <= 0.
            climb = np.maximum(g, 0.0)
            climb -= g
            climb *= 1.0 / ak
            np.minimum(climb, d, out=climb)
            d -= climb  # the rest of the jump, >= 0
            climb *= ak
            g += climb
        else:
            negative = g < 0.0
            arg = 1.0 - lam * g / ak
            with np.errstate(divide="ignore", invalid="ignore"):
                d0 = np.where(negative, np.where(arg > 0.0, np.log(arg) / lam, np.inf), 0.0)
            climb = np.minimum(d, d0)
            g = np.where(negative, ak / lam + (g - ak / lam) * np.exp(-lam * climb), g)
            g[negative & (d > d0)] = 0.0
            d -= climb
        # Relax towards g_inf over the rest of the jump: g_inf + (g1 - g_inf) exp(-rate rest).
        d *= -rate
        np.exp(d, out=d)
        g -= g_inf
        g *= d
        g += g_inf
        g *= s  # h_new
        new_state = np.empty_like(state)
        new_state[:, 0] = u
        new_state[:, 1] = g
        u_eff = self.k * u
        u_eff -= g
        return new_state, u_eff


def _bouc_wen_jump(h: float, du: float, ak: float, beta: float, gamma: float) -> float:
    """Closed-form Bouc-Wen (n = 1) state after an input jump du (V) from state h (V)."""
    if du == 0.0:
        return h
    s = 1.0 if du > 0.0 else -1.0
    d = abs(du)
    g = s * h
    rate = beta + gamma
    if g >= 0.0:
        g_inf = ak / rate
        return s * (g_inf + (g - g_inf) * math.exp(-rate * d))
    lam = beta - gamma
    if abs(lam) < 1e-12:
        d0 = -g / ak
        if d <= d0:
            return s * (g + ak * d)
    else:
        arg = 1.0 - lam * g / ak
        if arg <= 0.0:  # g never reaches 0 on this branch
            return s * (ak / lam + (g - ak / lam) * math.exp(-lam * d))
        d0 = math.log(arg) / lam
        if d <= d0:
            return s * (ak / lam + (g - ak / lam) * math.exp(-lam * d))
    return s * (ak / rate) * -math.expm1(-rate * (d - d0))


@dataclass(frozen=True)
class PrandtlIshlinskii(Hysteresis):
    """Prandtl-Ishlinskii hysteresis: a linear term plus weighted play operators.

    Parameters
    ----------
    linear_weight : float
        w_0 (-).
    radii : tuple of float
        Play radii r_i (V), non-negative.
    weights : tuple of float
        Play weights w_i (-).
    """

    linear_weight: float = 0.72
    radii: tuple[float, ...] = (3.0, 9.0, 15.0)
    weights: tuple[float, ...] = (0.13333333333333333,) * 3
    name: str = "prandtl-ishlinskii"

    def __post_init__(self) -> None:
        if len(self.radii) != len(self.weights) or not self.radii:
            raise ValueError("radii and weights must be non-empty and of equal length")
        if min(self.radii) < 0:
            raise ValueError(f"play radii must be >= 0 V, got {self.radii}")
        object.__setattr__(self, "_r", np.asarray(self.radii, dtype=float))
        object.__setattr__(self, "_w", np.asarray(self.weights, dtype=float))

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
        return abs(self.linear_weight) * u_max + float(np.abs(self._w).sum()) * u_max

    def step(self, state, u):
        plays = np.maximum(
            np.asarray(u)[..., None] - self._r,
            np.minimum(np.asarray(u)[..., None] + self._r, state[..., 1:]),
        )
        new = np.concatenate([np.asarray(u, dtype=float)[..., None], plays], axis=-1)
        return new, self.linear_weight * u + plays @ self._w


def make_hysteresis(kind: str | Hysteresis | None, rated_voltage: float) -> Hysteresis:
    """Hysteresis model from a name (``"bouc-wen"``, ``"prandtl-ishlinskii"``, None) or object."""
    if isinstance(kind, Hysteresis):
        return kind
    if kind is None or kind == "none":
        return NoHysteresis()
    if kind == "bouc-wen":
        return BoucWen.for_voltage(rated_voltage)
    if kind == "prandtl-ishlinskii":
        return PrandtlIshlinskii.for_voltage(rated_voltage)
    raise ValueError(
        f"unknown hysteresis {kind!r}; use 'bouc-wen', 'prandtl-ishlinskii', None or a Hysteresis"
    )
