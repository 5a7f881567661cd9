"""The controllers' descriptions as Markdown tables a reader can scan.

Each row's ``describe()`` (settings, gains, margins, horizon, native code ...) becomes a
two-column table; the seeds of one trained recipe share one table with a column each. What a
table would only repeat is left to the JSON: the loop polynomials (drawn in ``pid_loops.png``)
and the native builds' keys and digests (one line per generated function here).
"""

from __future__ import annotations

from typing import Any

from benchmarks.rows import seed_groups
from benchmarks.runner import BenchmarkResult

__all__ = ["controller_tables", "loop_table"]

_LEFT_OUT = ("name", "stats", "loop")
"""Top-level keys a table does not show (the row's name, run statistics, loop coefficients)."""

_MAX_LIST = 8
"""Lists of scalars up to this length are shown inline; longer ones are left to the JSON."""

_LOOP_COLUMNS = {
    "kp": ("gains", "kp"),
    "ki": ("gains", "ki"),
    "kd": ("gains", "kd"),
    "gain margin (dB)": ("gain_margin_db",),
    "phase margin (deg)": ("phase_margin_deg",),
    "crossover (Hz)": ("crossover_hz",),
    "Ms": ("ms",),
    "bandwidth (Hz)": ("bandwidth_hz",),
}
"""Columns of the tuned-loop table -> where each sits in a PID description."""

_LOOP_KEYS = {".".join(path) for path in _LOOP_COLUMNS.values()}
"""Description keys the tuned-loop table shows (left out of the row's own table)."""


def _text(value: Any) -> str | None:
    """A scalar (or short list of scalars) as table text; None for what the table leaves out."""
    if isinstance(value, bool) or value is None or isinstance(value, (str, int)):
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    scalars = isinstance(value, (list, tuple)) and all(
        isinstance(v, (bool, int, float, str)) for v in value
    )
    if scalars and 0 < len(value) <= _MAX_LIST:
        return ", ".join(str(_text(v)) for v in value)
    return None


def _label(key: str) -> str:
    """A key as shown: a stroke says which one it is (percentages use the full, two-sided one)."""
    return f"{key} (one-sided)" if key.endswith("stroke_um") else key


def _native(builds: dict[str, Any]) -> list[tuple[str, str]]:
    """One line per generated function: which path ran and why (compiler and digest: JSON)."""
    pairs = []
    for name, build in builds.items():
        if isinstance(build, dict):
            path = build.get("path") or ("compiled" if build.get("compiled") else "not compiled")
            reason = build.get("reason")
            pairs.append((f"native.{name}", f"{path}: {reason}" if reason else str(path)))
    return pairs


def _pairs(description: dict[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """(key, text) of a description, nested dicts as ``a.b``."""
    pairs: list[tuple[str, str]] = []
    for key, value in description.items():
        name = f"{prefix}{key}"
        if not prefix and key in _LEFT_OUT:
            continue
        if not prefix and key == "native" and isinstance(value, dict):
            pairs += _native(value)
        elif isinstance(value, dict):
            pairs += _pairs(value, name + ".")
        elif (text := _text(value)) is not None:
            pairs.append((_label(name), text))
    return pairs


def _markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    return "\n".join([*lines, *("| " + " | ".join(row) + " |" for row in rows)])


def _table(description: dict[str, Any], shown_elsewhere: set[str]) -> str:
    """A row's description as a two-column table."""
    pairs = [[k, v] for k, v in _pairs(description) if k not in shown_elsewhere]
    return _markdown_table(["setting or fact", "value"], pairs)


def _seeds_table(names: list[str], descriptions: list[dict[str, Any]]) -> str:
    """The seeds of one recipe: what they share once, then what differs, a column per seed."""
    columns = [dict(_pairs(d)) for d in descriptions]
    keys = list(dict.fromkeys(k for c in columns for k in c))
    shared = [k for k in keys if len({c.get(k) for c in columns}) == 1]
    differ = [[k, *(c.get(k, "") for c in columns)] for k in keys if k not in shared]
    parts = [
        _markdown_table(["setting or fact", "every seed"], [[k, columns[0][k]] for k in shared])
    ]
    if differ:
        parts.append(_markdown_table(["differs by seed", *names], differ))
    return "\n\n".join(parts)


def controller_tables(result: BenchmarkResult) -> str:
    """Every controller's settings and derived facts (gains, margins, horizon) as tables.

    A tuned loop's gains and margins are left to :func:`loop_table`, which shows them side by
    side; the seeds of one trained recipe share one heading.
    """
    described = {name: d for name, d in result.controllers.items() if isinstance(d, dict)}
    groups = seed_groups(list(described))
    parts = []
    for name, description in described.items():
        recipe = next((g for g, members in groups.items() if name in members), None)
        if recipe is None:
            in_loop_table = _LOOP_KEYS if _is_loop(description) else set()
            parts.append(f"### `{name}`\n\n{_table(description, in_loop_table)}\n")
        elif groups[recipe][0] == name:  # the recipe's tables, once, where its first seed sits
            members = groups[recipe]
            tables = _seeds_table(members, [described[m] for m in members])
            parts.append(f"### `{recipe}` ({len(members)} seeds)\n\n{tables}\n")
    return "\n".join(parts)


def _is_loop(description: dict[str, Any]) -> bool:
    """Whether a description is a tuned feedback loop's (it gives margins)."""
    return "gain_margin_db" in description


def loop_table(result: BenchmarkResult) -> str:
    """Gains and margins of every tuned feedback loop side by side ('' when none was run)."""
    rows = {
        name: d for name, d in result.controllers.items() if isinstance(d, dict) and _is_loop(d)
    }
    if not rows:
        return ""

    def value(d: dict[str, Any], path: tuple[str, ...]) -> str:
        for key in path:
            d = d.get(key) if isinstance(d, dict) else None
        return "" if d is None else (_text(d) or "")

    cells = [
        [f"`{name}`", *(value(d, p) for p in _LOOP_COLUMNS.values())] for name, d in rows.items()
    ]
    return _markdown_table(["loop", *_LOOP_COLUMNS], cells)
