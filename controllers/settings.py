"""What the model-based controllers' settings share: checks and defaults written once."""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from controllers.task import ControlTask
from piezo_env.checks import require_int
from piezo_env.randomization import DomainRandomization

__all__ = [
    "DISTURBANCE_STD",
    "GAIN_TOLERANCE",
    "LEARNED_GAIN_TOLERANCE",
    "MS_MAX",
    "OBSERVERS",
    "PROCESS_STD",
    "QP_SOLVERS",
    "USABLE_OSQP_STATUS",
    "check_initial_voltage",
    "check_settings",
    "damping_pair",
    "measurement_std",
    "number_at_least",
    "python_numbers",
]

QP_SOLVERS = ("daqp", "osqp")
"""The MPCs' QP solvers (:mod:`controllers.box_qp`): DAQP, the default (dense dual active set,
exact active set), or OSQP (operator splitting); their solve times on these QPs are in
``benchmarks/results/controller_latency.md``."""

USABLE_OSQP_STATUS = ("solved", "solved inaccurate")
"""OSQP statuses whose solution is applied; any other falls back to the shifted plan."""

DISTURBANCE_STD = 0.8
"""The observer's default output-disturbance random-walk step (um per sample), both MPCs'.

Chosen between a faster and a slower fixed observer on the nominal PL140 and the
Prandtl-Ishlinskii plant (``benchmarks/results/design_measurements.md``);
:class:`controllers.mpc.MPCSettings` says what it trades.
"""

OBSERVERS = ("bank", "fixed")
"""Observer choices of the model-based controllers: ``"bank"``
(:class:`controllers.observer.ObserverBank`, the default) or ``"fixed"`` (one
:class:`controllers.observer.DisturbanceObserver` with the settings' noise levels)."""

GAIN_TOLERANCE = DomainRandomization().free_deflection
"""Relative half-width of the bender's static gain the loops are screened and tuned on (-):
the datasheet's tolerance of the free deflection (deflection per volt), +-20 %
(:class:`controllers.tolerance_box.ToleranceBox`, the PIDs). The MPCs' learned gain reaches
further (:data:`LEARNED_GAIN_TOLERANCE`): 0.862-1.092 times a screened vertex's gain, inside the
0.64-2.25 that a loop with Ms <= :data:`MS_MAX` on a vertex stays stable under
(:func:`controllers.predictive.screen_bank`)."""

LEARNED_GAIN_TOLERANCE = 0.3101
"""Relative half-width of the interval the MPCs learn the bender's gain in (-): the datasheet's
free deflection (+-20 %) times what its hysteresis strength (+-30 %) does to the gain a linear
model of the nominal bender sees, up to x1.092 at small signals
(:func:`piezo_env.randomization.gain_tolerance`: 0.31004, rounded up; :mod:`controllers.gain`).
A learned gain confined to +-20 % stops short of such a bender's. Derived for the datasheet's
spread; for another, pass ``gain_tolerance=gain_tolerance(spread)``."""

STRENGTH_TOLERANCE = DomainRandomization().hysteresis_strength
"""Relative half-width of the bender's hysteresis strength that the adaptive MPC learns (-):
the datasheet's +-30 % (:class:`piezo_env.randomization.DomainRandomization`, which scales
the hysteretic part at the same major-loop peak; :mod:`controllers.drive`)."""

MS_MAX = 1.8
"""Bound on the sensitivity peak Ms = 1 / (modulus margin) of every loop the controllers close
on their own model (-): within Astrom and Murray's usual 1.2-2 (*Feedback Systems*, 2nd ed.,
sec. 10.3), the margin left for what no model of the box holds (higher modes, hysteresis
error). The PIDs are tuned to it; the MPCs' observer banks keep only filters within it, on
the box's vertices (:func:`controllers.predictive.screen_bank`) and, for the adaptive MPC, on
each member's own grid point (:meth:`controllers.adaptive.AdaptiveMPC.filter_screen`)."""

PROCESS_STD = 0.04
"""The observer's default input-referred process noise (equivalent V), both MPCs'.

One tuning for every plant, measured on the PL140: without process noise the filter leaves an
error at the first resonance uncorrected, and a smaller one leaves more of the
Prandtl-Ishlinskii plant's (``benchmarks/results/design_measurements.md``);
:class:`controllers.mpc.MPCSettings` says what it trades.
"""


def number_at_least(value: object, low: float) -> bool:
    """True for a finite real number (not a bool) >= ``low``: a Python or numpy int or float
    (``numpy.float32(0.3)`` as ``0.3``)."""
    return (
        isinstance(value, numbers.Real)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value >= low
    )


