"""Records of the identification experiment as files: the bridge from the testbed to a bench.

A records folder holds one file per record and a manifest, ``records.json``::

    {"format": "piezo-records", "version": 1, "kind": "excitation" | "measured",
     "bender": "PL140.10", "dt": 0.001, "drive_range_V": [-30.0, 30.0], "seed": 0,
     "records": {"prbs": "prbs.csv", "rich": "rich.csv", "selection": "selection.csv",
                 "validation": "validation.csv"},
     "purposes": {"prbs": "step a: ...", ...}, "datasheet": {...}, "excitation": {...},
     "noise_bound_um": null}

- ``piezo excite`` (:func:`write_excitation`) writes the input records, ``time_s,voltage_V``,
  as CSV and NPZ: exactly the signals :func:`identification.identify` drives the simulated
  bender with for that bender, sample time and seed (:func:`identification.experiment.
  experiment_inputs`). The selection record, besides the PRBS, rich and validation records,
  is the held-out record of step e: it chooses the network's features and judges step e'.
- A bench (or ``piezo simulate --records``, :func:`write_measured`) plays them and writes the
  measured records, ``time_s,voltage_V,deflection_um``: ``voltage_V`` the voltage actually
  applied (the amplifier's monitor output, around the bias: -30..30 V for a PL140 driven
  0..60 V about 30 V), ``deflection_um`` the measured tip deflection; ``deflection_um[k]`` is
  read before ``voltage_V[k]`` is applied (the alignment of
  :func:`identification.experiment.collect`).
- :func:`read_records` reads and checks them; :func:`identification.identify_records` runs
  steps b-f on them.

A single long record (``"records": {"record": "run.csv"}``) is split by ``split`` =
FRACTION: its first FRACTION is the estimation record, used as the PRBS record of steps b, b'
and as the rich record of steps d, e, e' (without a two-level input the decoupling of the
linear part (Bai 2004) holds only approximately, so the ARX part starts from the best linear
approximation and step e' refines both together); the rest is held out, its first half the
selection record of step e, its second half the validation record of step f. The bench is not
at rest where a held-out part begins (vibration, hysteresis memory), so the models run free
from the start of the record and are scored on the held-out part only.

Every check runs before any work and refuses in one line naming the file and the line or
field (:class:`RecordsError`, a ``ValueError``).
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import math
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike

from identification.config import IdentificationConfig
from identification.experiment import RECORD_NAMES, RECORD_PURPOSES, measure, sample_time

__all__ = [
    "EXCITATION_FIELDS",
    "MANIFEST",
    "RECORDS_FORMAT",
    "TIME_TOLERANCE_S",
    "VOLTAGE_TOLERANCE_V",
    "Records",
    "RecordsError",
    "manifest_digest",
    "minimum_samples",
    "read_excitation",
    "read_manifest",
    "read_records",
    "records_from_arrays",
    "records_from_env",
    "write_excitation",
    "write_measured",
]

RECORDS_FORMAT = "piezo-records"
RECORDS_VERSION = 1
MANIFEST = "records.json"

INPUT_COLUMNS = ("time_s", "voltage_V")
MEASURED_COLUMNS = ("time_s", "voltage_V", "deflection_um")

TIME_TOLERANCE_S = 1.5e-6
"""Largest distance (s) of a time stamp from its place on the manifest's grid,
``t_0 + k dt``. Time stamps written with 6 decimals are each off by at most 0.5 us, so a step
by at most 1 us; the remaining 0.5 us cover the float arithmetic of a clock that sums its
steps over 1e6 samples (1e6 x 2.2e-16 x 1000 s). A hardware-clocked acquisition card stays on
its grid; a drift beyond this means the manifest's dt is not the card's rate. Within it the
manifest's dt wins: the time column is checked, never used."""

VOLTAGE_TOLERANCE_V = 1e-6
"""Voltages may exceed the manifest's drive range by this much (V): the rounding of a value
written with 6 decimals. A monitor reading beyond it means the drive range (or the bias
subtracted) is wrong."""

