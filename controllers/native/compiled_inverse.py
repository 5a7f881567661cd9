"""Compiled inverse of the identified NLS (and of the plant's own hysteresis, for the oracle):
the voltage giving a target z, in generated C.

From the memory state ``s`` the NLS is a scalar map ``u -> z(u; s)`` on the drive range
``[u_lo, u_hi]`` (V -> equivalent V); so is any :class:`InverseMap` (the identified NLS as
:class:`NLSMap`, the oracle's Bouc-Wen or Prandtl-Ishlinskii hysteresis as
:class:`controllers.prediction.HysteresisMap`, whose strength is the ``parameters`` input, so
that one compiled function serves every value of it). :func:`inverse_function` builds it as
one casadi Function ``nls_inverse(z_target, state, u_lo, u_hi, u_guess, parameters) -> (u, z,
status, next_state, passes)``:

1. ``z`` at both range ends and at the warm start ``g`` (``u_guess``, clipped to the range;
   the previous input for Bouc-Wen and past-input features, whose maps kink there):
   the reachable range, and the side of ``g`` that brackets the target. A target outside
   ``[z(u_lo), z(u_hi)]`` gives that range end (status out-of-range, or ok within rounding of
   the end's output, as :func:`piezo_env.inverse.solve_increasing` decides it). A target equal
   to ``z(g)`` gives ``g`` (a root at the kink).
2. From the secant point of the bracket, safeguarded Newton steps with the exact derivative
   ``dz/du`` (casadi forward mode through features and network), each one pass of the map
   (one network pass for the NLS; one step of the closed form for a plant hysteresis):
   the bracket ``[a, b]`` shrinks to the evaluated point each iteration; a Newton step that
   leaves the bracket or does not halve the previous step becomes a bisection step (the
   ``rtsafe`` rule, so steps shrink at least geometrically and a kink inside the bracket only
   costs bisections). The iteration stops when the Newton step, or its estimated error
   ``|z''| step**2 / (2 z')`` for maps smooth inside the bracket (not play features), is below
   ``xtol`` (then ``u + step`` is returned with ``z`` extrapolated along the slope), or when
   the bracket has shrunk to rounding (a root at a kink). ``max_iter`` iterations are
   unrolled; each is a casadi ``Function.conditional`` whose generated C skips the network
   once the iteration has stopped, so a call costs the passes it uses (the three end and start
   values and the Newton passes it takes), not ``max_iter`` of them. (Unrolling with
   ``if_else`` in SX evaluates every iteration, and is slow to compile:
   ``benchmarks/results/design_measurements.md``.)

What is detected as non-monotone (status ``FALLBACK``; the caller then runs the map's numpy
inverse, :meth:`InverseMap.solve_inverse`: for the NLS
:meth:`identification.nls.NLS.solve_inverse`, which looks at a 17-node grid and picks among
several roots, for a plant hysteresis :meth:`piezo_env.hysteresis.Hysteresis.inverse`):
``z(u_lo) >= z(u_hi)``; ``z(g)`` outside ``[z(u_lo), z(u_hi)]`` beyond rounding (1e-12
relative) for ``g`` inside the range; an
iterate whose ``z`` lies outside its bracket's values (beyond rounding, 1e-12 relative); a
derivative ``<= 0`` at an iterate. The numpy path also checks the interior grid nodes, so a
wiggle between nodes that no iterate touches can be flagged there and not here; then this path
returns one exact root (status ok), which is the only root whenever the map is monotone. Not
stopping within ``max_iter`` iterations also returns ``FALLBACK``.

The function is generated as C, compiled once (cached on disk, see
:mod:`controllers.native.codegen`) and called through ctypes on preallocated buffers by
:class:`CompiledInverse`; without a working compiler :class:`CompiledInverse` runs the numpy
inverse instead, and says so in its ``native`` records
(:class:`controllers.native.codegen.NativeBuild`). Its speed and accuracy against the numpy
inverse, per call including the Python wrapper, are in ``benchmarks/results/inverse_speed.md``
(``python -m benchmarks.speed.inverse_speed``); most of a pass's cost is the network's tanh
and scalar products (``benchmarks/results/design_measurements.md``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from controllers.native.codegen import NUMPY, CompiledFunction, NativeBuild, compile_function
from piezo_env.inverse import InverseResult
from piezo_env.memo import ContentCache

__all__ = [
    "FALLBACK",
    "GRAPHS_KEPT",
    "OK",
    "OUT_OF_RANGE",
    "CompiledInverse",
    "InverseMap",
    "MixedMap",
    "NLSMap",
    "as_map",
    "inverse_function",
    "reachable_function",
]

OK, OUT_OF_RANGE, FALLBACK = 0, 1, 2
"""Status codes of :func:`inverse_function` (FALLBACK: run the numpy inverse instead)."""
STATUS_NAMES = ("ok", "out-of-range")
_FLAGS = ("-O2", "-shared", "-fPIC", "-ffp-contract=off")  # see codegen.DEFAULT_FLAGS
# Iteration vector: bracket (a, z(a), b, z(b)), iterate u, previous step, result, flags.
_A, _ZA, _B, _ZB, _U, _STEP, _U_OUT, _Z_OUT, _STATUS, _DONE, _PASSES = range(11)
_N_X = 11

GRAPHS_KEPT = 32
"""casadi Functions of inverses kept by content (:class:`CompiledInverse`), two per map (the
inverse and the reachable range). A benchmark worker meets up to six identified models, and
between two builds on one of them at most a group's oracles (10 drawn plants): 2 x 16."""

