"""Automatic tuning of the discrete PID on a prediction model's linear part, and its loop report.

Control law (parallel form, backward-Euler integral, filtered derivative), in z-transform::

    C(z) = kp + ki dt z / (z - 1) + kd (1 - a) / dt (z - 1) / (z - a),   a = exp(-dt / Tf)

**Tuning rule** (MIGO-style, Astrom & Hagglund 2006, ch. 7): maximise the integral gain ki (the
best rejection of low-frequency disturbances and model error) over (kp, ki, kd) subject to the
maximum sensitivity ``Ms = max_w |1 / (1 + L(e^jw dt))| <= Ms_max`` and a stable closed loop,
with ``L = C N P`` on a frequency grid up to the Nyquist frequency (:func:`frequency_grid`, the
same grid the report reads) and ``P`` the model's linear part (z -> um).

**How it is solved, and why so.** For fixed (kp, kd) the constraint at one frequency,
``|alpha + ki beta| >= 1 / Ms_max`` with ``alpha = 1 + (kp + kd D) N P`` and ``beta = I N P``
(I, D: the integral and derivative terms at that frequency), is a quadratic inequality in the
real ki: it excludes one open interval ``(k-, k+)``. The largest admissible ki reached from
ki = 0+ without crossing an excluded interval is therefore closed-form: the smallest ``k-`` of
the intervals that reach positive ki (none of them may contain 0). This ``ki*(kp, kd)`` is a
continuous function of the model's coefficients, so the tuning is too: the gains move smoothly
under a 1e-12 perturbation and do not depend on the BLAS or its thread count. (A gradient
search on the non-smooth ``min_w |1 + L|`` constraint follows different paths under different
rounding and can end at a dead controller.) ``ki*`` is maximised over a grid of
(kp, kd), then refined by bounded Nelder-Mead from the best grid points; on the path from
ki = 0+ the Nyquist curve never crosses the Ms circle, so the loop keeps the stability it has
at ki = 0+; the result is checked by the closed-loop poles all the same.

A degenerate result raises :class:`TuningError` instead of returning a controller that does
nothing: no stabilising gains, ki at the top of its search range, no gain crossover, or Ms
above the bound on the report's grid.

**Over a set of plants** (``box``: the vertices of the datasheet's tolerance box,
:mod:`controllers.tolerance_box`): the bound is one inequality per frequency and plant, so the set
is one long grid (each plant's own :func:`frequency_grid`, concatenated) and ki* is the
smallest over all of it; stability is checked on every plant. Same rule, same margin.

**Notch** (:func:`notch_filter`): zeros on the model's least damped pole pair
(:func:`resonance`), poles at the same natural frequency with a chosen damping, unit DC gain.
Over a box (:func:`robust_notch_damping`) that damping is chosen by the same rule: the one
that lets the largest integral gain meet the bound on every plant.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.optimize

from controllers.prediction import PredictionModel

__all__ = [
    "PIDGains",
    "TuningError",
    "closed_loop_report",
    "frequency_grid",
    "frequency_response",
    "loop_transfer",
    "notch_filter",
    "pid_transfer",
    "resonance",
    "robust_notch_damping",
    "tune_pid",
]

KP_RANGE = 5.0
"""Search range of kp, in units of 1 / (the model's DC gain)."""
KI_RANGE = 3.0
"""Search range of ki, in units of 1 / (DC gain x dt): reaching it is reported as degenerate."""
KD_RANGE = 5.0
"""Search range of kd, in units of dt / (DC gain)."""
_GRID_KP = 41
_GRID_KD = 21
_STABLE_WANTED = 3
"""Refined, stable candidates compared (best grid points first) before the best is taken."""
_MAX_CANDIDATES = 60
"""Grid points tried at most: a lightly damped mode near Nyquist can make the best ones
unstable between grid points, so the search goes on down the ranking (pure I is on it)."""


class TuningError(ValueError):
    """The tuning rule found no usable PID (the message says which check failed and why)."""


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
        Damping ratio of the notch's own poles (same natural frequency; from 1 on, two real
        poles whose product is the natural frequency squared: a notch and a low-pass).

    Returns
    -------
    num, den : numpy.ndarray
        Biquad coefficients in descending powers of z (den monic).
    """
    wn = abs(np.log(pole)) / dt
    if damping < 1.0:
        s = wn * complex(-damping, math.sqrt(1.0 - damping**2))
        poles = np.exp(np.array([s, np.conj(s)]) * dt)
    else:  # two real poles wn (-damping +- sqrt(damping^2 - 1)): a notch and a low-pass
        root = math.sqrt(damping**2 - 1.0)
        poles = np.exp(wn * np.array([-damping + root, -damping - root]) * dt)
    num = np.real(np.poly([pole, np.conj(pole)]))
    den = np.real(np.poly(poles))
    return num * (den.sum() / num.sum()), den


NOTCH_DAMPING_RANGE = (0.05, 10.0)
"""Range of the notch's pole damping (-), the settings' and the box search's. Low end: a notch
2.5 times the width of the PL140's own resonance (damping 0.02). High end: above 1 the poles
are real, ``wn (zeta +- sqrt(zeta^2 - 1))``, a low-pass corner near ``wn / (2 zeta)``; at 10
it sits at 1/20 of the resonance (8 Hz on the PL140), below where a loop that is to track at
all crosses over, so a larger damping cannot be the best one."""
_NOTCH_GRID = 49
"""Log-spaced grid points over :data:`NOTCH_DAMPING_RANGE` (12 % apart) before the Brent
refinement: numerical resolution only."""


def robust_notch_damping(
    model: PredictionModel,
    pole: complex,
    box: Sequence[PredictionModel],
    *,
    ms_max: float,
) -> float:
    """The notch pole damping that lets the largest integral gain meet Ms on every plant.

    The notch keeps its zeros on ``pole`` (the nominal resonance) and its poles at the same
    natural frequency; their damping sets how far the notch reaches (and, above 1, where its
    low-pass corner lies). It is chosen by the tuning rule itself: maximise the largest pure
    integral gain ki*(kp = kd = 0) that meets ``Ms <= ms_max`` on ``model`` and every plant of
    ``box`` (closed form, :func:`_largest_ki`), over :data:`NOTCH_DAMPING_RANGE`: a log-spaced
    grid, then bounded Brent between the best point's neighbours. With a resonance that may sit
    anywhere in the box's band at a damping ratio of 0.01, the loop must be gain-stabilised there
    (|L| <= 1 - 1/Ms whatever the phase), so how much integral gain survives the band is the
    measure of a notch.

    Parameters
    ----------
    model : PredictionModel
        Nominal model (its DC gain scales the result only).
    pole : complex
        Discrete resonant pole the notch's zeros sit on.
    box : sequence of PredictionModel
        The other plants the bound must hold on.
    ms_max : float
        Bound on the maximum sensitivity.

    Returns
    -------
    float
        Damping ratio of the notch's poles (-).
    """
    dt = model.dt
    loop, zinv = _stacked_loop((model, *box), None)
    integral = dt / (1.0 - zinv)
    zero_d = np.zeros_like(zinv)

    def ki_star(log_damping: float) -> float:
        notched = loop * _filter_response(notch_filter(pole, dt, math.exp(log_damping)), 1 / zinv)
        return float(_largest_ki(np.zeros(1), 0.0, notched, integral, zero_d, 1.0 / ms_max)[0])

    grid = np.linspace(*np.log(NOTCH_DAMPING_RANGE), _NOTCH_GRID)
    values = np.array([ki_star(x) for x in grid])
    k = int(np.argmax(values))
    low, high = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    res = scipy.optimize.minimize_scalar(
        lambda x: -ki_star(x), bounds=(low, high), method="bounded", options={"xatol": 1e-6}
    )
    best = float(res.x) if -res.fun >= values[k] else float(grid[k])
    return math.exp(best)


def _resonance_or_none(model: PredictionModel) -> float | None:
    try:
        return resonance(model.a, model.dt)[0]
    except ValueError:
        return None


def frequency_grid(dt: float, f_res: float | None) -> np.ndarray:
    """Frequencies (Hz) for tuning and report: 0.01 Hz to just below Nyquist, dense at f_res.

    Parameters
    ----------
    dt : float
        Sample time (s).
    f_res : float or None
        Resonance (Hz) to resolve finely (+-30 %), or None.
    """
    nyquist = 0.5 / dt
    grid = np.union1d(np.geomspace(0.01, 0.9999 * nyquist, 3000), np.linspace(10.0, nyquist, 2000))
    if f_res is not None:
        grid = np.union1d(grid, np.linspace(0.7 * f_res, min(1.3 * f_res, nyquist), 1500))
    return grid[grid < nyquist]


def frequency_response(model: PredictionModel, freqs: np.ndarray) -> np.ndarray:
    """P(e^jw dt) = C (zI - A)^-1 B of the linear part (um per unit z) at ``freqs`` (Hz).

    Evaluated from the state space (a linear solve per frequency), not from transfer-function
    polynomials, whose coefficients lose accuracy for lightly damped, high-order models. The
    last few results are kept by content (matrices, dt, frequencies): a tuning over a box asks
    for each plant's response several times. The array returned is read-only.
    """
    freqs = np.ascontiguousarray(freqs, dtype=np.float64)
    a, b, c = (np.ascontiguousarray(m, dtype=np.float64) for m in (model.a, model.b, model.c))
    return _cached_response(
        a.tobytes(), b[:, :1].tobytes(), c[0].tobytes(), a.shape[0], float(model.dt),
        freqs.tobytes(),
    )


@functools.lru_cache(maxsize=64)  # a box of 8 vertices and its nominal, a few times over
def _cached_response(
    a: bytes, b: bytes, c: bytes, n: int, dt: float, freqs: bytes
) -> np.ndarray:
    """:func:`frequency_response` on the raw bytes of its float64 inputs (the cache key)."""
    a_m = np.frombuffer(a).reshape(n, n)
    b_v, c_v = np.frombuffer(b), np.frombuffer(c)
    z = np.exp(2j * np.pi * np.frombuffer(freqs) * dt)
    pencil = z[:, None, None] * np.eye(n) - a_m[None, :, :]
    rhs = np.broadcast_to(b_v[:, None].astype(complex), (z.size, n, 1))
    x = np.linalg.solve(pencil, rhs)[:, :, 0]
    out = x @ c_v
    out.setflags(write=False)
    return out


def _filter_response(num_den: tuple[np.ndarray, np.ndarray] | None, z: np.ndarray) -> np.ndarray:
    if num_den is None:
        return np.ones_like(z)
    return np.polyval(num_den[0], z) / np.polyval(num_den[1], z)


def loop_transfer(
    model: PredictionModel, gains: PIDGains, notch: tuple[np.ndarray, np.ndarray] | None
) -> Any:
    """The open loop L = C N P as a python-control state-space system (sample time dt)."""
    import control

    dt = model.dt
    loop = control.tf(*pid_transfer(gains, dt), dt) * model.to_control()
    if notch is not None:
        loop = control.tf(notch[0], notch[1], dt) * loop
    return control.ss(loop)


def _closed_loop_stable(
    model: PredictionModel, gains: PIDGains, notch: tuple[np.ndarray, np.ndarray] | None
) -> bool:
    """Whether the unity feedback of L = C N P has every pole inside the unit circle."""
    import control

    closed = control.feedback(loop_transfer(model, gains, notch), 1)
    return bool(np.abs(closed.poles()).max() < 1.0 - 1e-9)


_CHUNK = 1 << 14
"""Elements (kp values x frequencies) per block of :func:`_largest_ki`: cache-sized blocks are
about twice as fast as one pass over the whole grid of a box."""


def _largest_ki(
    kp: np.ndarray, kd: float, loop: np.ndarray, integral: np.ndarray, deriv: np.ndarray, rho: float
) -> np.ndarray:
    """ki* for each kp (and this kd): the largest ki reached from 0+ with |1 + L| >= rho.

    ``loop`` is N P, ``integral`` and ``deriv`` the PID's I and D terms, all on the grid.
    Returns 0 where even ki = 0+ violates the bound. The smallest excluded interval's lower end
    is found block by block over the frequencies (the minimum does not depend on the blocks).
    """
    dl = deriv * loop
    beta = integral * loop
    b2 = beta.real**2 + beta.imag**2
    step = max(_CHUNK // max(kp.size, 1), 1)
    first = np.full(kp.size, np.inf)
    for i in range(0, loop.size, step):
        part = slice(i, i + step)
        block = _first_blocking(
            kp, kd, loop[part], dl[part], beta.real[part], beta.imag[part], b2[part], rho
        )
        np.minimum(first, block, out=first)
    return np.where(first > 0.0, first, 0.0)


def _first_blocking(
    kp: np.ndarray,
    kd: float,
    loop: np.ndarray,
    dl: np.ndarray,
    br: np.ndarray,
    bi: np.ndarray,
    b2: np.ndarray,
    rho: float,
) -> np.ndarray:
    """Per kp, the smallest lower end k- of the excluded ki intervals that reach positive ki.

    ``|alpha + ki beta| >= rho`` with ``alpha = 1 + (kp + kd D) N P`` (``dl = D N P``) and
    ``beta = I N P`` (real and imaginary parts ``br``, ``bi``, ``b2 = |beta|^2``) excludes the
    open interval between the roots of ``b2 ki^2 + 2 half ki + |alpha|^2 - rho^2``; real
    arithmetic in place, inf where nothing blocks.
    """
    ar = (1.0 + kd * dl.real) + kp[:, None] * loop.real
    ai = kd * dl.imag + kp[:, None] * loop.imag
    half = ar * br
    half += ai * bi
    c = ar * ar
    c += ai * ai
    c -= rho * rho
    c *= b2
    disc = half * half
    disc -= c
    blocking = disc > 0.0
    root = np.sqrt(np.maximum(disc, 0.0, out=disc), out=disc)
    blocking &= root > half  # the upper root -half + root is positive
    low = np.negative(half, out=half)
    low -= root
    low /= b2
    return np.where(blocking, low, np.inf).min(axis=1)


def tune_pid(
    model: PredictionModel,
    *,
    notch: tuple[np.ndarray, np.ndarray] | None,
    ms_max: float,
    derivative_filter_s: float,
    use_derivative: bool = True,
    box: Sequence[PredictionModel] = (),
) -> PIDGains:
    """Maximise ki subject to Ms <= ``ms_max`` and closed-loop stability (module docstring).

    Parameters
    ----------
    model : PredictionModel
        Its linear part (z -> um) is the plant; its DC gain scales the search ranges.
    notch : (num, den) or None
        Notch in series with the PID.
    ms_max : float
        Bound on the maximum sensitivity.
    derivative_filter_s : float
        Derivative filter time constant Tf (s), fixed during the search.
    use_derivative : bool
        Search kd too (else kd = 0: PI).
    box : sequence of PredictionModel
        More plants (e.g. the vertices of the datasheet's tolerance box,
        :func:`controllers.tolerance_box.vertex_models`) on which the same bound and stability must
        hold: the constraint is taken on every plant's frequency grid at once.

    Returns
    -------
    PIDGains

    Raises
    ------
    TuningError
        If no stabilising PID meets the bound, or the result is degenerate.
    """
    dt = model.dt
    plants = (model, *box)
    loop, zinv = _stacked_loop(plants, notch)
    dc_gain = float(np.real(frequency_response(model, np.zeros(1))[0]))
    if not dc_gain > 0.0:
        raise TuningError(
            f"the model's DC gain is {dc_gain:.3g} um per unit input; the tuning rule needs a "
            "positive one (a deflection that follows the voltage)"
        )
    a = math.exp(-dt / derivative_filter_s)
    integral = dt / (1.0 - zinv)
    deriv = (1.0 - a) / dt * (1.0 - zinv) / (1.0 - a * zinv)
    scale = np.array([1.0 / dc_gain, 1.0 / (dc_gain * dt), dt / dc_gain])
    rho = 1.0 / ms_max

    def ki_star(x: np.ndarray) -> float:
        """ki* in scaled units at scaled (kp, kd), capped at the search range."""
        ki = _largest_ki(np.array([x[0] * scale[0]]), x[1] * scale[2], loop, integral, deriv, rho)
        return min(float(ki[0]) / scale[1], KI_RANGE)

    def stable(rows: np.ndarray) -> np.ndarray:
        radius = [_closed_loop_radius(p, notch, rows * scale, a) for p in plants]
        return np.max(radius, axis=0) < 1.0 - 1e-9

    candidates = _grid_candidates(loop, integral, deriv, rho, scale, use_derivative, stable)
    best, stable_found = None, 0
    for start in candidates[:_MAX_CANDIDATES]:
        x, ki = _refine(ki_star, start, use_derivative)
        gains = PIDGains(
            float(x[0] * scale[0]), float(ki * scale[1]), float(x[1] * scale[2]),
            derivative_filter_s,
        )
        if ki > 0.0 and all(_closed_loop_stable(p, gains, notch) for p in plants):
            stable_found += 1
            if best is None or ki > best[0]:
                best = (ki, gains)
            if stable_found == _STABLE_WANTED:
                break
    if best is None:
        raise TuningError(f"ms_max: no stabilising PID found with Ms <= {ms_max}")
    _check_not_degenerate(best[0], model, best[1], notch, ms_max)
    for plant in box:
        ms = closed_loop_report(plant, best[1], notch)["ms"]
        if ms > ms_max * (1.0 + 1e-6):
            raise TuningError(f"the tuned loop's Ms on a plant of the box is {ms:.4g} > {ms_max}")
    return best[1]


def _stacked_loop(
    plants: Sequence[PredictionModel], notch: tuple[np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray]:
    """N P on each plant's own :func:`frequency_grid`, concatenated, and z^-1 on that grid.

    The Ms bound is one inequality per frequency and plant, so a set of plants is one long
    grid: the largest ki that meets the bound on all of them is the smallest over the union.
    """
    loops, zinvs = [], []
    for plant in plants:
        freqs = frequency_grid(plant.dt, _resonance_or_none(plant))
        zinv = np.exp(-2j * np.pi * freqs * plant.dt)
        loops.append(frequency_response(plant, freqs) * _filter_response(notch, 1.0 / zinv))
        zinvs.append(zinv)
    return np.concatenate(loops), np.concatenate(zinvs)


def _closed_loop_radius(
    model: PredictionModel,
    notch: tuple[np.ndarray, np.ndarray] | None,
    gains: np.ndarray,
    a: float,
) -> np.ndarray:
    """Spectral radius of the unity-feedback loop C N P for each row (kp, ki, kd) of ``gains``.

    The closed loop's state matrix is affine in the gains (the PID as an integrator state and a
    derivative-filter state), so all of them are built at once and their eigenvalues computed
    in one batched call.
    """
    import scipy.signal

    dt = model.dt
    kp, ki, kd = (gains[:, i] for i in range(3))
    kdd = kd * (1.0 - a) / dt
    c_pid = np.stack([ki * dt, kdd * (a - 1.0)], axis=1)  # (G, 2)
    d_pid = kp + ki * dt + kdd  # (G,)
    num, den = notch if notch is not None else (np.array([1.0]), np.array([1.0]))
    an, bn, cn, dn = scipy.signal.tf2ss(num, den)
    n_p, n_n, g = model.n_states, an.shape[0], gains.shape[0]
    n = n_p + 2 + n_n
    big = np.zeros((g, n, n))
    b_p, c_p = model.b[:, :1], model.c[:1, :]
    # Controller output u = dn (c_pid x_c + d_pid e) + cn x_n, with e = -y = -C x_p.
    big[:, :n_p, :n_p] = model.a - (dn[0, 0] * d_pid)[:, None, None] * (b_p @ c_p)
    big[:, :n_p, n_p : n_p + 2] = dn[0, 0] * b_p[None, :, :] * c_pid[:, None, :]
    big[:, :n_p, n_p + 2 :] = b_p @ cn
    big[:, n_p : n_p + 2, :n_p] = -np.ones((2, 1)) @ c_p
    big[:, n_p, n_p], big[:, n_p + 1, n_p + 1] = 1.0, a
    big[:, n_p + 2 :, :n_p] = -(d_pid[:, None, None] * (bn @ c_p))
    big[:, n_p + 2 :, n_p : n_p + 2] = bn[None, :, :] * c_pid[:, None, :]
    big[:, n_p + 2 :, n_p + 2 :] = an
    return np.abs(np.linalg.eigvals(big)).max(axis=1)


def _grid_candidates(
    loop: np.ndarray,
    integral: np.ndarray,
    deriv: np.ndarray,
    rho: float,
    scale: np.ndarray,
    use_derivative: bool,
    stable: Any,
) -> list[np.ndarray]:
    """Scaled (kp, kd) of a grid, best first (ties: the smaller gains).

    Only grid points connected to (0, 0) through points with ki* > 0 count, and of those only
    the ones whose closed loop at their ki* is stable (``stable`` maps scaled (kp, ki, kd) rows
    to booleans): a lightly damped mode near the Nyquist frequency can make a grid neighbour
    unstable without the sampled bound showing it.
    """
    import scipy.ndimage

    kp_grid = np.linspace(0.0, KP_RANGE, _GRID_KP)
    kd_grid = np.linspace(0.0, KD_RANGE, _GRID_KD) if use_derivative else np.zeros(1)
    table = np.stack(
        [
            _largest_ki(kp_grid * scale[0], kd * scale[2], loop, integral, deriv, rho)
            for kd in kd_grid
        ]
    )
    labels, _ = scipy.ndimage.label(table > 0.0)
    table = np.where(labels == labels[0, 0], table, 0.0) if labels[0, 0] else 0.0 * table
    kd_mesh, kp_mesh = np.meshgrid(kd_grid, kp_grid, indexing="ij")
    ki_scaled = np.minimum(table / scale[1], KI_RANGE)
    rows = np.stack([kp_mesh.ravel(), ki_scaled.ravel(), kd_mesh.ravel()], axis=1)
    positive = table.ravel() > 0.0
    ok = np.zeros(rows.shape[0], dtype=bool)
    ok[positive] = stable(rows[positive])
    table = np.where(ok.reshape(table.shape), table, 0.0)
    order = np.argsort(-table, axis=None, kind="stable")
    rows, cols = np.unravel_index(order, table.shape)
    return [
        np.array([kp_grid[c], kd_grid[r]])
        for r, c in zip(rows, cols, strict=True)
        if table[r, c] > 0.0
    ]


def _refine(ki_star: Any, start: np.ndarray, use_derivative: bool) -> tuple[np.ndarray, float]:
    """Maximise ki*(kp, kd) within one grid step of ``start`` (deterministic for given input).

    Bounded Brent on kp alone for a PI, bounded Nelder-Mead on (kp, kd) for a PID.
    """
    step = np.array([KP_RANGE / (_GRID_KP - 1), KD_RANGE / (_GRID_KD - 1)])
    low = np.maximum(start - step, 0.0)
    high = np.minimum(start + step, [KP_RANGE, KD_RANGE])
    if not use_derivative:
        res = scipy.optimize.minimize_scalar(
            lambda p: -ki_star(np.array([p, 0.0])),
            bounds=(low[0], high[0]),
            method="bounded",
            options={"xatol": 1e-10},
        )
        x = np.array([float(res.x), 0.0])
    else:
        simplex = np.clip(np.vstack([start, start + np.diag(step) / 2]), low, high)
        res = scipy.optimize.minimize(
            lambda x: -ki_star(x),
            start,
            method="Nelder-Mead",
            bounds=list(zip(low, high, strict=True)),
            options={"initial_simplex": simplex, "xatol": 1e-10, "fatol": 1e-14, "maxiter": 2000},
        )
        x = np.clip(res.x, low, high)
    # The grid point itself may beat a refinement stuck at a kink.
    return (x, ki_star(x)) if ki_star(x) >= ki_star(start) else (start, ki_star(start))


def _check_not_degenerate(
    ki_scaled: float,
    model: PredictionModel,
    gains: PIDGains,
    notch: tuple[np.ndarray, np.ndarray] | None,
    ms_max: float,
) -> None:
    """Raise TuningError for a result no one should run (see the module docstring)."""
    if ki_scaled >= KI_RANGE * (1.0 - 1e-9):
        raise TuningError(
            f"ki reached the top of its search range ({KI_RANGE} / (DC gain x dt)): the Ms "
            "bound does not limit the gain on this model; check the model's frequency response"
        )
    report = closed_loop_report(model, gains, notch)
    if not math.isfinite(report["crossover_hz"]):
        raise TuningError(f"the tuned loop has no gain crossover (gains {gains}): it does nothing")
    if report["ms"] > ms_max * (1.0 + 1e-6):
        raise TuningError(f"the tuned loop's Ms is {report['ms']:.4g} > ms_max = {ms_max}")


def closed_loop_report(
    model: PredictionModel, gains: PIDGains, notch: tuple[np.ndarray, np.ndarray] | None
) -> dict[str, float]:
    """Margins, Ms and closed-loop bandwidth of ``L = C N P`` on :func:`frequency_grid`.

    (``control.stability_margins`` solves polynomial equations in z and reports spurious
    crossings where the notch cancels the resonant poles, so the margins are read off the grid.)

    Returns
    -------
    dict
        ``gain_margin_db``, ``phase_margin_deg`` (the smallest angle between L and -1 at a
        gain crossing, either way round: a loop phase-stabilised at a resonance crosses with
        phase lead), ``crossover_hz`` (first |L| = 1), ``ms``,
        ``mt`` (peak |T|), ``bandwidth_hz`` (first frequency where |T| drops below -3 dB),
        ``resonance_loop_gain_db`` (|L| at the model's resonance, dB).
    """
    dt = model.dt
    f_res = _resonance_or_none(model)
    freqs = frequency_grid(dt, f_res)
    z = np.exp(2j * np.pi * freqs * dt)
    pid = _filter_response(pid_transfer(gains, dt), z) * _filter_response(notch, z)
    resp = pid * frequency_response(model, freqs)
    gain_cross = np.flatnonzero(np.diff(np.sign(np.abs(resp) - 1.0)))
    phase_cross = np.flatnonzero((np.diff(np.sign(resp.imag)) != 0) & (resp.real[:-1] < 0))
    phase = np.degrees(np.angle(resp[gain_cross]))
    pm = 180.0 - np.abs(phase)  # angle from -1 at each crossing, either way round
    gm = [-20 * np.log10(np.abs(resp[i])) for i in phase_cross]
    comp = np.abs(resp / (1.0 + resp))
    below = np.flatnonzero(comp < 1.0 / math.sqrt(2.0))
    peak = math.nan
    if f_res is not None:
        z_res = np.exp(2j * np.pi * np.array([f_res]) * dt)
        at_res = _filter_response(pid_transfer(gains, dt), z_res) * _filter_response(notch, z_res)
        peak = float(np.abs(at_res * frequency_response(model, np.array([f_res])))[0])
    return {
        "gain_margin_db": float(min(gm)) if gm else math.inf,
        "phase_margin_deg": float(pm.min()) if pm.size else math.inf,
        "crossover_hz": float(freqs[gain_cross[0]]) if gain_cross.size else math.nan,
        "ms": float(np.abs(1.0 / (1.0 + resp)).max()),
        "mt": float(comp.max()),
        "bandwidth_hz": float(freqs[below[0]]) if below.size else 0.5 / dt,
        "resonance_loop_gain_db": float(20 * np.log10(peak)) if peak > 0 else math.nan,
    }