def python_numbers(settings: object) -> None:
    """Replace every numpy scalar field of the (frozen) dataclass ``settings`` by the Python
    number it holds (``numpy.float32(0.3)`` by ``0.30000001192092896``, ``numpy.int64(12)`` by
    ``12``), so that a setting read from an array or a sweep's grid is the same setting and
    ``describe()`` stays JSON."""
    for item in dataclasses.fields(settings):  # type: ignore[arg-type]
        value = getattr(settings, item.name)
        if isinstance(value, np.generic) and not isinstance(value, (np.str_, np.bytes_)):
            object.__setattr__(settings, item.name, value.item())


def damping_pair(name: str, value: object) -> tuple[float, float]:
    """``value`` as a (low, high) pair of damping ratios with ``0 < low <= high < 1``, as
    floats; a ValueError naming ``name`` otherwise (a tuple or list of two real numbers)."""
    if not (
        isinstance(value, (tuple, list))
        and len(value) == 2
        and all(number_at_least(v, 0.0) for v in value)
        and 0.0 < value[0] <= value[1] < 1.0
    ):
        raise ValueError(
            f"{name} must be a pair (low, high) of damping ratios with 0 < low <= high < 1, "
            f"such as (0.01, 0.04), got {value!r}"
        )
    return float(value[0]), float(value[1])


def check_settings(
    settings: object,
    *,
    integers: tuple[str, ...] = (),
    non_negative: tuple[str, ...] = (),
    positive: tuple[str, ...] = (),
) -> None:
    """Raise ValueError naming the first field of ``settings`` outside its domain.

    ``integers`` must be integers >= 1, ``non_negative`` finite numbers >= 0, ``positive``
    finite numbers > 0; a ``measurement_std`` field, when present, must be None or > 0 (um),
    ``robust_bank`` and ``shortcut`` fields True or False, an ``observer`` field ``"bank"`` or
    ``"fixed"``, a ``bank_memory`` field an integer >= 1,
    a ``gain_tolerance`` field (in ``non_negative``) below 1 (a relative half-width), an
    ``initial_voltage`` field None or a finite number (the controller checks it against its
    drive range).
    """
    python_numbers(settings)
    for name in integers:
        require_int(name, getattr(settings, name))
    for name in non_negative:
        value = getattr(settings, name)
        if not number_at_least(value, 0.0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    for name in positive:
        value = getattr(settings, name)
        if not number_at_least(value, 0.0) or value == 0:
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    voltage = getattr(settings, "initial_voltage", None)
    if voltage is not None and not number_at_least(voltage, -math.inf):
        raise ValueError(f"initial_voltage must be None or a finite number (V), got {voltage!r}")
    for name in ("robust_bank", "shortcut"):
        flag = getattr(settings, name, True)
        if not isinstance(flag, bool):
            raise ValueError(f"{name} must be True or False, got {flag!r}")
    solver = getattr(settings, "qp_solver", "daqp")
    if solver not in QP_SOLVERS:
        raise ValueError(f"qp_solver must be one of {QP_SOLVERS}, got {solver!r}")
    observer = getattr(settings, "observer", "fixed")
    if observer not in OBSERVERS:
        raise ValueError(f"observer must be 'bank' or 'fixed', got {observer!r}")
    if hasattr(settings, "bank_memory"):
        require_int("bank_memory", settings.bank_memory)
    if not getattr(settings, "gain_tolerance", 0.0) < 1.0:
        raise ValueError(
            f"gain_tolerance must be < 1 (a relative half-width), got {settings.gain_tolerance!r}"
        )
    value = getattr(settings, "measurement_std", None)
    if value is not None and not (number_at_least(value, 0.0) and value > 0):
        raise ValueError(f"measurement_std must be > 0 um or None, got {value!r}")


def measurement_std(setting: float | None, task: ControlTask) -> float:
    """The sensor noise standard deviation (um) an observer assumes.

    ``setting`` if given, else the task's noise bound r as uniform noise, r / sqrt(3), at least
    0.05 um (an observer needs some measurement noise to stay well posed).
    """
    if setting is not None:
        return float(setting)
    return max(task.noise_bound_um / math.sqrt(3.0), 0.05)


def check_initial_voltage(settings: object, u_max: float) -> None:
    """Raise ValueError when an ``initial_voltage`` setting lies outside the drive range
    +-``u_max`` (V): the env refuses such a reset too."""
    voltage = getattr(settings, "initial_voltage", None)
    if voltage is not None and not abs(voltage) <= u_max:
        raise ValueError(
            f"initial_voltage must lie within the drive range +-{u_max:g} V, got {voltage!r}"
        )
