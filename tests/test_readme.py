"""The README's numbers are the committed results' (generated, never typed by hand)."""

from pathlib import Path

from benchmarks.readme import render

ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_agrees_with_the_committed_results():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert render(readme, ROOT) == readme, "run: python -m benchmarks.readme"
