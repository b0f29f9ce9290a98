"""Clocks, in integer nanoseconds as rosbags uses them.

``wall_ns`` stamps messages (ROS time is Unix time). ``monotonic_ns`` measures ages and
deadlines and never jumps.
"""

from __future__ import annotations

import time

NS_PER_S = 1_000_000_000


# The clocks themselves, not wrappers: they are read several times between a scan's arrival and
# the motor command, where each extra Python call counts.
wall_ns = time.time_ns
"""Unix time in nanoseconds, for message stamps."""

monotonic_ns = time.monotonic_ns
"""A clock that never jumps, in nanoseconds, for ages and deadlines."""


def seconds(ns: int) -> float:
    """Nanoseconds to seconds."""
    return ns / NS_PER_S


def nanoseconds(s: float) -> int:
    """Seconds to integer nanoseconds."""
    return round(s * NS_PER_S)
