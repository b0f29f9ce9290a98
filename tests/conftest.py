"""Shared fixtures: the shared fixtures folder, a device thread, async helpers."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import importlib.util
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.scip_fake import FakeHokuyo
from racecar_hw.runtime.devicethread import DeviceThread
from vesc.fake import FakeVesc

# Compiled modules are written and reused, Python's default, even where the environment turns that
# off (PYTHONDONTWRITEBYTECODE): the tests start hundreds of Python processes (daemons, sims, CLI
# tools, peers), and each would compile racecar-hw's modules and the rewritten tests from source again.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# No test listens on a default port: the guard in tests/portguard fails such a bind, in this
# process and (through PYTHONPATH) in every Python process a test starts.
PORTGUARD = Path(__file__).resolve().parent / "portguard"
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(PORTGUARD), *([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])])
_spec = importlib.util.spec_from_file_location("racecar_hw_portguard", PORTGUARD / "sitecustomize.py")
assert _spec is not None and _spec.loader is not None
_spec.loader.exec_module(importlib.util.module_from_spec(_spec))  # installs the guard here

# No timed assertions in tests: hypothesis's 200 ms deadline per example (and its "too slow" data
# check) fail on a loaded 2-core machine, so both are off for every property test.
settings.register_profile("racecar-hw", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("racecar-hw")

SHARED = Path(__file__).resolve().parents[2] / "shared"
BAGS = SHARED / "fixtures" / "bags"

#: Tests whose subject is not the network keep the daemon's Zenoh bridge off: its default listen
#: port (7447) is shared by every process on this machine, and a test never binds a fixed port.
NO_ZENOH = "zenoh.enabled=false"
#: ... and their DDS interface: its discovery reaches every DDS participant on this machine's loopback.
NO_DDS = "dds.enabled=false"
#: What a test that starts a daemon or a sim but is not about the network sets: no Zenoh bridge, no
#: DDS interface, and
#: the live view and the status page on free ports (port 0), never the defaults 8765 and 8080
#: (a user's running sim would clash with the tests; docs/live-view.md, "Ports").
QUIET_NET = (NO_ZENOH, NO_DDS, "foxglove.port=0", "web.port=0")


#: How a test that runs a real-time simulation in a process of its own puts it ahead of the other
#: load of a shared 2-core machine (see :func:`ahead_of_other_load`).
REALTIME_PRIORITY = 10
AHEAD_NICE = -10
#: ... and a process whose pace a test relies on, below the measuring sims (:func:`ahead_of_ordinary_load`)
ORDINARY_PRIORITY = 5


def ahead_of_other_load() -> None:
    """``preexec_fn`` for a real-time sim whose outcome a test checks: as root, FIFO real-time
    priority; otherwise a lower niceness, if allowed. What such a test measures is the daemon's
    behaviour against the simulated world, not the scheduling of other tenants of the machine (a
    scan held up 0.5 s by them is a stale scan to the safety controller); the lockstep simulation
    (issue 27) will make this unnecessary."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
    except (OSError, AttributeError):
        with contextlib.suppress(OSError):
            os.nice(AHEAD_NICE)


def ahead_of_ordinary_load() -> None:
    """``preexec_fn`` for a process whose pace a test relies on (a sim's trajectory, a peer's 20 Hz
    stream against the mux's 0.2 s timeout) but whose test measures nothing of the machine: as
    root, FIFO real-time priority below :data:`REALTIME_PRIORITY`, so that the sims of the tests
    that do measure (missed ticks under a flood, :func:`ahead_of_other_load`) still come first;
    otherwise a lower niceness, if allowed. (Those tests also run ``alone``: docs/tests.md.)"""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(ORDINARY_PRIORITY))
    except (OSError, AttributeError):
        with contextlib.suppress(OSError):
            os.nice(AHEAD_NICE)


@contextlib.contextmanager
def ahead_here() -> Iterator[None]:
    """:func:`ahead_of_ordinary_load` for a real-time run in this test's own process: the calling
    thread, and the threads it starts meanwhile (the fakes' device thread, the daemon's helpers),
    which inherit its policy; back to the ordinary policy at the end. For an in-process real-time
    run whose outcome rests on the wall clock's pace (a scan late for another worker's load is a
    stale scan, and a car that stops late hits the wall): the run waits on the clock most of the
    time, so it takes little from the other workers."""
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(ORDINARY_PRIORITY))
    except (OSError, AttributeError):
        yield  # not root: as it is
        return
    try:
        yield
    finally:
        os.sched_setscheduler(0, before[0], before[1])


def set_args(*assignments: str) -> list[str]:
    """``--set`` before each assignment, for a command line."""
    return [arg for item in assignments for arg in ("--set", item)]


