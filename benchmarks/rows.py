"""Row labels of the benchmark's tables and figures."""

from __future__ import annotations

import re

__all__ = ["seed_groups"]


def seed_groups(labels: list[str]) -> dict[str, list[str]]:
    """Rows that are seeds of one recipe (``ppo-seed0``, ``ppo-seed1`` ...): name -> labels."""
    groups: dict[str, list[str]] = {}
    for label in labels:
        match = re.fullmatch(r"(.+)-seed\d+", label)
        if match:
            groups.setdefault(match.group(1), []).append(label)
    return {name: members for name, members in groups.items() if len(members) > 1}
