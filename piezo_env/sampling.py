"""The default sample time of a bender: the rule that keeps its first resonance well sampled.

A bender's first resonance f_1 is known only within its datasheet tolerance s (relative, the
resonance spread of :class:`~piezo_env.randomization.DomainRandomization`, 0.2), so the highest
resonance the sample time must serve is (1 + s) f_1. The default sample time is the largest
value of :data:`DT_LADDER` with

    4 (1 + s) f_1 dt <= 1,

i.e. the highest resonance in the tolerance box stays at or below a quarter of the sampling
rate (half the Nyquist frequency): the discrete model then resolves the resonance's phase, and
a controller acting on it has a few samples per period. PL140 (160 Hz): 1 ms; PL128 (360 Hz):
0.5 ms; PL122 (600 Hz) and PL127 (420 Hz): 0.25 ms; PL112 (1800 Hz): 0.1 ms.
"""

from __future__ import annotations

import warnings

from piezo_env.datasheet import BenderDatasheet, get_datasheet
from piezo_env.randomization import DomainRandomization

__all__ = [
    "DT_LADDER",
    "RESONANCE_SAMPLES",
    "default_dt",
    "highest_resonance",
    "warn_if_resonance_aliases",
]

DT_LADDER: tuple[float, ...] = (1e-3, 5e-4, 2.5e-4, 2e-4, 1e-4, 5e-5, 2.5e-5, 2e-5, 1e-5)
"""Sample times (s) the default is chosen from, largest first: sampling rates of 1, 2, 4 and 5
x 10^k kHz, each a whole fraction of 1 ms (so 2 s episodes and 0.1 s holds are whole numbers
of samples) and at most 2x apart (a bender never samples faster than twice what the rule asks),
from the env's 1 ms to the 100 kHz of fast nanopositioning loops."""

RESONANCE_SAMPLES = 4.0
"""Samples per period of the highest first resonance of the tolerance box, at least (-)."""


def highest_resonance(bender: str | BenderDatasheet) -> float:
    """The top of the first resonance's tolerance box, (1 + s) f_1 (Hz).

    ``s`` is the datasheet's resonance tolerance, ``DomainRandomization().resonance``.
    """
    sheet = get_datasheet(bender)
    return (1.0 + DomainRandomization().resonance) * sheet.resonance


def default_dt(bender: str | BenderDatasheet) -> float:
    """The default sample time (s) of ``bender``: the largest of :data:`DT_LADDER` with
    ``4 (1 + s) f_1 dt <= 1``.

    Parameters
    ----------
    bender : str or BenderDatasheet
        Catalogue name (``"PL140"`` ...) or a datasheet.

    Returns
    -------
    float
        Sample time (s), one of :data:`DT_LADDER` (1 ms for the PL140).

    Raises
    ------
    ValueError
        If the bender is unknown, or its resonance is so high that even the smallest ladder
        value (10 us) breaks the rule: then pass ``dt`` explicitly.
    """
    f_top = highest_resonance(bender)
    for dt in DT_LADDER:
        if RESONANCE_SAMPLES * f_top * dt <= 1.0:
            return dt
    raise ValueError(
        f"the first resonance of {get_datasheet(bender).name} reaches {f_top:g} Hz within its "
        f"tolerance, above a quarter of the fastest default rate ({1.0 / DT_LADDER[-1]:g} Hz); "
        f"pass dt explicitly (at most {1.0 / (RESONANCE_SAMPLES * f_top):.3g} s)"
    )


def warn_if_resonance_aliases(bender: str | BenderDatasheet, dt: float) -> bool:
    """Warn (UserWarning) when an explicit sample time puts the highest first resonance of the
    tolerance box above the Nyquist frequency 1 / (2 dt); returns whether it did.

    Such a dt is the user's choice and stays legal (the discrete model is exact at any dt),
    but the sampled bender then aliases its first mode: a controller sees it at a false
    frequency and cannot act on it, and the benchmark's robustness rows can diverge on the
    box's stiff corners. The message names the default dt, which keeps four samples per
    period of that resonance.
    """
    f_top = highest_resonance(bender)
    if 2.0 * f_top * dt <= 1.0:
        return False
    sheet = get_datasheet(bender)
    try:
        fix = f"the default for the {sheet.name} is dt = {default_dt(sheet):g} s"
    except ValueError:
        fix = f"a dt of at most {1.0 / (RESONANCE_SAMPLES * f_top):.3g} s keeps four samples"
    warnings.warn(
        f"dt = {dt:g} s samples the {sheet.name} at {1.0 / dt:g} Hz, but its first resonance "
        f"reaches {f_top:g} Hz within the datasheet's tolerance, above the Nyquist frequency "
        f"{0.5 / dt:g} Hz: the sampled bender aliases its first mode and a controller cannot "
        f"act on it; {fix}",
        UserWarning,
        stacklevel=_caller_level(),
    )
    return True


def _caller_level() -> int:
    """The ``stacklevel`` of the first frame outside this package, gymnasium and dataclasses'
    generated code: the warning then names the line of the user's that asked for the dt
    (``gym.make``, ``PiezoBenderEnv``, ``TaskConfig``), however deep the call."""
    import sys
    from pathlib import Path

    package = Path(__file__).resolve().parent
    frame, level = sys._getframe(1), 1  # the caller of this function: its warn is level 1
    while frame is not None:
        name = frame.f_code.co_filename
        path = Path(name)
        generated = name.startswith("<")  # a dataclass's __init__, exec'd code
        if not (generated or path.resolve().parent == package or "gymnasium" in path.parts):
            return level
        frame, level = frame.f_back, level + 1
    return level