_graphs = ContentCache(GRAPHS_KEPT)


class InverseMap:
    """What the generated inverse inverts: a scalar memory map ``u -> z(u; s)`` on a drive
    range, strictly increasing in u for every state, continuous (kinks allowed, jumps not).

    Attributes
    ----------
    n_state : int
        Length of the memory state s.
    parameters : numpy.ndarray
        Numbers the generated functions take as an input rather than as constants (float64,
        possibly empty), so that one compiled function serves every value of them (the
        hysteresis strength of every Monte Carlo draw, for example).
    kinked : bool
        Whether the map may kink anywhere in the range (play operators): then the Newton
        iteration never stops on its curvature estimate (:func:`_newton_function`).
    """

    n_state: int
    parameters: np.ndarray
    kinked: bool

    def casadi_z(self, u: Any, s: Any, p: Any) -> tuple[Any, Any]:
        """casadi SX ``(z, next state)`` of the input ``u`` from the state ``s``, with the
        symbols ``p`` standing for :attr:`parameters`."""
        raise NotImplementedError

    def content(self) -> list[Any] | None:
        """What :meth:`casadi_z` and :meth:`ends` are computed from, for a content key
        (:func:`piezo_env.memo.content_key`); None (the default) when that is not known,
        and then nothing built from the map is kept."""
        return None

    def solve_inverse(
        self, z_target: float, state: np.ndarray, u_range: tuple[float, float]
    ) -> InverseResult:
        """The numpy inverse the generated one falls back to."""
        raise NotImplementedError

    def ends(self, state: np.ndarray, u_range: tuple[float, float]) -> tuple[float, float]:
        """z at both ends of ``u_range`` from ``state``, in numpy (unsorted)."""
        raise NotImplementedError


