"""``piezo compare``: the command line of :mod:`benchmarks.compare`."""

from __future__ import annotations

import argparse

from piezo_cli.command import CommandLineError, Subcommand

__all__ = ["COMPARE"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``piezo compare``."""
    parser.add_argument("old", metavar="OLD.json", help="benchmark.json of the earlier run")
    parser.add_argument("new", metavar="NEW.json", help="benchmark.json of the later run")
    parser.add_argument(
        "--strict", action="store_true", help="exit with status 1 when a change is beyond noise"
    )


def run(args: argparse.Namespace) -> int:
    """Print the table of changes; with --strict, fail on a change beyond the noise."""
    from benchmarks.compare import compare_files

    try:
        table, marked = compare_files(args.old, args.new)
    except ValueError as error:
        raise CommandLineError(str(error)) from None
    print(table)
    print(f"{marked} change(s) beyond the run-to-run noise")
    return 1 if args.strict and marked else 0


COMPARE = Subcommand(
    name="compare",
    help="what changed between two benchmark runs, beyond the run-to-run noise",
    description=(
        "Compare two benchmark.json files of piezo benchmark cell by cell (plant, controller, "
        "reference): RMSE before and after, the change, and whether it is beyond the noise "
        "(outside the 95 % intervals with --seeds, else more than 2 % relative)."
    ),
    add_arguments=add_arguments,
    run=run,
    examples=("piezo compare docs/benchmark/benchmark.json out/benchmark/benchmark.json",),
)
