"""The Zenoh bridge on a bus of its own, with real Zenoh sessions on loopback, and its config."""

from __future__ import annotations

import asyncio
import math
import subprocess
import sys

import numpy as np
import pytest
import zenoh
from conftest import async_wait_for
from hypothesis import given, settings
from hypothesis import strategies as st
from zenoh_util import endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Bool,
    LaserScan,
    Twist,
    Vector3,
    stamp_now,
)
from racecar_hw.config import load_config, network_topics
from racecar_hw.net import rmw
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge, all_finite
from racecar_hw.net.zenoh_config import ZenohParams, session_config
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.sources.cmd_vel import twist_to_ackermann
from safety.params import SafetyParams

NAV0 = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"


def _key(topic: str, cls: type, domain: int = 0) -> str:
    return rmw.topic_key(domain, topic, cls.ROS_TYPE, rmw.type_hash(cls.ROS_TYPE))


async def _bridge(bus: Bus, port: int, **params) -> ZenohBridge:
    p = ZenohParams(listen=[endpoint(port)], **params)
    rows = topic_table(MuxParams(), SafetyParams(), cmd_vel_topic="/cmd_vel")
    bridge = ZenohBridge(bus, p, rows)
    loop = asyncio.get_running_loop()
    bus.bind_loop(loop)
    await loop.run_in_executor(None, bridge.open, loop)
    return bridge


def test_incoming_samples_are_checked_before_they_reach_the_bus():
    async def run() -> tuple[list, object]:
        bus = Bus()
        got: list = []
        bus.subscribe(NAV0, got.append)
        port = free_port()
        bridge = await _bridge(bus, port)
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        try:
            pub = peer.declare_publisher(_key(NAV0, AckermannDriveStamped))
            good = ros2_types().serialize(AckermannDriveStamped(stamp_now("base_link", 1),
                                                                AckermannDrive(0.1, 0.0, 1.5)))
            nan = ros2_types().serialize(AckermannDriveStamped(drive=AckermannDrive(speed=math.nan)))
            attach = rmw.Attachment(1, 1, bytes(16)).encode()
            s = bridge.stats
            # a command row keeps only the newest sample: one at a time, each checked and counted
            for payload, attachment in [
                    (good, None),               # no attachment: rmw_zenoh drops it too
                    (good, b"\x01\x02"),        # not rmw_zenoh's attachment
                    (good[:9], attach),         # truncated CDR
                    (b"\xff" * 40, attach),     # garbage
                    (nan, attach),              # NaN speed
                    (good, attach)]:            # the only one that counts
                before = s.no_attachment + s.malformed + s.non_finite + s.received
                if attachment is None:
                    pub.put(payload)
                else:
                    pub.put(payload, attachment=attachment)
                await async_wait_for(lambda b=before: s.no_attachment + s.malformed + s.non_finite
                                     + s.received > b, timeout=20)
            await async_wait_for(lambda: got, timeout=20)
            await asyncio.sleep(0.2)
            return got, bridge.stats
        finally:
            peer.close()
            bridge.close()

    got, stats = asyncio.run(run())
    assert len(got) == 1 and got[0].drive.speed == pytest.approx(1.5)
    assert (stats.no_attachment, stats.malformed, stats.non_finite, stats.received) == (1, 3, 1, 1)


def test_outgoing_topics_are_not_serialized_while_nobody_subscribes_and_carry_the_attachment():
    async def run() -> tuple:
        bus = Bus()
        port = free_port()
        bridge = await _bridge(bus, port)
        scan = LaserScan(stamp_now("laser", 5), -1.0, 1.0, 0.5, 0.0, 0.025, 0.02, 10.0,
                         np.ones(5, np.float32), np.zeros(0, np.float32))
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        try:
            bus.publish("/scan", scan)
            await asyncio.sleep(0.3)
            skipped_before = bridge.stats.skipped
            samples: list = []
            sub = peer.declare_subscriber(_key("/scan", LaserScan), samples.append)
            out = next(o for o in bridge._outs if o.row.bus == "/scan")
            await async_wait_for(lambda: out.matching, timeout=20)
            for _ in range(3):
                bus.publish("/scan", scan)
            await async_wait_for(lambda: len(samples) >= 3, timeout=20)
            sub.undeclare()
            await async_wait_for(lambda: not out.matching, timeout=20)
            bus.publish("/scan", scan)
            return skipped_before, samples, bridge.stats.skipped
        finally:
            peer.close()
            bridge.close()

    skipped_before, samples, skipped_after = asyncio.run(run())
    assert skipped_before >= 1 and skipped_after == skipped_before + 1
    first = rmw.Attachment.decode(samples[0].attachment.to_bytes())
    assert [rmw.Attachment.decode(s.attachment.to_bytes()).sequence_number for s in samples] == [1, 2, 3]
    assert first.source_timestamp_ns > 1_600_000_000 * 10**9
    back = ros2_types().deserialize(samples[0].payload.to_bytes(), LaserScan)
    assert back.header.frame_id == "laser" and list(back.ranges) == [1.0] * 5


