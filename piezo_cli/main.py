"""``piezo``: the command line of the testbed, a thin dispatcher over the packages.

Each subcommand is one :class:`piezo_cli.command.Subcommand` registration in
:data:`SUBCOMMANDS`; its module adds its options and calls the package that owns the work. To
add a subcommand, write ``add_arguments(parser)`` and ``run(args) -> int`` in a new module under
``piezo_cli/`` (calling :func:`piezo_cli.output.prepare_output_dir` on its output folder and
:func:`piezo_cli.arguments.add_env_arguments` for the bender options), wrap them in a
``Subcommand`` and append it to :data:`SUBCOMMANDS`.
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
import textwrap
from importlib.metadata import PackageNotFoundError, version
from typing import NoReturn

from piezo_cli.benchmark import BENCHMARK
from piezo_cli.command import CommandLineError, Subcommand
from piezo_cli.compare import COMPARE
from piezo_cli.excite import EXCITE
from piezo_cli.identify import IDENTIFY
from piezo_cli.output import clear_incomplete, mark_incomplete, missing_folders, remove_if_empty
from piezo_cli.signals import Caught, signals_interrupt
from piezo_cli.simulate import SIMULATE
from piezo_cli.train_rl import TRAIN_RL

__all__ = ["SUBCOMMANDS", "build_parser", "console_main", "main"]

SUBCOMMANDS: list[Subcommand] = [SIMULATE, EXCITE, IDENTIFY, BENCHMARK, COMPARE, TRAIN_RL]
"""Every ``piezo`` subcommand, in the order ``piezo --help`` lists them."""

_DESCRIPTION = (
    "Simulate a piezoelectric bender (PI PICMA PL1xx family: finite-element beam with "
    "hysteresis and sensor noise), identify its Hammerstein model from data, and benchmark "
    "MPC against PID on it in closed loop."
)

_API_PHRASES = (
    (re.compile(r"\s*\(?\bor pass a BenderDatasheet\)?"), ""),
    (re.compile(r",?\s*\bor a Hysteresis\b"), ""),
    (re.compile(r"\bnoise_bound\b"), "--noise-bound"),
    (re.compile(r"\bdamping_ratio\b"), "damping ratio"),
    (re.compile(r"\bn_elements\b"), "number of elements"),
)


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults after each option's help (not for flags and options without one); paragraphs
    wrapped, blocks of several lines (the examples) kept as typed."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False or "(default:" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        blocks = []
        for block in text.split("\n\n"):
            if "\n" in block:
                blocks.append(textwrap.indent(block, indent))
            else:
                blocks.append(
                    textwrap.fill(block, width, initial_indent=indent, subsequent_indent=indent)
                )
        return "\n\n".join(blocks)


_NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.I)
"""What argparse reads as a negative number, not an option: any notation float() reads."""


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line: ``piezo simulate: <what is wrong>``.

    argparse takes an argument that starts with ``-`` for an option unless it matches its
    negative-number pattern, which knows ``-1`` and ``-0.5`` but not ``-1e-3``, so
    ``--dt -1e-3`` would end in "expected one argument". No option of ``piezo`` looks like a
    number, so every number-looking argument is a value here, which the option's type then
    checks (``--dt -1e-3``: "must be greater than 0").
    """

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see '{self.prog} --help')\n")


def _examples(lines: tuple[str, ...]) -> str | None:
    return "examples:\n" + "\n".join(f"  {line}" for line in lines) if lines else None


def _package_version() -> str:
    try:
        return version("piezo-testbed")
    except PackageNotFoundError:
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    """The ``piezo`` argument parser, with one subparser per entry of :data:`SUBCOMMANDS`.

    Returns
    -------
    argparse.ArgumentParser
        Parses ``argv``; ``args.subcommand`` is the chosen :class:`Subcommand`.
    """
    parser = _Parser(
        prog="piezo",
        description=_DESCRIPTION,
        epilog=_examples(tuple(line for command in SUBCOMMANDS for line in command.examples[:1]))
        + "\n\nRun 'piezo COMMAND --help' for the options of a command.",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in SUBCOMMANDS:
        subparser = sub.add_parser(
            command.name,
            help=command.help,
            description=command.description,
            epilog=_examples(command.examples),
            formatter_class=_HelpFormatter,
        )
        command.add_arguments(subparser)
        subparser.set_defaults(subcommand=command)
    return parser


def _for_terminal(message: str) -> str:
    """A package's error message in command-line terms, on one line."""
    for pattern, replacement in _API_PHRASES:
        message = pattern.sub(replacement, message)
    return " ".join(message.split())


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``piezo`` console script.

    Parameters
    ----------
    argv : list of str, optional
        Arguments after ``piezo``; default ``sys.argv[1:]``.

    Returns
    -------
    int
        Exit status: 0 done, 2 refused call (one line on stderr, nothing done), 1 a file or
        folder failed or a worker process was lost for good during the work, 128 + the
        signal's number when interrupted by SIGINT (130), SIGTERM (143) or SIGHUP (129): the
        workers are stopped, and an output folder that holds anything says in
        ``INCOMPLETE.txt`` that the run did not finish.
    """
    from piezo_parallel.pool import WorkerLost

    args = build_parser().parse_args(argv)
    prefix = f"piezo {args.command}"
    out = getattr(args, "out", None)
    new_folders = missing_folders(out)
    caught = Caught()
    try:
        with signals_interrupt() as caught:
            status = args.subcommand.run(args)
        clear_incomplete(out, prefix)
        return status
    except (CommandLineError, ValueError) as error:
        remove_if_empty(new_folders)
        print(f"{prefix}: {_for_terminal(str(error))}", file=sys.stderr)
        return 2
    except OSError as error:
        remove_if_empty(new_folders)
        where = f" {error.filename}" if error.filename else ""
        print(f"{prefix}: cannot write{where}: {error.strerror or error}", file=sys.stderr)
        return 1
    except WorkerLost as error:
        remove_if_empty(new_folders)
        mark_incomplete(out, prefix, f"stopped: {error}", replace=False)
        print(f"{prefix}: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM / SIGHUP as piezo_cli.signals
        signum = getattr(stop, "signum", None) or caught.signum or signal.SIGINT
        how = f"interrupted by {signal.Signals(signum).name}"
        remove_if_empty(new_folders)
        mark_incomplete(out, prefix, f"was {how}", replace=False)
        print(f"{prefix}: {how}", file=sys.stderr)
        return 128 + signum


def console_main() -> NoReturn:
    """The ``piezo`` console script: :func:`main`, then exit with its status without the
    interpreter's finalization (:func:`piezo_parallel.pool.quick_exit`: slow with torch
    loaded, and nothing is left for it once the command's work and output are done)."""
    from piezo_parallel.pool import quick_exit

    quick_exit(main())


if __name__ == "__main__":
    console_main()
