"""The ``piezo`` command line, run as a user would."""

from __future__ import annotations

import argparse
import csv
import errno
import json
import os
from importlib.metadata import version
from pathlib import Path

import pytest

import piezo_cli.main as cli
from piezo_cli.command import CommandLineError, Subcommand
from piezo_cli.main import build_parser, main
from piezo_cli.output import prepare_output_dir


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Exit status, stdout and stderr of ``piezo argv`` (argparse exits count as statuses)."""
    try:
        status = main(argv)
    except SystemExit as stop:
        status = stop.code if isinstance(stop.code, int) else 1
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def assert_refused(status: int, out: str, err: str, command: str, *fragments: str) -> None:
    """Exit 2, nothing on stdout, one line on stderr that names the command and the fragments."""
    assert status == 2
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"piezo {command}: ")
    assert "Traceback" not in err and "BenderDatasheet" not in err
    for fragment in fragments:
        assert fragment in lines[0]


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if a subcommand starts its work (the refusal must come first)."""

    def must_not_run(*args: object, **kwargs: object) -> None:
        pytest.fail("the work started although the call should have been refused")

    monkeypatch.setattr("piezo_env.simulate.run_open_loop", must_not_run)
    monkeypatch.setattr("identification.pipeline.identify", must_not_run)


def test_simulate_writes_csv_and_png(tmp_path, capsys):
    argv = ["simulate", "--signal", "triangle", "--amplitude", "20", "--duration", "0.5"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    with (tmp_path / "simulate.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0][:4] == ["time_s", "voltage_V", "effective_voltage_V", "deflection_um"]
    assert len(rows) == 1 + 500
    png = (tmp_path / "simulate.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "peak deflection" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["simulate.csv", "simulate.png"]


def test_readme_simulate_command_parses_unchanged():
    args = build_parser().parse_args(
        ["simulate", "--signal", "sine", "--amplitude", "30", "--frequency", "1"]
    )
    assert (args.signal, args.amplitude, args.frequency) == ("sine", 30.0, 1.0)
    assert args.subcommand.name == "simulate"
    args = build_parser().parse_args(["identify", "--out", "out/pl140"])
    assert (args.out, args.subcommand.name) == ("out/pl140", "identify")


# -- output folder: checked before any work ---------------------------------------------------


@pytest.mark.parametrize("command", ["simulate", "identify"])
def test_output_under_a_file_is_refused_before_work(command, tmp_path, capsys, no_work):
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    out = blocker / "x"
    status, stdout, err = run_cli([command, "--out", str(out)], capsys)
    assert_refused(
        status,
        stdout,
        err,
        command,
        f"cannot write to {out}: {blocker} is a file, not a folder; choose another --out",
    )


@pytest.mark.parametrize("command", ["simulate", "identify"])
def test_output_that_is_an_existing_file_is_refused_before_work(command, tmp_path, capsys, no_work):
    existing = tmp_path / "results.csv"
    existing.write_text("keep me")
    status, stdout, err = run_cli([command, "--out", str(existing)], capsys)
    assert_refused(
        status,
        stdout,
        err,
        command,
        f"cannot write to {existing}: it is a file, not a folder; choose another --out",
    )
    assert existing.read_text() == "keep me"


@pytest.mark.parametrize(
    ("code", "reason"),
    [(errno.EACCES, "permission denied"), (errno.EROFS, "read-only file system")],
)
def test_unwritable_output_folder_is_refused_before_work(
    code, reason, tmp_path, capsys, monkeypatch, no_work
):
    def refuse(*args: object, **kwargs: object) -> None:
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr("piezo_cli.output.mkstemp", refuse)
    status, stdout, err = run_cli(["simulate", "--out", str(tmp_path)], capsys)
    assert_refused(status, stdout, err, "simulate", f"cannot write to {tmp_path}: {reason};")


@pytest.mark.skipif(
    hasattr(os, "geteuid") and os.geteuid() == 0,
    reason="root writes into read-only folders; the monkeypatched variant covers this case",
)
def test_read_only_output_folder_is_refused(tmp_path, capsys, no_work):
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        status, stdout, err = run_cli(["identify", "--out", str(folder / "sub")], capsys)
    finally:
        folder.chmod(0o755)
    assert_refused(status, stdout, err, "identify", "permission denied; choose another --out")


def test_prepare_output_dir_creates_parents_and_leaves_no_probe(tmp_path):
    folder = prepare_output_dir(tmp_path / "a" / "b")
    assert folder == tmp_path / "a" / "b" and folder.is_dir()
    assert list(folder.iterdir()) == []
    assert prepare_output_dir(str(folder)) == folder  # an existing folder is fine


def test_prepare_output_dir_raises_command_line_error(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(CommandLineError, match=r"choose another --result$"):
        prepare_output_dir(tmp_path / "f", option="--result")
    with pytest.raises(CommandLineError, match="the path is empty"):
        prepare_output_dir("")


# -- values the run would clip, alias or choke on ---------------------------------------------


@pytest.mark.parametrize(
    ("argv", "fragments"),
    [
        (["--amplitude", "100"], ["--amplitude 100 V", "choose 0 to 30 V"]),
        (["--amplitude", "-5"], ["--amplitude -5 V", "choose 0 to 30 V"]),
        (["--amplitude", "nan"], ["--amplitude", "finite"]),
        (["--frequency", "0"], ["--frequency 0 Hz", "above 0 and below 500 Hz"]),
        (["--frequency", "-1"], ["--frequency -1 Hz", "above 0 and below 500 Hz"]),
        (["--frequency", "500"], ["--frequency 500 Hz", "Nyquist"]),
        (["--frequency", "30", "--dt", "0.05"], ["below 10 Hz", "--dt 0.05 s"]),
        (["--frequency", "nan"], ["--frequency", "finite"]),
        (["--frequency", "5", "--signal", "chirp"], ["--frequency applies only to"]),
        (["--dt", "1"], ["--frequency 1 Hz (the default)", "below 0.5 Hz"]),
        (["--duration", "1e9"], ["--duration 1e+09 s", "the limit is 1,000,000"]),
        (["--duration", "2", "--dt", "1e-6"], ["2,000,000 samples", "the limit is 1,000,000"]),
        (["--duration", "0"], ["--duration", "greater than 0"]),
        (["--duration", "-1"], ["--duration", "greater than 0"]),
        (["--duration", "nan"], ["--duration", "finite"]),
        (["--duration", "inf"], ["--duration", "finite"]),
        (["--noise-bound", "-1"], ["--noise-bound", "0 or more"]),
        (["--noise-bound", "inf"], ["--noise-bound", "finite"]),
        (["--dt", "0"], ["--dt", "greater than 0"]),
        (["--dt", "nan"], ["--dt", "finite"]),
        (["--seed", "-1"], ["--seed", "whole number >= 0"]),
        (["--seed", "1.5"], ["--seed", "whole number >= 0"]),
        (["--bender", "PL999"], ["unknown bender 'PL999'", "PL140"]),
        (["--hysteresis", "preisach"], ["--hysteresis", "bouc-wen"]),
        (["--signal", "sawtooth"], ["--signal", "invalid choice"]),
    ],
)
def test_simulate_refuses_out_of_range_values_before_work(
    argv, fragments, tmp_path, capsys, no_work
):
    out = tmp_path / "never"
    status, stdout, err = run_cli(["simulate", *argv, "--out", str(out)], capsys)
    assert_refused(status, stdout, err, "simulate", *fragments)
    assert not out.exists()


@pytest.mark.parametrize(
    "argv", [["--seed", "-3"], ["--noise-bound", "nan"], ["--dt", "-1"], ["--bender", "x"]]
)
def test_identify_refuses_bad_values_before_work(argv, tmp_path, capsys, no_work):
    status, stdout, err = run_cli(["identify", *argv, "--out", str(tmp_path / "o")], capsys)
    assert_refused(status, stdout, err, "identify", argv[0])


ROOT = Path(__file__).resolve().parents[1]
MODEL = str(ROOT / "docs" / "identify" / "model")
FEEDFORWARD_PI = "examples.feedforward_pi:FeedforwardPI"


@pytest.fixture
def no_output_folder(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if a subcommand makes its output folder (the refusal must come first)."""

    def must_not_make(*args: object, **kwargs: object) -> None:
        pytest.fail("the output folder was made although the call should have been refused")

    for module in ("benchmark", "identify", "simulate"):
        monkeypatch.setattr(f"piezo_cli.{module}.prepare_output_dir", must_not_make)
    monkeypatch.setattr("benchmarks.runner.run_benchmark", must_not_make)
    monkeypatch.chdir(ROOT)  # entry points import from the current folder, as python -m does


@pytest.mark.parametrize(
    ("argv", "fragments"),
    [
        (
            ["benchmark", "--model", MODEL, "--controllers", f"mpc,{FEEDFORWARD_PI}",
             "--option", "FeedforwardPI.kk=1"],
            ["unknown option(s) ['kk']", "valid: ki"],
        ),
        (
            ["benchmark", "--model", MODEL, "--controllers", f"mine={FEEDFORWARD_PI}",
             "--option", "mine.gain=2"],
            ["unknown option(s) ['gain']", "FeedforwardPI"],
        ),
        (["benchmark", "--model", MODEL, "--option", "mpc.horizon=0"], ["horizon"]),
        (["benchmark", "--model", MODEL, "--option", "lqr.q=1"], ["'lqr', which is not"]),
        (["benchmark", "--model", "/nonexistent/model"], ["cannot load the model"]),
        (["benchmark", "--model", MODEL, "--bender", "PL122"], ["identified on PL140.10"]),
        (["benchmark", "--model", MODEL, "--dt", "1e-4"], ["identified at dt = 0.001 s"]),
        (["benchmark", "--address", "auto"], ["--address is for --backend ray"]),
        (
            ["benchmark", "--model", MODEL, "--controllers", "mpc-adaptive",
             "--option", "mpc-adaptive.damping_range=0.02"],
            ["damping_range must be a pair (low, high)", "got 0.02"],
        ),
        (
            ["benchmark", "--model", MODEL, "--controllers", "mpc-adaptive",
             "--option", "mpc-adaptive.damping_range=0.04,0.01"],
            ["damping_range must be a pair (low, high)", "got (0.04, 0.01)"],
        ),
        (["benchmark", "--model", MODEL, "--option", "mpc.shortcut=no"], ["shortcut", "'no'"]),
        (["benchmark", "--model", MODEL, "--option", "nmpc.shortcut=none"], ["shortcut"]),
        (["benchmark", "--model", MODEL, "--controllers", "policy"], ["--policies DIR"]),
        (
            ["benchmark", "--model", MODEL, "--controllers", "mpc,ppo",
             "--option", "ppo-seed0.gain=2"],
            ["unknown option(s) ['gain'] for controller 'policy'", "valid: initial_voltage"],
        ),
        (
            ["benchmark", "--bender", "PL127", "--model", str(ROOT / "docs" / "benchmark-PL127"
             / "model"), "--controllers", "ppo"],
            ["no controller to run: policies: left out ppo-seed0", "dt = 0.00025 s"],
        ),
        (
            ["benchmark", "--model", MODEL, "--plants", "nominal,nominal"],
            ["plants must be distinct", "nominal more than once"],
        ),
        (
            ["benchmark", "--model", MODEL, "--references", "steps,steps"],
            ["references must be distinct"],
        ),
        (
            ["benchmark", "--model", MODEL, "--plants", "nominal", "--draws", "3"],
            ["--draws sets the random-plants"],
        ),
        (["identify", "--features", "bouc-wen", "--rate", "on"], ["features='play'"]),
        (["identify", "--records", "/nonexistent/records"], ["records.json: missing"]),
        (["identify", "--split", "0.5"], ["--split applies to --records"]),
        (["simulate", "--records", "/nonexistent/records"], ["records.json: missing"]),
        (["simulate", "--amplitude", "100"], ["--amplitude 100 V"]),
        (["identify", "--dt", "-1e-3"], ["--dt", "greater than 0, got '-1e-3'"]),
        (["benchmark", "--dt", "-1E-3"], ["--dt", "greater than 0, got '-1E-3'"]),
        (["simulate", "--duration", "-.5e1"], ["--duration", "greater than 0, got '-.5e1'"]),
    ],
)
@pytest.mark.filterwarnings("ignore:dt = .*aliases its first mode:UserWarning")  # on purpose
def test_bad_calls_are_refused_before_the_output_folder_is_made(
    argv, fragments, tmp_path, capsys, no_work, no_output_folder
):
    out = tmp_path / "new" / "out"
    status, stdout, err = run_cli([*argv, "--out", str(out)], capsys)
    assert_refused(status, stdout, err, argv[0], *fragments)
    assert not (tmp_path / "new").exists()


def test_an_option_of_comma_separated_numbers_is_a_tuple():
    from piezo_cli.benchmark import _option

    assert _option("mpc-adaptive.damping_range=0.01,0.04") == (
        "mpc-adaptive", "damping_range", (0.01, 0.04)
    )
    assert _option("pid.damping_range=1,2") == ("pid", "damping_range", (1, 2))
    assert _option("mine.label=a,b") == ("mine", "label", "a,b")  # not all numbers: text
    for text in ("mpc.rate_weight=nan", "mpc.rate_weight=inf", "pid.damping_range=0.01,nan"):
        with pytest.raises(argparse.ArgumentTypeError, match="not a finite number"):
            _option(text)


@pytest.mark.parametrize("name", ["PL140", "PL140.10", "pl140", "PL112.10"])
def test_bender_accepts_catalogue_names_with_and_without_suffix(name):
    args = build_parser().parse_args(["simulate", "--bender", name])
    assert args.bender == name.upper()


@pytest.mark.parametrize("text", ["-1", "-0.5", "-.5", "-1e-3", "-2.5E+2", "-1.e1"])
def test_negative_numbers_in_any_notation_are_values(text):
    args = build_parser().parse_args(["simulate", "--amplitude", text])
    assert args.amplitude == float(text)


@pytest.mark.parametrize("text", ["-inf", "-NaN"])
def test_negative_non_finite_words_are_values_the_type_refuses(text, tmp_path, capsys):
    status, stdout, err = run_cli(["simulate", "--amplitude", text, "--out", str(tmp_path)], capsys)
    assert_refused(status, stdout, err, "simulate", "--amplitude", "finite")


def test_off_words_keep_working():
    args = build_parser().parse_args(["simulate", "--hysteresis", "off", "--noise-bound", "off"])
    assert (args.hysteresis, args.noise_bound) == ("none", 0.0)


def test_package_errors_are_one_line_in_terminal_terms(tmp_path, capsys, monkeypatch):
    def fail(*args: object, **kwargs: object) -> None:
        raise ValueError(
            "unknown bender 'X'; choose one of ['PL140.10'] (the '.10' suffix is optional) or "
            "pass a BenderDatasheet\nnoise_bound must be a finite number >= 0 (um)"
        )

    monkeypatch.setattr("piezo_env.simulate.run_open_loop", fail)
    status, stdout, err = run_cli(["simulate", "--out", str(tmp_path)], capsys)
    assert_refused(status, stdout, err, "simulate", "--noise-bound must be")


def test_file_errors_during_the_work_are_one_line(tmp_path, capsys, monkeypatch):
    def fail(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "simulate.csv"))

    monkeypatch.setattr("piezo_env.simulate.run_open_loop", fail)
    status, _, err = run_cli(["simulate", "--out", str(tmp_path)], capsys)
    assert status == 1
    assert err.splitlines() == [
        f"piezo simulate: cannot write {tmp_path / 'simulate.csv'}: {os.strerror(errno.ENOSPC)}"
    ]


# -- help, version and the registration of subcommands -----------------------------------------


def test_version(capsys):
    status, out, _ = run_cli(["--version"], capsys)
    assert status == 0
    assert out.strip() == f"piezo {version('piezo-testbed')}"


def test_help_speaks_to_a_person_and_shows_defaults(capsys):
    status, out, _ = run_cli(["--help"], capsys)
    assert status == 0
    assert "dispatcher" not in out and "piezoelectric bender" in out
    assert "examples:" in out and "piezo identify --out out/pl140" in out
    status, out, _ = run_cli(["simulate", "--help"], capsys)
    assert status == 0
    flat = " ".join(out.split())
    for default in (
        "(default: sine)",
        "(default: 30.0)",
        "(default: 3.0)",
        "(default: 0)",
        "(default: PL140)",
        "(default: bouc-wen)",
        "(default: the bender's",  # --dt: piezo_env.default_dt of the bender
        "1 ms for the PL140",
        "(default: out/simulate)",
    ):
        assert default in flat
    assert "piezo simulate --signal sine --amplitude 30 --frequency 1" in out
    status, out, _ = run_cli(["identify", "--help"], capsys)
    assert "(default: out/identify)" in " ".join(out.split())


def test_a_subcommand_is_one_registration(tmp_path, capsys, monkeypatch):
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--out", default=str(tmp_path / "echo"))

    def run(args: argparse.Namespace) -> int:
        print(prepare_output_dir(args.out))
        return 0

    echo = Subcommand("echo", "print the output folder", "Echo.", add_arguments, run)
    monkeypatch.setattr(cli, "SUBCOMMANDS", [*cli.SUBCOMMANDS, echo])
    status, out, _ = run_cli(["echo"], capsys)
    assert (status, out.strip()) == (0, str(tmp_path / "echo"))
    status, stdout, err = run_cli(["echo", "--out", "/dev/null/x"], capsys)
    assert_refused(status, stdout, err, "echo", "/dev/null is a file, not a folder")


@pytest.mark.slow
def test_identify_writes_model_report_and_figures(tmp_path):
    assert main(["identify", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["validation"]["hammerstein"]["fit_percent"] > 95.0
    for name in ("model/model.json", "model/weights.npz", "report.md", "validation.png"):
        assert (tmp_path / name).exists()


def test_the_console_script_exits_with_its_status_after_its_output_and_exit_handlers():
    """``piezo`` skips the interpreter's finalization (piezo_parallel.pool.quick_exit), not
    the exit handlers or the end of its output, even into a pipe. Finalization would join a
    non-daemon thread that sleeps for ten minutes: the command ends without it."""
    import subprocess
    import sys

    code = (
        "import atexit, sys, threading, time; atexit.register(print, 'exit handlers ran'); "
        "threading.Thread(target=time.sleep, args=(600,)).start(); "
        "sys.argv = ['piezo', 'identify', '--split', '0.5']; "
        "from piezo_cli.main import console_main; print('before', end=''); console_main()"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 2
    assert done.stdout == "beforeexit handlers ran\n"
    assert done.stderr.startswith("piezo identify: --split applies to --records")