EXCITATION_FIELDS = (
    "prbs_amplitude",
    "prbs_clock",
    "rich_signal",
    "rich_amplitude",
    "rich_params",
    "validation_amplitude",
    "validation_hold",
)
"""The settings of :class:`IdentificationConfig` that make the input records; the manifest
carries them, so that the report describes the signals the bench was driven with."""


class RecordsError(ValueError):
    """A records folder or array that the identification refuses (one line: where and why)."""


@dataclass(frozen=True)
class Records:
    """The measured records of an identification and what is known of the bench.

    Attributes
    ----------
    records : dict
        Record name (:data:`identification.experiment.RECORD_NAMES`) -> ``(u, y)``: applied
        voltage (V) and measured deflection (um), ``y[k]`` before ``u[k]``.
    dt : float
        Sample time, s.
    drive_range_V : tuple of float
        Lowest and highest drive voltage, V; the network is scaled to it.
    bender : str
        The bender's name (a catalogue name, or the user's).
    datasheet : dict or None
        Its datasheet fields (:class:`piezo_env.BenderDatasheet`); a controller compares them
        with its env's before it runs the model.
    noise_bound_um : float or None
        The sensor's noise bound r (um, uniform +-r) when known: the report's noise floor.
    seed : int
        The identification seed the inputs were drawn with; it also seeds the training.
    plant : dict
        What is known of the plant behind the records (the env's hysteresis and options);
        empty for a bench.
    source : dict
        Where the records come from: ``{"kind": "env"}`` or ``{"kind": "records",
        "manifest": path, "manifest_sha256": digest}`` (and ``"split"``).
    shared : bool
        True when one record serves as both the PRBS and the rich record (a split record).
    lead_in : dict
        Record name -> samples at its start that the models run over from rest but that are
        not scored: a split record's held-out parts are the tail of the record from its start,
        since the bench was not at rest where they begin (vibration, hysteresis memory).
    """

    records: dict[str, tuple[np.ndarray, np.ndarray]]
    dt: float
    drive_range_V: tuple[float, float]
    bender: str
    datasheet: dict[str, Any] | None
    noise_bound_um: float | None
    seed: int = 0
    plant: dict[str, Any] = field(default_factory=dict)
    source: dict[str, Any] = field(default_factory=lambda: {"kind": "arrays"})
    shared: bool = False
    lead_in: dict[str, int] = field(default_factory=dict)

    @property
    def u_max(self) -> float:
        """Largest drive magnitude, V."""
        return float(max(abs(v) for v in self.drive_range_V))

    @property
    def stroke_um(self) -> float | None:
        """One-sided stroke (um): the datasheet's free deflection; None without a datasheet."""
        if self.datasheet is None:
            return None
        return float(self.datasheet["free_deflection"]) * 1e6


def minimum_samples(config: IdentificationConfig) -> int:
    """The fewest samples (per record) the identification accepts with ``config``'s orders.

    200, the floor of every record length of :class:`IdentificationConfig`, or 28 n for the
    largest order n if that is more: step b fits 2n parameters on three quarters of the PRBS
    record after n start-up samples, and asks at least ten equations per parameter, so
    ``3 N / 4 - n >= 20 n``.
    """
    return max(200, 28 * max(config.orders))


# -- from the environment ------------------------------------------------------------------


def records_from_env(env: gym.Env, inputs: Mapping[str, ArrayLike], seed: int) -> Records:
    """Drive ``env`` with the input records (:func:`identification.experiment.measure`) and
    return them with the env's facts (bender, datasheet, drive range, sensor noise bound)."""
    base = env.unwrapped
    plant = base.model
    measured = measure(env, inputs, seed)
    return Records(
        records=measured,
        dt=sample_time(env),
        drive_range_V=(float(env.action_space.low[0]), float(env.action_space.high[0])),
        bender=plant.name,
        datasheet=dataclasses.asdict(plant.params.datasheet),
        noise_bound_um=float(base.noise_bound),
        seed=int(seed),
        plant={"hysteresis": plant.hysteresis.name, "creep": plant.creep is not None},
        source={"kind": "env"},
    )


