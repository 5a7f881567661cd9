"""The README's numbers are the committed results' (generated, never typed by hand)."""

from pathlib import Path

from benchmarks.readme import render

ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_agrees_with_the_committed_results():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert render(readme, ROOT) == readme, "run: python -m benchmarks.readme"


def test_every_result_file_names_a_command_that_exists():
    """Each committed result's "Produced by" line runs a module that is there, so a reader can
    reproduce it (the tracking reports name their command in their own text)."""
    import importlib.util
    import re

    commands = {}
    for path in sorted((ROOT / "benchmarks" / "results").glob("*.md")):
        match = re.search(r"Produced by `python -m ([\w.]+)", path.read_text(encoding="utf-8"))
        if match:
            commands[path.name] = match.group(1)
    assert len(commands) >= 10, commands
    for name, module in commands.items():
        assert importlib.util.find_spec(module) is not None, (name, module)


def test_the_header_names_the_module_it_is_given():
    import pytest

    from benchmarks._common import header

    lines = header("T", "benchmarks.speed.env_speed", "--x 1")
    assert "Produced by `python -m benchmarks.speed.env_speed --x 1`." in lines
    with pytest.raises(ValueError, match="dotted module name"):
        header("T", "env_speed.py")
