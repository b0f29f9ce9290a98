"""The Zenoh bridge's thread wake-ups (issue 25, "the far side must be cheap"): a command stream
costs its input thread one wake-up per command and loses nothing; odometry rides the scan's
wake-up of the publisher thread when the scan is due within a control period, and wakes it itself
otherwise."""

from __future__ import annotations

import asyncio

import numpy as np
import zenoh
from conftest import async_wait_for
from zenoh_util import endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, LaserScan, Odometry
from racecar_hw.net import rmw
from racecar_hw.net import zenoh_bridge as bridge_module
from racecar_hw.net.rmw import SampleStamps
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge, _Out
from racecar_hw.net.zenoh_config import ZenohParams, session_config
from racecar_hw.rosmsg.typestore import ros2_types
from safety.params import SafetyParams
from vesc.driver import TOPIC_ODOM

NAV0 = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"
MS = 1_000_000
RIDE_S = 0.02


def _offline_bridge(monkeypatch, now: list[int]) -> tuple[ZenohBridge, _Out, _Out, list]:
    """A bridge that is not opened, its scan and odometry rows matched, the clock in ``now``, the
    outbox's puts recorded as (row, urgent)."""
    monkeypatch.setattr(bridge_module, "monotonic_ns", lambda: now[0])
    rows = topic_table(MuxParams(), SafetyParams())
    bridge = ZenohBridge(Bus(), ZenohParams(), rows, urgent={"/scan", TOPIC_ODOM}, early={"/scan"},
                         riders={TOPIC_ODOM}, ride_s=RIDE_S)
    scan_out, odom_out = (_Out(next(r for r in rows if r.bus == t), None, SampleStamps(bytes(16)),
                               latched=False) for t in ("/scan", TOPIC_ODOM))
    scan_out.matching = odom_out.matching = True
    puts: list = []
    bridge.outbox.put = lambda fn, out, msg, stamp, urgent=False, ride=False: puts.append(
        (out.row.bus, urgent))
    bridge._early["/scan"] = [(scan_out, bridge._enqueuer(scan_out))]
    return bridge, scan_out, odom_out, puts


def test_odometry_rides_the_next_scan_only_when_it_is_due_within_a_control_period(monkeypatch):
    now = [1000 * MS]
    bridge, scan_out, odom_out, puts = _offline_bridge(monkeypatch, now)
    odom = bridge._enqueuer(odom_out)

    odom(Odometry())  # no scan yet: nothing to ride
    bridge.send_early("/scan", LaserScan())
    odom(Odometry())  # one scan: its interval is not known yet
    assert puts == [(TOPIC_ODOM, True), ("/scan", True), (TOPIC_ODOM, True)]

    puts.clear()
    now[0] += 25 * MS  # 40 Hz scans: the next one is due 25 ms after this one
    bridge.send_early("/scan", LaserScan())
    now[0] += 4 * MS   # due in 21 ms: more than a control period, it wakes the thread itself
    odom(Odometry())
    now[0] += 1 * MS   # due in 20 ms: it rides
    odom(Odometry())
    now[0] += 19 * MS  # due in 1 ms: it rides
    odom(Odometry())
    now[0] += 2 * MS   # the scan is late: nothing to wait for
    odom(Odometry())
    assert puts == [("/scan", True), (TOPIC_ODOM, True), (TOPIC_ODOM, False), (TOPIC_ODOM, False),
                    (TOPIC_ODOM, True)]


def test_odometry_does_not_wait_for_a_scan_nobody_subscribed_to(monkeypatch):
    now = [1000 * MS]
    bridge, scan_out, odom_out, puts = _offline_bridge(monkeypatch, now)
    odom = bridge._enqueuer(odom_out)
    scan_out.matching = False  # the scan is not sent, so it wakes nothing
    for _ in range(3):
        bridge.send_early("/scan", LaserScan())
        now[0] += 5 * MS
        odom(Odometry())
        now[0] += 20 * MS
    assert puts == [(TOPIC_ODOM, True)] * 3
    assert bridge.stats.skipped == 3


def test_a_riding_odometry_goes_out_before_the_scan_in_the_same_wake_up(monkeypatch):
    """With the real outbox (not started): the rider is queued without waking the thread; the scan
    wakes it, and the queue holds both, odometry first."""
    now = [1000 * MS]
    bridge, scan_out, odom_out, _ = _offline_bridge(monkeypatch, now)
    del bridge.outbox.put  # the real one again
    bridge._early["/scan"] = [(scan_out, bridge._enqueuer(scan_out))]
    odom = bridge._enqueuer(odom_out)
    bridge.send_early("/scan", LaserScan())
    now[0] += 25 * MS
    bridge.send_early("/scan", LaserScan())
    bridge.outbox.clear()
    bridge.outbox._wake.wait(0)  # consume the scans' wake-up
    now[0] += 10 * MS
    odom(Odometry())
    assert not bridge.outbox._wake.is_set()
    bridge.send_early("/scan", LaserScan())
    assert bridge.outbox._wake.is_set()
    queued = [args[0].row.bus for _, args in bridge.outbox._queue]
    assert queued == [TOPIC_ODOM, "/scan"]


def _command(speed: float) -> bytes:
    return ros2_types().serialize(AckermannDriveStamped(drive=AckermannDrive(speed=speed)))


def test_a_command_stream_arrives_whole_and_a_flood_is_coalesced_to_its_newest():
    """The command row's thread offers a sample at once when none was offered within the period,
    and rests the rest of the period only when a sample comes sooner: then the newest goes."""
    async def run() -> tuple[list[float], object]:
        bus = Bus()
        got: list[float] = []
        bus.subscribe(NAV0, lambda msg: got.append(msg.drive.speed))
        port = free_port()
        rows = topic_table(MuxParams(), SafetyParams())
        bridge = ZenohBridge(bus, ZenohParams(listen=[endpoint(port)]), rows)
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        await loop.run_in_executor(None, bridge.open, loop)
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        try:
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
        finally:
            peer.close()
            bridge.close()

    got, counts = asyncio.run(run())
    assert np.allclose(got[:5], [0.1, 0.2, 0.3, 0.4, 0.5])
    assert np.isclose(got[-1], 1.299)
    assert len(got) < 100  # the flood was coalesced, not handed over message by message
    assert counts.received == 305 and counts.superseded >= 300 - len(got[5:])
