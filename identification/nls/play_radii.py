"""Learned play radii: play features differentiable in their radii (step e' of :func:`identify`).

With fixed radii the play features of a record are computed once and the output-error
refinement (:mod:`identification.nls.output_error`) only moves the network. A hysteresis whose
plays have radii between two grid radii (:func:`identification.features.default_play_radii`) is
then drawn from its neighbours, and the network's residual is what the MPC's inverse pays for.
This module puts the radii in the output-error objective.

Gradient in closed form. A play output ``p_t = max(u_t - r, min(u_t + r, p_t-1))`` is piecewise
linear in ``r``: where the lower edge is active (``p_t = u_t - r``) ``dp_t/dr = -1``, where the
upper edge is, ``+1``, and where the play holds, ``dp_t/dr = dp_t-1/dr`` (0 from rest). So the
derivative of every play output is the sign of the edge it last touched, found from the outputs
themselves after one numpy pass (:func:`play_radius_derivatives`), and
:class:`PlayRadiusFunction` feeds outputs and derivatives to torch autograd as a custom
Function: one pass of :func:`piezo_env.operators.play_sequence` per objective evaluation, no
recursion of T steps in the torch graph (which would cost one graph node per sample and
radius). The derivative is that of the record's outputs for the radii held everywhere, the
gradient of the refinement objective (except on the measure-zero set where ``p`` lies exactly
on an edge without being pushed, where it is one of the one-sided derivatives).

Why a separate, capped stage. An evaluation with the radii free recomputes the features, which
costs a play pass over the records besides the network and the free run; the radii are few (one
per play), settle within a few tens of L-BFGS iterations, and the stages that follow move only
the network and the linear part at the learned radii, with the features computed once. The
radii are kept ordered and positive as cumulative sums of softplus increments, started from
the grid (:func:`radius_coordinates`).

Rate-dependent plays (``IdentificationConfig.rate``). The plays of
:class:`identification.features.RatePlayFeatures` have radii ``r_i + c R_t`` with
``R_t = |u_t-1 - u_t-2| / dt`` the previous sample's rate, and move only when the input does
(a rising input raises an output to its lower edge, a falling one lowers it to its upper edge).
The same reasoning gives their derivatives: an output last set by its edge at sample s has
``dp/dr_i = -+1`` and ``dp/dc = -+R_s`` (the sign of that edge), so :class:`RatePlayFunction`
needs the edge each output last touched and the rate there, from one pass over the record's
moves (:func:`rate_play_runs`, :func:`rate_play_outputs`). The rate constant is learned as
``c = dt softplus(s)``, positive, in units of the sample time.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from piezo_env.operators import clamp_sequence, play_sequence

__all__ = [
    "PlayRadiusFunction",
    "RatePlayFunction",
    "play_radius_derivatives",
    "radii_from_coordinates",
    "radius_coordinates",
    "rate_play_outputs",
    "rate_play_runs",
]


def play_radius_derivatives(u: np.ndarray, radii: np.ndarray, plays: np.ndarray) -> np.ndarray:
    """d(play output)/d(radius) (T, n) of the outputs ``plays`` (T, n) of ``u`` (T,) from rest.

    -1 where the lower edge ``u_t - r`` was last touched, +1 where the upper edge ``u_t + r``
    was, 0 before either (module docstring). The edges are recomputed as the play recursion
    computes them, so the comparison is exact.
    """
    lower = u[:, None] - radii
    upper = u[:, None] + radii
    sign = np.where(plays == lower, -1.0, np.where(plays == upper, 1.0, 0.0))
    touched = sign != 0.0
    index = np.where(touched, np.arange(u.size)[:, None], -1)
    np.maximum.accumulate(index, axis=0, out=index)
    columns = np.arange(radii.size)[None, :]
    return np.where(index >= 0, sign[np.maximum(index, 0), columns], 0.0)


def radius_coordinates(radii: np.ndarray) -> np.ndarray:
    """Unconstrained coordinates ``a`` of increasing positive ``radii`` (V):
    ``r_i = sum_{j <= i} softplus(a_j)``."""
    steps = np.diff(np.asarray(radii, dtype=np.float64), prepend=0.0)
    if not np.all(steps > 0.0):
        raise ValueError(f"radii must be positive and increasing, got {radii}")
    return steps + np.log(-np.expm1(-steps))  # softplus^-1, stable for large steps


def radii_from_coordinates(a: Any) -> Any:
    """Radii (V) of the coordinates ``a`` (torch tensor): cumulative softplus increments."""
    import torch

    return torch.cumsum(torch.nn.functional.softplus(a), dim=0)


def _play_function() -> Any:
    import torch

    class _PlayRadius(torch.autograd.Function):
        @staticmethod
        def forward(ctx: Any, radii: Any, u: Any, rest: Any) -> Any:
            r = radii.detach().numpy()
            u_np = u.numpy()
            start = np.full(r.size, float(rest))
            plays, _ = play_sequence(u_np, r, start)
            ctx.save_for_backward(torch.from_numpy(play_radius_derivatives(u_np, r, plays)))
            return torch.from_numpy(plays)

        @staticmethod
        def backward(ctx: Any, grad: Any) -> Any:
            (derivative,) = ctx.saved_tensors
            return (grad * derivative).sum(dim=0), None, None

    return _PlayRadius


class PlayRadiusFunction:
    """Play outputs (T, n) of an input record as a torch function of the radii (n,), V.

    ``PlayRadiusFunction()(radii, u, rest)``: ``radii`` a float64 tensor (with gradient),
    ``u`` a float64 tensor (T,) of the record (V) and ``rest`` the input (V) the plays start
    at. The backward pass uses :func:`play_radius_derivatives`.
    """

    def __init__(self) -> None:
        self._function = _play_function()

    def __call__(self, radii: Any, u: Any, rest: float) -> Any:
        return self._function.apply(radii, u, rest)


def rate_play_runs(
    u: np.ndarray, dt: float, rest: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A record ``u`` (T,) from rest for the rate-dependent plays, reduced to its moves.

    Rate-dependent plays (:class:`identification.features.RatePlayFeatures`) move only when the
    input does, with radii grown by the previous sample's rate. Returns the indices of the
    samples where the input changes (``moves``), their inputs (V), their direction (+1 rising,
    -1 falling) and the previous sample's rate |u_t-1 - u_t-2| / dt there (V/s), and, for every
    sample, the index into ``moves`` of the last move at or before it (-1 before the first).
    """
    previous = np.concatenate(([rest], u[:-1]))
    rates = np.abs(u - previous) / dt
    previous_rate = np.concatenate(([0.0], rates[:-1]))
    moves = np.flatnonzero(u != previous)
    direction = np.sign(u[moves] - previous[moves])
    last = np.searchsorted(moves, np.arange(u.size), side="right") - 1
    return u[moves], direction, previous_rate[moves], last


