"""The one bounded work queue with its thread: shared by the network publishers and the bag recorder."""

from __future__ import annotations

import threading
import time

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


def test_a_full_queue_of_a_writer_keeps_what_it_has_and_drops_the_new_job() -> None:
    outbox = Outbox("test", size=3, drop="newest")
    seen: list[int] = []
    for n in range(5):
        outbox.put(seen.append, n)
    assert (len(outbox), outbox.dropped) == (3, 2)
    outbox.start()
    outbox.stop(DEADLINE_S)
    assert seen == [0, 1, 2]
    with pytest.raises(ValueError, match="drop"):
        Outbox("test", drop="random")


def test_setup_runs_in_the_thread_first_and_its_failure_is_raised_by_start() -> None:
    threads: list[str] = []
    outbox = Outbox("writer", size=10)
    outbox.put(lambda: threads.append(threading.current_thread().name))
    outbox.start(setup=lambda: threads.append(threading.current_thread().name))
    outbox.stop(DEADLINE_S)
    assert threads == ["writer", "writer"]

    def broken() -> None:
        raise OSError("disk full")

    failing = Outbox("writer", size=10)
    with pytest.raises(OSError, match="disk full"):
        failing.start(setup=broken)
    assert not failing.running


def test_on_batch_runs_after_each_batch_and_on_stop_after_the_last_job() -> None:
    events: list[str] = []
    batched = threading.Event()

    def on_batch() -> float:
        events.append("batch")
        batched.set()
        return 0.01  # wake again soon: a periodic flush

    outbox = Outbox("test", size=10, batch_s=30.0, on_batch=on_batch,
                    on_stop=lambda: events.append("stop"))
    outbox.start()
    try:
        assert batched.wait(DEADLINE_S)
        outbox.put(events.append, "job")
        # on_batch asked for 0.01 s, not 2 * batch_s (a minute): the job runs without a wake-up
        assert wait_until(lambda: "job" in events)
    finally:
        outbox.put(events.append, "last")
        outbox.stop(timeout_s=None)
    assert events[-2:] == ["last", "stop"]
    assert events.index("job") > 0 and events[events.index("job") + 1] == "batch"


def wait_until(condition, timeout_s: float = DEADLINE_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.005)
    return False


def test_a_wake_up_asked_for_twice_before_the_thread_looks_wakes_it_once() -> None:
    from racecar_hw.runtime.outbox import _Wake

    wake = _Wake()
    wake.set()
    wake.set()  # a second set before the thread woke: still one pending wake-up
    assert wake.is_set()
    started = time.monotonic()
    wake.wait(DEADLINE_S)  # returns at once
    assert not wake.is_set()
    assert time.monotonic() - started < DEADLINE_S
    wake.wait(0.01)  # nothing pending: only the timeout ends the wait
    assert not wake.is_set()

    woken = threading.Event()

    def sleeper() -> None:
        wake.wait(None)
        woken.set()

    thread = threading.Thread(target=sleeper, daemon=True)
    thread.start()
    wake.set()  # from another thread
    assert woken.wait(DEADLINE_S)
    thread.join(DEADLINE_S)


def test_the_thread_carries_its_name_at_the_os_where_the_os_names_threads() -> None:
    import sys
    from pathlib import Path

    if not sys.platform.startswith("linux"):
        pytest.skip("thread names at the OS are set on Linux only")
    names: list[str] = []
    outbox = Outbox("zenoh-publisher", size=10)
    outbox.put(lambda: names.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm")
                                    .read_text().strip()))
    outbox.start()
    outbox.stop(DEADLINE_S)
    assert names == ["zenoh-publisher"]


def _wakeups(thread: threading.Thread) -> int:
    from pathlib import Path

    for line in Path(f"/proc/self/task/{thread.native_id}/status").read_text().splitlines():
        if line.startswith("voluntary_ctxt_switches:"):
            return int(line.split()[1])
    raise AssertionError("no voluntary_ctxt_switches")


def test_an_idle_thread_sleeps_until_a_job_comes_and_then_runs_it() -> None:
    import sys

    done: list[str] = []
    outbox = Outbox("test", size=10, batch_s=0.01)
    outbox.start()
    try:
        assert wait_until(lambda: outbox._idle)
        if sys.platform.startswith("linux"):
            thread = outbox._thread
            assert thread is not None
            before = _wakeups(thread)
            time.sleep(0.5)  # on a timer it would have woken 25 times (every 2 * batch_s)
            assert _wakeups(thread) - before <= 2
        outbox.put(done.append, "plain")  # wakes the thread, which runs it after its batch
        assert wait_until(lambda: done == ["plain"])
        assert wait_until(lambda: outbox._idle)
        outbox.put(done.append, "urgent", urgent=True)
        assert wait_until(lambda: done == ["plain", "urgent"])
    finally:
        outbox.stop(DEADLINE_S)
    assert not outbox.running


def test_a_sleeping_thread_wakes_at_once_for_an_urgent_job_and_ends_at_stop() -> None:
    """Asleep with no timer: an urgent job runs with no batch wait, a plain one after its batch;
    stop() wakes it and it ends (a thread nobody woke would still be alive after DEADLINE_S)."""
    done: list[str] = []
    outbox = Outbox("test", size=10, batch_s=30.0)  # a batch wait would outlast the deadline
    outbox.start()
    thread = outbox._thread
    assert thread is not None
    try:
        assert wait_until(lambda: outbox._idle)
        outbox.put(done.append, "urgent", urgent=True)
        assert wait_until(lambda: done == ["urgent"])
        assert wait_until(lambda: outbox._idle)
    finally:
        outbox.stop(DEADLINE_S)
    assert not thread.is_alive()
    assert done == ["urgent"]


def test_stop_waits_for_a_slow_thread_while_it_makes_progress_and_not_for_a_stuck_one() -> None:
    """A recorder's stop: however slow the disk, every queued job runs while jobs get done; a job
    that never ends (a stuck disk) is left behind after ``stall_s`` without one, and stop says so
    (it once waited for ever, Ctrl-C and the service manager's stop with it)."""
    ran: list[int] = []
    slow = Outbox("slow", size=100)
    slow.start()
    for k in range(8):
        slow.put(lambda k=k: (threading.Event().wait(0.1), ran.append(k)))
    assert slow.stop(timeout_s=None, stall_s=5.0) is True
    assert ran == list(range(8))  # 0.8 s of jobs, none stalled 5 s: all ran

    unstuck = threading.Event()
    stuck = Outbox("stuck", size=100)
    stuck.start()
    stuck.put(unstuck.wait)
    stuck.put(lambda: ran.append(99))
    try:
        assert stuck.stop(timeout_s=None, stall_s=0.5) is False  # left behind, with a warning
        assert 99 not in ran
    finally:
        unstuck.set()
