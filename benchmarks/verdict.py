"""The benchmark's verdict: per reference, the best controller, its lead and what limits it.

The verdict is read on the nominal plant, or, when the run has none, on the first plant it
ran (:func:`verdict_plant`; the verdict says which). Oracle rows (``-oracle``: the controller
on the true plant's model) are yardsticks, not contenders. Two rows whose RMSE cannot be told apart
(:func:`benchmarks.cells.different`: within the 95 % intervals, or with one noise seed under
:data:`benchmarks.cells.TIE` relative) are a tie, and a tie bolds nobody.

What limits the best row, read from its cell's data in this order: the drive (more than
:data:`SATURATED` of the steps clipped); the model (RMSE well above the same reference on the
true plant's model, the oracle); the sensor noise (RMSE near the noise's own RMS, r / sqrt(3)
for noise uniform on [-r, r]); on a reference with jumps, the transients after them, with the
fraction of steps at the drive limit it measured; else the dynamics (at the oracle's level,
above the noise).
"""

from __future__ import annotations

import math
from typing import Any

from benchmarks.cells import TIE, aggregate, different
from benchmarks.references import REFERENCES
from benchmarks.runner import DRAWN_PLANTS, BenchmarkResult

__all__ = [
    "SATURATED",
    "cell_index",
    "headline_plants",
    "tie_rule",
    "verdict",
    "verdict_plant",
    "winners",
]

SATURATED = 0.05
"""Fraction of clipped steps above which the drive, not the controller, is called the limit."""

_AT_ORACLE = 1.25
"""RMSE within this factor of ``mpc-oracle``'s: the model is not what limits the row."""

_NEAR_NOISE = 2.0
"""RMSE within this factor of the sensor noise's RMS: the noise is what limits the row."""


def cell_index(result: BenchmarkResult) -> dict[tuple[str, str, str], dict[str, Any]]:
    """Cells (means over the noise seeds) by (plant, controller, reference), Monte Carlo draws
    left out."""
    return {
        (c["plant"], c["controller"], c["reference"]): c
        for c in aggregate(result.episodes)
        if c["plant"] not in DRAWN_PLANTS
    }


def winners(index: dict, plant: str, rows: list[str], ref: str) -> list[str]:
    """Rows with the best RMSE on ``ref`` (oracles aside): one, or those the best cannot be
    told apart from (:func:`benchmarks.cells.different`)."""
    cells = {
        r: index[(plant, r, ref)]
        for r in rows
        if (plant, r, ref) in index and not r.endswith("-oracle")
    }
    if not cells:
        return []
    best = min(cells.values(), key=lambda c: c["rmse_percent"])
    return [r for r, c in cells.items() if c is best or not different(c, best)]


def tie_rule(seeds: int) -> str:
    """One sentence: when two rows are called a tie in this run."""
    if seeds > 1:
        return (
            f"Each cell is the mean over {seeds} noise seeds; a lead within the 95 % intervals "
            "is called a tie and not bolded."
        )
    return (
        f"One noise seed per cell, so no interval: a lead under {100 * TIE:g} % is called a "
        "tie and not bolded (`--seeds N` gives intervals)."
    )


def verdict_plant(result: BenchmarkResult) -> str | None:
    """The plant the verdict reads: ``nominal`` when run, else the first plant of the run with
    cells of its own (None when only drawn plants ran: random plants, box corners)."""
    index = cell_index(result)
    plants = [p for p in result.config.plants if any(k[0] == p for k in index)]
    if "nominal" in plants:
        return "nominal"
    return plants[0] if plants else None


def headline_plants(result: BenchmarkResult, meta: dict[str, Any] | None = None) -> list[str]:
    """The plants the report opens with and the verdict reads: :func:`verdict_plant` (the
    paper's clean plant when run), then each plant that ran on a model identified on it
    (``meta["identify_on"]`` after its first: ``piezo benchmark --identify-on nominal,bench``
    gives the bench identified on the bench, as a user meets it)."""
    first = verdict_plant(result)
    if first is None:
        return []
    index = cell_index(result)
    own = list((meta or {}).get("identify_on") or [])[1:]
    return [first] + [
        p for p in own if p != first and any(k[0] == p for k in index)
    ]


def verdict(result: BenchmarkResult, meta: dict[str, Any] | None = None) -> list[str]:
    """Per reference of each headline plant, one Markdown line: the best row, its lead, what
    limits it.

    Parameters
    ----------
    result : BenchmarkResult
    meta : dict, optional
        The run's facts (:func:`benchmarks.report.write_benchmark`); its ``noise_bound_um``
        (sensor noise bound r, um) is the noise a row is compared with (without it, the
        nominal plant's: the env's default, :class:`piezo_env.TaskConfig`), and its
        ``identify_on`` names the plants that ran on their own model (:func:`headline_plants`).

    Returns
    -------
    list of str
        ``- REF: **`best`** (x %), L better than `next`; why`` per reference run on the
        verdict's plant (:func:`verdict_plant`), after a line naming that plant when it is not
        the nominal one; then, for each further headline plant, a line naming it and its own
        lines. A tie names every tied row and bolds none. Never empty: a run with only drawn
        plants gets one line saying where its ranking is.
    """
    plants = headline_plants(result, meta)
    if not plants:
        return [
            "- no verdict: only drawn plants ran "
            f"({', '.join(result.config.plants)}); their tables rank the rows over the draws"
        ]
    lines = []
    if plants[0] != "nominal":
        lines.append(
            f"- read on the plant `{plants[0]}`, the first this run ran (the nominal plant was "
            "not in --plants):"
        )
    lines += _plant_verdict(result, plants[0], meta)
    for plant in plants[1:]:
        lines.append(f"- on the plant `{plant}`, with the model identified on it:")
        lines += ["  " + line for line in _plant_verdict(result, plant, meta)]
    return lines


