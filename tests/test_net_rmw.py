"""rmw_zenoh's wire format: checked against rmw_zenoh's design document, the official ROS 2 type
descriptions (the PyPI ``ros-*-msgs`` wheels' JSON, and the rosidl generator that makes them) and
two independent implementations (Zenoh's own serializer, zenoh-ros2-sdk)."""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import pytest
import zenoh
import zenoh.ext
from hypothesis import example, given
from hypothesis import strategies as st

from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    OpenSpace,
    ScanRange,
    TFMessage,
    VescState,
    VescStateStamped,
)
from racecar_hw.net import rmw
from racecar_hw.net.topics import DEFAULT, LATCHED, SENSOR_DATA, Qos
from racecar_hw.rosmsg.typestore import ros2_types

SHARE = Path(sys.prefix) / "share"

# The examples of rmw_zenoh's docs/design.md (Jazzy and later), verbatim.
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DESIGN_KEY = f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
DESIGN_NODE = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DESIGN_SUB = ("@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
              f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
DESIGN_PUB = ("@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
              f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")


def test_data_keys_follow_the_design_document():
    assert rmw.topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == DESIGN_KEY
    assert rmw.type_hash("std_msgs/msg/String") == STRING_HASH
    assert rmw.topic_key(3, "/car1/scan", "sensor_msgs/msg/LaserScan", "H") == \
        "3/car1/scan/sensor_msgs::msg::dds_::LaserScan_/H"
    assert rmw.dds_type("ackermann_msgs/msg/AckermannDriveStamped") == \
        "ackermann_msgs::msg::dds_::AckermannDriveStamped_"
    assert rmw.ros_type("sensor_msgs::msg::dds_::LaserScan_") == "sensor_msgs/msg/LaserScan"


def test_liveliness_tokens_follow_the_design_document():
    node = rmw.Entity(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 0, rmw.NODE, "", "", "listener")
    assert node.token() == DESIGN_NODE
    sub = rmw.Entity(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10, rmw.SUBSCRIPTION, "", "", "listener",
                     "/chatter", "std_msgs::msg::dds_::String_", STRING_HASH, rmw.RmwQos(depth=10))
    assert sub.token() == DESIGN_SUB
    for token in (DESIGN_NODE, DESIGN_SUB, DESIGN_PUB):
        assert rmw.parse_token(token).token() == token
    pub = rmw.parse_token(DESIGN_PUB)
    assert (pub.kind, pub.node, pub.topic, pub.ros_type, pub.qos.depth) == \
        (rmw.PUBLISHER, "/talker", "/chatter", "std_msgs/msg/String", 7)


def test_namespaces_and_topics_are_mangled():
    ep = rmw.Entity(5, "ab", 0, 3, rmw.PUBLISHER, "", "/car1", "racecar_hw", "/car1/scan",
                    rmw.dds_type("sensor_msgs/msg/LaserScan"), "H", rmw.RmwQos.from_qos(SENSOR_DATA))
    assert ep.token() == ("@ros2_lv/5/ab/0/3/MP/%/%car1/racecar_hw/%car1%scan/"
                          "sensor_msgs::msg::dds_::LaserScan_/H/2::,5:,:,:,,")
    back = rmw.parse_token(ep.token())
    assert (back.namespace, back.topic, back.node) == ("/car1", "/car1/scan", "/car1/racecar_hw")


@pytest.mark.parametrize(("qos", "text"), [
    (DEFAULT, "::,10:,:,:,,"),                                  # reliable, volatile, depth 10
    (SENSOR_DATA, "2::,5:,:,:,,"),                              # best effort depth 5
    (LATCHED, ":1:,1:,:,:,,"),                                  # transient local depth 1
    (Qos(depth=42), "::,:,:,:,,"),                              # everything rmw_zenoh's default
])
def test_qos_strings_leave_out_rmw_zenohs_defaults(qos, text):
    assert rmw.qos_to_string(qos) == text
    assert rmw.qos_from_string(text).to_qos() == qos


def test_qos_strings_with_every_field_round_trip():
    full = rmw.RmwQos(rmw.BEST_EFFORT, rmw.TRANSIENT_LOCAL, rmw.KEEP_ALL, 3, (1, 2), (3, 4), 2, (5, 6))
    text = rmw.qos_to_string(full)
    assert text == "2:1:2,3:1,2:3,4:2,5,6"
    assert rmw.qos_from_string(text) == full


@pytest.mark.parametrize("bad", ["", "::", "::,10:,:,:,", "x::,10:,:,:,,", "9::,10:,:,:,,",
                                 "::,-1:,:,:,,", "::,10:,:,:,,:"])
def test_malformed_qos_strings_are_refused(bad):
    with pytest.raises(rmw.WireError):
        rmw.qos_from_string(bad)


@pytest.mark.parametrize("bad", [
    "@ros2_lv/0/z/0/0/NN/%/%",                              # too short
    "@other/0/z/0/0/NN/%/%/n",                              # not the admin space
    "@ros2_lv/0/z/0/0/XX/%/%/n",                            # unknown kind
    "@ros2_lv/x/z/0/0/NN/%/%/n",                            # domain not a number
    "@ros2_lv/0/z/0/0/NN//%/n",                             # empty part
    "@ros2_lv/0/z/0/1/MP/%/%/n/%t/a::msg::dds_::B_/H",      # endpoint without QoS
    "@ros2_lv/0/z/0/1/MP/%/%/n/%t/a::msg::dds_::B_/H/bad",  # bad QoS
])
def test_malformed_tokens_are_refused(bad):
    with pytest.raises(rmw.WireError):
        rmw.parse_token(bad)


@given(st.text(max_size=80))
@example("0" * 33)  # as long as an attachment: once handed to decode as a str, not as bytes
def test_parsing_any_text_raises_only_wire_errors(text):
    for parse, arg in ((rmw.parse_token, text), (rmw.qos_from_string, text),
                       (rmw.Attachment.decode, text.encode())):
        try:
            parse(arg)
        except rmw.WireError:
            pass


def test_the_attachment_is_zenohs_serialization_of_sequence_stamp_and_gid():
    gid = bytes(range(16))
    data = rmw.Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    assert len(data) == 33 and data[16] == 0x10
    reference = zenoh.ext.z_serialize((zenoh.ext.Int64(7), zenoh.ext.Int64(1_700_000_000_123_456_789), gid))
    assert data == reference.to_bytes()
    assert rmw.Attachment.decode(data) == rmw.Attachment(7, 1_700_000_000_123_456_789, gid)
    seq, stamp, back = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes],
                                               zenoh.ZBytes(data))
    assert (seq, stamp, back) == (7, 1_700_000_000_123_456_789, gid)


