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
"""

from __future__ import annotations

from typing import Any

import numpy as np

from piezo_env.operators import play_sequence

__all__ = [
    "PlayRadiusFunction",
    "play_radius_derivatives",
    "radii_from_coordinates",
    "radius_coordinates",
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