# -- from arrays ----------------------------------------------------------------------------


def records_from_arrays(
    records: Mapping[str, tuple[ArrayLike, ArrayLike]] | tuple[ArrayLike, ArrayLike],
    *,
    dt: float,
    drive_range_V: tuple[float, float],
    bender: str,
    config: IdentificationConfig,
    split: float | None = None,
    datasheet: dict[str, Any] | None = None,
    noise_bound_um: float | None = None,
    seed: int = 0,
    source: dict[str, Any] | None = None,
    where: Mapping[str, str] | None = None,
) -> Records:
    """Check measured arrays and make :class:`Records` of them.

    Parameters
    ----------
    records : mapping or tuple
        Record name -> ``(u, y)`` (V, um) for the four records of
        :data:`identification.experiment.RECORD_NAMES`, or one ``(u, y)`` pair (or a mapping
        with one entry) to be cut by ``split``.
    dt : float
        Sample time, s.
    drive_range_V : tuple of float
        Lowest and highest drive voltage, V.
    bender : str
        Bender name; a catalogue name gives the datasheet when ``datasheet`` is None.
    config : IdentificationConfig
        Its orders set the shortest record accepted (:func:`minimum_samples`).
    split : float, optional
        For one record: the fraction (0-1) that is the estimation record (see the module
        docstring for how the parts map onto the steps).
    datasheet, noise_bound_um, seed, source
        See :class:`Records`.
    where : mapping, optional
        Record name -> its file, for messages.

    Raises
    ------
    RecordsError
        A record missing, of another length in u and y, too short, not finite, or with
        voltages outside the drive range; a bad split.
    """
    where = dict(where or {})
    if isinstance(records, tuple):
        records = {"record": records}
    if not (_is_number(dt) and dt > 0):
        raise RecordsError(f"dt must be a positive number (s); got {dt!r}")
    if not (isinstance(bender, str) and bender.strip()):
        raise RecordsError(f"bender must name the bender, e.g. 'PL140'; got {bender!r}")
    low, high = _drive_range(drive_range_V, "drive_range_V")
    arrays = {}
    for name, (u, y) in records.items():
        label = where.get(name, f"record {name!r}")
        u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
        if u.ndim != 1 or u.shape != y.shape:
            raise RecordsError(
                f"{label}: voltage and deflection must be 1-D of one length; got shapes "
                f"{u.shape} and {y.shape}"
            )
        for column, values in (("voltage_V", u), ("deflection_um", y)):
            _check_finite(values, label, column, offset=0)
            if values.size and np.ptp(values) == 0.0:  # a drive left off, a sensor unplugged
                raise RecordsError(
                    f"{label}: column {column} holds one value ({values[0]:g}) in all "
                    f"{values.size} samples; a record to identify from must move both (check "
                    "the drive and the sensor's cable and range)"
                )
        _check_drive(u, low, high, label, offset=0)
        arrays[name] = (u, y)
    shared, lead_in = False, {}
    if split is not None:
        if len(arrays) != 1:
            raise RecordsError(
                f"split applies to a single record; got {len(arrays)} records "
                f"({', '.join(arrays)}): drop --split, or list one record"
            )
        ((name, (u, y)),) = arrays.items()
        arrays, lead_in = _split(u, y, split, where.get(name, f"record {name!r}"), config)
        shared = True
    else:
        _check_names(arrays)
    need = minimum_samples(config)
    for name, (u, _) in arrays.items():
        if len(u) - lead_in.get(name, 0) < need:
            label = where.get(name, f"record {name!r}")
            raise RecordsError(
                f"{label}: {len(u)} samples ({name} record), too short for ARX orders up to "
                f"{max(config.orders)}: the identification needs at least {need} per record; "
                "record longer"
            )
    if datasheet is None:
        datasheet = _catalogue_datasheet(bender)
    return Records(
        records=arrays,
        dt=float(dt),
        drive_range_V=(low, high),
        bender=bender,
        datasheet=datasheet,
        noise_bound_um=noise_bound_um,
        seed=int(seed),
        source=dict(source or {"kind": "arrays"}),
        shared=shared,
        lead_in=lead_in,
    )


