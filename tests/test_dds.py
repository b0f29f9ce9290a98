"""The DDS interface's parts: the ``dds`` section, Cyclone's configuration, the node graph message
(checked against rclpy's own serializer where the ROS 2 wheels are installed), the generated topic
types carrying raw CDR through a real Cyclone writer and reader, and the bridge in the daemon's
place: nothing serialized while no reader matches, commands checked and handed to the bus.

Cyclone runs here on this machine's loopback, on a random domain of its own; the tests against a
real ROS 2 node are in tests/test_dds_ros2.py (in a private network namespace)."""

from __future__ import annotations

import asyncio
import math
import random
import subprocess
import threading
import time

import pytest
from conftest import wait_for
from hypothesis import given, settings
from hypothesis import strategies as st

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Bool, String, Twist, Vector3
from racecar_hw.base.topics import MUX_SAFETY_TOPIC, NAV0_TOPIC
from racecar_hw.config import load_config
from racecar_hw.net import dds_graph
from racecar_hw.net.dds_config import DdsParams, cyclone_xml, security_plugins_available
from racecar_hw.net.topics import DEFAULT, LATCHED, Direction, Topic, topic_table
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.refusals import Refusals
from safety.params import SafetyParams

pytest.importorskip("cyclonedds", reason="cyclonedds (a dependency) is not installed")

from cyclonedds.domain import Domain, DomainParticipant  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic as DdsTopic  # noqa: E402

from racecar_hw.net.dds_bridge import DdsBridge, qos_of  # noqa: E402
from racecar_hw.net.dds_types import RawSample, raw_sample, ros2_factory  # noqa: E402


def _domain() -> int:
    """A domain of this test's own, so parallel runs on one machine do not meet."""
    return random.randrange(100, 230)


# --- the section ----------------------------------------------------------------------------------


def test_dds_is_on_and_stays_on_this_computer_by_default():
    p = load_config(None).dds
    assert p.enabled and p.local and p.accepts_commands and p.start_notice() is None
    xml = cyclone_xml(p)
    assert '<NetworkInterface address="127.0.0.1"/>' in xml
    assert "<AllowMulticast>false</AllowMulticast>" in xml and '<Peer address="127.0.0.1"/>' in xml
    # Cyclone 11 rejects Fast DDS 3's type information: without this nothing would match
    assert "<IgnoreTypeInformation>1.15</IgnoreTypeInformation>" in xml


def test_beyond_loopback_dds_takes_commands_only_when_a_key_says_so():
    lan = DdsParams(interface="192.168.1.20")
    assert not lan.local and not lan.accepts_commands
    notice = lan.start_notice()
    assert "publishing only" in notice and "dds.accept_unauthenticated_commands" in notice
    allowed = DdsParams(interface="eth0", accept_unauthenticated_commands=True)
    assert allowed.accepts_commands and "anyone on that network can drive the car" in allowed.start_notice()
    assert '<NetworkInterface name="eth0"/>' in cyclone_xml(allowed)


def test_the_participant_index_range_is_fast_dds_s_and_a_full_range_is_said_so():
    """Cyclone's default of 32 left the 33rd ROS 2 process on the computer without the car, and 32
    held ports kept the daemon from starting, blamed on dds.interface. The range is 0-120 now;
    with every one of its discovery ports held, the refusal names the domain and the cause."""
    import socket

    from racecar_hw.net.dds_config import MAX_PARTICIPANT_INDEX, participant_ports

    assert f"<MaxAutoParticipantIndex>{MAX_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>" in cyclone_xml(
        DdsParams()) and MAX_PARTICIPANT_INDEX == 120
    domain_id = 231  # its ports, 65160-65400, are above the ephemeral range on this machine kind
    ports = participant_ports(domain_id)
    assert ports[0] == 7410 + 250 * domain_id and ports[-1] == ports[0] + 240 < 65536
    held = []
    try:
        for port in ports[:40]:  # more than the old 32: the bridge still opens
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", port))
            held.append(s)
        bridge = DdsBridge(Bus(), DdsParams(domain_id=domain_id), [])
        loop = asyncio.new_event_loop()
        try:
            bridge.open(loop)
        finally:
            bridge.close()
        for port in ports[40:]:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", port))
            held.append(s)
        full = DdsBridge(Bus(), DdsParams(domain_id=domain_id), [])
        with pytest.raises(ConfigError, match=r"^dds\.domain_id: no free DDS participant index in domain"):
            full.open(loop)
        loop.close()
    finally:
        for s in held:
            s.close()


