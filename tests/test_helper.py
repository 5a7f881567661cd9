"""The helper process (:class:`piezo_parallel.helper.Helper`): calls in order, failures with the
worker's traceback, withdrawn calls, a dead worker and a stop that leaves nothing running."""

from __future__ import annotations

import time

import faulty
import pytest

from piezo_parallel import WorkerLost
from piezo_parallel.helper import Helper
from piezo_parallel.pool import RemoteTraceback


def test_calls_run_in_order_and_answer_each_ticket(tmp_path):
    with Helper() as helper:
        log = tmp_path / "ran"
        tickets = [helper.submit(faulty.append, i, str(log)) for i in range(4)]
        assert [helper.result(t) for t in reversed(tickets)] == [3, 2, 1, 0]
        assert log.read_text(encoding="utf-8").split() == ["0", "1", "2", "3"]


def test_a_failing_call_raises_its_exception_with_the_workers_traceback():
    with Helper() as helper:
        ticket = helper.submit(faulty.raise_value_error, "broken on purpose")
        with pytest.raises(ValueError, match="broken on purpose") as caught:
            helper.result(ticket)
        assert isinstance(caught.value.__cause__, RemoteTraceback)
        assert "raise_value_error" in str(caught.value.__cause__)
        assert helper.result(helper.submit(faulty.mark_then, 7, "/dev/null")) == 7


def test_a_withdrawn_call_that_has_not_started_never_runs(tmp_path):
    with Helper() as helper:
        busy = helper.submit(faulty.mark_then, 1, str(tmp_path / "busy"), 0.5)
        queued = helper.submit(faulty.mark_then, 2, str(tmp_path / "queued"))
        helper.withdraw(queued)
        assert helper.result(busy) == 1
        assert helper.result(helper.submit(faulty.mark_then, 3, str(tmp_path / "after"))) == 3
    assert not (tmp_path / "queued").exists()


def test_a_withdrawn_running_call_finishes_and_its_outcome_is_dropped(tmp_path):
    with Helper() as helper:
        running = helper.submit(faulty.mark_then, 1, str(tmp_path / "running"), 0.3)
        while not (tmp_path / "running").exists():
            time.sleep(0.01)
        helper.withdraw(running)
        assert helper.result(helper.submit(faulty.mark_then, 2, str(tmp_path / "next"))) == 2


def test_a_dead_worker_ends_every_unanswered_call_with_worker_lost():
    with Helper() as helper:
        dead = helper.submit(faulty.die)
        later = helper.submit(faulty.mark_then, 1, "/dev/null")
        for ticket in (dead, later):
            with pytest.raises(WorkerLost, match=r"killed by SIGKILL.*jobs=1"):
                helper.result(ticket)


def test_close_terminates_a_running_call_and_reaps_the_worker(tmp_path):
    helper = Helper()
    helper.submit(faulty.mark_then, 1, str(tmp_path / "long"), 60.0)
    while not (tmp_path / "long").exists():
        time.sleep(0.01)
    process = helper._worker.process
    start = time.monotonic()
    helper.close()
    assert time.monotonic() - start < 10.0 and not process.is_alive()
    with pytest.raises(RuntimeError, match="closed"):
        helper.submit(faulty.mark_then, 2, "/dev/null")


def test_a_failed_warm_up_only_costs_its_time():
    with Helper(warm_up=faulty.always_fail) as helper:
        assert helper.result(helper.submit(faulty.mark_then, 1, "/dev/null")) == 1


def test_an_answer_that_cannot_be_read_is_an_error_not_a_wait():
    with Helper() as helper:
        with pytest.raises(RuntimeError, match="cannot read the helper's answer to call 0"):
            helper.result(helper.submit(faulty.raise_unpicklable))
        assert helper.result(helper.submit(faulty.mark_then, 2, "/dev/null")) == 2


def test_arguments_are_pickled_when_submitted(tmp_path):
    with Helper() as helper:
        with pytest.raises(Exception, match="pickle"):
            helper.submit(faulty.mark_then, lambda: 1, "/dev/null")
        values = [1]
        busy = helper.submit(faulty.mark_then, 0, str(tmp_path / "busy"), 0.3)
        later = helper.submit(faulty.append, values, str(tmp_path / "log"))
        values.append(99)  # a change after submitting, before the call starts, does not reach it
        assert helper.result(busy) == 0 and helper.result(later) == [1]


def test_each_ticket_answers_once():
    with Helper() as helper:
        ticket = helper.submit(faulty.mark_then, 1, "/dev/null")
        assert helper.result(ticket) == 1
        with pytest.raises(KeyError, match="no call 0 is waiting"):
            helper.result(ticket)
        withdrawn = helper.submit(faulty.mark_then, 2, "/dev/null")
        helper.withdraw(withdrawn)
        with pytest.raises(KeyError):
            helper.result(withdrawn)


def test_a_call_taken_back_before_it_started_never_runs_there(tmp_path):
    """take_back drops a queued call (its caller computes it) and refuses one that started."""
    with Helper() as helper:
        running = helper.submit(faulty.mark_then, 1, str(tmp_path / "running"), 1.0)
        queued = helper.submit(faulty.mark_then, 2, str(tmp_path / "queued"))
        deadline = time.monotonic() + 60.0
        while not (tmp_path / "running").exists():  # the worker has started the first call
            assert time.monotonic() < deadline, "the helper never started its first call"
            time.sleep(0.01)
        assert not helper.idle
        assert helper.take_back(queued)
        assert not helper.take_back(running) and helper.result(running) == 1
        with pytest.raises(KeyError):
            helper.result(queued)
        assert helper.idle
    assert not (tmp_path / "queued").exists()


def test_only_an_open_live_worker_with_nothing_to_do_is_idle():
    import os

    helper = Helper()
    try:
        assert helper.idle
        with pytest.raises(WorkerLost):
            helper.result(helper.submit(os._exit, 3))
        assert not helper.idle  # gone: a call would fail
    finally:
        helper.close()
    assert not helper.idle
