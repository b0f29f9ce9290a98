"""Shared fixtures: the shared fixtures folder, a device thread, async helpers."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from racecar_hw.runtime.devicethread import DeviceThread

SHARED = Path(__file__).resolve().parents[2] / "shared"
BAGS = SHARED / "fixtures" / "bags"

#: Tests whose subject is not the network keep the daemon's Zenoh bridge off: its default listen
#: port (7447) is shared by every process on this machine, and a test never binds a fixed port.
NO_ZENOH = "zenoh.enabled=false"
#: ... and their DDS interface: its discovery reaches every DDS participant on this machine's loopback.
NO_DDS = "dds.enabled=false"


@pytest.fixture
def bag_fixtures() -> Path:
    """The real bags in ../shared/fixtures/bags; skips where ../shared is absent (a user's clone)."""
    if not BAGS.is_dir():
        pytest.skip(f"real bag fixtures not found at {BAGS} (../shared is absent in this clone)")
    return BAGS


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