def test_the_section_refuses_bad_values_naming_the_key(monkeypatch):
    with pytest.raises(ConfigError, match=r"dds\.multicast"):
        load_config(None, ["dds.multicast=true"])
    with pytest.raises(ConfigError, match=r"dds\.peers\[0\]"):
        load_config(None, ['dds.peers=["<evil/>"]'])
    with pytest.raises(ConfigError, match=r"dds\.interface"):
        load_config(None, ['dds.interface=""'])
    with pytest.raises(ConfigError, match=r"dds\.ros_distro"):
        load_config(None, ["dds.ros_distro=foxy"])
    with pytest.raises(ConfigError, match=r"dds\.nope"):
        load_config(None, ["dds.nope=1"])
    monkeypatch.setenv("ROS_DOMAIN_ID", "12")
    assert DdsParams().resolved_domain_id() == 12 and DdsParams(domain_id=3).resolved_domain_id() == 3
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ConfigError, match=r"dds\.domain_id"):
        DdsParams().validate()


def test_the_node_graph_gid_follows_the_distribution():
    assert DdsParams(ros_distro="humble").gid_size == 24 and DdsParams().gid_size == 16
    assert not DdsParams().null_participant_gid and DdsParams(ros_distro="kilted").null_participant_gid


def test_the_pypi_cyclone_build_has_no_dds_security_plugins():
    """Documented in docs/interop.md: hence no SROS2 keystore, and commands refused beyond loopback."""
    assert not security_plugins_available()


# --- the node graph message -----------------------------------------------------------------------


@pytest.mark.parametrize("gid_size", [16, 24])
def test_participant_info_round_trips(gid_size):
    info = dds_graph.ParticipantInfo(bytes(range(16)), [dds_graph.NodeInfo(
        "/car1", "racecar_hw", [bytes([1]) * 16], [bytes([2]) * 16, bytes([3]) * 16])])
    back = dds_graph.decode_participant_info(dds_graph.encode_participant_info(info, gid_size), gid_size)
    pad = bytes(gid_size - 16)
    assert back.gid == bytes(range(16)) + pad
    assert back.nodes[0].namespace == "/car1" and back.nodes[0].name == "racecar_hw"
    assert back.nodes[0].writers == [bytes([2]) * 16 + pad, bytes([3]) * 16 + pad]


