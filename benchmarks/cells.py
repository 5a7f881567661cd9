"""Table cells from episodes: every metric averaged over the seeds, with a 95 % interval.

One cell is one (plant, controller, reference) and, on the random plants, one draw. Its N
episodes are its noise seeds (``piezo benchmark --seeds``) times, for a row built on the
identified model, its identification seeds (``--identification-seeds``: each reruns the
identification on other data, so it varies the model as the noise seeds vary the sensor
noise). The cell holds the mean of every numeric metric and ``rmse_ci95_percent``, the
half-width of the 95 % confidence interval of the mean RMSE (Student's t with N - 1 degrees of
freedom, the N episodes taken as independent draws); with one episode there is no interval
(None). Wherever the project prints "mean +- x", x is this half-width.

Two cells are told apart only when their difference exceeds the combined half-widths (with
one seed: more than :data:`TIE` relative); otherwise they are a tie, and nothing is bolded.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["KEYS", "TIE", "aggregate", "ci95_half_width", "different"]

KEYS = ("plant", "controller", "reference", "draw")
"""What names a cell (``draw`` only on the random plants)."""

TIE = 0.02
"""Relative RMSE difference under which two single-seed cells are called a tie."""


def ci95_half_width(values: Any) -> float | None:
    """Half-width of the 95 % confidence interval of the mean of ``values`` (Student's t with
    n - 1 degrees of freedom); None for fewer than two values."""
    import scipy.stats

    values = np.asarray(values, dtype=float)
    n = values.size
    if n < 2:
        return None
    t_975 = float(scipy.stats.t.ppf(0.975, n - 1))
    return t_975 * float(np.std(values, ddof=1)) / math.sqrt(n)


COUNTED = {
    "observer_fallback_step": "observer_fallbacks",
    "set_invalidated_step": "set_invalidations",
}
"""Episode keys that hold the step at which something happened (None: it did not): a cell
counts its episodes in which it did, under the second name."""


def aggregate(episodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One cell per (plant, controller, reference, draw), in the order first seen."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for e in episodes:
        groups.setdefault(tuple(e.get(k) for k in KEYS), []).append(e)
    cells = []
    for members in groups.values():
        cell = {k: members[0][k] for k in KEYS if k in members[0]}
        for key, value in members[0].items():
            if key in KEYS or key in ("seed_index", "identification_seed"):
                continue
            if key in COUNTED:  # a step per episode, or None: count the episodes with one
                cell[COUNTED[key]] = sum(m.get(key) is not None for m in members)
                continue
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            values = [m[key] for m in members if m.get(key) is not None] if numeric else []
            if len(values) == 1:  # the mean of one number is that number, to the bit
                cell[key] = float(values[0])
            else:
                cell[key] = float(np.mean(values)) if numeric and values else value
        n = len(members)
        cell["seeds"] = n
        cell["identification_seeds"] = len({m.get("identification_seed") for m in members})
        cell["rmse_ci95_percent"] = ci95_half_width([m["rmse_percent"] for m in members])
        cells.append(cell)
    return cells


def different(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two cells' RMSE differ beyond the run-to-run noise (see the module docstring)."""
    ci_a, ci_b = a.get("rmse_ci95_percent"), b.get("rmse_ci95_percent")
    gap = abs(a["rmse_percent"] - b["rmse_percent"])
    if ci_a is not None and ci_b is not None:
        return gap > math.hypot(ci_a, ci_b)
    return gap > TIE * min(a["rmse_percent"], b["rmse_percent"])
