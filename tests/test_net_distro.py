"""``zenoh.ros_distro``: the bridge's keys and tokens for Humble's rmw_zenoh (``TypeHashNotSupported``)
or for Jazzy and later (RIHS01), on a bus of its own with real Zenoh sessions on loopback. The two
never meet on a key, as between real Humble and Jazzy nodes."""

from __future__ import annotations

import asyncio

import pytest
import zenoh
from conftest import async_wait_for
from zenoh_util import bridge_with_peer, endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import Bool, LaserScan
from racecar_hw.config import load_config
from racecar_hw.net import rmw
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.net.zenoh_config import ZenohParams, session_config
from racecar_hw.rosmsg.typestore import ros2_types
from safety.params import SafetyParams


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_the_bridge_speaks_the_configured_distribution_only(distro):
    async def run() -> tuple[list, list[str], int]:
        bus = Bus()
        got: list = []
        bus.subscribe("/estop", got.append)
        port = free_port()
        rows = topic_table(MuxParams(), SafetyParams())
        bridge = ZenohBridge(bus, ZenohParams(listen=[endpoint(port)], ros_distro=distro), rows)
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        await loop.run_in_executor(None, bridge.open, loop)
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        try:
            payload = ros2_types().serialize(Bool(True))
            attach = rmw.Attachment(1, 1, bytes(16)).encode()
            other = "jazzy" if distro == "humble" else "humble"
            wrong = peer.declare_publisher(rmw.topic_key(0, "/estop", Bool.ROS_TYPE,
                                                         rmw.wire_type_hash(Bool.ROS_TYPE, other)))
            right = peer.declare_publisher(rmw.topic_key(0, "/estop", Bool.ROS_TYPE,
                                                         rmw.wire_type_hash(Bool.ROS_TYPE, distro)))
            await asyncio.sleep(0.3)
            wrong.put(payload, attachment=attach)
            right.put(payload, attachment=attach)
            await async_wait_for(lambda: got, timeout=20)
            await asyncio.sleep(0.3)
            tokens = [str(r.ok.key_expr) for r in peer.liveliness().get(rmw.liveliness_pattern(0), timeout=5)
                      if r.ok is not None]
            return got, tokens, bridge.stats.received
        finally:
            peer.close()
            await loop.run_in_executor(None, bridge.close)

    got, tokens, received = asyncio.run(run())
    assert len(got) == 1 and received == 1  # the other distribution's key never reached the bridge
    endpoints = [rmw.parse_token(t) for t in tokens if "/NN/" not in t]
    assert endpoints
    expected = {"humble": {rmw.HUMBLE_TYPE_HASH}}.get(distro)
    hashes = {e.type_hash for e in endpoints}
    if expected is not None:
        assert hashes == expected
    else:
        assert all(h.startswith("RIHS01_") for h in hashes)
        scan = next(e for e in endpoints if e.topic == "/scan")
        assert scan.type_hash == rmw.type_hash(LaserScan.ROS_TYPE)


def test_an_unknown_distribution_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match="zenoh.ros_distro"):
        load_config(None, ["zenoh.ros_distro=iron"])
    assert load_config(None, ["zenoh.ros_distro=humble"]).zenoh.ros_distro == "humble"
    assert load_config(None).zenoh.ros_distro == "jazzy"


def test_the_client_set_for_humble_reads_a_humble_daemon_and_refuses_an_unknown_distribution():
    from racecar_hw.client import Car, ClientError  # noqa: PLC0415

    with pytest.raises(ClientError, match="ros_distro"):
        Car("tcp/127.0.0.1:1", ros_distro="iron")

    async def run() -> tuple[int, int]:
        bus = Bus()
        port = free_port()
        rows = topic_table(MuxParams(), SafetyParams())
        bridge = ZenohBridge(bus, ZenohParams(listen=[endpoint(port)], ros_distro="humble"), rows)
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        await loop.run_in_executor(None, bridge.open, loop)
        humble = await loop.run_in_executor(None, lambda: Car(endpoint(port), ros_distro="humble"))
        jazzy = await loop.run_in_executor(None, lambda: Car(endpoint(port)))
        try:
            scan = LaserScan(range_max=10.0)
            for _ in range(2000):
                bus.publish("/scan", scan)
                if humble.scan_stream.count >= 3:
                    break
                await asyncio.sleep(0.01)
            return humble.scan_stream.count, jazzy.scan_stream.count
        finally:
            humble.close()
            jazzy.close()
            await loop.run_in_executor(None, bridge.close)

    humble_scans, jazzy_scans = asyncio.run(run())
    assert humble_scans >= 3 and jazzy_scans == 0


def test_a_sample_from_rmw_zenoh_before_0_2_4_is_dropped_with_a_hint_to_update(caplog):
    """Jazzy's rmw_zenoh 0.2.0-0.2.3 attached a map with string keys; such a sample is told apart."""
    import zenoh.ext  # noqa: PLC0415

    old = zenoh.ext.z_serialize({"sequence_number": (1).to_bytes(8, "little"),
                                 "source_timestamp": (2).to_bytes(8, "little"),
                                 "source_gid": bytes(16)}).to_bytes()
    assert rmw.is_old_attachment(old) and not rmw.is_old_attachment(rmw.Attachment(1, 2, bytes(16)).encode())

    async def run() -> object:
        bus = Bus()
        async with bridge_with_peer(bus) as (bridge, peer):
            key = rmw.topic_key(0, "/estop", Bool.ROS_TYPE, rmw.type_hash(Bool.ROS_TYPE))
            pub = peer.declare_publisher(key)
            await asyncio.sleep(0.3)
            pub.put(ros2_types().serialize(Bool(True)), attachment=old)
            await async_wait_for(lambda: bridge.stats.old_attachment, timeout=20)
            return bridge.stats

    with caplog.at_level("WARNING", logger="racecar_hw.net.zenoh_bridge"):
        stats = asyncio.run(run())
    assert stats.old_attachment == 1 and stats.received == 0 and stats.malformed == 0
    assert "update rmw_zenoh" in caplog.text and "0.2.0-0.2.3" in caplog.text