def test_participant_info_bytes_equal_rclpy_serialization():
    """rclpy's own serializer (rmw_dds_common from the Kilted wheels) gives the same bytes."""
    from netns import ros_python

    python = ros_python()
    script = (
        "from rclpy.serialization import serialize_message\n"
        "from rmw_dds_common.msg import Gid, NodeEntitiesInfo, ParticipantEntitiesInfo\n"
        "g = lambda b: Gid(data=list(b))\n"
        "m = ParticipantEntitiesInfo(gid=g(bytes(range(16))), node_entities_info_seq=[NodeEntitiesInfo("
        "node_namespace='/', node_name='racecar_hw', reader_gid_seq=[g(b'\\x01' * 16)], "
        "writer_gid_seq=[g(b'\\x02' * 16), g(b'\\x03' * 16)])])\n"
        "print(serialize_message(m).hex())\n")
    proc = subprocess.run([python, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    ours = dds_graph.encode_participant_info(dds_graph.ParticipantInfo(bytes(range(16)), [dds_graph.NodeInfo(
        "/", "racecar_hw", [b"\x01" * 16], [b"\x02" * 16, b"\x03" * 16])]))
    assert ours.hex() == proc.stdout.strip()


def test_user_data_carries_the_type_hash_as_iron_and_later_do():
    assert dds_graph.user_data("RIHS01_ab") == b"typehash=RIHS01_ab;" and dds_graph.user_data(None) == b""
    assert dds_graph.topic_name("/car1/scan") == "rt/car1/scan"


# --- types and raw CDR through a real Cyclone writer and reader -----------------------------------


def test_every_row_type_gets_its_dds_name():
    factory = ros2_factory()
    config = load_config(None)
    from racecar_hw.config import network_topics

    for row in network_topics(config):
        ros_type = row.msgtype.ROS_TYPE
        pkg, _, name = ros_type.split("/")
        assert factory.topic_type(ros_type).__idl_typename__ == f"{pkg}::msg::dds_::{name}_"


def test_raw_cdr_goes_through_cyclone_unchanged():
    domain_id = _domain()
    domain = Domain(domain_id, cyclone_xml(DdsParams()))
    participant = DomainParticipant(domain_id)
    try:
        topic_type = ros2_factory().topic_type("geometry_msgs/msg/Twist")
        topic = DdsTopic(participant, "rt/dds_test_twist", topic_type)
        reader = DataReader(participant, topic, qos_of(DEFAULT))
        writer = DataWriter(participant, topic, qos_of(DEFAULT))
        cdr = ros2_types().serialize(Twist(Vector3(0.5, 0.0, 0.0), Vector3(0.0, 0.0, 0.6)))
        writer.write(raw_sample(topic_type, cdr))
        got: list[RawSample] = []
        wait_for(lambda: got.extend(reader.take(4)) or got, timeout=20)
        assert got[0].data == cdr
    finally:
        del participant, domain


# --- the bridge -----------------------------------------------------------------------------------


class _Car:
    """The bridge in the daemon's place: a bus, an event loop in a thread, and a Cyclone peer."""

    def __init__(self, rows: list[Topic], params: DdsParams) -> None:
        self.bus = Bus()
        self.loop = asyncio.new_event_loop()
        self.inputs: list[str] = []
        self.bridge = DdsBridge(self.bus, params, rows, on_input=self.inputs.append)

    def __enter__(self) -> _Car:
        import threading

        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.bus.bind_loop(self.loop)
        self.bridge.open(self.loop)
        return self

    def __exit__(self, *exc: object) -> None:
        self.bridge.close()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


def test_the_bridge_serializes_nothing_while_no_reader_matches_and_latches_what_it_must():
    domain_id = _domain()
    params = DdsParams(domain_id=domain_id)
    rows = [Topic("/dds_test/out", String, Direction.OUT, DEFAULT),
            Topic("/dds_test/latched", String, Direction.OUT, LATCHED)]
    with _Car(rows, params) as car:
        car.loop.call_soon_threadsafe(car.bus.publish, "/dds_test/latched", String("kept"))
        for _ in range(5):
            car.loop.call_soon_threadsafe(car.bus.publish, "/dds_test/out", String("nobody"))
        wait_for(lambda: car.bridge.stats.skipped >= 5, timeout=10)
        assert car.bridge.stats.published <= 1  # only the latched one
        # a reader joins late: the latched sample reaches it from the writer's history
        factory = ros2_factory()
        peer = DomainParticipant(domain_id)  # in the domain the bridge configured
        topic_type = factory.topic_type("std_msgs/msg/String")
        late = DataReader(peer, DdsTopic(peer, "rt/dds_test/latched", topic_type), qos_of(LATCHED))
        live = DataReader(peer, DdsTopic(peer, "rt/dds_test/out", topic_type), qos_of(DEFAULT))
        got: list[RawSample] = []
        wait_for(lambda: got.extend(late.take(4)) or got, timeout=30)
        assert ros2_types().deserialize(got[0].data, String).data == "kept"
        # once a reader matches, messages go out
        wait_for(lambda: car.bridge._outs[0].matching, timeout=30)
        live_got: list[RawSample] = []

        def sent() -> bool:
            car.loop.call_soon_threadsafe(car.bus.publish, "/dds_test/out", String("hello"))
            live_got.extend(live.take(4))
            return bool(live_got)

        wait_for(sent, timeout=30, interval=0.1)
        assert ros2_types().deserialize(live_got[0].data, String).data == "hello"


def test_commands_are_checked_then_handed_to_the_bus():
    domain_id = _domain()
    params = DdsParams(domain_id=domain_id)
    rows = [Topic("/dds_test/cmd", Twist, Direction.IN, DEFAULT, ros="/dds_test/cmd_vel"),
            Topic("/dds_test/estop", Bool, Direction.IN, DEFAULT)]
    with _Car(rows, params) as car:
        got: list[Twist] = []
        car.bus.subscribe("/dds_test/cmd", got.append)
        peer = DomainParticipant(domain_id)  # in the domain the bridge configured
        topic_type = ros2_factory().topic_type("geometry_msgs/msg/Twist")
        writer = DataWriter(peer, DdsTopic(peer, "rt/dds_test/cmd_vel", topic_type), qos_of(DEFAULT))
        wait_for(lambda: writer.get_publication_matched_status().current_count > 0, timeout=30)
        types = ros2_types()
        nan = types.serialize(Twist(Vector3(math.nan, 0.0, 0.0), Vector3()))
        s = car.bridge.stats
        writer.write(raw_sample(topic_type, nan))
        wait_for(lambda: s.non_finite == 1, timeout=30)
        # (a cut-short payload is refused by Cyclone itself, at a writer and at a reader, which
        # check CDR against the type: the fuzz test below feeds such bytes to our decoder)
        writer.write(raw_sample(topic_type, types.serialize(Twist(Vector3(0.4, 0.0, 0.0), Vector3()))))
        wait_for(lambda: got, timeout=30)
        assert got[0].linear.x == 0.4 and car.inputs == ["/dds_test/cmd"]
        # the receiving thread counts a sample after the inbox has taken it, so the loop may hand it
        # to the bus first
        wait_for(lambda: s.received == 1, timeout=30)
        assert s.malformed == 0 and s.refused == 0


def test_a_mux_input_closed_to_the_network_refuses_and_counts_every_sample_while_nav_drives():
    """The daemon's own rows for safety (network: false by default) and nav_0: a sample on safety
    is refused, counted per input with the key to change, and never reaches the bus (the mux)."""
    domain_id = _domain()
    params = DdsParams(domain_id=domain_id)
    table = {row.bus: row for row in topic_table(MuxParams(), SafetyParams())}
    safety, nav = table[MUX_SAFETY_TOPIC], table[NAV0_TOPIC]
    refusals = Refusals()
    car = _Car([safety, nav], params)
    car.bridge = DdsBridge(car.bus, params, [safety, nav], on_input=car.inputs.append, refusals=refusals)
    with car:
        got: dict[str, list] = {MUX_SAFETY_TOPIC: [], NAV0_TOPIC: []}
        for topic, into in got.items():
            car.bus.subscribe(topic, into.append)
        peer = DomainParticipant(domain_id)
        drive_type = ros2_factory().topic_type("ackermann_msgs/msg/AckermannDriveStamped")
        writers = [DataWriter(peer, DdsTopic(peer, "rt" + row.ros, drive_type), qos_of(DEFAULT))
                   for row in (safety, nav)]
        wait_for(lambda: all(w.get_publication_matched_status().current_count > 0 for w in writers),
                 timeout=30)
        cdr = ros2_types().serialize(AckermannDriveStamped(drive=AckermannDrive(speed=1.0)))
        for _ in range(5):
            writers[0].write(raw_sample(drive_type, cdr))
        wait_for(lambda: car.bridge.inbox.counts()[MUX_SAFETY_TOPIC].refused == 5, timeout=30)
        writers[1].write(raw_sample(drive_type, cdr))
        wait_for(lambda: got[NAV0_TOPIC], timeout=30)
        counts = car.bridge.inbox.counts()[MUX_SAFETY_TOPIC]
    reason = "mux input safety takes no network commands (mux.inputs[0].network: false)"
    assert got[MUX_SAFETY_TOPIC] == [] and car.inputs == [NAV0_TOPIC]
    assert (counts.received, counts.handed_over, counts.reasons) == (0, 0, {reason: 5})
    assert car.bridge.stats.refused == 5 and refusals.total("dds", reason) == 5


def test_a_command_flood_is_handed_over_at_most_once_per_period_and_e_stops_never_coalesce():
    """10,000 Twists as fast as a writer goes: the loop gets about one per control period, the
    newest; every e-stop message reaches on_estop, in order."""
    domain_id = _domain()
    params = DdsParams(domain_id=domain_id)
    rows = [Topic("/dds_test/cmd", Twist, Direction.IN, DEFAULT),
            Topic("/dds_test/estop", Bool, Direction.IN, DEFAULT)]
    stops: list[bool] = []
    car = _Car(rows, params)
    car.bridge = DdsBridge(car.bus, params, rows, on_input=car.inputs.append, period_s=0.05,
                           on_estop=lambda topic, msg, who: stops.append(msg.data),
                           estop_topic="/dds_test/estop")
    with car:
        got: list[Twist] = []
        car.bus.subscribe("/dds_test/cmd", got.append)
        peer = DomainParticipant(domain_id)
        twist_type = ros2_factory().topic_type("geometry_msgs/msg/Twist")
        bool_type = ros2_factory().topic_type("std_msgs/msg/Bool")
        twists = DataWriter(peer, DdsTopic(peer, "rt/dds_test/cmd", twist_type), qos_of(DEFAULT))
        estops = DataWriter(peer, DdsTopic(peer, "rt/dds_test/estop", bool_type), qos_of(DEFAULT))
        wait_for(lambda: twists.get_publication_matched_status().current_count > 0
                 and estops.get_publication_matched_status().current_count > 0, timeout=30)
        types = ros2_types()
        start = time.monotonic()
        for i in range(10000):
            cdr = types.serialize(Twist(Vector3(i / 1e4, 0.0, 0.0), Vector3()))
            twists.write(raw_sample(twist_type, cdr))
        for value in (True, False, True):
            estops.write(raw_sample(bool_type, types.serialize(Bool(value))))
        wait_for(lambda: got and got[-1].linear.x == 0.9999, timeout=30)
        took = time.monotonic() - start  # the first write to the newest one handed over
        wait_for(lambda: len(stops) == 3, timeout=30)
    assert stops == [True, False, True]
    # one hand-over per period at most (its count bounded by the time it all took, however slow)
    assert len(got) <= took / 0.05 + 2, (len(got), took)
    # and the flood is counted: the samples the reader dropped for newer ones are superseded (they
    # went uncounted: a review's 412,928 Twists in 8 s showed as 385 received, 15 superseded)
    # (a sample taken before its arrival is counted can shift one from one take to the next: a few)
    counts = car.bridge.inbox.counts()["/dds_test/cmd"]
    assert abs(counts.received - 10000) <= 10, counts
    assert counts.superseded == counts.received - len(got), counts


def test_one_thread_takes_every_command_row_each_at_most_once_per_period():
    """Two command rows, one flooded: one gate thread serves both; the quiet row's one message is
    handed over while the other row rests, and each row's newest message arrives."""
    domain_id = _domain()
    params = DdsParams(domain_id=domain_id)
    rows = [Topic("/dds_test/cmd", Twist, Direction.IN, DEFAULT),
            Topic("/dds_test/nav", Twist, Direction.IN, DEFAULT)]
    car = _Car(rows, params)
    car.bridge = DdsBridge(car.bus, params, rows, on_input=car.inputs.append, period_s=0.05)
    with car:
        assert [t.name for t in threading.enumerate()].count("dds-in") == 1
        flood: list[Twist] = []
        quiet: list[Twist] = []
        car.bus.subscribe("/dds_test/cmd", flood.append)
        car.bus.subscribe("/dds_test/nav", quiet.append)
        peer = DomainParticipant(domain_id)
        twist_type = ros2_factory().topic_type("geometry_msgs/msg/Twist")
        cmds = DataWriter(peer, DdsTopic(peer, "rt/dds_test/cmd", twist_type), qos_of(DEFAULT))
        navs = DataWriter(peer, DdsTopic(peer, "rt/dds_test/nav", twist_type), qos_of(DEFAULT))
        wait_for(lambda: cmds.get_publication_matched_status().current_count > 0
                 and navs.get_publication_matched_status().current_count > 0, timeout=30)
        types = ros2_types()
        start = time.monotonic()
        for i in range(5000):
            cmds.write(raw_sample(twist_type, types.serialize(Twist(Vector3(i / 1e4, 0.0, 0.0), Vector3()))))
            if i == 2500:
                navs.write(raw_sample(twist_type, types.serialize(Twist(Vector3(0.25, 0.0, 0.0), Vector3()))))
        wait_for(lambda: flood and flood[-1].linear.x == 0.4999 and quiet, timeout=30)
        took = time.monotonic() - start
    assert [m.linear.x for m in quiet] == [0.25]
    assert len(flood) <= took / 0.05 + 2, (len(flood), took)


class _Reader:
    """A Cyclone reader's take(), as the listener sees it, with given payloads."""

    def __init__(self, payloads: list[bytes]) -> None:
        self.payloads = payloads

    def take(self, n: int) -> list[RawSample]:
        out, self.payloads = self.payloads[:n], self.payloads[n:]
        return [RawSample(p) for p in out]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=120), max_size=5), st.sampled_from([Twist, Bool]))
