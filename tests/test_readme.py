"""The README and docs pages: their numbers are the committed results' (generated, never typed
by hand), their links resolve, and the README keeps its quick start up front."""

import copy
import json
import re
from pathlib import Path

import pytest

from benchmarks.readme import PAGES, headline_table, render

ROOT = Path(__file__).resolve().parents[1]

QUICK_START = (
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && "
    "pip install -e . && piezo benchmark --out out/benchmark",
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && "
    'pip install -e ".[test]" && python -m pytest -q',
)
"""The two commands of the quick start: the main job, and the tests (CI runs the latter)."""

PAGES_WITH_LINKS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


@pytest.mark.parametrize("page", PAGES)
def test_every_page_agrees_with_the_committed_results(page):
    text = (ROOT / page).read_text(encoding="utf-8")
    assert render(text, ROOT, page) == text, "run: python -m benchmarks.readme"


def test_the_readme_is_short_and_opens_with_the_quick_start():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250, len(lines)
    for command in QUICK_START:
        where = [i for i, line in enumerate(lines, start=1) if line == command]
        assert where and where[0] < 60, (command, where)


def _links(text: str) -> list[str]:
    """Targets of the markdown links and images of ``text``, code blocks and spans aside."""
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"\]\(([^)\s]+)\)", text)


@pytest.mark.parametrize("page", PAGES_WITH_LINKS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_points_at_a_file_that_exists(page):
    links = _links(page.read_text(encoding="utf-8"))
    relative = [link for link in links if not re.match(r"[a-z]+:", link)]
    missing = [link for link in relative
               if link.split("#")[0] and not (page.parent / link.split("#")[0]).exists()]
    assert not missing, missing


def test_the_link_check_sees_a_broken_link(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("[a](there.md) `[b](code.md)` ![c](img.png#x) [d](https://example.org)\n")
    assert _links(page.read_text()) == ["there.md", "img.png#x", "https://example.org"]


def test_a_diverged_episode_is_marked_in_the_table_not_given_an_rmse():
    data = json.loads((ROOT / "docs" / "benchmark" / "benchmark.json").read_text())
    assert "diverged" not in headline_table(data)  # the nominal plant: nothing diverged
    broken = copy.deepcopy(data)
    episode = next(e for e in broken["results"]["episodes"]
                   if e["plant"] == "nominal" and e["controller"] == "mpc"
                   and e["reference"] == "sine-10Hz")
    episode["max_error_percent"] = 150.0  # beyond the full stroke
    row = next(line for line in headline_table(broken).splitlines()
               if line.startswith("| `mpc` ("))
    cells = [c.strip() for c in row.strip("|").split("|")]
    references = broken["results"]["config"]["references"]
    assert cells[1 + references.index("sine-10Hz")] == "diverged"
    assert cells.count("diverged") == 1


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
