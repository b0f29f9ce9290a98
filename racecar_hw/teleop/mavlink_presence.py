"""Whether the ground station is there: its heartbeats, at most ``heartbeat_timeout_s`` apart.

A HEARTBEAT of type MAV_TYPE_GCS from the ground station's system id makes it present (a
STATUSTEXT says "GCS connected"); no heartbeat for more than the timeout makes it lost (counted
as ``gcs_timeouts``, logged, and a STATUSTEXT says so). Times are monotonic ns.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.teleop.mavlink_dialect import mavlink

log = logging.getLogger(__name__)


class StationPresence:
    """The ground station's heartbeat watch; ``statustext(text, severity)`` tells the station."""

    def __init__(self, heartbeat_timeout_s: float, counters: dict[str, int],
                 statustext: Callable[[str, int], None]) -> None:
        self.timeout_s = heartbeat_timeout_s
        self._timeout_ns = round(heartbeat_timeout_s * NS_PER_S)
        self.counters = counters
        self._statustext = statustext
        self.alive = False
        self.heartbeat_ns: int | None = None
        #: the longest time between two heartbeats of a connected station (ns)
        self.gap_max_ns = 0

    def heard(self, now: int) -> None:
        """A heartbeat of the station arrived at ``now``."""
        if self.alive and self.heartbeat_ns is not None:
            self.gap_max_ns = max(self.gap_max_ns, now - self.heartbeat_ns)
        self.heartbeat_ns = now
        if not self.alive:
            self.alive = True
            self._statustext("GCS connected", mavlink.MAV_SEVERITY_INFO)

    def lost(self, now: int) -> bool:
        """True (once) when a present station's last heartbeat is older than the timeout at ``now``."""
        if not self.alive or (self.heartbeat_ns is not None and now - self.heartbeat_ns <= self._timeout_ns):
            return False
        self.alive = False
        self.counters["gcs_timeouts"] += 1
        log.warning("MAVLink: ground station heartbeat lost (%.1f s): its teleop input is dropped",
                    self.timeout_s)
        self._statustext("GCS heartbeat lost: teleop input dropped", mavlink.MAV_SEVERITY_WARNING)
        return True


__all__ = ["StationPresence"]
