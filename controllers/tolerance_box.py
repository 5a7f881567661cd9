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
pole moved, its static contribution kept, every residue times the gain factor), and every other
bending mode of the model (each further complex pole pair) moved by the same frequency factor
with its damping ratio scaled as the first mode's (stiffness-proportional damping, zeta_k = zeta_1
omega_k / omega_1; :func:`box_model`): the datasheet's resonance tolerance is one
of stiffness over mass, and an Euler-Bernoulli beam's modal frequencies all scale with
sqrt(EI / m). A further mode may be an alias: a cantilever's second mode lies at 6.27 times the
first (:data:`CANTILEVER_RATIOS`), above the Nyquist frequency of every default sample time
(:func:`piezo_env.default_dt`), so the sampled model shows it folded (the PL127's 2.6 kHz mode
at 4 kHz sampling appears at 1.4 kHz), and a stiffer bender moves the alias *down*. Each
further mode's continuous frequency is therefore the fold of its sampled one nearest a
cantilever mode of the identified first resonance (:func:`unfolded_hz`), and it is that
frequency which the factor moves before the mode is sampled again. So the box needs nothing but
the identified model and the datasheet's tolerances.

The correction's factors are exact, not first-order: the first mode's continuous pole
``s = -sigma + j omega_d`` becomes ``alpha (beta (-sigma) + j omega_d)``; the damping ratio
``zeta'`` fixes ``beta = zeta' omega_d / (sigma sqrt(1 - zeta'^2))`` and the natural frequency
``f omega_n`` then fixes ``alpha = f omega_n / |beta (-sigma) + j omega_d|``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.pid_tuning import frequency_response
from controllers.prediction import PredictionModel
from controllers.settings import GAIN_TOLERANCE
from identification.arx import ARXModel
from identification.correction import ModalCorrection, ModalSplit
from piezo_env.randomization import DomainRandomization

__all__ = [
    "CANTILEVER_RATIOS",
    "DAMPING_RANGE",
    "MAX_ZETA",
    "RESONANCE_TOLERANCE",
    "ToleranceBox",
    "UnstableFitError",
    "Vertex",
    "arx_of",
    "box_model",
    "datasheet_model",
    "mode_correction",
    "unfolded_hz",
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


CANTILEVER_RATIOS = (
    (4.694091 / 1.875104) ** 2,
    (7.854757 / 1.875104) ** 2,
    (10.995541 / 1.875104) ** 2,
)
"""Natural frequencies of a uniform Euler-Bernoulli cantilever's 2nd-4th bending modes over its
first (-): (beta_k L / beta_1 L)^2, beta_k L the roots of 1 + cos(x) cosh(x) = 0."""


MAX_ZETA = 0.99
"""Largest damping ratio a further mode of :func:`box_model` is moved to (-): stiffness-
proportional damping can carry a high mode past critical damping, where its complex pair would
split into two real poles; it stays a pair just below."""


def unfolded_hz(sampled_hz: float, first_hz: float, dt: float) -> float:
    """Continuous frequency (Hz) of a mode seen at ``sampled_hz`` in a model sampled every
    ``dt`` (s) whose first mode lies at ``first_hz``: of the folds ``m / dt +- sampled_hz``
    (m = 0, 1, ...) the one nearest (in ratio) a cantilever mode
    (:data:`CANTILEVER_RATIOS` times ``first_hz``)."""
    fs = 1.0 / dt
    targets = np.array(CANTILEVER_RATIOS) * first_hz
    folds = np.arange(0, math.ceil(targets[-1] / fs) + 2) * fs
    candidates = np.concatenate([folds + sampled_hz, folds[1:] - sampled_hz])
    distance = np.abs(np.log(candidates[:, None] / targets[None, :])).min(axis=1)
    return float(candidates[np.argmin(distance)])


def box_model(arx: ARXModel, vertex: Vertex, *, further_modes: bool = True) -> ARXModel:
    """``arx`` (the nominal linear part) moved to ``vertex``: its first bending mode to the
    vertex's resonance factor and damping ratio and its static gain to the vertex's
    (:func:`mode_correction`), and, with ``further_modes``, every further complex pole pair's
    natural frequency times the resonance factor, its damping ratio times the first's factor
    (module docstring).

    Raises
    ------
    ValueError
        If the model has no complex pole pair (no mode to move).
    """
    dt = arx.dt
    split = ModalSplit(arx)
    first = split.p
    first_s = np.log(first) / dt
    first_hz = abs(first_s) / (2.0 * math.pi)
    zeta_ratio = 1.0 if vertex.damping is None else vertex.damping / (-first_s.real / abs(first_s))
    moved = split.scaled(mode_correction(split, dt, vertex))
    if not further_modes or (vertex.resonance == 1.0 and zeta_ratio == 1.0):
        return moved
    poles = arx.poles()
    for pole in (p for p in poles if p.imag > 1e-9 and p != first):
        current = moved.poles()
        further = ModalSplit(moved, pole=current[np.argmin(np.abs(current - pole))])
        decay = -math.log(abs(further.p)) / dt  # sigma (1/s): aliasing keeps the modulus
        sampled_hz = abs(np.angle(further.p)) / (2.0 * math.pi * dt)
        true_hz = unfolded_hz(sampled_hz, first_hz, dt)  # damped frequency
        # The continuous upper pole -sigma + j 2 pi f samples to p or to its conjugate.
        fold = round(true_hz * dt)
        p_old = further.p if true_hz - fold / dt >= 0 else np.conj(further.p)
        # Stiffness-proportional damping, zeta_k = zeta_1 omega_k / omega_1: every mode's
        # damping ratio moves by the first's factor (kept underdamped: the pair stays a pair).
        omega_n = math.hypot(decay, 2.0 * math.pi * true_hz)
        zeta = min(zeta_ratio * decay / omega_n, MAX_ZETA)
        s_new = vertex.resonance * omega_n * complex(-zeta, math.sqrt(1.0 - zeta**2))
        moved = further.moved(np.exp(s_new * dt), p_old=p_old)
    # Each move keeps its mode's static contribution exactly in theory; the polynomial
    # products of a high-order model (the FE plant's) lose digits, so the gain is set last.
    scale = vertex.gain * arx.static_gain() / moved.static_gain()
    return ARXModel(
        moved.a, moved.b * scale, dt=dt, noise_bound=arx.noise_bound, method=moved.method
    )


FIT_POINTS = 400
"""Frequencies (log-spaced, 0.1 Hz to 0.48 times the sampling rate) :func:`datasheet_model`
fits on: 2.1 % apart at 1 kHz sampling (2.4 % at 4 kHz), about the half-power bandwidth
(2 zeta) of the lightest-damped first mode the datasheet allows (zeta 0.01)."""

FIT_ITERATIONS = 100
"""Most Sanathanan-Koerner reweightings of :func:`datasheet_model`'s least squares, which stop
earlier at :data:`FIT_TOLERANCE`: twice the most the catalogue's grids were measured to need
(``benchmarks/results/design_measurements.md``); the fit error each member reports is the
measure of the result either way."""

FIT_TOLERANCE = 1e-10
"""Largest relative change of the fitted response between reweightings at which
:func:`datasheet_model` stops (-): far below the fit errors it reaches (1e-5 .. 1e-2)."""


def _fit_frequencies(dt: float) -> np.ndarray:
    """The :data:`FIT_POINTS` frequencies (Hz) :func:`datasheet_model` fits on."""
    return np.geomspace(0.1, 0.48 / dt, FIT_POINTS)


def _arx_response(arx: ARXModel, w: np.ndarray) -> np.ndarray:
    """``B(w) / A(w)`` at ``w = exp(-j omega dt)``."""
    powers = np.arange(1, max(arx.na, arx.nb) + 1)
    wk = w[:, None] ** powers[None, :]
    return (wk[:, : arx.nb] @ arx.b) / (1.0 - wk[:, : arx.na] @ arx.a)


@functools.lru_cache(maxsize=8)
def _fe_response(
    datasheet: Any, damping_ratio: float, dt: float, n_elements: int | None
) -> np.ndarray:
    """The linear part's response of the FE model of ``datasheet`` (no hysteresis) on the
    :data:`FIT_POINTS` frequencies of :func:`datasheet_model` (kept: every member of a set
    divides by the same nominal one; read-only)."""
    from piezo_env.model import PiezoBenderModel

    elements = {} if n_elements is None else {"n_elements": n_elements}
    plant = PiezoBenderModel(
        datasheet, dt=dt, hysteresis=None, damping_ratio=damping_ratio, **elements
    )
    return frequency_response(
        PredictionModel.from_plant(plant, reduce=False), _fit_frequencies(dt)
    )


class UnstableFitError(ValueError):
    """:func:`datasheet_model`'s fit came out unstable: that point has no datasheet model (the
    screens that meet it count it; any other error propagates)."""


def datasheet_model(
    arx: ARXModel,
    datasheet: Any,
    vertex: Vertex,
    *,
    damping_ratio: float,
    order: int,
    n_elements: int | None = None,
) -> tuple[ARXModel, float]:
    """``arx`` (the identified linear part) moved to ``vertex`` by the datasheet's physics.

    The FE model of :mod:`piezo_env` built from ``datasheet`` (first-mode damping
    ``damping_ratio``, ``n_elements`` beam elements as the env's, default its default; no
    hysteresis) and the same model at the vertex (free deflection and
    resonance times the vertex's factors, its damping ratio) give the ratio ``R(omega)`` by
    which the tolerance moves the response, every mode and alias included (stiffness-
    proportional damping moves the higher modes' damping with the first's). The member is the
    ARX(order, order) fitted to ``G_arx(omega) R(omega)`` on :data:`FIT_POINTS` frequencies by
    Sanathanan-Koerner iterations (linear least squares on ``A G - B``, reweighted by
    ``1 / |G A|``: the relative error), its static gain then set to the vertex's exactly.
    Where the identified model is right about the nominal bender, the member is right about
    the vertex to the fit's accuracy, and a member moved mode by mode (:func:`box_model`) is
    not: that one keeps every mode it cannot see (an alias carried as a real pole, the modes
    lumped into its feed-through) where the nominal bender has them
    (``benchmarks/results/design_measurements.md``).

    Returns
    -------
    (ARXModel, float)
        The member, and the fit's largest relative error over the band below half the sampling
        rate (-).

    Raises
    ------
    UnstableFitError
        If the fit is unstable (a pole on or outside the unit circle).
    """
    from piezo_env.datasheet import get_datasheet

    dt = arx.dt
    sheet = get_datasheet(datasheet)
    moved_sheet = dataclasses.replace(
        sheet,
        free_deflection=sheet.free_deflection * vertex.gain,
        resonance=sheet.resonance * vertex.resonance,
    )
    w = np.exp(-2j * math.pi * _fit_frequencies(dt) * dt)
    vertex_zeta = damping_ratio if vertex.damping is None else vertex.damping
    nominal = _fe_response(sheet, float(damping_ratio), float(dt), n_elements)
    moved = _fe_response(moved_sheet, float(vertex_zeta), float(dt), n_elements)
    target = _arx_response(arx, w) * moved / nominal
    powers = w[:, None] ** np.arange(1, order + 1)[None, :]
    weight = 1.0 / np.abs(target)
    fitted_response = None
    for _ in range(FIT_ITERATIONS):
        # G = sum a_k w^k G + sum b_k w^k, in relative terms, real and imaginary parts stacked.
        rows = np.concatenate([powers * target[:, None], powers], axis=1) * weight[:, None]
        rhs = target * weight
        theta = np.linalg.lstsq(
            np.concatenate([rows.real, rows.imag]),
            np.concatenate([rhs.real, rhs.imag]),
            rcond=None,
        )[0]
        denominator = 1.0 - powers @ theta[:order]
        weight = 1.0 / np.abs(target * denominator)
        response = (powers @ theta[order:]) / denominator
        if fitted_response is not None:
            change = np.max(np.abs(response / fitted_response - 1.0))
            if change < FIT_TOLERANCE:
                break
        fitted_response = response
    fitted = ARXModel(theta[:order], theta[order:], dt=dt)
    if np.any(np.abs(fitted.poles()) >= 1.0):
        raise UnstableFitError(
            f"the datasheet member at {vertex.label()} came out unstable (poles "
            f"{np.round(fitted.poles(), 4).tolist()}); use member_set='modes'"
        )
    scale = vertex.gain * arx.static_gain() / fitted.static_gain()
    member = ARXModel(
        fitted.a, fitted.b * scale, dt=dt, noise_bound=arx.noise_bound, method="datasheet-ratio"
    )
    error = float(np.max(np.abs(_arx_response(member, w) / target - 1.0)))
    return member, error


def _scaled(model: PredictionModel, gain: float) -> PredictionModel:
    """``model`` with its linear part's gain times ``gain``: every output scaled."""
    tracked = None if model.tracked is None else model.tracked * gain
    return dataclasses.replace(model, c=model.c * gain, tracked=tracked)


def vertex_models(
    model: PredictionModel, box: ToleranceBox, *, further_modes: bool = False
) -> list[tuple[Vertex, PredictionModel]]:
    """The linear part of each vertex of ``box`` around ``model`` (module docstring).

    Parameters
    ----------
    model : PredictionModel
        The nominal model; its first bending mode is its complex pole pair of largest modulus
        (as in :func:`identification.correction.scale_modes`). A box of the gain alone needs
        no mode: its vertices scale the output.
    box : ToleranceBox
    further_modes : bool
        Move every further mode too (:func:`box_model`; the observer bank's screen). False
        (the default): the first mode alone, the box the PIDs are tuned over
        (:mod:`controllers.pid_tuning`), whose notch and gains are built around that mode.

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
            (vertex, _scaled(model, vertex.gain))
            for vertex in box.vertices()
        ]
    arx = arx_of(model)
    out = []
    for vertex in box.vertices():
        moved = box_model(arx, vertex, further_modes=further_modes)
        a, b, c, _ = moved.state_space_matrices()
        # The realization of the measured output's ARX: a plant's steered output (an oracle's
        # tip behind a sensor) has no place in it, and the loops close on the measurement.
        out.append((vertex, dataclasses.replace(model, a=a, b=b, c=c, tracked=None)))
    return out
