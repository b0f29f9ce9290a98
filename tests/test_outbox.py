"""The one bounded work queue with its thread: shared by the network publishers and the bag recorder."""

from __future__ import annotations

import threading

import pytest

from racecar_hw.runtime.outbox import WAKE_AT, Outbox

DEADLINE_S = 10.0


def test_jobs_run_in_order_and_a_failing_job_does_not_stop_the_thread() -> None:
    outbox = Outbox("test", size=100)
    seen: list[int] = []
    last = threading.Event()

    def job(n: int) -> None:
        if n == 2:
            raise RuntimeError("a client went away")
        seen.append(n)
        if n == 4:
            last.set()

    outbox.start()
    try:
        for n in range(5):
            outbox.put(job, n)
        assert last.wait(DEADLINE_S)
    finally:
        outbox.stop(DEADLINE_S)
    assert seen == [0, 1, 3, 4]
    assert (outbox.done, outbox.failed) == (4, 1)


def test_a_full_queue_drops_the_oldest_and_counts_it() -> None:
    outbox = Outbox("test", size=3)  # not started: nothing is taken off the queue
    seen: list[int] = []
    for n in range(5):
        outbox.put(seen.append, n)
    assert len(outbox) == 3
    assert outbox.dropped == 2
    outbox.start()
    outbox.stop(DEADLINE_S)  # stopping runs what is queued
    assert seen == [2, 3, 4]


def test_only_an_urgent_job_or_a_full_batch_wakes_the_thread() -> None:
    outbox = Outbox("test", size=100)  # not started: the wake flag stays as put leaves it
    outbox.put(print)
    assert not outbox._wake.is_set()
    outbox.put(print, urgent=True)
    assert outbox._wake.is_set()

    batch = Outbox("test", size=100)
    for _ in range(WAKE_AT - 1):
        batch.put(print)
    assert not batch._wake.is_set()
    batch.put(print)
    assert batch._wake.is_set()


def test_control_idle_wakes_only_when_a_run_is_due_and_jobs_wait() -> None:
    outbox = Outbox("test", size=100)
    outbox._drain_due = float("inf")
    outbox.put(print)
    outbox.control_idle()
    assert not outbox._wake.is_set()
    outbox._drain_due = 0.0
    outbox.control_idle()
    assert outbox._wake.is_set()

    empty = Outbox("test", size=100)
    empty._drain_due = 0.0
    empty.control_idle()
    assert not empty._wake.is_set()


def test_a_queue_without_room_is_refused() -> None:
    with pytest.raises(ValueError, match="size"):
        Outbox("test", size=0)
