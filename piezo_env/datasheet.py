"""Datasheet values of the PI PICMA bender family.

The numbers are the manufacturer's catalogue values as publicly transcribed (tolerances about
+-20 %). Displacement and blocking force are quoted for the one-sided rated voltage of 30 V,
i.e. the 0..60 V differential drive around a 30 V bias.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from piezo_env.checks import require_number

__all__ = ["CATALOGUE", "BenderDatasheet", "get_datasheet"]


@dataclass(frozen=True)
class BenderDatasheet:
    """Datasheet of a clamped-free piezoelectric bimorph bender.

    Parameters
    ----------
    name : str
        Type designation, e.g. ``"PL140.10"``.
    length : float
        Overall ceramic length L (m).
    width : float
        Width W (m).
    thickness : float
        Total thickness T of the bimorph (m).
    free_length : float
        Free (unclamped) length of the cantilever (m).
    free_deflection : float
        Free tip deflection at the rated voltage, one side (m).
    blocking_force : float
        Blocking force at the rated voltage (N).
    capacitance_half : float
        Electrical capacitance of one half of the bimorph (F).
    resonance : float
        Unloaded first resonant frequency (Hz).
    rated_voltage : float
        One-sided rated voltage U_r at which deflection and force are quoted (V).
    """

    name: str
    length: float
    width: float
    thickness: float
    free_length: float
    free_deflection: float
    blocking_force: float
    capacitance_half: float
    resonance: float
    rated_voltage: float = 30.0

    def __post_init__(self) -> None:
        for field in fields(self):
            if field.name == "name":
                continue
            require_number(
                f"BenderDatasheet.{field.name}", getattr(self, field.name), low=0.0, low_open=True
            )
        if self.free_length > self.length:
            raise ValueError(
                f"free_length {self.free_length} m exceeds the ceramic length {self.length} m"
            )


def _mm(x: float) -> float:
    return x * 1e-3


CATALOGUE: dict[str, BenderDatasheet] = {
    sheet.name: sheet
    for sheet in (
        BenderDatasheet(
            "PL112.10", _mm(18), _mm(9.6), _mm(0.67), _mm(12), 100e-6, 2.1, 1.1e-6, 1800.0
        ),
        BenderDatasheet(
            "PL122.10", _mm(25), _mm(9.6), _mm(0.67), _mm(22), 310e-6, 1.25, 2.5e-6, 600.0
        ),
        BenderDatasheet(
            "PL127.10", _mm(31), _mm(9.6), _mm(0.67), _mm(27), 450e-6, 1.1, 3.4e-6, 420.0
        ),
        BenderDatasheet(
            "PL128.10", _mm(36), _mm(6.15), _mm(0.67), _mm(28), 450e-6, 0.55, 1.2e-6, 360.0
        ),
        BenderDatasheet(
            "PL140.10", _mm(45), _mm(11.0), _mm(0.55), _mm(40), 1000e-6, 0.5, 4.1e-6, 160.0
        ),
    )
}


def get_datasheet(bender: str | BenderDatasheet) -> BenderDatasheet:
    """Return a catalogue datasheet by name (``"PL140"`` or ``"PL140.10"``), or pass one through.

    Raises
    ------
    ValueError
        If the name is not in the catalogue; the message lists the valid names.
    """
    if isinstance(bender, BenderDatasheet):
        return bender
    if not isinstance(bender, str):
        raise ValueError(
            f"bender must be a catalogue name or a BenderDatasheet, got {type(bender).__name__}"
        )
    key = bender.strip().upper()
    for name, sheet in CATALOGUE.items():
        if key in (name, name.split(".")[0]):
            return sheet
    raise ValueError(
        f"unknown bender {bender!r}; choose one of {sorted(CATALOGUE)} "
        "(the '.10' suffix is optional) or pass a BenderDatasheet"
    )
