"""The lock that runs the tests marked ``alone`` while no other pytest-xdist worker runs a test
(tests/conftest.py, :class:`~conftest.PaceLock`; docs/tests.md, "Alone"): real ``flock`` locks on
files, taken from threads (each :class:`PaceLock` opens files of its own, so its locks conflict with
the others' as another worker's would)."""

from __future__ import annotations

import threading
import time

from conftest import PaceLock, wait_for

#: How long a lock that must wait is watched not to be given (s): a loaded machine can only make
#: this check pass wrongly, never fail wrongly.
STILL_WAITING_S = 0.3


def _take(lock: PaceLock, alone: bool, got: list[str], name: str) -> threading.Thread:
    thread = threading.Thread(target=lambda: (lock.hold(alone), got.append(name)), daemon=True)
    thread.start()
    return thread


def test_tests_hold_it_together(tmp_path):
    one, two = PaceLock(tmp_path, False), PaceLock(tmp_path, False)
    got: list[str] = []
    one.hold(alone=False)
    _take(two, False, got, "two").join(10)
    assert got == ["two"]
    one.release()
    two.release()


def test_an_alone_test_waits_for_the_running_ones_and_no_new_one_starts_meanwhile(tmp_path):
    running, alone, new = (PaceLock(tmp_path, False) for _ in range(3))
    got: list[str] = []
    running.hold(alone=False)
    _take(alone, True, got, "alone")
    wait_for(lambda: (tmp_path / "alone.begun").exists())  # it holds the turnstile, and waits
    _take(new, False, got, "new")
    time.sleep(STILL_WAITING_S)
    assert got == []  # the alone one waits for the running one; the new one for the alone one
    running.release()
    wait_for(lambda: got == ["alone"])
    time.sleep(STILL_WAITING_S)
    assert got == ["alone"]
    alone.hold(alone=True)  # the next test alone too: kept, not given back in between
    assert got == ["alone"] and alone.exclusive
    alone.release()
    wait_for(lambda: got == ["alone", "new"])
    new.release()


def test_a_first_test_waits_until_the_alone_tests_have_begun(tmp_path):
    first, alone = PaceLock(tmp_path, session_has_alone=True), PaceLock(tmp_path, False)
    got: list[str] = []
    _take(first, False, got, "first")
    time.sleep(STILL_WAITING_S)
    assert got == []
    alone.hold(alone=True)
    time.sleep(STILL_WAITING_S)
    assert got == []  # begun, and holding the lock
    alone.release()
    wait_for(lambda: got == ["first"])
    first.release()
    # later tests do not wait for the alone ones again
    first.hold(alone=False)
    first.release()