def test_the_command_decoder_survives_any_bytes(payloads, cls):
    """Hostile samples: whatever the bytes, the receive path drops and counts them or hands a
    finite message on; it never raises into Cyclone's thread."""
    row = Topic("/x", cls, Direction.IN, DEFAULT)
    bridge = DdsBridge(Bus(), DdsParams(), [row])
    loop = asyncio.new_event_loop()
    bridge.inbox.bind(loop)
    try:
        bridge._receiver(row)(_Reader(list(payloads)))
        s = bridge.stats
        assert s.received + s.malformed + s.non_finite == len(payloads)
    finally:
        loop.close()


def test_a_refusing_bridge_counts_and_drops_every_command():
    bridge = DdsBridge(Bus(), DdsParams(interface="10.0.0.1"), [])
    loop = asyncio.new_event_loop()
    bridge.inbox.bind(loop)
    try:
        good = ros2_types().serialize(Bool(True))
        bridge._receiver(Topic("/estop", Bool, Direction.IN, DEFAULT))(_Reader([good, good]))
        assert bridge.stats.refused == 2 and bridge.stats.received == 0
        assert bridge.refusals.total("dds") == 2
    finally:
        loop.close()


def test_the_node_graph_names_the_node_in_its_namespace_with_every_endpoint():
    """ros_discovery_info as a late joiner reads it: /car1/racecar_hw, the participant's GID, and
    the GIDs of the bridge's writers and readers (the topics are rt/car1/...)."""
    domain_id = _domain()
    params = DdsParams(domain_id=domain_id)
    rows = [Topic("/dds_test/out", String, Direction.OUT, DEFAULT),
            Topic("/dds_test/in", Bool, Direction.IN, DEFAULT)]
    car = _Car(rows, params)
    car.bridge = DdsBridge(car.bus, params, rows, namespace="car1")
    with car:
        from racecar_hw.net.dds_types import TypeFactory

        peer = DomainParticipant(domain_id)
        info_type = TypeFactory(dds_graph.graph_store(16)).topic_type(dds_graph.DISCOVERY_TYPE)
        reader = DataReader(peer, DdsTopic(peer, dds_graph.DISCOVERY_TOPIC, info_type), qos_of(LATCHED))
        got: list[RawSample] = []
        wait_for(lambda: got.extend(reader.take(4)) or got, timeout=30)
        info = dds_graph.decode_participant_info(got[0].data)
        bridge = car.bridge
        assert info.gid == bridge.participant.guid.bytes
        node, = info.nodes
        assert (node.namespace, node.name) == ("/car1", "racecar_hw")
        assert node.writers == [o.writer.guid.bytes for o in bridge._outs]
        assert node.readers == [r.guid.bytes for r in bridge._readers]
        # the writer is on rt/car1/...: a reader there matches it
        late = DataReader(peer, DdsTopic(peer, "rt/car1/dds_test/out",
                                         ros2_factory().topic_type("std_msgs/msg/String")), qos_of(DEFAULT))
        wait_for(lambda: bridge._outs[0].matching, timeout=30)
        assert late.get_subscription_matched_status().current_count == 1


