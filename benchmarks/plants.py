"""The plants of the benchmark: the nominal bender and the robustness plants.

Each plant is a function of the nominal bender's catalogue name that returns
``PiezoBender-v0`` keyword arguments: changes from the nominal bender the model was identified
on, derived from that bender's own datasheet. A controller is always built for the nominal task
and runs unchanged on every plant; every plant steps at the nominal bender's sample time
(:func:`sample_time`), which the runner passes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

__all__ = [
    "BENCH_CURRENT_MA",
    "BENCH_SENSOR_HZ",
    "BOX_CORNERS",
    "DEFAULT_BENDER",
    "DRAWN_PLANTS",
    "DRIFT",
    "EPISODE_S",
    "MONTE_CARLO",
    "MONTE_CARLO_REFERENCES",
    "NOMINAL_STROKE_UM",
    "PLANTS",
    "VERTICES",
    "sample_time",
    "stroke_um",
    "vertex_options",
]

DEFAULT_BENDER = "PL140"
"""The bender of ``piezo benchmark`` unless ``--bender`` names another."""

NOMINAL_STROKE_UM = 1000.0
"""One-sided stroke of the nominal PL140 (um), the reference amplitudes' scale: the references
of another bender are scaled by its stroke over this."""

EPISODE_S = 2.0
"""Length of a benchmark episode (s), at any sample time: 2000 steps at 1 ms."""


def sample_time(bender: str) -> float:
    """Sample time (s) of the benchmark of ``bender``: its default, :func:`piezo_env.default_dt`
    (1 ms for the PL140, 0.25 ms for the PL127). Every plant of the benchmark steps at it."""
    from piezo_env import default_dt

    return default_dt(bender)


def stroke_um(bender: str) -> float:
    """One-sided stroke of ``bender`` (um), its free deflection: the percentages' scale."""
    from piezo_env import get_datasheet

    return get_datasheet(bender).free_deflection * 1e6


def _tolerance_sheet(bender: str, scale: float) -> Any:
    """``bender`` whose stiffness and resonance are off by ``scale`` (blocking force as rated)."""
    from piezo_env import get_datasheet

    sheet = get_datasheet(bender)
    return dataclasses.replace(
        sheet,
        name=f"{sheet.name} (stiffness and resonance x{scale:g})",
        free_deflection=sheet.free_deflection / scale,
        resonance=sheet.resonance * scale,
    )


BENCH_CURRENT_MA = 50.0
"""Current limit of the ``bench`` plant's amplifier at the PL140 (mA).

The benchmark's sines are half-stroke (500 um, about 15 V of effective voltage quasi-statically):
at 50 mA (S = I / C_p = 6.1 V/ms on the PL140's 8.2 uF) the 50 Hz sine needs about 71 % of the
slew limit in steady state (the beam's gain there is 1.08 times the static one) and reaches it
in transients, as a full-stroke 50 Hz sine does at 100 mA (the ``amplifier=True`` default); the
100 Hz sine (beam gain 1.52) needs about 100 % of it. Another bender's current scales with its
capacitance and rated voltage, so that its slew limit in rated voltages per second (and so in
stroke per second on its references, which are the same fractions of its stroke) stays the
PL140's."""

BENCH_SENSOR_HZ = 20e3
"""First-order bandwidth of the ``bench`` plant's displacement sensor (Hz), no delay: its lag
of 8 us costs 0.25 % of the stroke at a full-stroke 50 Hz sine when uncompensated."""

DRIFT = {"piezo_coefficient": (1.0, 1.05), "stiffness": (1.0, 0.95), "duration": 2.0}
"""The ``drift`` plant: over the 2 s episode the piezoelectric coefficient rises 5 % and the
stiffness falls 5 % (static gain +10.5 %, first resonance -2.5 %), the direction a warming soft
PZT bender takes; compressed into one episode so that adaptation has to keep up."""


def _bench(bender: str) -> dict[str, Any]:
    """Amplifier, sensor, rate-dependent hysteresis and a bench's disturbances (the
    amplifier's output noise, the floor's vibration at the tip, the sensor's quantisation:
    :class:`piezo_env.Disturbance`'s typical values) at their documented values."""
    from piezo_env import Amplifier, Sensor, get_datasheet

    sheet = get_datasheet(bender)
    nominal = get_datasheet(DEFAULT_BENDER)
    capacitance = sheet.capacitance_half / nominal.capacitance_half
    current = BENCH_CURRENT_MA * capacitance * sheet.rated_voltage / nominal.rated_voltage
    return {
        "bender": bender,
        "amplifier": Amplifier(current_limit_mA=current),
        "sensor": Sensor(delay=0, bandwidth_Hz=BENCH_SENSOR_HZ),
        "hysteresis": "rate-dependent",
        "disturbance": True,
    }


