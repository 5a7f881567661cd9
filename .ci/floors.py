"""Print pip constraints that pin every direct dependency of pyproject.toml to its floor.

CI installs the project under these constraints once, so that every ``>=`` in pyproject.toml
is proven, not hoped. torch is left out: its floor cannot be installed here (only the CPU
build of torch 2.13.0 is on the machine; other versions pull multi-GB CUDA builds).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import tomllib

SKIP = {"torch", "piezo-testbed"}


def floors(pyproject: Path) -> list[str]:
    """``name==floor`` for every ``name>=floor`` requirement, extras included, sorted."""
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    requirements = list(project["dependencies"])
    for extra in project.get("optional-dependencies", {}).values():
        requirements += extra
    pins = {}
    for requirement in requirements:
        match = re.fullmatch(r"([A-Za-z0-9_.\-]+)(\[[^\]]*\])?\s*>=\s*([0-9][^,;\s]*)", requirement)
        if match is None:
            if requirement.split("[")[0] not in SKIP:
                sys.exit(f"floors.py: cannot read a floor from {requirement!r}")
            continue
        name = match.group(1).lower()
        if name not in SKIP:
            pins[name] = f"{name}=={match.group(3)}"
    return sorted(pins.values())


if __name__ == "__main__":
    print("\n".join(floors(Path(__file__).resolve().parents[1] / "pyproject.toml")))
