"""What changed between two benchmark runs (``piezo compare OLD.json NEW.json``).

Cells are matched by plant, controller, reference and draw (means over their noise seeds,
:mod:`benchmarks.cells`). A change is marked when it is beyond the run-to-run noise: outside
the combined 95 % intervals when both runs have several seeds, else more than
:data:`benchmarks.cells.TIE` relative. Cells only one run has are listed as added or removed.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from benchmarks.cells import KEYS, aggregate, different

__all__ = ["compare_files", "compare_runs", "load_run"]


def load_run(path: str | Path) -> dict[str, Any]:
    """A benchmark.json, checked enough to compare (ValueError names what is wrong)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable benchmark.json ({error})") from None
    if not isinstance(data, dict) or "episodes" not in data.get("results", {}):
        raise ValueError(f"{path}: no results.episodes: not a benchmark.json of piezo benchmark")
    return data


def _cells(data: dict[str, Any]) -> dict[tuple, dict[str, Any]]:
    return {tuple(c.get(k) for k in KEYS): c for c in aggregate(data["results"]["episodes"])}


def compare_runs(old: dict[str, Any], new: dict[str, Any]) -> tuple[str, int]:
    """A Markdown table of every cell's RMSE in both runs, and the number of marked changes."""
    before, after = _cells(old), _cells(new)
    lines = [
        "| plant | controller | reference | old RMSE % | new RMSE % | change | beyond noise |",
        "|---|---|---|---|---|---|---|",
    ]
    marked = 0
    for key in [*before, *(k for k in after if k not in before)]:
        label = " | ".join(str(k) for k in key[:3])
        label += f" (draw {key[3]})" if key[3] is not None else ""
        if key not in after or key not in before:
            state = "removed" if key not in after else "added"
            lines.append(f"| {label} | {_value(before.get(key))} | {_value(after.get(key))} | "
                         f"{state} | |")
            continue
        a, b = before[key], after[key]
        ratio = b["rmse_percent"] / a["rmse_percent"] if a["rmse_percent"] else 1.0
        change = 100.0 * (ratio - 1.0)
        beyond = different(a, b)
        marked += beyond
        lines.append(f"| {label} | {_value(a)} | {_value(b)} | {change:+.1f} % | "
                     f"{'**yes**' if beyond else ''} |")
    return "\n".join(lines), marked


def _value(cell: dict[str, Any] | None) -> str:
    if cell is None:
        return ""
    ci = cell.get("rmse_ci95_percent")
    return f"{cell['rmse_percent']:.3f}" + (f" +- {ci:.3f}" if ci is not None else "")


def compare_files(old_path: str | Path, new_path: str | Path) -> tuple[str, int]:
    """:func:`compare_runs` of two benchmark.json files."""
    return compare_runs(load_run(old_path), load_run(new_path))
