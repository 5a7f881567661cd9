"""Row labels of the benchmark's tables and figures."""

from __future__ import annotations

import re

__all__ = ["row_color", "seed_groups"]


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
)
_PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
    "#bcbd22", "#17becf", "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd",
)


def row_color(label: str) -> str:
    """The colour of a row in every figure of every run (a matplotlib colour string).

    The project's controllers have fixed colours; any other row (a policy, a user's controller)
    takes one from the rest of the palette by a checksum of its recipe name, so seeds of one
    recipe share it and a name always gets the same colour.
    """
    import zlib

    if label in _KNOWN_ROWS:
        return _PALETTE[_KNOWN_ROWS.index(label)]
    recipe = re.sub(r"-seed\d+$", "", label)
    rest = _PALETTE[len(_KNOWN_ROWS) :]
    return rest[zlib.crc32(recipe.encode()) % len(rest)]