def test_the_graph_shows_the_node_and_every_topic():
    async def run() -> list[rmw.Entity]:
        bus = Bus()
        port = free_port()
        bridge = await _bridge(bus, port, namespace="/car7", domain_id=4)
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        try:
            replies = peer.liveliness().get(rmw.liveliness_pattern(4), timeout=5)
            return [rmw.parse_token(str(r.ok.key_expr)) for r in replies if r.ok is not None]
        finally:
            peer.close()
            bridge.close()

    entities = asyncio.run(run())
    nodes = [e for e in entities if e.kind == rmw.NODE]
    assert [n.node for n in nodes] == ["/car7/racecar_hw"]
    pubs = {e.topic: e for e in entities if e.kind == rmw.PUBLISHER}
    subs = {e.topic: e for e in entities if e.kind == rmw.SUBSCRIPTION}
    assert pubs["/car7/scan"].ros_type == "sensor_msgs/msg/LaserScan"
    assert pubs["/car7/scan"].qos.reliability == rmw.BEST_EFFORT
    assert pubs["/car7/tf_static"].qos.durability == rmw.TRANSIENT_LOCAL
    assert subs["/car7" + NAV0].type_hash == rmw.type_hash("ackermann_msgs/msg/AckermannDriveStamped")
    assert subs["/car7/cmd_vel"].ros_type == "geometry_msgs/msg/Twist"
    assert len({e.gid() for e in entities}) == len(entities)


def test_a_port_in_use_is_refused_at_start_in_one_line_naming_the_listen_and_the_fix():
    async def run() -> None:
        port = free_port()
        first = await _bridge(Bus(), port)  # stands in for rmw_zenohd holding the port
        try:
            with pytest.raises(ConfigError) as err:
                await _bridge(Bus(), port)
        finally:
            first.close()
        assert err.value.key == "zenoh.listen[0]"
        text = str(err.value)
        assert "\n" not in text and ".rs:" not in text, text
        assert f"{endpoint(port)} is already in use" in text and "rmw_zenohd" in text
        assert f'zenoh.connect: ["{endpoint(port)}"]' in text and "zenoh.enabled: false" in text

    asyncio.run(run())


# --- configuration ------------------------------------------------------------------------------


@pytest.mark.parametrize("listen", ["tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/192.168.1.5:7447",
                                    "tls/0.0.0.0:7447"])
def test_a_listen_beyond_loopback_without_authentication_is_refused(listen):
    with pytest.raises(ConfigError, match=r"zenoh\.listen\[0\]") as err:
        load_config(None, [f'zenoh.listen=["{listen}"]'])
    assert "auth.dictionary_file" in str(err.value)


def test_multicast_scouting_is_refused_even_with_authentication(tmp_path):
    """Scouting makes the car open sessions to whatever LAN peer answers; the dictionary only checks
    the sessions others open to the car, so it does not make scouting safe."""
    users = tmp_path / "users.txt"
    users.write_text("laptop:a-long-random-password\n")
    for extra in ([], [f"zenoh.auth.dictionary_file={users}"]):
        with pytest.raises(ConfigError, match="multicast scouting listens on every interface") as err:
            load_config(None, ["zenoh.multicast_scouting=true", *extra])
        assert err.value.key == "zenoh.multicast_scouting" and "connect" in str(err.value)
    load_config(None, ["zenoh.multicast_scouting=false"])


