"""SIGTERM and SIGHUP stop a ``piezo`` command the way Ctrl-C does.

A batch scheduler, ``timeout``, ``docker stop`` and systemd end a job with SIGTERM (a closed
terminal sends SIGHUP). Python's default for them ends the process at once, without unwinding:
its workers are orphaned and its output folder is left half-written. Inside
:func:`signals_interrupt`, SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` where the work
is, so the same clean-up runs as after Ctrl-C (``finally`` blocks stop the workers, the command
keeps what finished) and the command exits with status 128 + the signal's number.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType

__all__ = ["SIGNALS", "Caught", "Interrupted", "signals_interrupt"]

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""The signals that interrupt a command."""


class Interrupted(KeyboardInterrupt):
    """A command stopped by a signal; a ``KeyboardInterrupt``, so every handler of Ctrl-C
    handles it too.

    Parameters
    ----------
    signum : int
        The signal's number; :attr:`status` is the exit status a shell expects after it.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def name(self) -> str:
        """The signal's name, ``"SIGTERM"``."""
        return signal.Signals(self.signum).name

    @property
    def status(self) -> int:
        """128 + the signal's number: 130 after SIGINT, 143 after SIGTERM, 129 after SIGHUP."""
        return 128 + self.signum

    def __str__(self) -> str:
        return f"interrupted by {self.name}"


@dataclass
class Caught:
    """The signal that interrupted a :func:`signals_interrupt` block (None: none did).

    Code between the signal and the ``except`` may turn :class:`Interrupted` into a plain
    ``KeyboardInterrupt`` (Ray's C++ core does when a signal handler raises inside
    ``ray.wait``); this record keeps which signal it was.
    """

    signum: int | None = None


@contextmanager
def signals_interrupt() -> Iterator[Caught]:
    """Raise :class:`Interrupted` on SIGINT, SIGTERM and SIGHUP inside the block.

    The first signal raises; later ones are ignored until the block is left, so that the
    clean-up it started (stopping workers, marking the output folder) is not cut short by a
    second Ctrl-C or a scheduler's repeated SIGTERM. The previous handlers are restored on
    exit. Outside the main thread (where Python cannot set handlers) the block runs unchanged.

    Yields
    ------
    Caught
        Which signal interrupted the block.
    """
    caught = Caught()
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return

    def stop(signum: int, frame: FrameType | None) -> None:
        for number in SIGNALS:
            signal.signal(number, signal.SIG_IGN)
        caught.signum = signum
        raise Interrupted(signum)

    saved = {number: signal.getsignal(number) for number in SIGNALS}
    for number in SIGNALS:
        signal.signal(number, stop)
    try:
        yield caught
    finally:
        for number, handler in saved.items():
            signal.signal(number, handler if handler is not None else signal.SIG_DFL)