class NLSMap(InverseMap):
    """The identified NLS (:class:`identification.nls.NLS`: memory features, then the network)
    as an :class:`InverseMap`; its weights are constants of the generated code."""

    def __init__(self, nls: Any) -> None:
        self.nls = nls
        self.n_state = nls.n_state
        self.parameters = np.zeros(0)
        self.kinked = nls.feature_set == "play"

    def casadi_z(self, u: Any, s: Any, p: Any) -> tuple[Any, Any]:
        features, new_state = self.nls.feature_map.casadi_step(u, s)
        return self.nls.to_casadi()(features), new_state

    def content(self) -> list[Any]:
        """:func:`nls_content` of the NLS."""
        return nls_content(self.nls)

    def solve_inverse(
        self, z_target: float, state: np.ndarray, u_range: tuple[float, float]
    ) -> InverseResult:
        return self.nls.solve_inverse(z_target, state, u_range=u_range)

    def ends(self, state: np.ndarray, u_range: tuple[float, float]) -> tuple[float, float]:
        network = self.nls.to_numpy()
        low, high = network(self.nls.feature_map.candidates(np.array(u_range), state))
        return float(low), float(high)


class MixedMap(NLSMap):
    """The identified NLS's output mixed with its input, ``a z(u; s) + b u`` (equivalent V),
    ``(a, b)`` the generated functions' parameter input (:attr:`parameters`): the drive of a
    bender whose hysteresis strength differs from the identified one
    (:mod:`controllers.drive`). Increasing wherever ``a z' + b > 0``; the caller keeps (a, b)
    there (:class:`controllers.drive.DriveEstimate` bounds them so)."""

    def __init__(self, nls: Any, a: float = 1.0, b: float = 0.0) -> None:
        super().__init__(nls)
        self.parameters = np.array([a, b], dtype=float)

    def casadi_z(self, u: Any, s: Any, p: Any) -> tuple[Any, Any]:
        z, new_state = super().casadi_z(u, s, p)
        return p[0] * z + p[1] * u, new_state

    def content(self) -> list[Any]:
        """The NLS's content, marked as mixed ((a, b) are inputs, not content)."""
        return ["mixed", *super().content()]

    def solve_inverse(
        self, z_target: float, state: np.ndarray, u_range: tuple[float, float]
    ) -> InverseResult:
        a, b = self.parameters
        return self.nls.solve_inverse(z_target, state, u_range=u_range, mix=(a, b))

    def ends(self, state: np.ndarray, u_range: tuple[float, float]) -> tuple[float, float]:
        low, high = super().ends(state, u_range)
        a, b = self.parameters
        return float(a * low + b * u_range[0]), float(a * high + b * u_range[1])


def nls_content(nls: Any) -> list[Any]:
    """What an identified NLS computes from, for a content key: its feature map (a frozen
    dataclass of numbers) and its network parameters (the normalised arrays the evaluators
    are folded from)."""
    return ["nls", nls.feature_map, nls.arrays()]


def as_map(source: Any) -> InverseMap:
    """``source`` itself if it is an :class:`InverseMap`, else an identified NLS's
    :class:`NLSMap`."""
    return source if isinstance(source, InverseMap) else NLSMap(source)


def _evaluators(source: InverseMap) -> tuple[Any, Any, Any]:
    """SX Functions ``(u, s, p) -> z``, ``(u, s, p) -> (z, dz/du)`` and
    ``(u, s, p) -> next state``."""
    import casadi

    u = casadi.SX.sym("u")
    s = casadi.SX.sym("s", source.n_state)
    p = casadi.SX.sym("p", source.parameters.size)
    z, new_state = source.casadi_z(u, s, p)
    slope = casadi.jtimes(z, u, casadi.SX(1.0))
    return (
        casadi.Function("nls_z", [u, s, p], [z]),
        casadi.Function("nls_z_slope", [u, s, p], [z, slope]),
        casadi.Function("nls_next_state", [u, s, p], [new_state]),
    )


