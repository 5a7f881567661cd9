"""Records as files: excite -> measure -> identify from records gives the env's model, and every
malformed record is refused in one line, before any work, leaving no output folder."""

from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from short_runs import FAST, FAST_SEED

from identification.config import IdentificationConfig
from identification.pipeline import identify, identify_records
from identification.records import (
    TIME_TOLERANCE_S,
    RecordsError,
    read_excitation,
    read_records,
    records_from_env,
    write_excitation,
    write_measured,
)
from piezo_cli.main import main
from piezo_env import default_dt

STEPS = {k: v for k, v in FAST.items() if not k.endswith("_samples")}
"""The settings of steps b-f alone: record lengths come from the records."""


def _model_arrays(model) -> dict[str, np.ndarray]:
    return {"theta": model.arx.theta, **model.nls.arrays()}


def _excite_and_measure(root: Path, config: IdentificationConfig, bender: str) -> Path:
    """Excitation records of ``config`` written to ``root/excitation`` and measured on
    ``bender`` by ``piezo simulate --records`` into ``root/measured``, as the CLI does."""
    write_excitation(root / "excitation", config, bender=bender, dt=default_dt(bender))
    argv = ["simulate", "--records", str(root / "excitation"), "--bender", bender]
    assert main([*argv, "--out", str(root / "measured")]) == 0
    return root / "measured"


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> Path:
    """Short records of the PL140 (the seed of the session's short run), excited and measured
    as the CLI does."""
    config = IdentificationConfig(seed=FAST_SEED, env_kwargs={"bender": "PL140"}, **FAST)
    return _excite_and_measure(tmp_path_factory.mktemp("records"), config, "PL140")


@pytest.fixture(scope="module")
def identified_from_measured(measured):
    """``identify_records`` on :func:`measured`, with the short settings of steps b-f."""
    return identify_records(measured, config=IdentificationConfig(**STEPS))


