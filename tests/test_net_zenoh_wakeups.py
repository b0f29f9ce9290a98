"""The Zenoh bridge's thread wake-ups (issue 25, "the far side must be cheap"): a command stream
costs its input thread one wake-up per command and loses nothing."""

from __future__ import annotations

import asyncio

import numpy as np
from conftest import async_wait_for
from zenoh_util import bridge_with_peer

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, LaserScan, Odometry
from racecar_hw.net import rmw
from racecar_hw.net.rmw import SampleStamps
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge, _Out
from racecar_hw.net.zenoh_config import ZenohParams
from racecar_hw.rosmsg.typestore import ros2_types
from safety.params import SafetyParams
from vesc.driver import TOPIC_ODOM

NAV0 = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"


def test_odometry_wakes_the_publisher_at_once_even_right_after_a_scan():
    """Odometry leaves as soon as it is published (it does not wait for the next scan's wake-up:
    measured in issue 25, not shipped; docs/benchmarks.md "The far side")."""
    rows = topic_table(MuxParams(), SafetyParams())
    bridge = ZenohBridge(Bus(), ZenohParams(), rows, urgent={"/scan", TOPIC_ODOM}, early={"/scan"})
    scan_out, odom_out = (_Out(next(r for r in rows if r.bus == t), None, SampleStamps(bytes(16)),
                               latched=False) for t in ("/scan", TOPIC_ODOM))
    scan_out.matching = odom_out.matching = True
    assert bridge.early.take("/scan", False, bridge._enqueuer(scan_out))
    odom = bridge._enqueuer(odom_out)
    for _ in range(3):  # the outbox is not started: its wake flag stays as put leaves it
        bridge.send_early("/scan", LaserScan())
        assert bridge.outbox._wake.wait(0)
        odom(Odometry())
        assert bridge.outbox._wake.wait(0)
    assert [args[0].row.bus for _, args in bridge.outbox._queue] == ["/scan", TOPIC_ODOM] * 3


def _command(speed: float) -> bytes:
    return ros2_types().serialize(AckermannDriveStamped(drive=AckermannDrive(speed=speed)))


def test_a_command_stream_arrives_whole_and_a_flood_is_coalesced_to_its_newest():
    """The command row's thread offers a sample at once when none was offered within the period,
    and rests the rest of the period only when a sample comes sooner: then the newest goes."""
    async def run() -> tuple[list[float], object]:
        bus = Bus()
        got: list[float] = []
        bus.subscribe(NAV0, lambda msg: got.append(msg.drive.speed))
        async with bridge_with_peer(bus) as (bridge, peer):
            key = rmw.topic_key(0, NAV0, AckermannDriveStamped.ROS_TYPE,
                                rmw.type_hash(AckermannDriveStamped.ROS_TYPE))
            pub = peer.declare_publisher(key)
            seq = 0

            def put(speed: float) -> None:
                nonlocal seq
                seq += 1
                pub.put(_command(speed), attachment=rmw.Attachment(seq, 1, bytes(16)).encode())

            # a client answering at its own pace: every command reaches the bus
            for n in range(5):
                put(0.1 * (n + 1))
                await async_wait_for(lambda n=n: len(got) == n + 1, timeout=20)
            # a flood: the newest arrives, most of the rest are superseded, all are counted
            for n in range(300):
                put(1.0 + n / 1000.0)
            await async_wait_for(lambda: got and np.isclose(got[-1], 1.299), timeout=20)
            await async_wait_for(lambda: bridge.inbox.counts()[NAV0].received == 305, timeout=20)
            return got, bridge.inbox.counts()[NAV0]

    got, counts = asyncio.run(run())
    assert np.allclose(got[:5], [0.1, 0.2, 0.3, 0.4, 0.5])
    assert np.isclose(got[-1], 1.299)
    assert len(got) < 100  # the flood was coalesced, not handed over message by message
    assert counts.received == 305 and counts.superseded >= 300 - len(got[5:])