def test_the_scan_is_queued_for_dds_right_after_the_motor_write_not_from_the_bus():
    """As for Zenoh (tests/test_net_bridge.py): the control path hands the scan to the DDS
    publisher right after the motor write, before the bookkeeping, the obstacle memory and the
    bus's subscribers, and wakes its thread; the bridge does not take the scan from the bus."""
    import asyncio

    import numpy as np

    from racecar_hw.base.clock import monotonic_ns
    from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, LaserScan
    from racecar_hw.config import load_config
    from racecar_hw.daemon import Daemon

    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "zenoh.enabled=false", "foxglove.enabled=false",
                                "web.enabled=false", f"dds.domain_id={_domain()}"])
    daemon = Daemon(config)
    assert daemon.dds is not None
    dds = daemon.dds
    events: list = []

    async def run() -> list:
        loop = asyncio.get_running_loop()
        daemon.bus.bind_loop(loop)
        dds.outbox.put = lambda fn, *args, urgent=False: events.append(("queued", urgent))
        await loop.run_in_executor(None, dds.open, loop)
        try:
            callbacks = [s.callback for s in daemon.bus._subs.get("/scan", [])]
            next(o for o in dds._outs if o.row.bus == "/scan").matching = True  # a reader matched
            daemon.control._write = lambda drive: events.append("motor write")
            daemon.safety.remember = lambda: events.append("obstacle memory")  # type: ignore[method-assign]
            daemon.mux.last_output = AckermannDriveStamped(drive=AckermannDrive())
            daemon.stats.ticks, daemon.stats.last_tick_ns = 1, monotonic_ns()
            daemon.control.take_scan(LaserScan(angle_min=-1.0, angle_increment=0.01,
                                               ranges=np.full(201, 5.0, dtype=np.float32)))
            return callbacks
        finally:
            dds.close()

    callbacks = asyncio.run(run())
    assert not any(c.__qualname__.startswith("DdsBridge") or "enqueue" in c.__qualname__ for c in callbacks)
    assert events == ["motor write", ("queued", True), "obstacle memory"]
