"""Shared fixtures: the shared fixtures folder, a device thread, async helpers."""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import os
import subprocess
import sys
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
    that do measure (missed ticks under a flood, :func:`ahead_of_other_load`) on the other worker
    still come first; otherwise a lower niceness, if allowed."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(ORDINARY_PRIORITY))
    except (OSError, AttributeError):
        with contextlib.suppress(OSError):
            os.nice(AHEAD_NICE)


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


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` run first (in their collection order; every worker collects the same
    order), so that with pytest-xdist's workers a long test does not start last and leave one
    worker running alone at the end."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
