"""Where the independent computations of one identification run: :func:`step_runner`.

Three steps hold computations that do not depend on each other:

- step b fits the ARX part at every candidate order (:func:`identification.steps.estimate_arx`);
- step e trains one network per candidate feature set, each from its own seed on the same
  data (:func:`identification.steps.fit_nonlinearity`);
- step e' refines the chosen network and then, depending on what that refinement shows, also
  a rate-dependent variant (``rate="auto"``, when the learned radii let the records determine a
  rate constant) or the play rival (learned radii, when the choice is not at the sensor's noise
  floor) (:func:`identification.steps.refine_and_choose`). Each of those starts from step e's
  result alone, so it can start before the decision that needs it is made: the rate-dependent
  refinement always does, the rival when no sensor bound can rule it out (measured records
  without one); with a bound it waits for the noise-floor test, which on the nominal PL140
  finds it unneeded, and two processes sharing two cores slow each other more than a rival
  started in vain could save. A rival refined in this process hands its own rate-dependent
  refinement to the helper, as step e's play choice does (the bench plant when step e chose
  Bouc-Wen features).

Where nothing else runs beside, the helper would sit idle; the figures of
:func:`identification.outputs.write_outputs` are drawn on both processes then
(:attr:`StepRunner.idle`). A refinement's objective is not shared: since its free run is the
ARX recursion (:mod:`identification.nls.free_run`), an evaluation costs about what sending the
parameters to the helper and its gradient back costs. In step e every
candidate goes to the helper while this process imports torch and makes its first training,
which it needs for step e' anyway; it then takes back (:meth:`Pending.take_back`) the candidates
the helper has not started.

A :class:`StepRunner` runs such a computation "beside" the main line. With one job it is
computed here, when its result is first asked for (a computation the decision does not need is
never computed: the work is what it was before there was a runner). With two or more, a
:class:`piezo_parallel.helper.Helper` process, started when the run starts so that its start-up
overlaps the experiment, computes it while this process computes the main line; one whose
decision falls the other way is withdrawn. The helper fits step b's smaller orders first, then
imports torch and makes its first training (its warm-up) while this process ends steps b-d.

The model is the same to the bit whatever the jobs: every computation is deterministic (float64,
one torch thread, its own seeded generators), reads nothing another one writes, and gets the
same arrays, pickled exactly; only where it runs changes (a test holds it). One helper, not
more: the run's two parallel branches are at most two wide.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from typing import Any, Protocol

__all__ = ["Pending", "StepRunner", "step_runner"]


class Pending(Protocol):
    """A computation started by :meth:`StepRunner.beside` or :meth:`StepRunner.here`."""

    def result(self) -> Any:
        """Its value (computed, or waited for, on the first call)."""

    def withdraw(self) -> None:
        """It is no longer wanted."""

    def take_back(self) -> bool:
        """Compute it in this process (at :meth:`result`) if the helper has not started it;
        whether it will be computed here."""


class _Here:
    """Computed in this process on the first :meth:`result` (never, if withdrawn first)."""

    def __init__(self, call: Callable[[], Any]) -> None:
        self._call: Callable[[], Any] | None = call
        self._value: Any = None
        self._withdrawn = False

    def result(self) -> Any:
        if self._call is not None:
            self._value, self._call = self._call(), None
        return self._value

    def withdraw(self) -> None:
        self._call, self._withdrawn = None, True

    def take_back(self) -> bool:
        return not self._withdrawn


class _There:
    """Computed by the helper process, or here once taken back before the helper started it."""

    def __init__(self, helper: Any, call: Callable[[], Any]) -> None:
        self._helper, self._ticket, self._call = helper, helper.submit(call), call
        self._done, self._taken, self._value = False, False, None

    def result(self) -> Any:
        if not self._done:
            value = self._call() if self._taken else self._helper.result(self._ticket)
            self._value, self._done = value, True
        return self._value

    def withdraw(self) -> None:
        if not self._done:
            if not self._taken:
                self._helper.withdraw(self._ticket)
            self._done = True

    def take_back(self) -> bool:
        if not (self._done or self._taken):
            self._taken = self._helper.take_back(self._ticket)
        return self._taken


class StepRunner:
    """Runs an identification's independent computations here or beside it (module docstring).

    Parameters
    ----------
    helper : piezo_parallel.helper.Helper, optional
        The process that computes :meth:`beside` calls; None computes them here, lazily.
    warm_up : callable, optional
        A module-level function the helper runs, its outcome discarded, when
        :meth:`warm_up_helper` is first called.
    """

    def __init__(self, helper: Any | None = None, warm_up: Callable[[], Any] | None = None) -> None:
        self._helper = helper
        self._warm_up = warm_up if helper is not None else None

    @property
    def parallel(self) -> bool:
        """Whether :meth:`beside` runs on another process."""
        return self._helper is not None

    @property
    def idle(self) -> bool:
        """Whether a helper is there and computes nothing now, so that a computation asked of
        it starts at once (the figures are then drawn on both processes)."""
        return self._helper is not None and self._helper.idle

    def warm_up_helper(self) -> None:
        """Queue the helper's warm-up behind what was asked of it so far (once; nothing
        without a helper or a warm-up). Step b calls it once its orders are queued: the helper
        fits some of them while this process fits the others, then imports torch and makes its
        first training while this process finishes steps b to d (before, its warm-up ran first
        and it sat idle through part of step b)."""
        warm_up, self._warm_up = self._warm_up, None
        if warm_up is not None:
            self._helper.withdraw_later(self._helper.submit(warm_up))

    def beside(self, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Pending:
        """``function(*args, **kwargs)`` (module-level) on the helper, or here when first
        asked for."""
        call = partial(function, *args, **kwargs)
        return _There(self._helper, call) if self._helper is not None else _Here(call)

    def take_back_from_last(self, pending: list[Pending]) -> None:
        """Compute here, from the last, the ones of ``pending`` (queued on the helper in order)
        the helper has not started, until it has started one: the helper works from the
        first, this process from the last, and neither waits for the other longer than one
        computation. Nothing to do without a helper (each is computed when asked for)."""
        if not self.parallel:
            return
        for item in reversed(pending):
            if not item.take_back():
                break
            item.result()

    @staticmethod
    def here(function: Callable[..., Any], *args: Any, **kwargs: Any) -> Pending:
        """``function(*args, **kwargs)`` in this process, when first asked for."""
        return _Here(partial(function, *args, **kwargs))


@contextmanager
def step_runner(jobs: int = 1, warm_up: Callable[[], Any] | None = None) -> Iterator[StepRunner]:
    """A :class:`StepRunner` for one identification; with ``jobs >= 2`` its helper process is
    started now and stopped when the block ends (a computation still running is terminated).

    Parameters
    ----------
    jobs : int
        Processes the run may use (>= 1): 1 computes everything here; 2 or more start one
        helper (module docstring).
    warm_up : callable, optional
        A module-level function the helper runs when the run asks for it
        (:meth:`StepRunner.warm_up_helper`, which step b calls behind its orders):
        :func:`identification.steps.warm_up`, its imports and torch's first training.
    """
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be an integer >= 1 (processes to use), got {jobs!r}")
    if jobs == 1:
        yield StepRunner()
        return
    from piezo_parallel.helper import Helper

    with Helper() as helper:
        yield StepRunner(helper, warm_up)
