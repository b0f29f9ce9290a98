"""The seeds' scan summaries: ``/scan_range`` and ``/open_space`` for every ``/scan``.

For each ``sensor_msgs/LaserScan`` on the scan topic this publishes

* a ``racecar_msgs/ScanRange`` on ``/scan_range`` (F1TENTH ROS lab): the scan's header (stamp and
  frame), then the closest and farthest valid range in metres;
* a ``racecar_msgs/OpenSpace`` on ``/open_space`` (MIT lab 1C): the angle (radians, laser frame,
  CCW, 0 ahead), then the distance (metres) of the longest valid return.

A valid range is finite and within the scan's [range_min, range_max] (``lidar_drivers.base
.summarize``): the inf and nan readings drivers use for "no return" and "error" are ignored. A scan
with no valid beam still gets both messages, with nan fields, so a consumer sees every scan.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from lidar_drivers.base import summarize
from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.messages import Header, LaserScan, OpenSpace, ScanRange, Time
from racecar_hw.base.params import param

log = logging.getLogger(__name__)


@dataclass
class ScanSummaryParams:
    """Where scans come from and where their summaries go."""

    scan_topic: str = param("/scan", "sensor_msgs/LaserScan input", topic=True)
    scan_range_topic: str = param("/scan_range", "racecar_msgs/ScanRange output (closest, farthest)",
                                  topic=True)
    open_space_topic: str = param("/open_space", "racecar_msgs/OpenSpace output (angle, distance)",
                                  topic=True)


def scan_range(scan: LaserScan) -> ScanRange:
    """The closest and farthest valid range of ``scan``, under a copy of its header."""
    s = summarize(scan)
    header = Header(Time(scan.header.stamp.sec, scan.header.stamp.nanosec), scan.header.frame_id)
    return ScanRange(header, s.closest, s.farthest)


def open_space(scan: LaserScan) -> OpenSpace:
    """The angle and distance of the longest valid return of ``scan``."""
    s = summarize(scan)
    return OpenSpace(angle=s.farthest_angle, distance=s.farthest)


class ScanSummaryPublisher:
    """Subscribes to the scan topic and publishes both summaries for each scan."""

    def __init__(self, bus: Bus, params: ScanSummaryParams | None = None) -> None:
        self.bus = bus
        self.params = params if params is not None else ScanSummaryParams()
        self.summarized = 0
        self.empty_scans = 0
        self._sub: Subscription | None = None
        bus.declare(self.params.scan_range_topic, ScanRange)
        bus.declare(self.params.open_space_topic, OpenSpace)

    def start(self) -> None:
        """Start summarising scans (idempotent)."""
        if self._sub is None:
            self._sub = self.bus.subscribe(self.params.scan_topic, self.on_scan)

    def close(self) -> None:
        """Stop summarising; safe to call twice."""
        if self._sub is not None:
            self._sub.close()
            self._sub = None

    def __enter__(self) -> ScanSummaryPublisher:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def on_scan(self, scan: LaserScan) -> None:
        """Publish the summaries of one scan."""
        s = summarize(scan)
        if s.valid_beams == 0:
            self.empty_scans += 1
        header = Header(Time(scan.header.stamp.sec, scan.header.stamp.nanosec), scan.header.frame_id)
        self.bus.publish(self.params.scan_range_topic, ScanRange(header, s.closest, s.farthest))
        self.bus.publish(self.params.open_space_topic, OpenSpace(s.farthest_angle, s.farthest))
        self.summarized += 1
