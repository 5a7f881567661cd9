"""Argument checks written once: every package validates its settings with these.

Each check raises ``ValueError`` naming the argument, what it must be and what it got, and
returns the value as a plain Python number so that a numpy integer or float passes unchanged
in value. A ``bool`` is never a number here (``True`` is not a count).
"""

from __future__ import annotations

import math
import numbers

__all__ = ["require_int", "require_number"]


def require_int(name: str, value: object, *, minimum: int = 1) -> int:
    """``value`` as an ``int``, if it is an integer (not a bool) >= ``minimum``.

    Parameters
    ----------
    name : str
        Argument name, for the message.
    value : object
        What the caller passed.
    minimum : int
        Smallest allowed value.

    Raises
    ------
    ValueError
        If ``value`` is not an integer >= ``minimum``.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def require_number(
    name: str,
    value: object,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """``value`` as a ``float``, if it is a finite real number (not a bool) in range.

    Parameters
    ----------
    name : str
        Argument name, for the message.
    value : object
        What the caller passed.
    low, high : float or None
        Bounds (inclusive unless ``low_open`` or ``high_open``); None: unbounded on that side.
    low_open : bool
        Exclude ``low`` itself (``> low`` instead of ``>= low``).
    high_open : bool
        Exclude ``high`` itself (``< high`` instead of ``<= high``).

    Raises
    ------
    ValueError
        If ``value`` is not a finite number inside the range.
    """
    ok = (
        not isinstance(value, bool)
        and isinstance(value, numbers.Real)
        and math.isfinite(float(value))
    )
    if ok and low is not None:
        ok = float(value) > low if low_open else float(value) >= low
    if ok and high is not None:
        ok = float(value) < high if high_open else float(value) <= high
    if not ok:
        parts = []
        if low is not None:
            parts.append(f"{'>' if low_open else '>='} {low:g}")
        if high is not None:
            parts.append(f"{'<' if high_open else '<='} {high:g}")
        bound = f" {' and '.join(parts)}" if parts else ""
        raise ValueError(f"{name} must be a finite number{bound}, got {value!r}")
    return float(value)