def test_a_listen_beyond_loopback_with_authentication_is_accepted(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("laptop:a-long-random-password\n")
    load_config(None, ['zenoh.listen=["tcp/0.0.0.0:7447"]', f"zenoh.auth.dictionary_file={users}"])
    pem = {}
    for name, kind in (("c.pem", "CERTIFICATE"), ("k.pem", "PRIVATE KEY"), ("ca.pem", "CERTIFICATE")):
        pem[name] = tmp_path / name
        pem[name].write_text(f"-----BEGIN {kind}-----\nMAo=\n-----END {kind}-----\n")
    load_config(None, ['zenoh.listen=["tls/0.0.0.0:7447"]', f"zenoh.tls.listen_certificate={pem['c.pem']}",
                       f"zenoh.tls.listen_private_key={pem['k.pem']}",
                       f"zenoh.tls.root_ca_certificate={pem['ca.pem']}", "zenoh.tls.enable_mtls=true"])
    load_config(None, ['zenoh.listen=["tcp/127.0.0.1:7447", "tcp/[::1]:7448", "tcp/localhost:7449"]'])


def test_the_daemon_refuses_to_start_on_an_open_listen_with_a_clear_message(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "sim", "--duration", "1", "--no-status",
                           "--set", 'zenoh.listen=["tcp/0.0.0.0:7447"]', "--report",
                           str(tmp_path / "r.json")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert "zenoh.listen[0]" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize(("override", "key"), [
    ('zenoh.listen=["tcp/127.0.0.1"]', "zenoh.listen[0]"),
    ('zenoh.connect=["carrier-pigeon/x:1"]', "zenoh.connect[0]"),
    ("zenoh.mode=broker", "zenoh.mode"),
    ("zenoh.namespace=/car 1", "zenoh.namespace"),
    ("zenoh.node_name=racecar/hw", "zenoh.node_name"),
    ("zenoh.profile=autoware", "zenoh.profile"),
    ("zenoh.remap={/nowhere: /x}", "zenoh.remap./nowhere"),
    ("zenoh.remap={/odom: not-a-name}", "zenoh.remap./odom"),
    ("zenoh.remap={/odom: /scan}", "zenoh.remap"),
    ("zenoh.domain_id=300", "zenoh.domain_id"),
    ("zenoh.auth.user=me", "zenoh.auth.password"),
    ("zenoh.colour=blue", "zenoh.colour"),
])
def test_bad_zenoh_settings_are_refused_naming_the_key(override, key):
    with pytest.raises(ConfigError) as err:
        load_config(None, [override])
    assert err.value.key == key, str(err.value)


def test_profiles_and_remaps_name_the_topics():
    f1 = {r.bus: r.ros for r in network_topics(load_config(None, ["zenoh.profile=f1tenth"]))}
    assert f1[NAV0] == "/drive" and f1["/vesc/low_level/ackermann_cmd_mux/input/teleop"] == "/teleop"
    assert f1["/vesc/sensors/core"] == "/sensors/core" and f1["/scan"] == "/scan"
    remapped = load_config(None, ["zenoh.profile=f1tenth", "zenoh.remap={/odom: /vesc/odom}"])
    assert {r.bus: r.ros for r in network_topics(remapped)}["/odom"] == "/vesc/odom"


def test_the_cmd_vel_input_sits_between_nav_0_and_nav_1():
    config = load_config(None)
    inputs = {i.name: i for i in config.mux.inputs}
    assert inputs["nav_0"].priority > inputs["cmd_vel"].priority == 18 > inputs["nav_1"].priority
    assert "cmd_vel" not in {i.name for i in load_config(None, ["zenoh.cmd_vel=false"]).mux.inputs}
    assert "cmd_vel" in {i.name for i in load_config(None, ["zenoh.enabled=false"]).mux.inputs}  # DDS
    neither = load_config(None, ["zenoh.enabled=false", "dds.enabled=false"])
    assert "cmd_vel" not in {i.name for i in neither.mux.inputs}


def test_the_domain_id_comes_from_the_environment_unless_configured(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    assert ZenohParams().resolved_domain_id() == 7
    assert ZenohParams(domain_id=3).resolved_domain_id() == 3
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ConfigError, match="zenoh.domain_id"):
        ZenohParams().resolved_domain_id()


# --- /cmd_vel and the finite check --------------------------------------------------------------


def test_twist_becomes_an_ackermann_command_with_the_wheelbase():
    drive = twist_to_ackermann(Twist(Vector3(x=1.0), Vector3(z=0.5)), 0.25, 0.4)
    assert drive.speed == 1.0 and drive.steering_angle == pytest.approx(math.atan(0.25 * 0.5 / 1.0))
    back = twist_to_ackermann(Twist(Vector3(x=-1.0), Vector3(z=0.5)), 0.25, 0.4)
    assert back.steering_angle == pytest.approx(-math.atan(0.125))  # reversing: the same yaw rate
    assert twist_to_ackermann(Twist(Vector3(x=0.0), Vector3(z=1.0)), 0.25, 0.4).steering_angle == 0.0
    assert twist_to_ackermann(Twist(Vector3(x=0.5), Vector3(z=9.0)), 0.25, 0.26).steering_angle == 0.26
    assert twist_to_ackermann(Twist(Vector3(x=math.inf)), 0.25, 0.26) is None


def test_all_finite_looks_into_nested_messages_and_arrays():
    assert all_finite(AckermannDriveStamped()) and all_finite(Bool(True))
    assert not all_finite(Twist(angular=Vector3(z=math.nan)))
    scan = LaserScan(ranges=np.array([1.0, np.inf], np.float32))
    assert not all_finite(scan)


def test_the_bridge_takes_a_scan_only_after_the_daemon_wrote_its_motor_command():
    """The scan reaches the bridge's queue from the daemon's control path, right after the motor write
    (and before the bookkeeping and the bus's subscribers), and wakes the publisher at once; the
    bridge does not subscribe to the scan on the bus."""
    from racecar_hw.base.clock import monotonic_ns
    from racecar_hw.daemon import Daemon

    port = free_port()
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", f'zenoh.listen=["{endpoint(port)}"]',
                                "foxglove.enabled=false", "web.enabled=false"])
    daemon = Daemon(config)
    assert daemon.zenoh is not None and daemon.cmd_vel is not None
    events: list = []

    class Motor:  # the VESC driver's command(), where the scan path writes the motor command
        def command(self, drive: AckermannDrive) -> None:
            events.append("motor write")

    def remembered() -> None:
        events.append("obstacle memory")

    async def run() -> list:
        loop = asyncio.get_running_loop()
        daemon.bus.bind_loop(loop)
        daemon.zenoh.outbox.put = lambda fn, *args, urgent=False: events.append(("queued", urgent))
        await loop.run_in_executor(None, daemon.zenoh.open, loop)
        try:
            callbacks = [s.callback for s in daemon.bus._subs.get("/scan", [])]
            scan_out = next(o for o in daemon.zenoh._outs if o.row.bus == "/scan")
            scan_out.matching = True  # as if a remote node subscribed
            daemon.control._write = Motor().command
            daemon.safety.remember = remembered  # type: ignore[method-assign]
            daemon.mux.last_output = AckermannDriveStamped()
            daemon.stats.ticks, daemon.stats.last_tick_ns = 1, monotonic_ns()
            daemon.control.take_scan(LaserScan(angle_min=-1.0, angle_increment=0.01,
                                               ranges=np.full(201, 5.0, dtype=np.float32)))
            return callbacks
        finally:
            daemon.zenoh.close()

    callbacks = asyncio.run(run())
    assert not any(c.__qualname__.startswith("ZenohBridge") for c in callbacks)
    assert events == ["motor write", ("queued", True), "obstacle memory"]


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, payload: bytes, attachment: bytes | None) -> None:
        self.payload = _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)