def _start_function() -> Any:
    """SX Function ``(t, lo, hi, g, z_lo, z_hi, z_g) -> x``: range checks and the bracket."""
    import casadi

    t, lo, hi, g, z_lo, z_hi, z_g = (casadi.SX.sym(n) for n in "t lo hi g zl zh zg".split())
    if_else, land, lnot = casadi.if_else, casadi.logic_and, casadi.logic_not
    x = [casadi.SX(0.0)] * _N_X
    below = z_g < t  # the root lies in (g, hi]
    x[_A], x[_ZA] = if_else(below, g, lo), if_else(below, z_g, z_lo)
    x[_B], x[_ZB] = if_else(below, hi, g), if_else(below, z_hi, z_g)
    x[_U] = x[_A] + (t - x[_ZA]) * (x[_B] - x[_A]) / (x[_ZB] - x[_ZA])
    x[_STEP] = x[_B] - x[_A]
    # z(g) beyond an end's value by rounding is not evidence of a non-monotone map (a warm
    # start an ulp inside the range, where a play feature's pass differs from the end's in
    # ulps): the same tolerance as the iterations' test.
    rounding = 1e-12 * (1.0 + casadi.fabs(t))
    inside = land(z_lo - rounding <= z_g, z_g <= z_hi + rounding)
    # Cases from the least to the most important: each overrides the ones before.
    cases = [
        (t == z_g, g, z_g, OK),
        (t <= z_lo, lo, z_lo, _end_status(t, z_lo)),
        (t >= z_hi, hi, z_hi, _end_status(t, z_hi)),
        (land(land(lo < g, g < hi), lnot(inside)), g, z_g, FALLBACK),
        (z_hi <= z_lo, lo, z_lo, FALLBACK),
    ]
    for condition, u_out, z_out, status in cases:
        x[_U_OUT] = if_else(condition, u_out, x[_U_OUT])
        x[_Z_OUT] = if_else(condition, z_out, x[_Z_OUT])
        x[_STATUS] = if_else(condition, status, x[_STATUS])
        x[_DONE] = if_else(condition, 1.0, x[_DONE])
    x[_PASSES] = casadi.SX(3.0)
    return casadi.Function(
        "nls_inverse_start", [t, lo, hi, g, z_lo, z_hi, z_g], [casadi.vertcat(*x)]
    )


def _end_status(t: Any, z_end: Any) -> Any:
    """OK within rounding of a range end's output (batched and single passes differ in ulps),
    else OUT_OF_RANGE."""
    import casadi

    return casadi.if_else(
        casadi.fabs(t - z_end) <= 1e-12 * (1.0 + casadi.fabs(t)), OK, OUT_OF_RANGE
    )