def _check_names(arrays: Mapping[str, Any]) -> None:
    """The four records of :data:`identification.experiment.RECORD_NAMES`, no other."""
    if len(arrays) == 1 and not set(arrays) & set(RECORD_NAMES):
        raise RecordsError(
            f"one record ({next(iter(arrays))}) and no split: pass --split FRACTION (e.g. "
            "0.7) to cut it into estimation and validation, or list the records "
            + ", ".join(RECORD_NAMES)
        )
    missing = [name for name in RECORD_NAMES if name not in arrays]
    if missing:
        raise RecordsError(
            f"missing record(s) {', '.join(missing)}: the identification needs "
            + ", ".join(RECORD_NAMES)
            + " (piezo excite writes them all)"
        )
    unknown = sorted(set(arrays) - set(RECORD_NAMES))
    if unknown:
        raise RecordsError(f"unknown record(s) {unknown}; expected {', '.join(RECORD_NAMES)}")


def _split(
    u: np.ndarray, y: np.ndarray, fraction: float, label: str, config: IdentificationConfig
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, int]]:
    """Cut one record: estimation (PRBS and rich), then selection and validation halves, each
    held-out part with the record before it as its lead-in."""
    if not (isinstance(fraction, (int, float)) and 0.0 < fraction < 1.0):
        raise RecordsError(f"split must be a fraction between 0 and 1 (e.g. 0.7); got {fraction!r}")
    n = len(u)
    cut = round(fraction * n)
    half = cut + (n - cut) // 2
    need = minimum_samples(config)
    sizes = {"estimation": cut, "selection": half - cut, "validation": n - half}
    short = {k: v for k, v in sizes.items() if v < need}
    if short:
        raise RecordsError(
            f"{label}: {n} samples split at {fraction:g} gives "
            + ", ".join(f"{k} {v}" for k, v in sizes.items())
            + f" samples; each part needs at least {need}: record longer or move the split"
        )
    estimation = (u[:cut], y[:cut])
    records = {
        "prbs": estimation,
        "rich": estimation,
        "selection": (u[:half], y[:half]),
        "validation": (u, y),
    }
    return records, {"selection": cut, "validation": half}


def _catalogue_datasheet(bender: str) -> dict[str, Any] | None:
    from piezo_env import CATALOGUE, get_datasheet

    key = bender.strip().upper()
    if not any(key in (name, name.split(".")[0]) for name in CATALOGUE):
        return None
    return dataclasses.asdict(get_datasheet(key))


# -- files ----------------------------------------------------------------------------------


