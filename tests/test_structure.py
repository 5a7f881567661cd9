"""The house's shape: imports point one way, between packages and between modules.

The import graph is read from the source (every ``import`` and ``from ... import``, at module
level or inside a function), so a lazy import cannot hide a circle. Imports under
``if TYPE_CHECKING:`` are left out: they never run, they only name types for annotations.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAYERS = {
    "piezo_env": set(),
    "piezo_parallel": set(),
    "identification": {"piezo_env", "piezo_parallel"},
    "controllers": {"piezo_env", "identification"},
    "piezo_rl": {"piezo_env", "controllers", "piezo_parallel"},
    "benchmarks": {"piezo_env", "identification", "controllers", "piezo_parallel", "piezo_rl"},
    "piezo_cli": {
        "piezo_env",
        "identification",
        "controllers",
        "piezo_parallel",
        "piezo_rl",
        "benchmarks",
    },
}
"""Package -> the packages of ours it may import (besides itself)."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {
        _module_name(path): path
        for package in LAYERS
        for path in sorted((ROOT / package).rglob("*.py"))
    }


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Modules of ours that ``name`` imports (the longest known prefix of each import)."""
    is_package = path.name == "__init__.py"
    found = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    type_only = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and ast.unparse(node.test).endswith("TYPE_CHECKING")
        for inner in ast.walk(node)
    }
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        for target in targets:
            parts = target.split(".")
            for k in range(len(parts), 0, -1):
                candidate = ".".join(parts[:k])
                if candidate in known:
                    if candidate != name:
                        found.add(candidate)
                    break
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) for name, path in modules.items()}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    """The import graph, read once for the module's tests (the source does not change while
    they run)."""
    return _graph()


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle, or None (iterative depth-first search)."""
    state: dict[str, int] = {}
    for root in sorted(graph):
        if state.get(root):
            continue
        stack = [(root, iter(sorted(graph[root])))]
        path = [root]
        state[root] = 1
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                stack.pop()
                path.pop()
                state[node] = 2
            elif state.get(child) == 1:
                return [*path[path.index(child) :], child]
            elif not state.get(child):
                state[child] = 1
                path.append(child)
                stack.append((child, iter(sorted(graph[child]))))
    return None


def _is_package_init_reexport(importer: str, imported: str) -> bool:
    """A package's ``__init__`` importing its own submodules is how it exports them."""
    return imported.startswith(importer + ".")


def test_packages_import_only_the_layers_below(graph):
    wrong = [
        f"{importer} -> {imported}"
        for importer, targets in graph.items()
        for imported in targets
        if imported.split(".")[0] != importer.split(".")[0]
        and imported.split(".")[0] not in LAYERS[importer.split(".")[0]]
    ]
    assert not wrong, "imports against the layering:\n" + "\n".join(sorted(wrong))


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_no_import_cycle_between_modules(package, graph):
    # A package's __init__ re-exports its submodules; a submodule importing the package's
    # __init__ back is the only way a circle runs through it, and that edge is kept.
    inner = {
        name: {
            t
            for t in targets
            if t.split(".")[0] == package and not _is_package_init_reexport(name, t)
        }
        for name, targets in graph.items()
        if name.split(".")[0] == package
    }
    cycle = _cycle(inner)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
