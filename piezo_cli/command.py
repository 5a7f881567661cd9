"""What every ``piezo`` subcommand is made of, and the error a subcommand raises for a bad call.

A subcommand is one :class:`Subcommand` registration: its name, a one-line help, a function
that adds its arguments to an argparse parser and a function that runs it. ``piezo_cli.main``
turns the list of registrations into the parser and dispatches to ``run``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["CommandLineError", "Subcommand"]


class CommandLineError(Exception):
    """A call the command line refuses before doing any work.

    ``piezo`` prints the message as one line, ``piezo <command>: <message>``, on stderr and exits
    with status 2 (the status argparse uses for usage errors). Write the message for a person at
    a terminal: name the option, the value and what would be accepted.
    """


@dataclass(frozen=True)
class Subcommand:
    """One ``piezo`` subcommand.

    Attributes
    ----------
    name : str
        The word typed after ``piezo`` (``"simulate"``).
    help : str
        One line shown by ``piezo --help``.
    description : str
        Paragraph shown at the top of ``piezo <name> --help``.
    add_arguments : callable
        ``add_arguments(parser)`` adds the subcommand's options to its parser.
    run : callable
        ``run(args) -> int`` validates the parsed arguments (raising :class:`CommandLineError`
        before any work), does the work by calling the package that owns it and returns the exit
        status.
    examples : tuple of str
        Command lines shown under "examples" in the help.
    """

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    examples: tuple[str, ...] = ()
