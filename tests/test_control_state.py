"""The read model every display reads (racecar_hw.control.state): no value outlives its device.

A reviewer watched the status line show ``scan 39.8 Hz`` for seconds while no scan came (the lidar
stalled, reconnecting), and ``speed +0.60 m/s`` beside ``vesc lost since ...``: the scan rate was
updated only when a scan arrived, and the speed was the last odometry, however old. Tests on a
virtual clock (racecar_hw.base.clock.use_virtual_time) move time by hand.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import QUIET_NET

from racecar_hw.base.clock import SIM_EPOCH_NS, use_virtual_time
from racecar_hw.base.messages import LaserScan
from racecar_hw.config import load_config
from racecar_hw.daemon import Daemon
from racecar_hw.runtime.status import plain_line

OFF = ("gamepad.enabled=false", "status.enabled=false", "foxglove.enabled=false", "web.enabled=false",
       *QUIET_NET)
MS = 1_000_000


class Clock:
    """A virtual monotonic clock (ns) that moves only when told."""

    def __init__(self) -> None:
        self.now = SIM_EPOCH_NS

    def __call__(self) -> int:
        return self.now


def _scan() -> LaserScan:
    msg = LaserScan(angle_min=-1.0, angle_increment=0.01, range_min=0.02, range_max=30.0,
                    ranges=np.full(201, 25.0, dtype=np.float32))
    msg.header.frame_id = "laser"
    return msg


def test_the_scan_rate_goes_to_zero_when_no_scan_came_for_a_second_and_counts_only_recent_scans():
    clock = Clock()
    with use_virtual_time(clock):
        # a lidar configured (never started: the scans are handed to the control path here)
        daemon = Daemon(load_config(None, ["vesc.enabled=false", "lidar.model=ust-10lx",
                                           "lidar.tcp=127.0.0.1:9", *OFF]))
        for _ in range(20):  # 40 Hz
            daemon.control.take_scan(_scan())
            clock.now += 25 * MS
        assert daemon.live_state().lidar_rate_hz == pytest.approx(40.0)
        clock.now += 1100 * MS  # the lidar went quiet for a second
        assert daemon.live_state().lidar_rate_hz == 0.0
        assert "scan 0.0 Hz" in plain_line(daemon.snapshot())
        for _ in range(3):  # back at 40 Hz: the gap does not drag the rate down
            daemon.control.take_scan(_scan())
            clock.now += 25 * MS
        assert daemon.live_state().lidar_rate_hz == pytest.approx(40.0)
