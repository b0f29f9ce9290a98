"""The read model every display reads (racecar_hw.control.state): no value outlives its device.

A reviewer watched the status line show ``scan 39.8 Hz`` for seconds while no scan came (the lidar
stalled, reconnecting), and ``speed +0.60 m/s`` beside ``vesc lost since ...``: the scan rate was
updated only when a scan arrived, and the speed was the last odometry, however old. Tests on a
virtual clock (racecar_hw.base.clock.use_virtual_time) move time by hand; the last runs the daemon
against the fake VESC and the fake Hokuyo and mutes both.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from conftest import QUIET_NET, async_wait_for

from racecar_hw.base.clock import NS_PER_S, SIM_EPOCH_NS, monotonic_ns, use_virtual_time
from racecar_hw.base.messages import LaserScan, Odometry, VescStateStamped
from racecar_hw.base.topics import TOPIC_CORE
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


def test_odometry_older_than_odom_timeout_s_shows_no_speed():
    clock = Clock()
    with use_virtual_time(clock):
        # no VESC: odometry from elsewhere on /odom, judged by its age alone
        daemon = Daemon(load_config(None, ["vesc.enabled=false", "lidar.enabled=false", *OFF]))
        timeout_ns = round(daemon.config.safety.odom_timeout_s * NS_PER_S)
        odom = Odometry()
        odom.twist.twist.linear.x = 0.6
        daemon.bus.publish("/odom", odom)
        clock.now += timeout_ns
        assert daemon.live_state().measured_mps == pytest.approx(0.6)
        assert "speed +0.60 m/s" in plain_line(daemon.snapshot())
        clock.now += 1
        assert daemon.live_state().measured_mps is None
        assert daemon.snapshot().speed_mps is None
        assert plain_line(daemon.snapshot()).startswith("speed - |")


def test_speed_and_battery_are_unknown_while_the_vesc_link_is_not_up(monkeypatch):
    """Fresh telemetry counts only while the VESC's link is up: an unplugged VESC's last reply may
    be younger than ``odom_timeout_s`` when the link drops."""
    clock = Clock()
    up = [True]
    with use_virtual_time(clock):
        daemon = Daemon(load_config(None, ["vesc.port=/dev/null-vesc", "lidar.enabled=false", *OFF]))
        vesc = daemon.vesc
        assert vesc is not None
        monkeypatch.setattr(type(vesc), "connected", property(lambda self: up[0]))
        odom = Odometry()
        odom.twist.twist.linear.x = 0.6
        daemon.bus.publish("/odom", odom)
        core = VescStateStamped()
        core.state.voltage_input = 11.8
        daemon.bus.publish(TOPIC_CORE, core)
        assert daemon.live_state().measured_mps == pytest.approx(0.6)
        up[0] = False  # the link dropped the moment after that reply
        assert daemon.live_state().measured_mps is None
        up[0] = True
        assert daemon.live_state().battery_v == pytest.approx(11.8)
        up[0] = False
        assert daemon.live_state().battery_v is None


def test_a_slow_vesc_poll_is_not_stale_telemetry(monkeypatch):
    """``vesc.poll_rate_hz`` may be as low as 1 Hz: its replies, 0.67 s apart at 1.5 Hz, are fresh
    until two poll periods have passed (against 0.5 s, battery and speed flickered to '-')."""
    clock = Clock()
    with use_virtual_time(clock):
        daemon = Daemon(load_config(None, ["vesc.port=/dev/null-vesc", "vesc.poll_rate_hz=1.5",
                                           "lidar.enabled=false", *OFF]))
        assert daemon.vesc is not None
        monkeypatch.setattr(type(daemon.vesc), "connected", property(lambda self: True))
        core = VescStateStamped()
        core.state.voltage_input = 11.8
        daemon.bus.publish(TOPIC_CORE, core)
        clock.now += 670 * MS  # one poll period later, the next reply not in yet
        assert daemon.live_state().battery_v == pytest.approx(11.8)
        clock.now += 700 * MS  # two periods without a reply: stale
        assert daemon.live_state().battery_v is None


def test_speed_battery_and_scan_rate_are_unknown_once_the_fake_devices_go_quiet(fakes, tmp_path):
    fake_vesc, fake_lidar = fakes
    host, port = fake_lidar.tcp_address
    config = load_config(None, [f"vesc.port={tmp_path / 'vesc'}", "lidar.model=ust-10lx",
                                f"lidar.tcp={host}:{port}", *OFF])
    daemon = Daemon(config)

    def scan_age_ns() -> int:
        entry = daemon.bus.latest_entry(config.safety.scan_topic)
        return monotonic_ns() - entry.received_ns if entry is not None else 0

    async def scenario() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(daemon.run(stop))
        try:
            await async_wait_for(lambda: daemon.snapshot().speed_mps is not None
                                 and daemon.snapshot().battery_v is not None
                                 and (daemon.snapshot().scan_rate_hz or 0.0) > 10.0, timeout=60)
            fake_vesc.mute(True)
            fake_lidar.mute(True)
            vesc = daemon.vesc
            assert vesc is not None
            # the VESC declared lost, and no scan for longer than the scan rate's window (1 s)
            await async_wait_for(lambda: not vesc.connected and scan_age_ns() > 1.5 * NS_PER_S,
                                 timeout=60)
            snap = daemon.snapshot()
            assert snap.speed_mps is None and snap.battery_v is None
            assert snap.scan_rate_hz == 0.0
            line = plain_line(snap)
            assert line.startswith("speed - |") and "battery - |" in line and "scan 0.0 Hz" in line
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)

    asyncio.run(scenario())
