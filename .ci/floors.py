"""The dependency floors of pyproject.toml as pip constraints, and a check of what got installed.

    python .ci/floors.py            print ``name==floor`` for every direct dependency
    python .ci/floors.py --check    exit 1 unless every one is installed at exactly its floor

CI installs the project under these constraints once (the lowest-versions job), so that every
``>=`` in pyproject.toml is proven, not hoped; ``--check`` then proves that the constraints
really applied (pip ignores a constraint on a package that nothing requires). The floors are
written once, in pyproject.toml: every requirement there must read ``name>=floor`` (extras on
the name allowed), and a package named in several places must have the same floor in each.

torch is left out: its floor cannot be installed here (only the CPU build of torch 2.13.0 is
on the machine; other versions pull multi-GB CUDA builds). The project's own extras
(``piezo-testbed[ray]``) are not dependencies.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

PROJECT = "piezo-testbed"
UNTESTED = {"torch"}
PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
_FLOOR = re.compile(r"([A-Za-z0-9][A-Za-z0-9_.\-]*)\s*(\[[^\]]*\])?\s*>=\s*([0-9][0-9A-Za-z.]*)")


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def floors(pyproject: Path = PYPROJECT) -> dict[str, str]:
    """``{name: floor}`` for every direct dependency, extras included, torch left out.

    Raises ValueError for a requirement without a readable floor and for a package given two
    different floors.
    """
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    requirements = [("dependencies", r) for r in project.get("dependencies", [])]
    for extra, listed in project.get("optional-dependencies", {}).items():
        requirements += [(f"extra {extra!r}", r) for r in listed]
    found: dict[str, tuple[str, str]] = {}
    for where, requirement in requirements:
        name = _canonical(re.split(r"[\s\[<>=!~;]", requirement.strip(), maxsplit=1)[0])
        if name == PROJECT:
            continue
        match = _FLOOR.fullmatch(requirement.strip())
        if match is None:
            raise ValueError(f"{where}: {requirement!r} does not read 'name>=floor'")
        floor = match.group(3)
        if name in found and found[name][0] != floor:
            raise ValueError(
                f"{name} has two floors: {found[name][0]} ({found[name][1]}) and {floor} ({where})"
            )
        found[name] = (floor, where)
    return {name: floor for name, (floor, _) in sorted(found.items()) if name not in UNTESTED}


def constraints(pins: dict[str, str]) -> str:
    """The pip constraints file: one ``name==floor`` a line."""
    return "".join(f"{name}=={floor}\n" for name, floor in pins.items())


def _same_release(installed: str, floor: str) -> bool:
    """``1.25.0`` is the release ``1.25`` names (pip pads with zeros the same way)."""

    def parts(version: str) -> list[str]:
        numbers = version.split(".")
        while len(numbers) > 1 and numbers[-1] == "0":
            numbers.pop()
        return numbers

    return parts(installed) == parts(floor)


def mismatches(pins: dict[str, str], version: Callable[[str], str] = metadata.version) -> list[str]:
    """One line per pinned package that is missing or not at its floor (empty: all hold)."""
    problems = []
    for name, floor in pins.items():
        try:
            installed = version(name)
        except metadata.PackageNotFoundError:
            problems.append(f"{name}: not installed (floor {floor})")
            continue
        if not _same_release(installed, floor):
            problems.append(f"{name}: {installed} installed, floor {floor}")
    return problems


def main(argv: list[str]) -> int:
    try:
        pins = floors()
    except ValueError as error:
        print(f"floors.py: {error}", file=sys.stderr)
        return 2
    if argv == ["--check"]:
        problems = mismatches(pins)
        for line in problems:
            print(f"floors.py: {line}", file=sys.stderr)
        if not problems:
            print(f"floors.py: all {len(pins)} direct dependencies at their floors")
        return 1 if problems else 0
    if argv:
        print(__doc__, file=sys.stderr)
        return 2
    sys.stdout.write(constraints(pins))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
