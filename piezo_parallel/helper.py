"""One spawned worker process that runs calls beside this process: :class:`Helper`.

The pool (:mod:`piezo_parallel.pool`) runs a known list of tasks and returns when they are done.
A computation whose independent parts appear one after the other (the identification's
candidate fits, then a refinement that may or may not be needed) wants a worker that is
started early, so that its imports overlap this process's own work, and that takes calls as
they come while this process computes beside it. :class:`Helper` is that worker: calls run one
at a time, in the order submitted; :meth:`Helper.result` waits for one. A call that is no longer
wanted is withdrawn (:meth:`Helper.withdraw`): dropped if it has not started, left to finish and
its outcome discarded if it has. :meth:`Helper.close` stops the worker, terminating a call still
running, so that nothing outlives the computation that started it.

The worker is the pool's (the same spawned process, signal handling and exit with its parent),
and a call's exception comes back as the pool's do, with the worker's traceback chained. A
worker that dies (the out-of-memory killer's SIGKILL, a crash in native code) ends every call
not yet answered with :class:`~piezo_parallel.pool.WorkerLost` (naming how it ended); no call
runs twice, and the caller decides what to do. A call's arguments are pickled when it is
submitted, so the worker gets them as they were then, and an argument that cannot be pickled
is refused at once.
"""

from __future__ import annotations

import threading
import traceback
from collections import deque
from collections.abc import Callable
from multiprocessing import get_context
from multiprocessing.connection import wait
from multiprocessing.reduction import ForkingPickler
from typing import Any

from piezo_parallel.pool import RemoteTraceback, WorkerLost, _Call, _ending, _start, _stop

__all__ = ["Helper"]


def _no_default(*_args: Any) -> None:
    """The worker's default function: a helper sends every call with its own function."""
    raise RuntimeError("a helper runs only calls sent with their function")


class Helper:
    """A spawned worker process running submitted calls one at a time (module docstring).

    Parameters
    ----------
    warm_up : callable, optional
        A module-level function run first in the worker (its imports, say), so that the first
        real call does not pay for them. Its outcome is discarded, a failure too: a warm-up
        only saves time, and a cause that outlives it (a module that cannot be imported) makes
        the calls that need it fail with their own error.
    """

    def __init__(self, warm_up: Callable[[], Any] | None = None) -> None:
        self._worker = _start(get_context("spawn"), _no_default)
        self._lock = threading.Condition()
        self._queue: deque[tuple[int, bytes]] = deque()
        self._answers: dict[int, tuple[str, Any, str]] = {}
        self._waiting: set[int] = set()  # submitted, neither answered to result() nor withdrawn
        self._running: int | None = None
        self._next = 0
        self._lost: str | None = None
        self._closed = False
        if warm_up is not None:  # runs first; its outcome, a failure too, is discarded
            self.withdraw_later(self.submit(warm_up))
        self._feeder = threading.Thread(target=self._feed, name="piezo-helper", daemon=True)
        self._feeder.start()

    def submit(self, function: Callable[..., Any], *args: Any) -> int:
        """Queue ``function(*args)`` (module-level, picklable; pickled now); returns its
        ticket."""
        call = ForkingPickler.dumps(_Call(function, args))  # what Connection.send would send
        with self._lock:
            if self._closed:
                raise RuntimeError("the helper is closed")
            ticket = self._next
            self._next += 1
            self._queue.append((ticket, bytes(call)))
            self._waiting.add(ticket)
            self._lock.notify_all()
        return ticket

    def result(self, ticket: int) -> Any:
        """Wait for the call ``ticket`` and return its value, or raise its exception (the
        worker's traceback chained) or :class:`~piezo_parallel.pool.WorkerLost`; each ticket
        answers once (KeyError after that, or after :meth:`withdraw`)."""
        with self._lock:
            if ticket not in self._waiting:
                raise KeyError(f"no call {ticket} is waiting for its result")
            while ticket not in self._answers:
                if self._lost is not None:
                    raise WorkerLost(
                        f"the helper process {self._lost} before call {ticket} was answered; "
                        "run without a helper (jobs=1) to compute it in this process"
                    )
                if self._closed:
                    raise RuntimeError("the helper is closed")
                self._lock.wait()
            kind, value, text = self._answers.pop(ticket)
            self._waiting.discard(ticket)
        if kind == "error":
            raise value from RemoteTraceback(text)
        return value

    def withdraw(self, ticket: int) -> None:
        """The call ``ticket`` is no longer wanted: dropped if not started; otherwise it runs
        on, and its outcome is discarded."""
        with self._lock:
            self._unqueue(ticket)
            self._waiting.discard(ticket)
            self._answers.pop(ticket, None)

    def take_back(self, ticket: int) -> bool:
        """Drop the call ``ticket`` if the worker has not started it (the caller computes it
        itself then); True when it was dropped, False when it has started or been answered."""
        with self._lock:
            if not self._unqueue(ticket):
                return False
            self._waiting.discard(ticket)
            return True

    def withdraw_later(self, ticket: int) -> None:
        """The call ``ticket`` runs, but its outcome is not wanted (a warm-up)."""
        with self._lock:
            self._waiting.discard(ticket)
            self._answers.pop(ticket, None)

    @property
    def idle(self) -> bool:
        """Whether a call submitted now would start at once: the worker is alive, the helper
        open, and nothing runs or waits."""
        with self._lock:
            lost_or_closed = self._lost is not None or self._closed
            return not (lost_or_closed or self._running is not None or self._queue)

    def _unqueue(self, ticket: int) -> bool:
        """Drop the call ``ticket`` from the queue (under the lock); whether it was there."""
        queued = [t for t, _ in self._queue]
        if ticket not in queued:
            return False
        del self._queue[queued.index(ticket)]
        return True

    def close(self) -> None:
        """Stop the worker (a call still running is terminated) and reap it."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.clear()
            running = self._running is not None
            self._lock.notify_all()
        if running:  # the feeder waits on the worker: its end wakes the feeder
            self._worker.process.terminate()
        self._feeder.join()  # before the pipe is closed under it
        self._worker.task = 0 if self._worker.process.is_alive() and running else None
        _stop([self._worker])

    def __enter__(self) -> Helper:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _feed(self) -> None:
        """The feeder thread: send the next call when the worker is idle, file its answer.

        Whatever goes wrong here is filed as the call's answer or as the worker's loss, so
        that :meth:`result` never waits for an answer that cannot come."""
        worker = self._worker
        while True:
            with self._lock:
                while not self._queue and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                ticket, call = self._queue.popleft()
                self._running = ticket
            answer: tuple[str, Any, str] | None
            try:
                worker.conn.send_bytes(call)
                wait([worker.conn, worker.process.sentinel])
                answer = worker.conn.recv() if worker.conn.poll() else None
            except (EOFError, OSError):  # the worker is gone: its sentinel tells how
                answer = None
            except BaseException as error:  # an answer that cannot be unpickled here
                failure = RuntimeError(f"cannot read the helper's answer to call {ticket}: {error}")
                answer = ("error", failure, traceback.format_exc())
            with self._lock:
                self._running = None
                if self._closed:
                    return
                if answer is None:  # the worker died
                    self._lost = _ending(worker)
                    self._lock.notify_all()
                    return
                if ticket in self._waiting:
                    self._answers[ticket] = answer
                self._lock.notify_all()
