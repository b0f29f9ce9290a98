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


SESSION_CONFTEST = '''
import importlib.util
spec = importlib.util.spec_from_file_location("racecar_hw_test_conftest", {conftest!r})
ours = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ours)
pytest_itemcollected = ours.pytest_itemcollected
pytest_collection_modifyitems = ours.pytest_collection_modifyitems
pytest_collection_finish = ours.pytest_collection_finish
pytest_runtest_protocol = ours.pytest_runtest_protocol
'''

SESSION_TESTS = '''
import json, os, time
import pytest

def _ran(name, start=None):
    start = time.time() if start is None else start
    time.sleep(0.3)
    with open({log!r}, "a") as f:
        f.write(json.dumps([name, os.environ["PYTEST_XDIST_WORKER"], start, time.time()]) + "\\n")

@pytest.mark.parametrize("k", range(4))
def test_ordinary(k):
    _ran(f"ordinary{{k}}")

@pytest.mark.slow
def test_slow():
    _ran("slow")

@pytest.mark.alone
@pytest.mark.parametrize("k", range(2))
def test_alone(k):
    # a quiet test runs meanwhile: it takes no lock (had it waited, this would wait its 60 s out)
    deadline = time.monotonic() + 60
    while not os.path.exists({quiet_started!r}) and time.monotonic() < deadline:
        time.sleep(0.01)
    _ran(f"alone{{k}}")

@pytest.mark.quiet
@pytest.mark.parametrize("k", range(2))
def test_quiet(k):
    start = time.time()  # before the alone test can see the file and take its own start
    open({quiet_started!r}, "a").close()
    _ran(f"quiet{{k}}", start)
'''


def test_with_xdist_the_alone_tests_run_first_on_one_worker_and_by_themselves(tmp_path):
    """The whole arrangement in a pytest session of its own with three workers (pyproject.toml's
    options, this folder's hooks): the alone tests (collected last here) go to one worker, begin
    before any other test but the quiet ones, and no test but a quiet one runs while one of them
    does."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    log = tmp_path / "ran.jsonl"
    (tmp_path / "conftest.py").write_text(SESSION_CONFTEST.format(
        conftest=str(Path(__file__).with_name("conftest.py"))))
    quiet_started = tmp_path / "quiet.started"
    (tmp_path / "test_session.py").write_text(SESSION_TESTS.format(log=str(log),
                                                                   quiet_started=str(quiet_started)))
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "3", "-p", "no:cacheprovider", "-c", "/dev/null",
         "--rootdir", str(tmp_path), "--basetemp", str(tmp_path / "basetemp"),  # not pytest's numbered ones
         "--dist", "loadgroup", "--no-loadscope-reorder",
         "-o", "markers=slow\nalone\nquiet", "-W", "ignore::pytest.PytestUnknownMarkWarning",
         str(tmp_path / "test_session.py")], capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    ran = {name: (worker, start, end)
           for name, worker, start, end in map(json.loads, log.read_text().splitlines())}
    assert len(ran) == 9, ran
    alone = [ran.pop(f"alone{k}") for k in range(2)]
    quiet = [ran.pop(f"quiet{k}") for k in range(2)]
    # a quiet test ran while the first alone one waited (it did not wait its 60 s out)
    assert min(start for _, start, _ in quiet) < min(start for _, start, _ in alone), (alone, quiet)
    assert alone[0][0] == alone[1][0]  # one worker, back to back
    first = min(start for _, start, _ in alone)
    assert all(start >= first for _, start, _ in ran.values())  # they began first
    for _, a_start, a_end in alone:  # and nothing ran beside them
        assert all(end <= a_start or start >= a_end for _, start, end in ran.values()), (alone, ran)
