"""The dependency floors in pyproject.toml, as CI's lowest-versions job reads them (.ci/floors.py).

The job itself (a fresh environment at the floors, then the suite) runs in .ci/run; these tests
keep pyproject.toml readable by it: every direct dependency states a floor, a package named in
two places has one floor, and the floors are written nowhere else.
"""

from __future__ import annotations

import importlib.util
import re
import sys
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load_floors_module():
    spec = importlib.util.spec_from_file_location("ci_floors", ROOT / ".ci" / "floors.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


floors_py = _load_floors_module()


def _write(tmp_path: Path, dependencies: list[str], extras: dict[str, list[str]]) -> Path:
    def toml_list(items: list[str]) -> str:
        return "[" + ", ".join(f'"{item}"' for item in items) + "]"

    text = f'[project]\nname = "piezo-testbed"\ndependencies = {toml_list(dependencies)}\n'
    text += "[project.optional-dependencies]\n"
    text += "".join(f"{name} = {toml_list(items)}\n" for name, items in extras.items())
    path = tmp_path / "pyproject.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_every_direct_dependency_but_torch_has_a_floor_the_job_installs():
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    project = floors_py.tomllib.loads(text)["project"]
    named = {
        re.split(r"[\s\[<>=!~;]", requirement, maxsplit=1)[0].lower()
        for requirement in project["dependencies"]
        + [r for extra in project["optional-dependencies"].values() for r in extra]
    }
    pins = floors_py.floors()
    assert set(pins) == named - {"torch", "piezo-testbed"}
    assert "torch>=2.2" in project["dependencies"]  # stated, not installable here (see floors.py)
    for name, floor in pins.items():
        assert re.fullmatch(r"[0-9]+(\.[0-9]+)*", floor), (name, floor)


def test_the_constraints_pin_each_package_once():
    lines = floors_py.constraints(floors_py.floors()).splitlines()
    names = [line.split("==")[0] for line in lines]
    assert len(names) == len(set(names)) and names == sorted(names)
    assert all(re.fullmatch(r"[a-z0-9\-]+==[0-9.]+", line) for line in lines)


def test_a_requirement_without_a_floor_or_with_two_floors_is_refused(tmp_path):
    ok = _write(tmp_path, ["numpy>=1.25", "torch>=2.2"], {"a": ["Stable_Baselines3>=2.6"]})
    assert floors_py.floors(ok) == {"numpy": "1.25", "stable-baselines3": "2.6"}
    with pytest.raises(ValueError, match="does not read 'name>=floor'"):
        floors_py.floors(_write(tmp_path, ["numpy"], {}))
    with pytest.raises(ValueError, match="does not read 'name>=floor'"):
        floors_py.floors(_write(tmp_path, ["numpy>=1.25,<3"], {}))
    twice = {"rl": ["stable-baselines3>=2.6"], "t": ["stable_baselines3>=2.5"]}
    with pytest.raises(ValueError, match=r"stable-baselines3 has two floors: 2\.6 .* and 2\.5"):
        floors_py.floors(_write(tmp_path, [], twice))
    # the project's own extras are not dependencies
    assert floors_py.floors(_write(tmp_path, ["numpy>=1.25"], {"t": ["piezo-testbed[ray]"]})) == {
        "numpy": "1.25"
    }


def test_the_check_finds_missing_and_other_versions():
    installed = {"numpy": "1.25.0", "scipy": "1.14.1"}

    def version(name: str) -> str:
        if name not in installed:
            raise metadata.PackageNotFoundError(name)
        return installed[name]

    pins = {"numpy": "1.25", "scipy": "1.13", "ray": "2.10"}
    assert floors_py.mismatches(pins, version) == [
        "scipy: 1.14.1 installed, floor 1.13",
        "ray: not installed (floor 2.10)",
    ]
    assert floors_py.mismatches({"numpy": "1.25.0"}, version) == []
    assert floors_py.mismatches({"numpy": "1.2"}, version) == ["numpy: 1.25.0 installed, floor 1.2"]


def test_ci_installs_the_floors_and_runs_the_suite_there():
    script = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    floors_job = script[script.index(".ci/floors.py >") :]
    for command in (
        '-c "$scratch/floors.txt" -e ".[test]"',
        "python .ci/floors.py --check",
        "ruff check .",
        "python -m pytest -q",
    ):
        assert command in floors_job, command
    assert "OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 python -m pytest" in script
