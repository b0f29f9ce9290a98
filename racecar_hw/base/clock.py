"""Clocks, in integer nanoseconds as rosbags uses them.

``wall_ns`` stamps messages (ROS time is Unix time). ``monotonic_ns`` measures ages and
deadlines and never jumps. ``monotonic`` is the same clock in seconds (deadlines of waits).

Both read the process's time source, which is the host's clocks unless a simulation in lockstep
installed a virtual one (:func:`use_virtual_time`): then every component of the daemon, its
timers, ages and message stamps run on sim time, and ``wall_ns`` equals ``monotonic_ns``, the
sim time in ns since the simulation's epoch (:data:`SIM_EPOCH_NS`). There is one time source per
process. CPU-time measurements (``time.thread_time_ns``) stay real.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

NS_PER_S = 1_000_000_000

#: Where a virtual clock starts: 1 s, since ROS reads a time of zero as "no clock yet".
SIM_EPOCH_NS = NS_PER_S

_wall: Callable[[], int] = time.time_ns
_monotonic: Callable[[], int] = time.monotonic_ns


def wall_ns() -> int:
    """Unix time in nanoseconds, for message stamps (sim time under a virtual clock)."""
    return _wall()


def monotonic_ns() -> int:
    """A clock that never jumps, in nanoseconds, for ages and deadlines."""
    return _monotonic()


def monotonic() -> float:
    """:func:`monotonic_ns` in seconds."""
    return _monotonic() / NS_PER_S


def is_virtual() -> bool:
    """Whether a virtual clock is installed (a simulation in lockstep)."""
    return _monotonic is not time.monotonic_ns


@contextlib.contextmanager
def use_virtual_time(now_ns: Callable[[], int]) -> Iterator[None]:
    """Make ``now_ns`` (sim time in ns) the process's monotonic and wall clock while inside."""
    global _wall, _monotonic
    if is_virtual():
        raise RuntimeError("a virtual clock is installed already (one per process)")
    _wall = _monotonic = now_ns
    try:
        yield
    finally:
        _wall, _monotonic = time.time_ns, time.monotonic_ns


def seconds(ns: int) -> float:
    """Nanoseconds to seconds."""
    return ns / NS_PER_S


def nanoseconds(s: float) -> int:
    """Seconds to integer nanoseconds."""
    return round(s * NS_PER_S)