def test_zenoh_ros2_sdk_reads_our_attachment():
    attachment = pytest.importorskip("zenoh_ros2_sdk.attachment")
    theirs = attachment.Attachment.from_bytes(rmw.Attachment(3, 42, b"\xab" * 16).encode())
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (3, 42, b"\xab" * 16)


@pytest.mark.parametrize("bad", [b"", bytes(32), bytes(34), bytes(16) + b"\x0f" + bytes(16)])
def test_malformed_attachments_are_refused(bad):
    with pytest.raises(rmw.WireError):
        rmw.Attachment.decode(bad)


def test_the_gid_is_the_xxh3_of_the_token_and_differs_per_entity():
    a = rmw.parse_token(DESIGN_PUB)
    b = rmw.parse_token(DESIGN_SUB)
    assert len(a.gid()) == 16 and a.gid() != b.gid()
    assert a.gid() == rmw.gid_of(DESIGN_PUB)


@pytest.mark.parametrize("name", ["/scan", "/car1/scan", "/vesc/sensors/core", "/a_b/c9"])
def test_valid_topic_names(name):
    assert rmw.check_topic_name(name) == name


@pytest.mark.parametrize("name", ["scan", "/", "/scan/", "//scan", "/9scan", "/sc an", "/a__b", "/é"])
def test_invalid_topic_names_are_refused(name):
    with pytest.raises(rmw.WireError):
        rmw.check_topic_name(name)


def test_namespaces_are_normalised():
    assert rmw.check_namespace("") == "" and rmw.check_namespace("/") == ""
    assert rmw.check_namespace("car1") == "/car1"
    with pytest.raises(rmw.WireError):
        rmw.check_namespace("/car 1")


# --- RIHS01 type hashes against the official type descriptions ---------------------------------

OFFICIAL = [("sensor_msgs", "LaserScan"), ("sensor_msgs", "Imu"), ("nav_msgs", "Odometry"),
            ("geometry_msgs", "Twist"), ("geometry_msgs", "TransformStamped"), ("std_msgs", "String"),
            ("std_msgs", "Bool"), ("std_msgs", "Float64"), ("std_msgs", "Header"),
            ("diagnostic_msgs", "DiagnosticArray")]


def _official_json(pkg: str, name: str) -> dict:
    path = SHARE / pkg / "msg" / f"{name}.json"
    if not path.exists():
        pytest.skip(f"{path} absent: install the test extra (ros-{pkg.replace('_', '-')} wheels)")
    return json.loads(path.read_text())


