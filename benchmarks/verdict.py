"""The benchmark's verdict: per reference, the best controller, its lead and what limits it.

The verdict is read on the nominal plant. Oracle rows (``-oracle``: the controller on the true
plant's model) are yardsticks, not contenders. Two rows whose RMSE cannot be told apart
(:func:`benchmarks.cells.different`: within the 95 % intervals, or with one noise seed under
:data:`benchmarks.cells.TIE` relative) are a tie, and a tie bolds nobody.

What limits the best row, in this order of evidence: the drive (more than
:data:`SATURATED` of the steps clipped); the oracle (the same reference on the true plant's
model: near it, the floor is not the model); the sensor noise (RMSE against the noise's own RMS,
r / sqrt(3) for noise uniform on [-r, r]); on a reference with jumps, the transients after
them.
"""

from __future__ import annotations

import math
from typing import Any

from benchmarks.cells import TIE, aggregate, different
from benchmarks.references import REFERENCES
from benchmarks.runner import DRAWN_PLANTS, BenchmarkResult

__all__ = ["SATURATED", "cell_index", "tie_rule", "verdict", "winners"]

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


def verdict(result: BenchmarkResult, meta: dict[str, Any] | None = None) -> list[str]:
    """Per nominal reference, one Markdown line: the best row, its lead, what limits it.

    Parameters
    ----------
    result : BenchmarkResult
    meta : dict, optional
        The run's facts (:func:`benchmarks.report.write_benchmark`); its ``noise_bound_um``
        (sensor noise bound r, um) is the noise a row without an oracle is compared with.
        Without it, the nominal plant's: the env's default (:class:`piezo_env.TaskConfig`).

    Returns
    -------
    list of str
        ``- REF: **`best`** (x %), L better than `next`; why`` per reference run on the
        nominal plant; a tie names every tied row and bolds none.
    """
    index = cell_index(result)
    rows = [r for r in result.config.rows if not r.endswith("-oracle")]
    noise = (meta or {}).get("noise_bound_um", _nominal_noise_bound())
    lines = []
    for ref in result.config.references:
        ranked = sorted(
            (index[("nominal", r, ref)]["rmse_percent"], r)
            for r in rows
            if ("nominal", r, ref) in index
        )
        if not ranked:
            continue
        best_value, best = ranked[0]
        tied = winners(index, "nominal", rows, ref)
        rest = [(v, r) for v, r in ranked if r not in tied]
        if len(tied) > 1:
            head = f"tie between {', '.join(f'`{t}`' for t in tied)} ({best_value:.3f} %)"
        elif rest:
            head = f"**`{best}`** ({best_value:.3f} %)"
        else:
            head = f"`{best}` ({best_value:.3f} %), the only controller run"
        if rest:
            head += f", {_lead(rest[0][0] / best_value)} than `{rest[0][1]}`"
        why = _why(index, best, ref, 2.0 * result.config.stroke_um, noise)
        lines.append(f"- {ref}: {head}; {why}")
    return lines


def _nominal_noise_bound() -> float:
    """Sensor noise bound of the nominal plant (um): it keeps the env's default."""
    from piezo_env import TaskConfig

    return float(TaskConfig().noise_bound)


def _lead(ratio: float) -> str:
    """A lead readable at any size: '3.2x better', or '4.1 % better' under 10 %."""
    return f"{ratio:.1f}x better" if ratio >= 1.1 else f"{100 * (ratio - 1):.1f} % better"


def _why(
    index: dict, row: str, ref: str, full_stroke_um: float, noise_bound_um: float | None
) -> str:
    """What limits the best row on ``ref``: drive-, model-, noise- or jump-limited (one line)."""
    cell = index[("nominal", row, ref)]
    if cell["saturated_fraction"] > SATURATED:
        return (
            f"drive-limited: {100 * cell['saturated_fraction']:.0f} % of the steps saturated, "
            "the amplifier's range sets the floor"
        )
    oracle = index.get(("nominal", "mpc-oracle", ref))
    smooth = REFERENCES[ref].smooth
    if oracle is not None:
        ratio = cell["rmse_percent"] / oracle["rmse_percent"]
        if ratio >= _AT_ORACLE:
            return f"model-limited: {ratio:.1f}x `mpc-oracle`, which predicts with the true plant"
        if not smooth:
            return (
                f"jump-limited: at the oracle's level ({ratio:.2f}x `mpc-oracle`), a jump "
                "takes several samples at the drive limit"
            )
        return f"noise-limited: at the oracle's level ({ratio:.2f}x `mpc-oracle`)"
    if not smooth:
        return _jump_reason(cell)
    if noise_bound_um:
        noise_rms = noise_bound_um / math.sqrt(3.0)  # uniform on [-r, r]
        times = cell["rmse_percent"] / 100.0 * full_stroke_um / noise_rms
        if times < _NEAR_NOISE:
            return f"noise-limited: {times:.1f}x the sensor noise's RMS ({noise_rms:.2g} um)"
        return (
            f"{times:.0f}x the sensor noise's RMS ({noise_rms:.2g} um): dynamics or model "
            "error sets it (run `mpc-oracle` beside it to tell which)"
        )
    return "no oracle row or noise bound to compare it with"


def _jump_reason(cell: dict[str, Any]) -> str:
    """Why a row's error on a reference with jumps is what it is, from its step figures."""
    rise, overshoot = cell.get("rise_time_ms"), cell.get("overshoot_percent")
    if rise is None or overshoot is None:
        return "jump-limited: the error sits in the transients after the jumps"
    return (
        f"jump-limited: the error sits in the transients after the jumps (rise {rise:.0f} ms, "
        f"overshoot {overshoot:.0f} %; run `mpc-oracle` beside it to see the floor)"
    )
