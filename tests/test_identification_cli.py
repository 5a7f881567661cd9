"""``piezo identify`` tells a user what came out in a few lines; the JSON stays in the folder."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from piezo_cli.identify import summary
from piezo_cli.main import main

COMMITTED = Path(__file__).resolve().parents[1] / "docs" / "identify"


@pytest.fixture
def report() -> dict:
    """The report of the committed ``piezo identify`` run."""
    return json.loads((COMMITTED / "report.json").read_text(encoding="utf-8"))


def test_identify_prints_a_short_summary_and_no_json(report, tmp_path, monkeypatch, capsys):
    def fake_identify(*, config, progress, runner):
        progress("a) ...")
        return SimpleNamespace(report=report)

    def fake_write(result, out, runner=None):
        (Path(out) / "model").mkdir()
        (Path(out) / "report.json").write_text(json.dumps(result.report), encoding="utf-8")
        return [Path(out) / "model", Path(out) / "report.json"]

    monkeypatch.setattr("identification.pipeline.identify", fake_identify)
    monkeypatch.setattr("identification.pipeline.write_outputs", fake_write)
    assert main(["identify", "--jobs", "1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "{" not in out and '"arx"' not in out
    assert len(out.splitlines()) <= 12
    assert f"ARX order {report['arx']['order']}" in out
    assert f"NLS memory features: {report['nls']['features']}" in out
    fit = report["validation"]["hammerstein"]["fit_percent"]
    assert f"Hammerstein model: fit {fit:.2f} %" in out
    assert out.rstrip().endswith(f"files in {tmp_path}: model/, report.json")


def test_summary_says_whether_the_features_were_chosen(report):
    assert "(chosen on a selection record)" in summary(report)
    asked = {**report, "config": {**report["config"], "features": "play"}}
    assert "(as asked)" in summary(asked)


def test_summary_says_what_became_of_a_rate_constant(report):
    """A learned rate constant is in the summary: set to 0 when the records cannot determine
    it (so that --rate on never ends silently rate-independent), else its value."""
    import copy

    assert "rate-" not in summary(report)  # no rate learned: nothing said
    learned = copy.deepcopy(report)
    first = learned["nls"]["output_error"]["stages"][0]
    first.update(rate_time_s=0.0, rate_note="the records do not determine the rate constant")
    line = next(x for x in summary(learned).splitlines() if "NLS memory features" in x)
    assert line.endswith("rate-independent: the records do not determine the rate constant")
    first.update(rate_time_s=2.5e-4, rate_note=None)
    assert "rate-dependent (c = 0.00025 s)" in summary(learned)