@pytest.fixture
def bag_fixtures() -> Path:
    """The real bags in ../shared/fixtures/bags; skips where ../shared is absent (a user's clone)."""
    if not BAGS.is_dir():
        pytest.skip(f"real bag fixtures not found at {BAGS} (../shared is absent in this clone)")
    return BAGS


@pytest.fixture
def fakes(device_thread, tmp_path):
    """A fake VESC on a pty (``tmp_path/vesc``) and a fake UST-10LX on a free loopback TCP port,
    seeing the shipped room, served by a device thread: ``(vesc, lidar)``."""
    vesc = FakeVesc(str(tmp_path / "vesc"))
    lidar = FakeHokuyo("ust-10lx", RoomRangeSource(), tcp=("127.0.0.1", 0))
    device_thread.spawn(vesc.serve())
    device_thread.spawn(lidar.serve())
    assert vesc.ready.wait(10) and lidar.ready.wait(10)
    return vesc, lidar


@pytest.fixture
def device_thread() -> Iterator[DeviceThread]:
    """A running thread for fake devices, stopped after the test."""
    with DeviceThread() as thread:
        yield thread


def wait_for(predicate: Callable[[], object], timeout: float = 10.0, interval: float = 0.01) -> None:
    """Wait until ``predicate()`` is truthy, failing the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s: {predicate}")
        time.sleep(interval)


async def async_wait_for(predicate: Callable[[], object], timeout: float = 10.0,
                         interval: float = 0.005) -> None:
    """Like :func:`wait_for`, inside an event loop."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s: {predicate}")
        await asyncio.sleep(interval)