def _plant_verdict(result: BenchmarkResult, plant: str, meta: dict[str, Any] | None) -> list[str]:
    """The verdict's lines of one plant."""
    index = cell_index(result)
    rows = [r for r in result.config.rows if not r.endswith("-oracle")]
    noise = (meta or {}).get("noise_bound_um", _nominal_noise_bound())
    lines = []
    for ref in result.config.references:
        ranked = sorted(
            (index[(plant, r, ref)]["rmse_percent"], r) for r in rows if (plant, r, ref) in index
        )
        if not ranked:
            continue
        best_value, best = ranked[0]
        tied = winners(index, plant, rows, ref)
        rest = [(v, r) for v, r in ranked if r not in tied]
        if len(tied) > 1:
            head = f"tie between {', '.join(f'`{t}`' for t in tied)} ({best_value:.3f} %)"
        elif rest:
            head = f"**`{best}`** ({best_value:.3f} %)"
        else:
            head = f"`{best}` ({best_value:.3f} %), the only controller run"
        if rest:
            head += f", {_lead(rest[0][0] / best_value)} than `{rest[0][1]}`"
        why = _why(index, (plant, best, ref), 2.0 * result.config.stroke_um, noise)
        lines.append(f"- {ref}: {head}; {why}")
    if not lines:
        lines.append(f"- no verdict: no controller other than an oracle ran on `{plant}`")
    return lines


def _nominal_noise_bound() -> float:
    """Sensor noise bound of the nominal plant (um): it keeps the env's default."""
    from piezo_env import TaskConfig

    return float(TaskConfig().noise_bound)


def _lead(ratio: float) -> str:
    """A lead readable at any size: '3.2x better', or '4.1 % better' under 10 %."""
    return f"{ratio:.1f}x better" if ratio >= 1.1 else f"{100 * (ratio - 1):.1f} % better"


def _why(
    index: dict, key: tuple[str, str, str], full_stroke_um: float, noise_bound_um: float | None
) -> str:
    """What limits the best row's cell ``key`` (plant, row, reference), from its data: drive-,
    model-, noise-, jump- or dynamics-limited (one line)."""
    plant, _, ref = key
    cell = index[key]
    saturated = cell["saturated_fraction"]
    if saturated > SATURATED:
        return (
            f"drive-limited: {100 * saturated:.0f} % of the steps saturated, "
            "the amplifier's range sets the floor"
        )
    oracle = index.get((plant, "mpc-oracle", ref))
    ratio = None if oracle is None else cell["rmse_percent"] / oracle["rmse_percent"]
    if ratio is not None and ratio >= _AT_ORACLE:
        return (
            f"model-limited: {ratio:.1f}x `mpc-oracle`, which predicts with the true plant "
            "(and steers the tip behind a sensor)"
        )
    at_oracle = "" if ratio is None else f"; at the oracle's level ({ratio:.2f}x `mpc-oracle`)"
    times = None
    if noise_bound_um:
        noise_rms = noise_bound_um / math.sqrt(3.0)  # uniform on [-r, r]
        times = cell["rmse_percent"] / 100.0 * full_stroke_um / noise_rms
        noise_text = f"{times:.1f}x the sensor noise's RMS ({noise_rms:.2g} um)"
        if times < _NEAR_NOISE:
            return f"noise-limited: {noise_text}" + at_oracle
    if not REFERENCES[ref].smooth:
        return _jump_reason(cell) + at_oracle
    if times is None:
        return "no noise bound to compare it with" + at_oracle
    if ratio is not None:
        return f"dynamics-limited: {noise_text}" + at_oracle
    return (
        f"{times:.0f}x the sensor noise's RMS ({noise_rms:.2g} um): dynamics or model "
        "error sets it (run `mpc-oracle` beside it to tell which)"
    )


def _jump_reason(cell: dict[str, Any]) -> str:
    """Why a row's error on a reference with jumps is what it is, from its step figures and
    the fraction of its steps at the drive limit."""
    rise, overshoot = cell.get("rise_time_ms"), cell.get("overshoot_percent")
    saturated = f"{100 * cell['saturated_fraction']:.1f} % of the steps at the drive limit"
    if rise is None or overshoot is None:
        return f"jump-limited: the error sits in the transients after the jumps ({saturated})"
    return (
        f"jump-limited: the error sits in the transients after the jumps (rise {rise:.0f} ms, "
        f"overshoot {overshoot:.0f} %, {saturated})"
    )
