"""Rate-independent hysteresis operators, one implementation each, with their backends.

Both the plant (:mod:`piezo_env.hysteresis`) and the identified model's memory features
(``identification.features``) use these functions; each operator has a scalar fast path (plain
floats), a numpy batch (broadcasting) and a casadi expression, written side by side so that
they cannot drift apart.

Play (backlash) operator of radius r (V)::

    p <- max(u - r, min(u + r, p))

Bouc-Wen operator, exponent 1 (A = alpha k, V/V; beta, gamma in 1/V)::

    dh = A du - beta |du| h - gamma du |h|

Along a monotone jump of size d = |du> with s = sign(du) and g = s h it is the linear ODE
dg/dd = A - (beta + gamma) g while g >= 0 and dg/dd = A - (beta - gamma) g while g < 0, so the
jump is integrated in closed form (piecewise exponential, switching once at g = 0): exact for
any jump and independent of the rate. The normalized operator of the identification features,
``dh = du - b |du| h - b du |h|`` with ``b = 1 / (2 level)``, is the special case A = 1,
beta = gamma = b (:func:`normalized_bouc_wen`).

Bounded loops (Ikhouane & Rodellar, "On the hysteretic Bouc-Wen model", Nonlinear Dynamics 42,
2005, and Ikhouane, Manosa & Rodellar, "Dynamic properties of the hysteretic Bouc-Wen model",
Systems & Control Letters 56, 2007): with A > 0 and exponent 1, h stays bounded for every
bounded input and every initial state iff beta + gamma > 0 and beta - gamma >= 0 (their
sigma = beta / (beta + gamma) >= 1/2). The proof in this parametrization: on the g >= 0 branch
g relaxes monotonically towards h_max = A / (beta + gamma); on the g < 0 branch dg/dd =
A - (beta - gamma) g >= A > 0, so g climbs towards 0 and never falls below its start. Hence
[-h_max, h_max] is invariant and a start from rest (h = 0) never leaves it. With
beta - gamma < 0 the g < 0 branch has the repelling point g = -A / (gamma - beta); a reversal from
near +h_max crosses it whenever beta < 0 and h then diverges (issue: beta = -0.01, gamma = 0.05).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "BoucWenBatch",
    "bouc_wen_bound",
    "bouc_wen_casadi",
    "bouc_wen_jump",
    "bouc_wen_jump_batch",
    "bouc_wen_slope",
    "check_bouc_wen",
    "clamp_sequence",
    "normalized_bouc_wen",
    "play",
    "play_casadi",
    "play_sequence",
    "play_slope",
    "rate_play_sequence",
]

_LINEAR_LAMBDA = 1e-12
"""|beta - gamma| (1/V) below which the g < 0 branch is taken as linear (beta = gamma)."""


# ---------------------------------------------------------------------------------------------
# play operator


def play(p: Any, u: Any, r: Any) -> np.ndarray:
    """Play outputs after input ``u`` (V) from outputs ``p`` (V), radii ``r`` (V); broadcasts."""
    return np.maximum(u - r, np.minimum(u + r, p))


def play_slope(p: Any, u: Any, r: Any) -> np.ndarray:
    """d(play output)/du (0 or 1) of :func:`play` at ``u`` (V) from ``p`` (V); broadcasts.

    At a kink (``u = p +- r``) the slope of the side that moves away from ``p`` is 0.
    """
    return ((u - r > p) | (u + r < p)).astype(np.float64)


CLAMP_CHUNK = 8
"""Samples per chunk of :func:`clamp_sequence`'s scan: each level of it makes log2(chunk) + 2
passes over its data and hands a sequence one chunk-th as long to the next level; 8 was the
fastest of 8, 16 and 32 on records of the identification's lengths
(``benchmarks/results/design_measurements.md``). Speed only: every chunk gives the same
values."""


def clamp_sequence(lower: np.ndarray, upper: np.ndarray, start: Any) -> np.ndarray:
    """Outputs (T, n) of ``p_t = max(lower_t, min(upper_t, p_t-1))`` from ``p_-1 = start``.

    ``lower`` and ``upper`` (T, n) hold each sample's bounds (``lower <= upper``; +-inf leave a
    side open, both infinite hold p); ``start`` broadcasts to (n,). Every play below is this
    recursion: the symmetric play's bounds are ``u -+ r``, a directional play's one of them.

    Computed without a loop over samples, and exactly: a clamp after a clamp is a clamp, with
    the second applied to the first's bounds, ``g o f = clamp(., g(lo_f), g(hi_f))``, so the
    prefix compositions come from an associative scan (within chunks of :data:`CLAMP_CHUNK`
    samples by doubling, then over the chunks' ends by the same function, recursively), and
    ``p_t`` is the composition up to t applied to ``start``. Only max and min of the given
    numbers are taken, never a sum, so every output is the value the sample-by-sample
    recursion gives (tested); only where +0 and -0 tie may the sign of the zero differ, as the
    max and min meet them in another order.
    """
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    if lower.ndim != 2 or upper.shape != lower.shape:
        raise ValueError(
            f"lower and upper must be (samples, outputs) arrays of one shape, got "
            f"{lower.shape} and {upper.shape}"
        )
    t, n = lower.shape
    if t <= CLAMP_CHUNK:
        lo, hi = lower.copy(), upper.copy()
        _compose_prefix(lo, hi)
        return np.maximum(lo, np.minimum(hi, start))
    chunks = -(-t // CLAMP_CHUNK)
    lo = np.empty((chunks * CLAMP_CHUNK, n))
    hi = np.empty_like(lo)
    lo[:t], hi[:t] = lower, upper
    lo[t:], hi[t:] = -np.inf, np.inf  # the identity clamp pads the last chunk
    lo_chunks = lo.reshape(chunks, CLAMP_CHUNK, n)
    hi_chunks = hi.reshape(chunks, CLAMP_CHUNK, n)
    _compose_prefix(lo_chunks, hi_chunks)
    carry = np.empty((chunks, n))  # p just before each chunk
    carry[0] = start
    carry[1:] = clamp_sequence(lo_chunks[:-1, -1], hi_chunks[:-1, -1], start)
    out = np.maximum(lo_chunks, np.minimum(hi_chunks, carry[:, None, :]))
    return out.reshape(chunks * CLAMP_CHUNK, n)[:t]


def _compose_prefix(lo: np.ndarray, hi: np.ndarray) -> None:
    """In place along the second-to-last axis: the clamps ``(lo, hi)`` replaced by their
    prefix compositions (Hillis and Steele's doubling scan)."""
    length = lo.shape[-2]
    shift = 1
    while shift < length:
        later_lo, later_hi = lo[..., shift:, :], hi[..., shift:, :]
        new_lo = np.maximum(later_lo, np.minimum(later_hi, lo[..., :-shift, :]))
        new_hi = np.maximum(later_lo, np.minimum(later_hi, hi[..., :-shift, :]))
        later_lo[...], later_hi[...] = new_lo, new_hi
        shift *= 2


def play_sequence(u: np.ndarray, r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Play outputs (T, n) of an input sequence ``u`` (T,) from outputs ``p`` (n,), all in V.

    Returns the outputs and the final outputs (a new array; ``p`` is not written). The
    recursion :func:`play` sample by sample, computed by :func:`clamp_sequence`.
    """
    u = np.asarray(u, dtype=np.float64)
    out = clamp_sequence(u[:, None] - r, u[:, None] + r, p)
    return out, (out[-1].copy() if u.size else np.array(p, dtype=np.float64))


def rate_play_sequence(
    u: np.ndarray, r: np.ndarray, rate_time: float, dt: float, state: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rate-dependent directional plays over an input sequence ``u`` (T,), V.

    The plays of :class:`piezo_env.hysteresis.RateDependentPrandtlIshlinskii` with weights
    left out: radii ``r + rate_time |u_t-1 - u_t-2| / dt`` (V; ``rate_time`` in s, ``dt`` in
    s), a rising input raises an output only to ``u_t - rho``, a falling one lowers it only to
    ``u_t + rho``, a held one leaves it. ``state`` is ``[u_t-1 (V), previous rate (V/s),
    play outputs (V)...]`` as in that class.

    Returns
    -------
    plays : numpy.ndarray, shape (T, n)
        Play outputs, V.
    final : numpy.ndarray
        The state after the last sample (a new array; ``state`` is not written).
    """
    previous = np.concatenate(([state[0]], u[:-1]))
    rates = np.abs(u - previous) / dt
    lag = rate_time * np.concatenate(([state[1]], rates[:-1]))
    rising, falling = (u > previous)[:, None], (u < previous)[:, None]
    radius = r + lag[:, None]
    lower = np.where(rising, u[:, None] - radius, -np.inf)
    upper = np.where(falling, u[:, None] + radius, np.inf)
    out = clamp_sequence(lower, upper, np.array(state[2:], dtype=np.float64))
    final = np.empty(state.size)
    final[0] = u[-1] if u.size else state[0]
    final[1] = rates[-1] if u.size else state[1]
    final[2:] = out[-1] if u.size else state[2:]
    return out, final


def play_casadi(p: Any, u: Any, radii: Any) -> Any:
    """casadi column of play outputs after input ``u`` from outputs ``p`` (one per radius)."""
    import casadi

    return casadi.vertcat(
        *[casadi.fmax(u - r, casadi.fmin(u + r, p[i])) for i, r in enumerate(radii)]
    )


# ---------------------------------------------------------------------------------------------
# Bouc-Wen operator (exponent 1)


def check_bouc_wen(amplitude: float, beta: float, gamma: float) -> None:
    """Raise a ValueError unless (A, beta, gamma) give a bounded Bouc-Wen loop (see module).

    Parameters
    ----------
    amplitude : float
        A = alpha k (V/V), must be > 0.
    beta, gamma : float
        Shape parameters (1/V): beta + gamma > 0 and beta - gamma >= 0 are required.
    """
    values = {"A = alpha k": amplitude, "beta": beta, "gamma": gamma}
    for name, value in values.items():
        if not math.isfinite(value):
            raise ValueError(f"Bouc-Wen {name} must be finite, got {value}")
    if amplitude <= 0.0:
        raise ValueError(f"Bouc-Wen needs alpha k > 0 (got {amplitude}): make k and alpha positive")
    if beta + gamma <= 0.0:
        raise ValueError(
            f"Bouc-Wen needs beta + gamma > 0 for a bounded loop (got beta={beta}, gamma={gamma}, "
            f"sum {beta + gamma}): h grows without bound otherwise; raise beta"
        )
    if beta - gamma < 0.0:
        raise ValueError(
            f"Bouc-Wen needs beta >= gamma for a bounded loop from every state (Ikhouane & "
            f"Rodellar: sigma = beta/(beta+gamma) >= 1/2); got beta={beta}, gamma={gamma}. "
            "Raise beta to at least gamma"
        )


def bouc_wen_bound(amplitude: Any, beta: Any, gamma: Any) -> Any:
    """h_max = A / (beta + gamma) (V): |h| never exceeds it from a start inside (see module)."""
    return amplitude / (beta + gamma)


def normalized_bouc_wen(levels: Any) -> tuple[float, Any, Any]:
    """(A, beta, gamma) of the normalized operators with saturation ``levels`` (V): 1, b, b.

    ``b = 1 / (2 level)`` (1/V), so that h_max = level.
    """
    b = 0.5 / np.asarray(levels, dtype=np.float64)
    return 1.0, b, b


def bouc_wen_jump(h: float, du: float, ak: float, beta: float, gamma: float) -> float:
    """Scalar closed-form state (V) after an input jump ``du`` (V) from state ``h`` (V).

    ``ak`` is A = alpha k; plain floats only (the plant's single-env fast path).
    """
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
    if abs(lam) < _LINEAR_LAMBDA:
        d0 = -g / ak
        if d <= d0:
            return s * (g + ak * d)
    else:
        # log1p and expm1: with beta close to gamma, ak / lam is huge and the textbook form
        # ak/lam + (g - ak/lam) e^(-lam d) cancels it away (seen: 3e-5 V steps in u_eff).
        d0 = math.log1p(-lam * g / ak) / lam
        if d <= d0:
            return s * (g * math.exp(-lam * d) - ak * math.expm1(-lam * d) / lam)
    return s * (ak / rate) * -math.expm1(-rate * (d - d0))


def bouc_wen_jump_batch(h: Any, du: Any, ak: Any, beta: Any, gamma: Any) -> np.ndarray:
    """Numpy closed-form state (V) after jumps ``du`` (V) from states ``h`` (V); broadcasts.

    ``ak``, ``beta`` and ``gamma`` may be arrays (one operator per entry). For repeated calls
    build a :class:`BoucWenBatch` once (it precomputes the parameter algebra).
    """
    return BoucWenBatch(ak, beta, gamma)(h, du)


class BoucWenBatch:
    """Numpy backend of the Bouc-Wen jump for fixed parameters (A = ``ak``, ``beta``, ``gamma``).

    The same algebra as :func:`bouc_wen_jump` in array form: in g = sign(du) h, a negative g
    first climbs (linearly when beta = gamma, else exponentially) towards 0 over the distance
    d0, then the rest of the jump relaxes g towards g_inf = A / (beta + gamma). Calling it with
    states ``h`` (V) and jumps ``du`` (V) returns the new states; broadcasts. A jump of 0 keeps
    ``h`` (to rounding).
    """

    def __init__(self, ak: Any, beta: Any, gamma: Any) -> None:
        self.ak, self.beta, self.gamma = ak, beta, gamma
        self.lam = beta - gamma
        self.linear = bool(np.all(np.abs(self.lam) < _LINEAR_LAMBDA))
        self.unit = bool(np.all(np.asarray(ak) == 1.0))
        self.inv_ak = 1.0 / ak
        self.g_inf = ak / (beta + gamma)
        self.neg_rate = -(beta + gamma)

    def __call__(self, h: Any, du: Any) -> np.ndarray:
        s = np.copysign(1.0, du)
        g = h * s
        if self.linear:
            # climb = min(d, d0) with d0 = max(-g, 0) / ak; g1 = g + ak climb is <= 0.
            climb = np.maximum(g, 0.0)
            climb -= g
            if not self.unit:
                climb *= self.inv_ak
            d = np.abs(du)
            np.minimum(climb, d, out=climb)
            if d.shape == climb.shape:
                d -= climb
                rest = d  # the rest of the jump, >= 0
            else:
                rest = d - climb
            if not self.unit:
                climb *= self.ak
            g += climb
        else:
            g, rest = self._curved_climb(g, np.abs(du))
        # Relax towards g_inf over the rest of the jump: g_inf + (g1 - g_inf) exp(-rate rest).
        rest *= self.neg_rate
        np.exp(rest, out=rest)
        g -= self.g_inf
        g *= rest
        g += self.g_inf
        g *= s
        return g

    def _curved_climb(self, g: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(g after the climb towards 0, rest of the jump) when beta != gamma somewhere."""
        ak, lam = self.ak, self.lam
        flat = np.abs(lam) < _LINEAR_LAMBDA
        negative = g < 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            d0 = np.where(negative, np.log1p(-lam * g / ak) / lam, 0.0)
            d0 = np.where(flat, np.where(negative, -g / ak, 0.0), d0)
            climb = np.minimum(d, d0)
            # The cancellation-free form of ak/lam + (g - ak/lam) e^(-lam climb).
            curved = g * np.exp(-lam * climb) - ak * np.expm1(-lam * climb) / lam
        g = np.where(negative, np.where(flat, g + ak * climb, curved), g)
        g[negative & (d > d0)] = 0.0
        return g, d - climb


def bouc_wen_slope(h_new: Any, du: Any, ak: Any, beta: Any, gamma: Any) -> Any:
    """dh/du (V/V) at the end of a jump ``du`` (V) that ended in state ``h_new`` (V).

    The ODE's right-hand side A - beta sign(du) h - gamma |h|; for ``du = 0`` the slope of an
    increasing input. Broadcasts.
    """
    s = np.copysign(1.0, du)
    return ak - beta * s * h_new - gamma * np.abs(h_new)


def bouc_wen_casadi(h: Any, du: Any, ak: float, beta: float, gamma: float) -> Any:
    """casadi expression of :func:`bouc_wen_jump` for one operator (float parameters)."""
    import casadi

    s = casadi.if_else(du >= 0, 1.0, -1.0)
    d = casadi.fabs(du)
    g = s * h
    rate, lam = beta + gamma, beta - gamma
    if abs(lam) < _LINEAR_LAMBDA:
        climb = casadi.fmin(d, casadi.fmax(-g, 0.0) / ak)
        g1 = g + ak * climb
    else:
        d0 = casadi.if_else(g < 0, casadi.log1p(casadi.fmax(-lam * g / ak, 0.0)) / lam, 0.0)
        climb = casadi.fmin(d, d0)
        curved = g * casadi.exp(-lam * climb) - ak * casadi.expm1(-lam * climb) / lam
        g1 = casadi.if_else(g < 0, curved, g)
    g_inf = ak / rate
    return s * (g_inf + (g1 - g_inf) * casadi.exp(-rate * (d - climb)))