def manifest_digest(path: str | Path) -> str:
    """SHA-256 of a manifest file (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_excitation(
    out: str | Path, config: IdentificationConfig, *, bender: str, dt: float
) -> list[Path]:
    """Write the input records of the identification of ``bender`` at ``dt`` (s) into ``out``.

    Each record of :func:`identification.experiment.experiment_inputs` as ``NAME.csv``
    (``time_s,voltage_V``) and ``NAME.npz`` (the same arrays), and the manifest
    ``records.json``. ``config.seed`` draws them; the voltages are written with 17 significant
    digits, so the CSV holds exactly the signals :func:`identification.identify` uses.

    Returns
    -------
    list of pathlib.Path
        The files written, the manifest last.
    """
    from identification.experiment import experiment_inputs
    from piezo_env import get_datasheet

    sheet = get_datasheet(bender)
    config = config.at_sample_time(dt)
    inputs = experiment_inputs(config, dt)
    out = Path(out)
    paths = []
    for name, u in inputs.items():
        paths += _write_record(out, name, {"time_s": _times(len(u), dt), "voltage_V": u})
    u_max = float(sheet.rated_voltage)
    manifest = {
        "format": RECORDS_FORMAT,
        "version": RECORDS_VERSION,
        "kind": "excitation",
        "bender": sheet.name,
        "dt": float(dt),
        "drive_range_V": [-u_max, u_max],
        "seed": int(config.seed),
        "records": {name: f"{name}.csv" for name in inputs},
        "purposes": dict(RECORD_PURPOSES),
        "columns": {
            "time_s": "time of the sample, s, on the grid k dt",
            "voltage_V": "drive voltage to apply at that time, V, around the amplifier's bias",
        },
        "measure": (
            "play each record from rest at dt; write NAME.csv with time_s,voltage_V,"
            "deflection_um: the applied voltage (amplifier monitor, bias subtracted) and the "
            "deflection read just before each voltage is applied; then list them in a "
            "records.json like this one with kind 'measured' and your sensor's noise_bound_um"
        ),
        "noise_bound_um": None,
        "datasheet": dataclasses.asdict(sheet),
        "excitation": {name: getattr(config, name) for name in EXCITATION_FIELDS},
    }
    return [*paths, _write_manifest(out, manifest)]


def write_measured(
    out: str | Path, records: Records, *, excitation: Path | None = None
) -> list[Path]:
    """Write measured records (``NAME.csv`` with ``time_s,voltage_V,deflection_um`` and
    ``NAME.npz``) and their manifest into ``out``, as a bench would.

    ``excitation``: the manifest of the input records played (its path and digest are
    recorded, and its excitation settings carried over).

    Returns
    -------
    list of pathlib.Path
        The files written, the manifest last.
    """
    out = Path(out)
    paths = []
    for name, (u, y) in records.records.items():
        columns = {"time_s": _times(len(u), records.dt), "voltage_V": u, "deflection_um": y}
        paths += _write_record(out, name, columns)
    manifest: dict[str, Any] = {
        "format": RECORDS_FORMAT,
        "version": RECORDS_VERSION,
        "kind": "measured",
        "bender": records.bender,
        "dt": records.dt,
        "drive_range_V": list(records.drive_range_V),
        "seed": records.seed,
        "records": {name: f"{name}.csv" for name in records.records},
        "purposes": {name: RECORD_PURPOSES[name] for name in records.records},
        "noise_bound_um": records.noise_bound_um,
        "datasheet": records.datasheet,
        "plant": records.plant,
    }
    if excitation is not None:
        source = json.loads(excitation.read_text(encoding="utf-8"))
        manifest["excitation"] = source.get("excitation")
        manifest["excitation_manifest"] = {
            "path": str(excitation.resolve()),
            "sha256": manifest_digest(excitation),
        }
    return [*paths, _write_manifest(out, manifest)]


def _times(n: int, dt: float) -> np.ndarray:
    return np.arange(n) * dt


def _write_record(out: Path, name: str, columns: dict[str, np.ndarray]) -> list[Path]:
    """``NAME.csv`` (time with 9 decimals, the rest with 17 significant digits: exact) and
    ``NAME.npz``."""
    out.mkdir(parents=True, exist_ok=True)
    csv_path, npz_path = out / f"{name}.csv", out / f"{name}.npz"
    header = ",".join(columns)
    table = np.column_stack(list(columns.values()))
    formats = ["%.9f"] + ["%.17g"] * (len(columns) - 1)
    np.savetxt(csv_path, table, fmt=formats, delimiter=",", header=header, comments="")
    with npz_path.open("wb") as handle:
        np.savez(handle, **columns)
    return [csv_path, npz_path]


def _write_manifest(out: Path, manifest: dict[str, Any]) -> Path:
    path = out / MANIFEST
    path.write_text(json.dumps(manifest, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path


def read_records(
    folder: str | Path, config: IdentificationConfig, *, split: float | None = None
) -> Records:
    """Read and check the measured records listed in ``folder/records.json``.

    Parameters
    ----------
    folder : str or path-like
        A folder holding ``records.json`` and the files it lists (CSV with the header
        ``time_s,voltage_V,deflection_um``, in any column order, UTF-8 with or without a BOM,
        LF or CRLF line ends; or NPZ with those arrays).
    config : IdentificationConfig
        Its orders set the shortest record accepted.
    split : float, optional
        For a manifest with a single record: the estimation fraction.

    Returns
    -------
    Records
        With ``source`` naming the manifest and its SHA-256.

    Raises
    ------
    RecordsError
        One line naming the file and the line or field: a missing manifest, field, record or
        column; a dt or drive range that is not a number; a time column that decreases, leaves
        the manifest's grid by more than :data:`TIME_TOLERANCE_S` or steps by another dt; a
        value that is not a finite number; voltages outside the drive range; a record too short.
    """
    folder = Path(folder)
    path = folder / MANIFEST
    manifest = _read_manifest(path)
    if manifest.get("kind") == "excitation":
        raise RecordsError(
            f"{path}: field 'kind' is 'excitation': these are the inputs to play, not "
            "measurements; play them on the bench (or piezo simulate --records) and identify "
            "from the measured folder"
        )
    dt = _positive(manifest, "dt", path)
    low, high = _drive_range(manifest.get("drive_range_V"), f"{path}: field 'drive_range_V'")
    listed = manifest["records"]
    arrays, where = {}, {}
    for name, file in listed.items():
        record = _listed(folder, path, name, file)
        columns, offset = _read_columns(record)
        _check_time(columns["time_s"], dt, record, path, offset)
        arrays[name] = (columns["voltage_V"], columns["deflection_um"])
        where[name] = str(record)
        _check_drive(columns["voltage_V"], low, high, str(record), offset=offset)
    noise = manifest.get("noise_bound_um")
    if noise is not None and not (_is_number(noise) and noise >= 0):
        raise RecordsError(f"{path}: field 'noise_bound_um' must be a number >= 0 (um) or null")
    source = {
        "kind": "records",
        "manifest": str(path.resolve()),
        "manifest_sha256": manifest_digest(path),
    }
    if split is not None:
        source["split"] = split
    try:
        records = records_from_arrays(
            arrays,
            dt=dt,
            drive_range_V=(low, high),
            bender=manifest["bender"],
            config=config,
            split=split,
            datasheet=manifest.get("datasheet"),
            noise_bound_um=None if noise is None else float(noise),
            seed=int(manifest.get("seed", 0)),
            source=source,
            where=where,
        )
    except RecordsError as error:  # what the listed records hold together: the manifest's
        if str(error).startswith(str(folder)):
            raise
        raise RecordsError(f"{path}: {error}") from None
    plant = manifest.get("plant") or {}
    return dataclasses.replace(records, plant=dict(plant))


def read_excitation(folder: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and check the input records of ``folder/records.json`` (``time_s,voltage_V``).

    Returns
    -------
    manifest : dict
        The manifest.
    inputs : dict of numpy.ndarray
        Record name -> drive voltage, V.

    Raises
    ------
    RecordsError
        As :func:`read_records`, for the columns of an input record.
    """
    folder = Path(folder)
    path = folder / MANIFEST
    manifest = _read_manifest(path)
    dt = _positive(manifest, "dt", path)
    low, high = _drive_range(manifest.get("drive_range_V"), f"{path}: field 'drive_range_V'")
    inputs = {}
    for name, file in manifest["records"].items():
        record = _listed(folder, path, name, file)
        columns, offset = _read_columns(record, INPUT_COLUMNS)
        _check_time(columns["time_s"], dt, record, path, offset)
        _check_drive(columns["voltage_V"], low, high, str(record), offset=offset)
        inputs[name] = columns["voltage_V"]
    return manifest, inputs