@contextlib.contextmanager
def reaped(proc: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """``proc`` for the block; killed and waited for if it still runs when the block ends."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


#: The marker of a test that runs while no other pytest-xdist worker runs one (docs/tests.md, "Alone").
ALONE = "alone"
#: ... and of one that may run beside them, taking no lock (:func:`_quiet`).
QUIET = "quiet"
#: How long (s) a worker's first test waits for the session's alone tests to begin before it starts
#: anyway (they are handed out first, so they begin within seconds; the bound covers a worker lost).
ALONE_START_WAIT_S = 60.0


def _alone(item: pytest.Item | None) -> bool:
    return item is not None and item.get_closest_marker(ALONE) is not None


def _quiet(item: pytest.Item | None) -> bool:
    """Marked ``quiet`` and in no pytest-xdist group, or in a shared lockstep run's group
    (tests/lockstep_sim.py ``shares_run``: every test of one is a lockstep run in its own process
    with every network interface off; the determinism test's CPU burner runs at SCHED_IDLE). A
    group's tests run on one worker one after another, so a group is quiet as a whole or not at
    all: one of its tests that waited for the lock would hold up the quiet ones after it."""
    if item is None:
        return False
    group = item.get_closest_marker("xdist_group")
    if group is not None:
        return str(group.args[0] if group.args else group.kwargs.get("name", "")).startswith("lockstep-")
    return item.get_closest_marker(QUIET) is not None


def pytest_itemcollected(item: pytest.Item) -> None:
    """The tests marked ``alone`` form one pytest-xdist group (added as each is collected: before
    pytest-xdist reads the groups into the test ids)."""
    if _alone(item):
        item.add_marker(pytest.mark.xdist_group(ALONE))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The order the workers are handed tests in (pyproject.toml's ``--no-loadscope-reorder`` keeps
    it; every worker collects the same order): first the tests marked ``alone``, in one pytest-xdist
    group so that one worker runs them back to back while the others wait (:class:`PaceLock`); then
    the ``slow`` ones, so that a long test does not start last and leave one worker running alone
    at the end; then the groups of tests sharing a run (several tests each); then the rest, each in
    its collection order. The quiet tests (:func:`_quiet`: the ``quiet`` modules' and the shared
    lockstep runs' groups) come right after the alone ones: the other workers run them while the
    alone tests run (:class:`PaceLock`)."""
    items.sort(key=lambda item: (not _alone(item), not _quiet(item), item.get_closest_marker("slow") is None,
                                 item.get_closest_marker("xdist_group") is None))


class PaceLock:
    """Tests marked ``alone`` run while no other pytest-xdist worker runs a test: a reader-writer lock
    over two files that every worker of the session opens (``flock``, Linux), with writer preference.

    Every test holds the lock shared from before its setup to after its teardown; an ``alone`` test
    holds it exclusive, and keeps it through the next test when that one is ``alone`` too. A reader
    takes the turnstile file, then the lock shared, and lets the turnstile go; a writer takes the
    turnstile and keeps it while it waits for the readers to finish and while it runs, so no new
    reader starts meanwhile (it is not starved). A worker holds one lock at a time and gives it back
    after each test: one waiting for the exclusive lock holds no shared one, so no deadlock; a worker
    that dies lets go of its locks with its files. Module and session fixtures are set up and torn
    down inside a test's hold; one that outlives its test (a module's shared sim) may still run
    beside an alone test, which is why the alone tests run first, before any such fixture exists.
    A worker's first test also waits (up to :data:`ALONE_START_WAIT_S`) until the alone tests have
    begun, where the session has any: otherwise the other workers' first tests would start first
    and the alone ones wait for the longest of them.

    A quiet test (:func:`_quiet`: computation or a lockstep run in the test's own process at the
    ordinary priority, no socket, subprocess but a SCHED_IDLE burner, or wall-clock wait) takes no
    lock: it may run beside an alone test. The
    flood tests' sims run at FIFO priority, ahead of it; beside the web page's sim and browser it
    takes a share of the cores at their priority, as any other program would.
    """

    def __init__(self, folder: Path, session_has_alone: bool) -> None:
        self.turnstile = folder / "alone.turnstile"
        self.rw = folder / "alone.rw"
        self.begun = folder / "alone.begun"
        self.wait_for_alone = session_has_alone
        self._held: list[int] = []  # file descriptors, locked
        self.exclusive = False

    def _lock(self, path: Path, how: int) -> int:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        fcntl.flock(fd, how)
        return fd

    def hold(self, alone: bool) -> None:
        """Take the lock for a test: exclusive if ``alone`` (kept if already held), else shared."""
        if self._held:
            if self.exclusive and alone:
                return
            self.release()
        if alone:
            self._held.append(self._lock(self.turnstile, fcntl.LOCK_EX))
            self.begun.touch()
            self._held.append(self._lock(self.rw, fcntl.LOCK_EX))
            self.exclusive = True
            return
        if self.wait_for_alone:
            self.wait_for_alone = False
            deadline = time.monotonic() + ALONE_START_WAIT_S
            while not self.begun.exists() and time.monotonic() < deadline:
                time.sleep(0.05)
        turnstile = self._lock(self.turnstile, fcntl.LOCK_EX)
        try:
            self._held.append(self._lock(self.rw, fcntl.LOCK_SH))
        finally:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
            os.close(turnstile)

    def release(self) -> None:
        """Let go of whatever is held (the lock before the turnstile)."""
        while self._held:
            fd = self._held.pop()
            fcntl.flock(fd, fcntl.LOCK_UN)  # explicitly: a process forked by the test shares the file
            os.close(fd)
        self.exclusive = False


PACE_LOCK = pytest.StashKey[PaceLock]()


def pytest_collection_finish(session: pytest.Session) -> None:
    """In a pytest-xdist worker: the session's :class:`PaceLock`, in the folder all workers share
    (the parent of each worker's ``--basetemp``)."""
    config = session.config
    if not hasattr(config, "workerinput"):
        return  # one process: nothing runs beside a test
    folder = config._tmp_path_factory.getbasetemp().parent  # noqa: SLF001 - pytest's own factory
    config.stash[PACE_LOCK] = PaceLock(folder, any(_alone(item) for item in session.items))


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Each test's setup, call and teardown inside the :class:`PaceLock` (outside pytest-timeout's
    timer, which also wraps the whole protocol: the wait for the lock is not the test's time)."""
    lock = item.config.stash.get(PACE_LOCK, None)
    if lock is None:
        yield
        return
    if _quiet(item):
        lock.release()
        yield
        return
    lock.hold(_alone(item))
    try:
        yield
    finally:
        if not (_alone(item) and _alone(nextitem)):
            lock.release()


class StuckDisk:
    """A disk under ``root`` whose fsync hangs from :meth:`stick` on until released (at the end of
    the test): the physical world the reviewer made with strace's fsync delay injection."""

    def __init__(self, root: Path, real_fsync: Callable[[int], None]) -> None:
        self.root, self._real = str(root), real_fsync
        self.stuck = threading.Event()
        self.blocked = threading.Event()  # a thread waits in fsync
        self.released = threading.Event()

    def stick(self) -> None:
        self.stuck.set()

    def fsync(self, fd: int) -> None:
        if self.stuck.is_set() and os.readlink(f"/proc/self/fd/{fd}").startswith(self.root):
            self.blocked.set()
            self.released.wait()
        self._real(fd)


@pytest.fixture
def stuck_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[StuckDisk]:
    disk = StuckDisk(tmp_path, os.fsync)
    monkeypatch.setattr(os, "fsync", disk.fsync)
    yield disk
    disk.released.set()  # the abandoned writer thread finishes and ends