@pytest.mark.parametrize(("pkg", "name"), OFFICIAL)
def test_type_hashes_equal_the_official_packages(pkg, name):
    official = _official_json(pkg, name)["type_hashes"][0]
    assert official["type_name"] == f"{pkg}/msg/{name}"
    assert rmw.type_hash(f"{pkg}/msg/{name}") == official["hash_string"]


def test_the_reference_lists_the_same_hashes():
    # the values in ../shared/reference/interop.md, from the official packages
    assert rmw.type_hash("sensor_msgs/msg/LaserScan") == \
        "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
    assert rmw.type_hash("geometry_msgs/msg/Twist") == \
        "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"


def _rosidl_hashes(package: str, classes: list) -> dict[str, str]:
    """RIHS01 hashes computed by ROS 2's own generator (rosidl_adapter + rosidl_generator_type_description)
    from our ``.msg`` definitions, with the dependencies' official JSON descriptions."""
    adapter = pytest.importorskip("rosidl_adapter.msg")
    generator = pytest.importorskip("rosidl_generator_type_description")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "msg").mkdir()
        tuples = []
        for cls in classes:
            name = cls.ROS_TYPE.rsplit("/", 1)[1]
            (root / "msg" / f"{name}.msg").write_text(cls.MSGDEF)
            adapter.convert_msg_to_idl(root, package, Path("msg") / f"{name}.msg", root / "idl")
            tuples.append(f"{root / 'idl'}:{name}.idl")
        deps = ("std_msgs", "builtin_interfaces", "geometry_msgs")
        args = {"package_name": package, "output_dir": str(root / "out"), "idl_tuples": tuples,
                "include_paths": [f"{dep}:{SHARE / dep}" for dep in deps]}
        (root / "args.json").write_text(json.dumps(args))
        out = {}
        for path in generator.generate_type_hash(str(root / "args.json")):
            first = json.loads(Path(path).read_text())["type_hashes"][0]
            out[first["type_name"]] = first["hash_string"]
        return out


@pytest.mark.parametrize(("package", "classes", "expected"), [
    # ackermann_msgs (ros-drivers/ackermann_msgs, ros2 branch: the same fields as our MSGDEF)
    ("ackermann_msgs", [AckermannDrive, AckermannDriveStamped],
     {"ackermann_msgs/msg/AckermannDriveStamped":
      "RIHS01_48ca7612a08d3bb72744fd98b71b7cf2ea24c6ad50fa4e1aa0bbad963c90d8cf"}),
    ("vesc_msgs", [VescState, VescStateStamped], {}),
    ("racecar_msgs", [ScanRange, OpenSpace], {}),
    ("tf2_msgs", [TFMessage],
     {"tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"}),
])
def test_type_hashes_equal_ros2s_own_generator(package, classes, expected, capsys):
    if not (SHARE / "std_msgs" / "msg" / "Header.json").exists():
        pytest.skip("the official std_msgs JSON is absent: install the test extra")
    official = _rosidl_hashes(package, classes)
    for cls in classes:
        assert rmw.type_hash(cls.ROS_TYPE) == official[cls.ROS_TYPE] == ros2_types().digest(cls.ROS_TYPE)
    for name, value in expected.items():
        assert official[name] == value


# --- distributions ------------------------------------------------------------------------------

HUMBLE_SUB = DESIGN_SUB.replace(STRING_HASH, "TypeHashNotSupported")


def test_tokens_of_every_current_release_parse():
    # Humble (0.1.x): TypeHashNotSupported where later releases put the hash
    humble = rmw.parse_token(HUMBLE_SUB)
    assert humble.type_hash == rmw.HUMBLE_TYPE_HASH and humble.token() == HUMBLE_SUB
    # Lyrical/Rolling (0.10+): an optional 14th field after the QoS
    newer = DESIGN_PUB + "/backends:cuda"
    entity = rmw.parse_token(newer)
    assert (entity.topic, entity.type_hash, entity.qos.depth) == ("/chatter", STRING_HASH, 7)
    assert entity.backends == "backends:cuda" and entity.token() == newer
    for bad in (newer + "/more", DESIGN_NODE + "/x"):
        with pytest.raises(rmw.WireError):
            rmw.parse_token(bad)


def test_the_type_hash_field_follows_the_peers_distribution():
    assert rmw.wire_type_hash("std_msgs/msg/String") == STRING_HASH
    assert rmw.wire_type_hash("std_msgs/msg/String", "jazzy") == STRING_HASH
    assert rmw.wire_type_hash("std_msgs/msg/String", "humble") == "TypeHashNotSupported"
    with pytest.raises(rmw.WireError, match="jazzy, humble"):
        rmw.wire_type_hash("std_msgs/msg/String", "iron")
