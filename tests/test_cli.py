"""The ``piezo`` command line, run as a user would."""

from __future__ import annotations

import csv
import json

import pytest

from piezo_cli.main import main


def test_simulate_writes_csv_and_png(tmp_path, capsys):
    assert (
        main(
            [
                "simulate",
                "--signal",
                "triangle",
                "--amplitude",
                "20",
                "--duration",
                "0.5",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    with (tmp_path / "simulate.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0][:4] == ["time_s", "voltage_V", "effective_voltage_V", "deflection_um"]
    assert len(rows) == 1 + 500
    png = (tmp_path / "simulate.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "peak deflection" in capsys.readouterr().out


def test_simulate_reports_bad_input_clearly(tmp_path, capsys):
    assert main(["simulate", "--bender", "PL999", "--out", str(tmp_path)]) == 2
    assert "unknown bender" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["simulate", "--signal", "sawtooth"])


@pytest.mark.slow
def test_identify_writes_model_report_and_figures(tmp_path):
    assert main(["identify", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["validation"]["hammerstein"]["fit_percent"] > 95.0
    for name in ("model/model.json", "model/weights.npz", "report.md", "validation.png"):
        assert (tmp_path / name).exists()
