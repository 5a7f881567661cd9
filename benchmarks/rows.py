"""Row labels of the benchmark's tables and figures."""

from __future__ import annotations

import re
from collections.abc import Sequence

__all__ = ["row_color", "row_colors", "seed_groups"]


def seed_groups(labels: list[str]) -> dict[str, list[str]]:
    """Rows that are seeds of one recipe (``ppo-seed0``, ``ppo-seed1`` ...): name -> labels."""
    groups: dict[str, list[str]] = {}
    for label in labels:
        match = re.fullmatch(r"(.+)-seed\d+", label)
        if match:
            groups.setdefault(match.group(1), []).append(label)
    return {name: members for name, members in groups.items() if len(members) > 1}


_KNOWN_ROWS = (
    "pid",
    "pid-notch",
    "pid-ff",
    "mpc",
    "nmpc",
    "mpc-oracle",
    "nmpc-oracle",
    "nmpc-ipopt",
    "mpc-adaptive",
    "ppo",
    "ppo-dr",
)
"""The project's rows (the committed policies by recipe, ``ppo-seed0`` -> ``ppo``), each with
its fixed colour: the same in every figure of every run."""

_PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
    "#bcbd22", "#17becf", "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd",
)
"""matplotlib's tab10 and five darker tab20b/c shades: the first colours of the known rows,
the rest for any other row of a run."""


def _recipe(label: str) -> str:
    return re.sub(r"-seed\d+$", "", label)


def row_color(label: str) -> str:
    """The fixed colour of one of the project's rows (a matplotlib colour string).

    Raises
    ------
    ValueError
        For another row (a user's controller or policy): its colour depends on the run's
        other rows, :func:`row_colors`.
    """
    recipe = _recipe(label)
    if recipe not in _KNOWN_ROWS:
        raise ValueError(f"{label!r} has no fixed colour; use row_colors(rows) for a run's rows")
    return _PALETTE[_KNOWN_ROWS.index(recipe)]


def row_colors(labels: Sequence[str]) -> dict[str, str]:
    """The colour of every row of a run, pairwise distinct between recipes.

    The project's rows keep their fixed colour (:func:`row_color`); any other recipe (a user's
    controller, a policy of one's own) takes, in order of first appearance, the next colour
    of the palette that no known row uses, then evenly spaced hues. The seeds of one recipe
    (``mine-seed0``, ``mine-seed1``) share its colour: the figures draw a recipe once.
    """
    from matplotlib.colors import hsv_to_rgb, to_hex

    free = list(_PALETTE[len(_KNOWN_ROWS) :])
    others = list(dict.fromkeys(_recipe(x) for x in labels if _recipe(x) not in _KNOWN_ROWS))
    extra = max(0, len(others) - len(free))
    free += [to_hex(hsv_to_rgb((k / extra, 0.6, 0.55))) for k in range(extra)]
    assigned = dict(zip(others, free, strict=False))
    return {
        x: assigned[_recipe(x)] if _recipe(x) in assigned else row_color(x) for x in labels
    }