def _drift(bender: str) -> dict[str, Any]:
    from piezo_env import Drift

    return {"bender": bender, "drift": Drift(**DRIFT)}


PLANTS: dict[str, Callable[[str], dict[str, Any]]] = {
    "nominal": lambda bender: {"bender": bender},
    "damping-0.01": lambda bender: {"bender": bender, "damping_ratio": 0.01},
    "damping-0.04": lambda bender: {"bender": bender, "damping_ratio": 0.04},
    "prandtl-ishlinskii": lambda bender: {"bender": bender, "hysteresis": "prandtl-ishlinskii"},
    "creep": lambda bender: {"bender": bender, "creep": True},
    "noise-3um": lambda bender: {"bender": bender, "noise_bound": 3.0},
    "stiffness+20%": lambda bender: {"bender": _tolerance_sheet(bender, 1.2)},
    "stiffness-20%": lambda bender: {"bender": _tolerance_sheet(bender, 0.8)},
    "random-plants": lambda bender: {"bender": bender, "randomize": True},
    "box-corners": lambda bender: {"bender": bender},
    "bench": _bench,
    "drift": _drift,
}
"""Plant name -> (nominal bender -> env keyword arguments): changes from the nominal bender.

``random-plants`` is the Monte Carlo table: each of ``BenchmarkConfig.draws`` episodes per
reference draws a new plant from the datasheet tolerances (``piezo_env.DomainRandomization``:
stiffness, blocking force and resonance +-20 %, damping 0.01-0.04, hysteresis +-30 %) with
its own seed; the report gives the distribution of each controller's RMSE over the draws.

``box-corners`` is the tolerance box's corners: one episode per reference on each of the
:data:`VERTICES` (:func:`vertex_options`), the report giving the distribution and the worst.

``bench`` is a real bench: a current-limited amplifier (:data:`BENCH_CURRENT_MA`), a 20 kHz
displacement sensor (:data:`BENCH_SENSOR_HZ`), rate-dependent Prandtl-Ishlinskii hysteresis
(loop 1.5x as wide at a full-stroke 50 Hz sine as quasi-static) and the disturbances a bench
has (:class:`piezo_env.Disturbance`: amplifier output noise, floor vibration at the tip, sensor
quantisation), each documented in :mod:`piezo_env`. A controller may know the amplifier's slew
limit (a datasheet value: ``env.unwrapped.slew_limit``); the rest it does not. ``drift`` moves
the piezoelectric coefficient and the stiffness during the episode (:data:`DRIFT`).
"""

MONTE_CARLO = "random-plants"

BOX_CORNERS = "box-corners"

DRAWN_PLANTS = (MONTE_CARLO, BOX_CORNERS)
"""The plants whose table is a distribution over plants (draws or vertices), one noise seed
each, on :data:`MONTE_CARLO_REFERENCES`."""

VERTICES = (
    (0.8, 0.8, 0.01),
    (0.8, 0.8, 0.04),
    (0.8, 1.2, 0.01),
    (0.8, 1.2, 0.04),
    (1.2, 0.8, 0.01),
    (1.2, 0.8, 0.04),
    (1.2, 1.2, 0.01),
    (1.2, 1.2, 0.04),
)
"""The corners of the datasheet's tolerance box that move the tip's response: (free
deflection, first resonance) relative to the datasheet's, and the first-mode damping ratio
(+-20 %, +-20 %, 0.01 / 0.04: ``piezo_env.DomainRandomization``'s box). The blocking force,
the fourth datasheet tolerance, moves the stiffness and the piezo moment together and leaves
the response as it is, so its 8 other corners repeat these."""


def vertex_options(bender: str, vertex: tuple[float, float, float]) -> dict[str, Any]:
    """``PiezoBender-v0`` keyword arguments of ``bender`` at one of the :data:`VERTICES`.

    No ``dt``: pass the nominal bender's, :func:`sample_time` (as the benchmark and the
    corners study do). Left out, the env's default dt would follow the vertex's resonance
    (the PL127 at resonance x0.8 gets 0.5 ms, not the nominal's 0.25 ms), and a controller
    made for the nominal bender is refused there (:func:`controllers.run_episode`)."""
    from piezo_env import get_datasheet

    deflection, resonance, damping = vertex
    sheet = get_datasheet(bender)
    sheet = dataclasses.replace(
        sheet,
        name=f"{sheet.name} (free deflection x{deflection:g}, resonance x{resonance:g})",
        free_deflection=sheet.free_deflection * deflection,
        resonance=sheet.resonance * resonance,
    )
    return {"bender": sheet, "damping_ratio": damping}


MONTE_CARLO_REFERENCES = ("sine-10Hz", "sine-50Hz", "multisine")
"""The references run on the random plants (when selected)."""