def _copy(measured: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "records"
    shutil.copytree(measured, folder)
    return folder


def _edit_line(path: Path, line: int, column: str, value: str) -> None:
    """Set ``column`` of 1-based ``line`` of a CSV record to the text ``value``."""
    lines = path.read_text(encoding="utf-8").splitlines()
    header = lines[0].split(",")
    cells = lines[line - 1].split(",")
    cells[header.index(column)] = value
    lines[line - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


@pytest.mark.parametrize("bender", ["PL140", "PL127"])
def test_excite_simulate_identify_round_trip_gives_the_env_model(bender, tmp_path, request):
    """The CLI's excite -> simulate --records -> identify_records on the files gives bitwise
    the model identify(env) gives with the same settings and seed. (The PL140's runs are
    shared: the session's run from the env, the module's records and their identification.)"""
    config = IdentificationConfig(seed=FAST_SEED, env_kwargs={"bender": bender}, **FAST)
    if bender == "PL140":
        reference = request.getfixturevalue("fast_pl140_identification")
        folder = request.getfixturevalue("measured")
        result = request.getfixturevalue("identified_from_measured")
    else:
        reference = identify(config=config)
        folder = _excite_and_measure(tmp_path, config, bender)
        result = identify_records(folder, config=IdentificationConfig(**STEPS))
    manifest, inputs = read_excitation(folder.parent / "excitation")
    expected = {"prbs", "rich", "selection", "validation"}
    assert set(manifest["records"]) == set(manifest["purposes"]) == expected
    np.testing.assert_array_equal(inputs["prbs"], reference.data["u_prbs"])
    got, want = _model_arrays(result.model), _model_arrays(reference.model)
    assert got.keys() == want.keys()
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert result.report["validation"] == reference.report["validation"]
    source = result.model.metadata["records"]
    manifest_path = folder / "records.json"
    assert source["kind"] == "records" and source["manifest"] == str(manifest_path.resolve())
    import hashlib

    assert source["manifest_sha256"] == hashlib.sha256(manifest_path.read_bytes()).hexdigest()
    assert reference.model.metadata["records"] == {"kind": "env"}


def test_excite_writes_the_pipeline_signals_as_csv_npz_and_manifest(tmp_path, capsys):
    assert main(["excite", "--bender", "PL127", "--seed", "2", "--out", str(tmp_path)]) == 0
    manifest = json.loads((tmp_path / "records.json").read_text(encoding="utf-8"))
    assert manifest["bender"] == "PL127.10" and manifest["seed"] == 2
    assert manifest["dt"] == default_dt("PL127") and manifest["drive_range_V"] == [-30.0, 30.0]
    config = IdentificationConfig(seed=2, env_kwargs={"bender": "PL127"})
    from identification.experiment import experiment_inputs

    inputs = experiment_inputs(config, manifest["dt"])
    for name, file in manifest["records"].items():
        header = (tmp_path / file).read_text(encoding="utf-8").splitlines()[0]
        assert header == "time_s,voltage_V"
        table = np.loadtxt(tmp_path / file, delimiter=",", skiprows=1)
        np.testing.assert_array_equal(table[:, 1], inputs[name])
        with np.load(tmp_path / file.replace(".csv", ".npz")) as npz:
            np.testing.assert_array_equal(npz["voltage_V"], inputs[name])
        assert manifest["purposes"][name]


def test_identify_records_command_writes_the_outputs_of_identify(measured, tmp_path, monkeypatch):
    """``piezo identify --records``: model files, report and figures, as ``piezo identify``
    writes them; the model names the manifest it came from."""
    monkeypatch.setattr(
        "identification.pipeline.IdentificationConfig",
        functools.partial(
            IdentificationConfig, **{k: v for k, v in STEPS.items() if k != "features"}
        ),
    )
    out = tmp_path / "id"
    assert (
        main(["identify", "--records", str(measured), "--features", "play", "--out", str(out)]) == 0
    )
    names = {p.name for p in out.iterdir()}
    assert {"model", "report.json", "report.md", "validation.png"} <= names
    model = json.loads((out / "model" / "model.json").read_text(encoding="utf-8"))
    assert model["metadata"]["records"]["manifest"] == str((measured / "records.json").resolve())
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["environment"]["records"]["kind"] == "records"
    assert "Records: " in (out / "report.md").read_text(encoding="utf-8")


# -- every malformed record refused in one line, exit 2, no output folder ------------------


def _refused(folder: Path, tmp_path: Path, capsys, *extra: str) -> str:
    out = tmp_path / "new" / "out"
    assert main(["identify", "--records", str(folder), *extra, "--out", str(out)]) == 2
    assert not (tmp_path / "new").exists()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_decreasing_time_is_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    _edit_line(folder / "rich.csv", 12, "time_s", "0.001")
    err = _refused(folder, tmp_path, capsys)
    assert "rich.csv, line 12" in err and "does not increase" in err
    assert "time_s 0.001 s" in err and "np." not in err  # the number, not numpy's repr


def test_non_uniform_time_is_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    _edit_line(folder / "prbs.csv", 40, "time_s", "0.038010")  # 10 us late
    err = _refused(folder, tmp_path, capsys)
    assert "prbs.csv, line 40" in err and "not uniform" in err
    assert "time_s 0.03801 s" in err and "np." not in err


def test_nan_and_inf_are_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    _edit_line(folder / "validation.csv", 7, "deflection_um", "nan")
    err = _refused(folder, tmp_path, capsys)
    assert "validation.csv, line 7" in err and "deflection_um" in err and "finite" in err
    assert "deflection_um is nan;" in err
    _edit_line(folder / "validation.csv", 7, "deflection_um", "1.0")
    _edit_line(folder / "validation.csv", 9, "voltage_V", "inf")
    err = _refused(folder, tmp_path, capsys)
    assert "validation.csv, line 9" in err and "voltage_V" in err


@pytest.mark.parametrize(("record", "column"), [("prbs", "voltage_V"), ("rich", "deflection_um")])
def test_a_column_that_never_moves_is_refused_naming_its_file(
    measured, tmp_path, capsys, record, column
):
    """A drive left off or a sensor unplugged: one value in the whole column."""
    folder = _copy(measured, tmp_path)
    path = folder / f"{record}.csv"
    lines = path.read_text(encoding="utf-8").splitlines()
    for k in range(2, len(lines) + 1):
        _edit = lines[k - 1].split(",")
        _edit[lines[0].split(",").index(column)] = "0.5"
        lines[k - 1] = ",".join(_edit)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert f"{record}.csv" in err and f"column {column} holds one value (0.5)" in err


def test_a_missing_column_is_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    text = (folder / "selection.csv").read_text(encoding="utf-8")
    (folder / "selection.csv").write_text(text.replace("deflection_um", "y", 1), encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert "selection.csv, line 1" in err and "missing column(s) deflection_um" in err


def test_a_missing_record_is_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    (folder / "rich.csv").unlink()
    err = _refused(folder, tmp_path, capsys)
    assert "rich.csv: missing" in err
    manifest = json.loads((folder / "records.json").read_text(encoding="utf-8"))
    del manifest["records"]["rich"]
    (folder / "records.json").write_text(json.dumps(manifest), encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert "missing record(s) rich" in err


@pytest.mark.parametrize(
    ("field", "value", "fragment"),
    [
        ("datasheet", "PL140", "field 'datasheet' must be an object"),
        ("plant", ["x"], "field 'plant' must be an object"),
        ("bender", None, "field 'bender' must name the bender"),
        ("excitation", "x", "field 'excitation' must be an object"),
        ("excitation", {"validation_hold": "x"}, "field 'excitation': validation_hold"),
    ],
)
def test_a_malformed_manifest_field_is_refused_naming_the_manifest(
    field, value, fragment, measured, tmp_path, capsys
):
    folder = _copy(measured, tmp_path)
    manifest = json.loads((folder / "records.json").read_text(encoding="utf-8"))
    manifest[field] = value
    (folder / "records.json").write_text(json.dumps(manifest), encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert "records.json: " in err and fragment in err


def test_a_record_that_is_not_utf8_or_not_an_npz_is_refused_naming_it(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    data = (folder / "prbs.csv").read_bytes().splitlines(keepends=True)
    data[4] = data[4].replace(b"\n", b" \xe9\n")
    (folder / "prbs.csv").write_bytes(b"".join(data))
    err = _refused(folder, tmp_path, capsys)
    assert "prbs.csv, line 5: not UTF-8 text (byte 0xe9)" in err
    folder = _copy(measured, tmp_path / "npz")
    (folder / "prbs.npz").write_bytes(b"not a zip file")
    manifest = json.loads((folder / "records.json").read_text(encoding="utf-8"))
    manifest["records"]["prbs"] = "prbs.npz"
    (folder / "records.json").write_text(json.dumps(manifest), encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert "prbs.npz: not an NPZ of numeric arrays" in err


def test_a_dt_that_disagrees_with_the_manifest_is_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    manifest = json.loads((folder / "records.json").read_text(encoding="utf-8"))
    manifest["dt"] = 1.001e-3
    (folder / "records.json").write_text(json.dumps(manifest), encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert "records.json field 'dt' says 0.001001 s" in err and "steps by 0.001 s" in err


def test_a_record_too_short_for_the_orders_is_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    lines = (folder / "selection.csv").read_text(encoding="utf-8").splitlines()
    (folder / "selection.csv").write_text("\n".join(lines[:151]) + "\n", encoding="utf-8")
    err = _refused(folder, tmp_path, capsys)
    assert "selection.csv: 150 samples" in err and "at least 200" in err


def test_voltages_outside_the_drive_range_are_refused(measured, tmp_path, capsys):
    folder = _copy(measured, tmp_path)
    _edit_line(folder / "rich.csv", 30, "voltage_V", "30.5")
    err = _refused(folder, tmp_path, capsys)
    assert "rich.csv, line 30" in err and "outside the drive range [-30, 30] V" in err


# -- what a bench writes is accepted -------------------------------------------------------


def _rewrite_times(path: Path, fmt: str, scale: float = 1.0) -> None:
    lines = path.read_text(encoding="utf-8").splitlines()
    out = [lines[0]]
    for k, line in enumerate(lines[1:]):
        cells = line.split(",")
        cells[0] = format(k * 1e-3 * scale, fmt)
        out.append(",".join(cells))
    path.write_text("\n".join(out) + "\n", encoding="utf-8")


def test_time_stamps_rounded_to_6_decimals_are_accepted(measured, tmp_path):
    folder = _copy(measured, tmp_path)
    for name in ("prbs", "rich", "selection", "validation"):
        _rewrite_times(folder / f"{name}.csv", ".6f")
    assert (folder / "prbs.csv").read_text(encoding="utf-8").splitlines()[2].startswith("0.001000,")
    config = IdentificationConfig(**STEPS)
    got, want = read_records(folder, config), read_records(measured, config)
    for name, (u, y) in want.records.items():
        np.testing.assert_array_equal(got.records[name][0], u)
        np.testing.assert_array_equal(got.records[name][1], y)


def test_a_csv_with_a_bom_and_crlf_line_ends_is_accepted(measured, tmp_path):
    folder = _copy(measured, tmp_path)
    text = (folder / "rich.csv").read_text(encoding="utf-8")
    (folder / "rich.csv").write_bytes(("\ufeff" + text.replace("\n", "\r\n")).encode("utf-8"))
    config = IdentificationConfig(**STEPS)
    got, want = read_records(folder, config), read_records(measured, config)
    np.testing.assert_array_equal(got.records["rich"][0], want.records["rich"][0])
    np.testing.assert_array_equal(got.records["rich"][1], want.records["rich"][1])


def test_the_manifest_dt_wins_over_the_time_column_within_tolerance(measured, tmp_path):
    """A clock 1e-7 slow over 2000 samples ends 0.2 us late: within the tolerance, so the
    records load at the manifest's dt exactly; 1e-6 slow ends 2 us late, and is refused."""
    folder = _copy(measured, tmp_path)
    _rewrite_times(folder / "prbs.csv", ".12f", scale=1 + 1e-7)
    records = read_records(folder, IdentificationConfig(**STEPS))
    assert records.dt == 1e-3
    assert 1999 * 1e-3 * 1e-6 > TIME_TOLERANCE_S
    _rewrite_times(folder / "prbs.csv", ".12f", scale=1 + 1e-6)
    with pytest.raises(RecordsError, match=r"field 'dt' says 0\.001 s"):
        read_records(folder, IdentificationConfig(**STEPS))


# -- one long record, split ------------------------------------------------------------------


def test_a_single_long_record_is_split_into_estimation_selection_and_validation(tmp_path):
    from identification.experiment import collect
    from piezo_env.signals import make_signal

    env = gym.make("piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1)
    rng = np.random.default_rng(4)
    u = make_signal("random", 4000, dt=1e-3, rng=rng, amplitude=20.0, hold=10)
    u, y = collect(env, u, seed=5)
    result = identify_records(
        (u, y),
        split=0.6,
        dt=1e-3,
        drive_range_V=(-30.0, 30.0),
        bender="PL140",
        config=IdentificationConfig(**STEPS),
    )
    assert len(result.data["u_val"]) == 800  # the second half of the held-out 40 %
    np.testing.assert_array_equal(result.data["u_val"], u[3200:])
    assert result.report["validation"]["hammerstein"]["fit_percent"] > 95.0
    with pytest.raises(RecordsError, match="pass --split FRACTION"):
        identify_records((u, y), dt=1e-3, drive_range_V=(-30, 30), bender="PL140")
    with pytest.raises(RecordsError, match="each part needs at least 200"):
        identify_records((u, y), split=0.95, dt=1e-3, drive_range_V=(-30, 30), bender="PL140")


def test_an_excitation_folder_is_not_taken_for_measurements(measured, tmp_path, capsys):
    err = _refused(measured.parent / "excitation", tmp_path, capsys)
    assert "field 'kind' is 'excitation'" in err


def test_split_on_a_records_folder_of_four_records_is_refused(measured, tmp_path, capsys):
    err = _refused(measured, tmp_path, capsys, "--split", "0.7")
    assert "split applies to a single record" in err


def test_simulate_records_refuses_another_bender(measured, tmp_path, capsys):
    excitation = measured.parent / "excitation"
    argv = ["simulate", "--records", str(excitation), "--bender", "PL127"]
    assert main([*argv, "--out", str(tmp_path / "new")]) == 2
    assert "made for the PL140.10" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_records_from_env_and_write_measured_keep_the_arrays_exactly(tmp_path):
    env = gym.make("piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1)
    u = np.random.default_rng(0).uniform(-30, 30, 300)
    records = records_from_env(env, {"validation": u}, seed=1)
    write_measured(tmp_path, records)
    table = np.loadtxt(tmp_path / "validation.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table[:, 1], records.records["validation"][0])
    np.testing.assert_array_equal(table[:, 2], records.records["validation"][1])


def test_npz_records_read_as_their_csv(measured, tmp_path):
    folder = _copy(measured, tmp_path)
    manifest = json.loads((folder / "records.json").read_text(encoding="utf-8"))
    manifest["records"] = {k: v.replace(".csv", ".npz") for k, v in manifest["records"].items()}
    (folder / "records.json").write_text(json.dumps(manifest), encoding="utf-8")
    config = IdentificationConfig(**STEPS)
    got, want = read_records(folder, config), read_records(measured, config)
    for name, (u, y) in want.records.items():
        np.testing.assert_array_equal(got.records[name][0], u)
        np.testing.assert_array_equal(got.records[name][1], y)


def test_split_without_records_is_refused(tmp_path, capsys):
    assert main(["identify", "--split", "0.7", "--out", str(tmp_path / "new")]) == 2
    assert "--split applies to --records" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_arrays_identify_as_the_folder_they_were_read_from(measured, identified_from_measured):
    config = IdentificationConfig(**STEPS)
    records = read_records(measured, config)
    from_folder = identified_from_measured
    from_arrays = identify_records(
        records.records,
        dt=records.dt,
        drive_range_V=records.drive_range_V,
        bender="PL140",
        seed=records.seed,
        config=config,
    )
    for name, value in _model_arrays(from_folder.model).items():
        np.testing.assert_array_equal(_model_arrays(from_arrays.model)[name], value)
    assert from_arrays.model.metadata["records"] == {"kind": "arrays"}
    assert from_arrays.model.metadata["datasheet"] == from_folder.model.metadata["datasheet"]


def test_identify_records_refuses_bad_arguments_before_any_work():
    """The Python API refuses what the command line refuses, before any step runs."""
    u, y = np.zeros(1000), np.zeros(1000)
    good = {"dt": 1e-3, "drive_range_V": (-30.0, 30.0), "bender": "PL140"}
    with pytest.raises(ValueError, match="seed must be an integer >= 0, got -3"):
        identify_records((u, y), split=0.7, seed=-3, **good)
    with pytest.raises(RecordsError, match="dt must be a positive number"):
        identify_records((u, y), split=0.7, **{**good, "dt": "0.001"})
    with pytest.raises(RecordsError, match="bender must name the bender"):
        identify_records((u, y), split=0.7, **{**good, "bender": 140})
    for name, value in good.items():  # a folder's manifest says what they are: not ignored
        with pytest.raises(ValueError, match=f"{name}: for arrays only"):
            identify_records("no-such-folder", **{name: value})
