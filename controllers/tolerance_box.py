"""The datasheet's tolerance box as a set of linear models, built from one identified model.

A bender bought to the datasheet is one draw from its tolerances. Its response to the voltage
depends on three of them: the free deflection (the static gain), the first resonance and that
mode's damping ratio (the blocking force moves stiffness and piezo moment together and leaves
the response as it is). The vertices of that box are the benders a fixed controller must still
hold. Each vertex's linear part is the identified nominal model with

- its static gain times the free-deflection factor ``1 +- gain``;
- its first bending mode moved to the resonance factor ``1 +- resonance`` times the identified
  natural frequency, with the damping ratio set to the vertex's (``damping[0]`` or
  ``damping[1]``),

by the modal correction of :mod:`identification.correction` (:func:`scale_modes`: the mode's
pole moved, its static contribution kept, every residue times the gain factor). So the box
needs nothing but the identified model and the datasheet's tolerances.

The correction's factors are exact, not first-order: the first mode's continuous pole
``s = -sigma + j omega_d`` becomes ``alpha (beta (-sigma) + j omega_d)``; the damping ratio
``zeta'`` fixes ``beta = zeta' omega_d / (sigma sqrt(1 - zeta'^2))`` and the natural frequency
``f omega_n`` then fixes ``alpha = f omega_n / |beta (-sigma) + j omega_d|``.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np

from controllers.prediction import PredictionModel
from controllers.settings import GAIN_TOLERANCE
from identification.arx import ARXModel
from identification.correction import ModalCorrection, ModalSplit
from piezo_env.randomization import DomainRandomization

__all__ = [
    "DAMPING_RANGE",
    "RESONANCE_TOLERANCE",
    "ToleranceBox",
    "Vertex",
    "arx_of",
    "mode_correction",
    "vertex_models",
]

RESONANCE_TOLERANCE = DomainRandomization().resonance
"""Relative half-width of the first resonance (-): the datasheet's +-20 %."""
DAMPING_RANGE = DomainRandomization().damping_ratio
"""(low, high) first-mode damping ratio (-) of a bender to the datasheet: 0.01 .. 0.04 (the
range :class:`piezo_env.DomainRandomization` draws from)."""


@dataclass(frozen=True)
class ToleranceBox:
    """Relative tolerances of the plant a controller must hold (the datasheet's by default).

    Attributes
    ----------
    gain : float
        Relative half-width of the static gain (free deflection per volt), in [0, 1).
    resonance : float
        Relative half-width of the first resonance frequency, in [0, 1).
    damping : (float, float) or None
        (low, high) first-mode damping ratio, each in (0, 1); None keeps the model's own.
    """

    gain: float = GAIN_TOLERANCE
    resonance: float = RESONANCE_TOLERANCE
    damping: tuple[float, float] | None = DAMPING_RANGE

    def __post_init__(self) -> None:
        for name in ("gain", "resonance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 <= value < 1.0):
                raise ValueError(f"{name} tolerance must be a number in [0, 1), got {value!r}")
        if self.damping is not None:
            low, high = (float(v) for v in self.damping)
            if not 0.0 < low <= high < 1.0:
                raise ValueError(
                    f"damping range must be (low, high) with 0 < low <= high < 1, got "
                    f"{self.damping!r}"
                )
            object.__setattr__(self, "damping", (low, high))

    @property
    def is_nominal(self) -> bool:
        """True when the box is the nominal model alone."""
        return self.gain == 0.0 and self.resonance == 0.0 and self.damping is None

    def vertices(self) -> list[Vertex]:
        """The distinct vertices (gain factor, resonance factor, damping ratio or None)."""
        gains = sorted({1.0 - self.gain, 1.0 + self.gain})
        resonances = sorted({1.0 - self.resonance, 1.0 + self.resonance})
        dampings: list[float | None] = [None] if self.damping is None else sorted(set(self.damping))
        return [Vertex(*v) for v in itertools.product(gains, resonances, dampings)]


@dataclass(frozen=True)
class Vertex:
    """One vertex of a :class:`ToleranceBox`.

    Attributes
    ----------
    gain : float
        Static gain factor (-).
    resonance : float
        First-resonance frequency factor (-).
    damping : float or None
        First-mode damping ratio (-); None: the model's own.
    """

    gain: float
    resonance: float
    damping: float | None

    def label(self) -> str:
        """``"x0.8, x1.2, 0.01"`` (gain, resonance, damping), as in the corners report."""
        damping = "model" if self.damping is None else f"{self.damping:g}"
        return f"x{self.gain:g}, x{self.resonance:g}, {damping}"


def arx_of(model: PredictionModel) -> ARXModel:
    """The linear part (z -> um) of ``model`` as an ARX model ``B(q^-1) / A(q^-1)``.

    From the transfer function of the state space, with common factors ``z`` (poles and zeros
    at the origin: pure delays of a measured-history realization) taken off, so an identified
    ARX(na, nb) with ``na <= nb`` comes back as ARX(n, n), n its transfer function's order.
    """
    import scipy.signal

    num, den = scipy.signal.ss2tf(model.a, model.b[:, :1], model.c[:1, :], np.zeros((1, 1)))
    num, den = np.real_if_close(num[0]).astype(float), np.real(den).astype(float)
    scale = np.abs(num).max()
    while den.size > 2 and abs(den[-1]) < 1e-12 and abs(num[-1]) < 1e-12 * scale:
        num, den = num[:-1], den[:-1]
    den = den / den[0]
    return ARXModel(-den[1:], num[1:], dt=model.dt)


def mode_correction(split: ModalSplit, dt: float, vertex: Vertex) -> ModalCorrection:
    """The exact factors that put the first mode of ``split`` (sample time ``dt``, s) at the
    vertex's resonance factor and damping ratio, and its gain at the vertex's (module
    docstring)."""
    s = np.log(split.p) / dt
    sigma, omega_d = -s.real, s.imag
    beta = 1.0
    if vertex.damping is not None:
        zeta = vertex.damping
        beta = zeta * omega_d / (sigma * math.sqrt(1.0 - zeta**2))
    alpha = vertex.resonance * abs(s) / abs(complex(-beta * sigma, omega_d))
    return ModalCorrection(gain=vertex.gain, frequency=alpha, damping=beta)


def vertex_models(
    model: PredictionModel, box: ToleranceBox
) -> list[tuple[Vertex, PredictionModel]]:
    """The linear part of each vertex of ``box`` around ``model`` (module docstring).

    Parameters
    ----------
    model : PredictionModel
        The nominal model; its first bending mode is its complex pole pair of largest modulus
        (as in :func:`identification.correction.scale_modes`). A box of the gain alone needs
        no mode: its vertices scale the output.
    box : ToleranceBox

    Returns
    -------
    list of (Vertex, PredictionModel)
        The model with the vertex's linear part (measured-history realization of the
        corrected ARX; nonlinearity and bounds unchanged). Empty for a nominal box.

    Raises
    ------
    ValueError
        If the box moves a mode the model does not have (no complex pole pair).
    """
    if box.is_nominal:
        return []
    if box.resonance == 0.0 and box.damping is None:  # the gain alone: no mode to move
        return [
            (vertex, dataclasses.replace(model, c=model.c * vertex.gain))
            for vertex in box.vertices()
        ]
    arx = arx_of(model)
    split = ModalSplit(arx)
    out = []
    for vertex in box.vertices():
        corrected = split.scaled(mode_correction(split, model.dt, vertex))
        a, b, c, _ = corrected.state_space_matrices()
        out.append((vertex, dataclasses.replace(model, a=a, b=b, c=c)))
    return out