@given(payload=st.one_of(st.binary(max_size=120), st.just(ros2_types().serialize(Bool(True))),
                        st.just(ros2_types().serialize(Twist(Vector3(x=math.inf))))),
       attachment=st.one_of(st.none(), st.binary(max_size=40)),
       topic=st.sampled_from([NAV0, "/estop", "/cmd_vel"]))
@settings(max_examples=300, deadline=None)
def test_any_bytes_from_the_network_are_counted_never_raised(payload, attachment, topic):
    if attachment is not None and len(attachment) == 33:
        attachment = attachment[:16] + b"\x10" + attachment[17:]  # often well-formed
    rows = {r.bus: r for r in topic_table(MuxParams(), SafetyParams(), cmd_vel_topic="/cmd_vel")}
    bridge = ZenohBridge(Bus(), ZenohParams(), list(rows.values()))
    loop = asyncio.new_event_loop()  # not running: a hand-over only queues
    bridge.inbox.bind(loop)
    try:
        bridge.inputs.receiver(rows[topic])(_Sample(payload, attachment))
    finally:
        loop.close()
    s = bridge.stats
    assert s.no_attachment + s.malformed + s.non_finite + s.received == 1


def test_without_cyclonedds_the_daemon_runs_without_dds_and_says_so(monkeypatch, caplog, tmp_path):
    """cyclonedds is a dependency on x86_64 only: elsewhere, unless installed, DDS is off, with a
    warning that names the package and the key."""
    import racecar_hw.daemon as daemon_module
    import racecar_hw.interfaces as interfaces_module

    monkeypatch.setattr(interfaces_module, "cyclone_available", lambda: False)
    config = load_config(None, [f"vesc.port={tmp_path / 'no-vesc'}", "lidar.enabled=false",
                                "gamepad.enabled=false", "status.enabled=false", "safety.mode=off",
                                "zenoh.enabled=false", "foxglove.enabled=false", "web.enabled=false"])
    with caplog.at_level("WARNING"):
        daemon = daemon_module.Daemon(config)
    assert daemon.dds is None
    assert "pip install cyclonedds" in caplog.text and "dds.enabled: false" in caplog.text