def _listed(folder: Path, manifest: Path, name: str, file: Any) -> Path:
    """The file of record ``name``, which must exist."""
    if not isinstance(file, str) or not file:
        raise RecordsError(f"{manifest}: field 'records.{name}' must be a file name")
    record = folder / file
    if not record.is_file():
        raise RecordsError(f"{record}: missing (listed as record {name!r} in {manifest})")
    return record


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """The checked manifest of a records folder (``records.json``)."""
    return _read_manifest(Path(folder) / MANIFEST)


def _read_manifest(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise RecordsError(
            f"{path}: missing; a records folder holds records.json listing its records "
            "(piezo excite writes one)"
        )
    try:
        manifest = json.loads(path.read_text(encoding="utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise RecordsError(f"{path}: not valid JSON: {error}") from None
    if not isinstance(manifest, dict):
        raise RecordsError(f"{path}: expected a JSON object")
    for key in ("bender", "dt", "drive_range_V", "records"):
        if key not in manifest:
            raise RecordsError(f"{path}: missing field {key!r}")
    if not isinstance(manifest["records"], dict) or not manifest["records"]:
        raise RecordsError(f"{path}: field 'records' must map record names to files")
    bender = manifest["bender"]
    if not (isinstance(bender, str) and bender.strip()):
        raise RecordsError(
            f"{path}: field 'bender' must name the bender, e.g. \"PL140\"; got {bender!r}"
        )
    seed = manifest.get("seed", 0)
    if type(seed) is not int or seed < 0:
        raise RecordsError(f"{path}: field 'seed' must be a whole number >= 0; got {seed!r}")
    datasheet = manifest.get("datasheet")
    if datasheet is not None and not (
        isinstance(datasheet, dict) and _is_number(datasheet.get("free_deflection"))
    ):
        raise RecordsError(
            f"{path}: field 'datasheet' must be an object with 'free_deflection', a number (m), "
            f"or null; got {datasheet!r}"
        )
    plant = manifest.get("plant")
    if plant is not None and not isinstance(plant, dict):
        raise RecordsError(
            f"{path}: field 'plant' must be an object (what the records' plant was) or null; "
            f"got {plant!r}"
        )
    return manifest


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _positive(manifest: dict[str, Any], key: str, path: Path) -> float:
    value = manifest[key]
    if not (_is_number(value) and value > 0):
        raise RecordsError(f"{path}: field {key!r} must be a positive number; got {value!r}")
    return float(value)


def _drive_range(value: Any, label: str) -> tuple[float, float]:
    if not (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(_is_number(v) for v in value)
        and value[0] < value[1]
    ):
        raise RecordsError(f"{label} must be [lowest, highest] volts; got {value!r}")
    return float(value[0]), float(value[1])


def _read_columns(
    path: Path, names: tuple[str, ...] = MEASURED_COLUMNS
) -> tuple[dict[str, np.ndarray], int]:
    """The columns ``names`` of a record, and the offset from array index to the line number
    (2 for a CSV: the header is line 1; 0 for an NPZ, whose messages name the index)."""
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = [c for c in names if c not in data.files]
                if missing:
                    raise RecordsError(f"{path}: missing array(s) {', '.join(missing)}")
                columns = {c: np.asarray(data[c], dtype=float) for c in names}
        except RecordsError:
            raise
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
            raise RecordsError(
                f"{path}: not an NPZ of numeric arrays {', '.join(names)} ({error})"
            ) from None
        for column, values in columns.items():
            if values.shape != columns["time_s"].shape or values.ndim != 1:
                raise RecordsError(f"{path}: array {column} must be 1-D, as long as time_s")
            _check_finite(values, str(path), column, offset=0)
        return columns, 0
    try:
        with path.open(encoding="utf-8-sig", newline="") as handle:
            rows = list(csv.reader(handle))
    except UnicodeDecodeError:
        data = path.read_bytes()
        try:  # the whole file at once, for the offset of the first bad byte in it
            data.decode("utf-8")
            start = 0
        except UnicodeDecodeError as error:
            start = error.start
        line = data[:start].count(b"\n") + 1
        raise RecordsError(
            f"{path}, line {line}: not UTF-8 text (byte {data[start]:#04x}); save the record as "
            "UTF-8 CSV"
        ) from None
    if not rows:
        raise RecordsError(f"{path}: empty; expected the header {','.join(names)}")
    header = [cell.strip() for cell in rows[0]]
    missing = [c for c in names if c not in header]
    if missing:
        raise RecordsError(
            f"{path}, line 1: missing column(s) {', '.join(missing)}; the header must name "
            f"{','.join(names)} (got {','.join(header)})"
        )
    body = rows[1:]
    while body and not any(cell.strip() for cell in body[-1]):
        body.pop()  # a blank last line
    index = [header.index(c) for c in names]
    columns = {}
    for column, i in zip(names, index, strict=True):
        columns[column] = _parse_column(body, i, path, column)
        _check_finite(columns[column], str(path), column, offset=2)
    return columns, 2


def _parse_column(rows: list[list[str]], i: int, path: Path, column: str) -> np.ndarray:
    try:
        return np.array([row[i] for row in rows], dtype=float)
    except (ValueError, IndexError):
        for k, row in enumerate(rows):
            try:
                float(row[i])
            except (ValueError, IndexError):
                cell = row[i] if i < len(row) else "nothing"
                raise RecordsError(
                    f"{path}, line {k + 2}: column {column} holds {cell!r}, not a number"
                ) from None
        raise


def _where(k: int, offset: int) -> str:
    """Sample ``k`` as a reader finds it: a CSV's line (``offset`` 2), an array's index (0)."""
    return f"line {k + offset}" if offset else f"sample {k}"


def _check_finite(values: np.ndarray, label: str, column: str, *, offset: int) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        k = int(bad[0])
        where = _where(k, offset)
        raise RecordsError(
            f"{label}, {where}: column {column} is {float(values[k])!r}; every value must be a "
            f"finite number ({bad.size} are not)"
        )


def _check_drive(u: np.ndarray, low: float, high: float, label: str, *, offset: int) -> None:
    bad = np.flatnonzero((u < low - VOLTAGE_TOLERANCE_V) | (u > high + VOLTAGE_TOLERANCE_V))
    if bad.size:
        k = int(bad[0])
        where = _where(k, offset)
        raise RecordsError(
            f"{label}, {where}: voltage_V {u[k]:g} V is outside the drive range "
            f"[{low:g}, {high:g}] V ({bad.size} samples are); subtract the amplifier's bias, "
            "or correct drive_range_V in the manifest"
        )


def _check_time(t: np.ndarray, dt: float, record: Path, manifest: Path, offset: int) -> None:
    """The time column must increase and stay within :data:`TIME_TOLERANCE_S` of
    ``t_0 + k dt``, dt the manifest's: a column that steps evenly by another dt is a dt that
    disagrees with the manifest; one with an uneven step (a lost or repeated sample, a
    software clock) is not uniform."""
    steps = np.diff(t)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise RecordsError(
            f"{record}, {_where(k, offset)}: time_s {float(t[k])!r} s does not increase (previous "
            f"{float(t[k - 1])!r} s); the records must be sampled in time order"
        )
    if t.size < 2:
        return
    typical = float(np.median(steps))
    uneven = np.flatnonzero(np.abs(steps - typical) > TIME_TOLERANCE_S)
    off = np.abs(t - t[0] - np.arange(t.size) * dt)
    if abs(typical - dt) > TIME_TOLERANCE_S or (not uneven.size and off.max() > TIME_TOLERANCE_S):
        step = typical if uneven.size else (t[-1] - t[0]) / (t.size - 1)
        raise RecordsError(
            f"{record}: time_s steps by {step:.9g} s but {manifest} field 'dt' says {dt:.9g} s "
            f"(tolerance {TIME_TOLERANCE_S * 1e6:g} us per sample from t_0 + k dt); write the "
            "acquisition's sample time as dt"
        )
    if uneven.size:
        k = int(uneven[0]) + 1
        raise RecordsError(
            f"{record}, {_where(k, offset)}: time_s {float(t[k])!r} s is {steps[k - 1]:.9g} s "
            f"after the previous sample, not dt = {dt:g} s (tolerance "
            f"{TIME_TOLERANCE_S * 1e6:g} us): the samples are not uniform (a lost or repeated "
            "sample?); record on a fixed clock"
        )