def _newton_function(
    z_slope: Any, n_state: int, n_parameters: int, xtol: float, extrapolate: bool
) -> Any:
    """SX Function ``(x, t, s, p) -> x``: one safeguarded Newton iteration (one network pass).

    With ``extrapolate`` the iteration also stops when the error of the Newton step just
    computed, ``|z''| step**2 / (2 z')`` with ``z''/2`` from the secants to both bracket ends
    (a kink there only overestimates it), is below ``xtol``: one pass fewer, exact for maps
    smooth inside the bracket (Bouc-Wen and past-input features kink only at the warm start,
    a bracket end).
    """
    import casadi

    x = casadi.SX.sym("x", _N_X)
    t, s = casadi.SX.sym("t"), casadi.SX.sym("s", n_state)
    p = casadi.SX.sym("p", n_parameters)
    if_else, land, lnot, fabs = casadi.if_else, casadi.logic_and, casadi.logic_not, casadi.fabs
    u = x[_U]
    zu, slope = z_slope(u, s, p)
    newton = (t - zu) / slope
    below = zu < t
    a, za = if_else(below, u, x[_A]), if_else(below, zu, x[_ZA])
    b, zb = if_else(below, x[_B], u), if_else(below, x[_ZB], zu)
    u_next = u + newton
    inside = land(land(a < u_next, u_next < b), fabs(newton) <= 0.5 * fabs(x[_STEP]))
    u_next = if_else(inside, u_next, 0.5 * (a + b))
    converged = fabs(newton) <= xtol
    if extrapolate:
        a0, za0, b0, zb0 = x[_A], x[_ZA], x[_B], x[_ZB]
        half_curvature = casadi.fmax(
            fabs((za0 - zu) / (a0 - u) - slope) / (u - a0),
            fabs((zb0 - zu) / (b0 - u) - slope) / (b0 - u),
        )
        small = half_curvature * newton * newton <= xtol * slope
        converged = casadi.logic_or(converged, land(small, fabs(newton) < 0.5 * (b0 - a0)))
    u_conv = casadi.fmin(casadi.fmax(u + newton, a), b)
    pinched = b - a <= 1e-13 * (1.0 + fabs(a))  # bracketed to rounding: a root at a kink
    near_a = t - za <= zb - t
    rounding = 1e-12 * (1.0 + fabs(t))  # passes at nearby inputs differ in ulps
    increasing = land(land(x[_ZA] - rounding <= zu, zu <= x[_ZB] + rounding), slope > 0.0)
    cases = [  # each overrides the ones before
        (pinched, if_else(near_a, a, b), if_else(near_a, za, zb), OK),
        (converged, u_conv, zu + slope * (u_conv - u), OK),
        (lnot(increasing), u, zu, FALLBACK),
    ]
    new = [a, za, b, zb, u_next, u_next - u, x[_U_OUT], x[_Z_OUT], x[_STATUS], x[_DONE]]
    for condition, u_out, z_out, status in cases:
        new[_U_OUT] = if_else(condition, u_out, new[_U_OUT])
        new[_Z_OUT] = if_else(condition, z_out, new[_Z_OUT])
        new[_STATUS] = if_else(condition, status, new[_STATUS])
        new[_DONE] = if_else(condition, 1.0, new[_DONE])
    new.append(x[_PASSES] + 1.0)
    return casadi.Function("nls_inverse_newton", [x, t, s, p], [casadi.vertcat(*new)])


def inverse_function(
    source: Any, *, max_iter: int = 40, xtol: float = 1e-9, extrapolate: bool | None = None
) -> Any:
    """casadi Function of the whole inverse (see the module docstring).

    Parameters
    ----------
    source : InverseMap or identification.nls.NLS
        The map (an identified NLS is taken as its :class:`NLSMap`).
    max_iter : int
        Newton iterations unrolled (each skipped once the iteration has stopped).
    xtol : float
        Estimated voltage error (V) below which the iteration stops.
    extrapolate : bool, optional
        Stop on the curvature estimate (see :func:`_newton_function`); default: True unless
        the map is :attr:`InverseMap.kinked`.

    Returns
    -------
    casadi.Function
        ``nls_inverse(z_target, state, u_lo, u_hi, u_guess, parameters) -> (u, z, status,
        next_state, passes)``: voltage (V), z at it (equivalent V), status code (:data:`OK`,
        :data:`OUT_OF_RANGE`, :data:`FALLBACK`), memory state after ``u``, network passes.
    """
    import casadi

    source = as_map(source)
    z_only, z_slope, next_state = _evaluators(source)
    if extrapolate is None:
        extrapolate = not source.kinked
    n_parameters = source.parameters.size
    newton = _newton_function(z_slope, source.n_state, n_parameters, xtol, extrapolate)
    arguments = newton.mx_in()
    skip = casadi.Function("nls_inverse_skip", arguments, [arguments[0]])
    iteration = casadi.Function.conditional("nls_inverse_iteration", [newton], skip)
    t, lo, hi, g = (casadi.MX.sym(n) for n in ("z_target", "u_lo", "u_hi", "u_guess"))
    s = casadi.MX.sym("state", source.n_state)
    p = casadi.MX.sym("parameters", n_parameters)
    g_in = casadi.fmin(casadi.fmax(g, lo), hi)
    x = _start_function()(
        t, lo, hi, g_in, z_only(lo, s, p), z_only(hi, s, p), z_only(g_in, s, p)
    )
    for _ in range(max_iter):
        x = iteration(x[_DONE], x, t, s, p)  # index 0 runs Newton, 1 (done) skips it
    status = casadi.if_else(x[_DONE] > 0.0, x[_STATUS], FALLBACK)
    return casadi.Function(
        "nls_inverse",
        [t, s, lo, hi, g, p],
        [x[_U_OUT], x[_Z_OUT], status, next_state(x[_U_OUT], s, p), x[_PASSES]],
        ["z_target", "state", "u_lo", "u_hi", "u_guess", "parameters"],
        ["u", "z", "status", "next_state", "passes"],
    )