def rate_play_outputs(
    u: np.ndarray,
    direction: np.ndarray,
    lag: np.ndarray,
    radii: np.ndarray,
    rest: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directional plays at the moves of a record (:func:`rate_play_runs`), the sign of the
    edge each output last touched (-1 lower, +1 upper, 0 none: the derivative by the radius)
    and the move where it touched it (-1 none).

    ``lag`` (V) is the rate's share of the radius at each move, ``rate_time`` times the
    previous rate; the edge of a rising move is ``u - (r + lag)``, of a falling one
    ``u + (r + lag)``, as in :func:`piezo_env.operators.rate_play_sequence`.
    """
    rising = (direction > 0)[:, None]
    radius = radii + lag[:, None]
    edges = np.where(rising, u[:, None] - radius, u[:, None] + radius)
    out = clamp_sequence(
        np.where(rising, edges, -np.inf), np.where(rising, np.inf, edges), float(rest)
    )
    sign = np.where(out == edges, -direction[:, None], 0.0)
    touched = sign != 0.0
    index = np.where(touched, np.arange(u.size)[:, None], -1)
    np.maximum.accumulate(index, axis=0, out=index)
    columns = np.arange(radii.size)[None, :]
    fill = np.maximum(index, 0)
    return out, np.where(index >= 0, sign[fill, columns], 0.0), np.where(index >= 0, fill, -1)


def _rate_play_function() -> Any:
    import torch

    class _RatePlay(torch.autograd.Function):
        @staticmethod
        def forward(ctx: Any, radii: Any, rate_time: Any, moves: Any, rest: float) -> Any:
            u, direction, rate = moves
            r = radii.detach().numpy()
            lag = float(rate_time) * rate
            plays, sign, touch = rate_play_outputs(u, direction, lag, r, rest)
            # d p / d rate_time: the sign of the edge last touched times the rate there.
            by_rate = sign * np.where(touch >= 0, rate[np.maximum(touch, 0)], 0.0)
            ctx.save_for_backward(torch.from_numpy(sign), torch.from_numpy(by_rate))
            return torch.from_numpy(plays)

        @staticmethod
        def backward(ctx: Any, grad: Any) -> Any:
            sign, by_rate = ctx.saved_tensors
            return (grad * sign).sum(dim=0), (grad * by_rate).sum(), None, None

    return _RatePlay


class RatePlayFunction:
    """Rate-dependent play outputs at a record's moves as a torch function of the base radii
    (n,) and the rate constant (s): ``RatePlayFunction()(radii, rate_time, moves, rest)`` with
    ``moves = (u, direction, previous rate)`` from :func:`rate_play_runs` (numpy arrays)."""

    def __init__(self) -> None:
        self._function = _rate_play_function()

    def __call__(self, radii: Any, rate_time: Any, moves: tuple, rest: float) -> Any:
        return self._function.apply(radii, rate_time, moves, rest)
