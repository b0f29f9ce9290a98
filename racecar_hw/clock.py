"""Clocks, in integer nanoseconds as rosbags uses them.

``wall_ns`` stamps messages (ROS time is Unix time). ``monotonic_ns`` measures ages and
deadlines and never jumps.
"""

from __future__ import annotations

import time

NS_PER_S = 1_000_000_000


def wall_ns() -> int:
    """Unix time in nanoseconds, for message stamps."""
    return time.time_ns()


def monotonic_ns() -> int:
    """A clock that never jumps, in nanoseconds, for ages and deadlines."""
    return time.monotonic_ns()


def seconds(ns: int) -> float:
    """Nanoseconds to seconds."""
    return ns / NS_PER_S


def nanoseconds(s: float) -> int:
    """Seconds to integer nanoseconds."""
    return round(s * NS_PER_S)