def reachable_function(source: Any) -> Any:
    """casadi Function ``nls_reachable(state, u_lo, u_hi, parameters) -> (z_lo, z_hi)``: z at
    both range ends from ``state`` (two passes, no derivative)."""
    import casadi

    source = as_map(source)
    z_only = _evaluators(source)[0]
    s = casadi.MX.sym("state", source.n_state)
    p = casadi.MX.sym("parameters", source.parameters.size)
    lo, hi = casadi.MX.sym("u_lo"), casadi.MX.sym("u_hi")
    return casadi.Function(
        "nls_reachable",
        [s, lo, hi, p],
        [z_only(lo, s, p), z_only(hi, s, p)],
        ["state", "u_lo", "u_hi", "parameters"],
        ["z_lo", "z_hi"],
    )


class CompiledInverse:
    """The inverse of a map (the identified NLS, or the plant's own hysteresis for the oracle)
    in generated C, with the map's numpy inverse as its fallback.

    :meth:`solve` calls the compiled :func:`inverse_function` on preallocated buffers and
    returns what the map's numpy inverse (:meth:`InverseMap.solve_inverse`, for the NLS
    :meth:`identification.nls.NLS.solve_inverse`) returns (to within ``xtol``);
    when the compiled path reports ``FALLBACK`` (non-monotone map, see the module docstring),
    for a non-finite target, or when no compiler works, it runs that numpy inverse instead.
    :meth:`reachable` gives the reachable range from the generated :func:`reachable_function`
    (cheaper than the numpy network: ``benchmarks/results/design_measurements.md``).

    Parameters
    ----------
    source : InverseMap or identification.nls.NLS
        The map; an identified network with its memory features is taken as its
        :class:`NLSMap`.
    u_range : (float, float)
        Drive range (V) searched.
    compiled : bool
        Try generated C (else always the numpy inverse).
    max_iter : int
        Newton iterations unrolled in the generated function.
    xtol : float
        Estimated voltage error (V) at which the iteration stops.
    """

    def __init__(
        self,
        source: Any,
        u_range: Sequence[float],
        *,
        compiled: bool = True,
        max_iter: int = 40,
        xtol: float = 1e-9,
    ) -> None:
        self.map = as_map(source)
        self.u_range = (float(u_range[0]), float(u_range[1]))
        self.fallbacks = 0
        self._function: CompiledFunction | None = None
        self._reachable: CompiledFunction | None = None
        self.backend = "numpy (compilation not requested)"
        self.native: list[NativeBuild] = []
        """What each native build did (:class:`controllers.native.codegen.NativeBuild`)."""
        self.functions: tuple[Any, Any] | None = None
        """The casadi Functions ``(nls_inverse, nls_reachable)`` when both are compiled (the
        MPC's fused step, :mod:`controllers.native.fused_step`, compiles them again with its
        own code); None otherwise."""
        # The casadi graphs are a pure function of the map and the settings, and most of the
        # set-up: kept by content (GRAPHS_KEPT), so the same map's inverse is built once.
        content = self.map.content()
        if compiled:
            function = _graphs.get_or_compute(
                None if content is None else ["inverse", *content, max_iter, xtol],
                lambda: inverse_function(self.map, max_iter=max_iter, xtol=xtol),
            )
            self._function, build = compile_function(
                function, flags=_FLAGS, cache="inverse", fallback=NUMPY
            )
            self.native.append(build)
            self.backend = str(build)
        if self._function is not None:
            ends = _graphs.get_or_compute(
                None if content is None else ["reachable", *content],
                lambda: reachable_function(self.map),
            )
            self._reachable, build = compile_function(
                ends, flags=_FLAGS, cache="inverse", fallback=NUMPY
            )
            self.native.append(build)
        if self._function is not None:
            inputs, outputs = self._function.inputs, self._function.outputs
            self._target, self._state, low, high, self._guess, parameters = inputs
            low[0], high[0] = self.u_range
            parameters[:] = self.map.parameters
            self._u, self._z, self._status, self._next, self._passes = (
                o.reshape(-1) for o in outputs
            )
        if self._reachable is not None:
            self.functions = (function, ends)
            self._reachable.inputs[1][0], self._reachable.inputs[2][0] = self.u_range
            self._reachable.inputs[3][:] = self.map.parameters
            self._ends = [o.reshape(-1) for o in self._reachable.outputs]

    def set_parameters(self, parameters: Any) -> None:
        """Invert the map at new :attr:`InverseMap.parameters` (the same count) from now on:
        the generated functions take them as an input, so nothing is compiled again."""
        self.map.parameters[:] = parameters
        if self._function is not None:
            self._function.inputs[5][:] = self.map.parameters
        if self._reachable is not None:
            self._reachable.inputs[3][:] = self.map.parameters

    @property
    def compiled(self) -> bool:
        """Whether the generated C is in use."""
        return self._function is not None

    @property
    def passes(self) -> int:
        """Network passes of the last compiled call (ends, warm start and Newton steps)."""
        return int(self._passes[0]) if self._function is not None else 0

    def solve(self, z_target: float, state: np.ndarray, u_guess: float | None = None) -> Any:
        """Voltage giving ``z_target`` (equivalent V) from the memory ``state``.

        Parameters
        ----------
        z_target : float
            Desired hidden signal, equivalent V.
        state : numpy.ndarray
            Feature state before this sample (float64, not validated on the compiled path).
        u_guess : float, optional
            Warm start, V. Default: ``state[0]``, the previous input for Bouc-Wen and
            past-input features, the narrowest play's output (within its radius of the
            previous input) for play features.

        Returns
        -------
        piezo_env.inverse.InverseResult
            Voltage (V), z at it (equivalent V), status (``"ok"``, ``"out-of-range"``, or
            ``"non-monotone"`` from the numpy fallback) and the state after the voltage.
        """
        if self._function is None or not math.isfinite(z_target):
            return self.map.solve_inverse(z_target, state, self.u_range)
        self._target[0] = z_target
        self._state[:] = state
        self._guess[0] = state[0] if u_guess is None else u_guess
        self._function.run()
        status = int(self._status[0])
        if status == FALLBACK:
            self.fallbacks += 1
            return self.map.solve_inverse(z_target, state, self.u_range)
        return InverseResult(
            float(self._u[0]), float(self._z[0]), STATUS_NAMES[status], self._next.copy()
        )

    def reachable(
        self, state: np.ndarray, u_range: tuple[float, float] | None = None
    ) -> tuple[float, float]:
        """Range of z (equivalent V) reachable in one sample from ``state`` over ``u_range``
        (V; default the drive range, the slew window with a slew limit).

        Generated C (two passes), else :meth:`InverseMap.ends` in numpy; sorted like
        :meth:`controllers.prediction.IdentifiedNLS.reachable`.
        """
        ends = self.u_range if u_range is None else u_range
        if self._reachable is None:
            low, high = self.map.ends(state, ends)
        else:
            inputs = self._reachable.inputs
            inputs[0][:] = state
            inputs[1][0], inputs[2][0] = ends
            self._reachable.run()
            low, high = self._ends[0][0], self._ends[1][0]
        return (float(low), float(high)) if low <= high else (float(high), float(low))
