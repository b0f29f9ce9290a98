"""racecar_hw.rosmsg.typestore: type hashes, the reference's worked bytes, and conversion round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.base.errors import BagError
from racecar_hw.base.messages import (
    CUSTOM_TYPES,
    AckermannDrive,
    AckermannDriveStamped,
    Header,
    LaserScan,
    TFMessage,
    Time,
    TransformStamped,
)
from racecar_hw.rosmsg.typestore import MESSAGE_CLASSES, BagTypes, ros1_types, ros2_types

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

CDR_BYTES = ("000100000c000000590100000a000000626173655f6c696e6b0000000000803e000000000000c03f"
             "0000000000000000")
ROS1_BYTES = ("070000000c0000005901000009000000626173655f6c696e6b0000803e000000000000c03f0000"
              "000000000000")


def worked_example() -> AckermannDriveStamped:
    return AckermannDriveStamped(Header(Time(12, 345), "base_link"),
                                 AckermannDrive(steering_angle=0.25, speed=1.5))


def test_hashes_match_reference() -> None:
    t1, t2 = ros1_types(), ros2_types()
    ads, ad, scan = ("ackermann_msgs/msg/AckermannDriveStamped", "ackermann_msgs/msg/AckermannDrive",
                     "sensor_msgs/msg/LaserScan")
    assert t1.digest(ads) == "1fd5d7f58889cefd44d29f6653240d0c"
    assert t1.digest(ad) == "3512e91b48d69674a0e86fadf1ea8231"
    assert t1.digest(scan) == "90c7ef2dc6895d81024acba2ac42f369"
    assert t2.digest(ads) == "RIHS01_48ca7612a08d3bb72744fd98b71b7cf2ea24c6ad50fa4e1aa0bbad963c90d8cf"
    assert t2.digest(ad) == "RIHS01_acf287a224a947dd1b0b87d6d76cdb73f497b0237b8fc73be2173b2ebbb82c99"
    assert t2.digest(scan) == "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
    # tf2_msgs/TFMessage registered into the ROS 1 store gets the real ROS 1 md5.
    assert t1.digest("tf2_msgs/msg/TFMessage") == "94810edda583a504dfda3829e70d7eec"


def test_worked_bytes() -> None:
    msg = worked_example()
    assert ros2_types().serialize(msg).hex() == CDR_BYTES
    assert ros1_types().serialize(msg, seq=7).hex() == ROS1_BYTES
    assert ros2_types().deserialize(bytes.fromhex(CDR_BYTES), AckermannDriveStamped) == msg
    assert ros1_types().deserialize(bytes.fromhex(ROS1_BYTES), AckermannDriveStamped) == msg


def test_custom_types_registered_in_both_stores() -> None:
    for types in (ros1_types(), ros2_types()):
        for cls in CUSTOM_TYPES:
            assert types.has(cls.ROS_TYPE)
            assert types.msgdef(cls.ROS_TYPE)
    assert ros1_types().has("tf2_msgs/msg/TFMessage")


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("typename", sorted(MESSAGE_CLASSES))
def test_every_message_class_round_trips(version: int, typename: str) -> None:
    types = ros1_types() if version == 1 else ros2_types()
    cls = MESSAGE_CLASSES[typename]
    msg = cls()
    back = types.deserialize(types.serialize(msg), cls)
    assert type(back) is cls
    assert repr(back) == repr(msg)


def test_nested_list_round_trip() -> None:
    tf = TFMessage([TransformStamped(Header(Time(1, 2), "odom"), "base_link"),
                    TransformStamped(Header(Time(3, 4), "base_link"), "laser")])
    for types in (ros1_types(), ros2_types()):
        back = types.deserialize(types.serialize(tf), TFMessage)
        assert back == tf


def test_bad_ros_version() -> None:
    with pytest.raises(ValueError):
        BagTypes(3)


def test_unknown_class_lookup_is_a_bag_error() -> None:
    class Fake:
        __msgtype__ = "nope/msg/Nope"

    with pytest.raises(BagError, match="nope/msg/Nope"):
        ros2_types().from_ros(Fake())


f32 = st.floats(width=32, allow_nan=False)
stamps = st.builds(Time, st.integers(0, 2**31 - 1), st.integers(0, 999_999_999))
headers = st.builds(Header, stamps, st.text(max_size=20))
drives = st.builds(AckermannDrive, f32, f32, f32, f32, f32)


@settings(max_examples=150, deadline=None)
@given(header=headers, drive=drives, seq=st.integers(0, 2**32 - 1))
def test_ackermann_round_trip(header: Header, drive: AckermannDrive, seq: int) -> None:
    msg = AckermannDriveStamped(header, drive)
    assert ros2_types().deserialize(ros2_types().serialize(msg), AckermannDriveStamped) == msg
    assert ros1_types().deserialize(ros1_types().serialize(msg, seq), AckermannDriveStamped) == msg


range_values = st.floats(width=32, allow_nan=True, allow_infinity=True)


@settings(max_examples=100, deadline=None)
@given(header=headers, angle=f32, ranges=st.lists(range_values, max_size=1100),
       with_intensities=st.booleans())
def test_laserscan_round_trip(header: Header, angle: float, ranges: list[float],
                              with_intensities: bool) -> None:
    r = np.array(ranges, dtype=np.float32)
    scan = LaserScan(header, angle_min=-angle, angle_max=angle, angle_increment=0.0043,
                     range_min=0.02, range_max=30.0, ranges=r,
                     intensities=r[::-1].copy() if with_intensities else np.zeros(0, np.float32))
    for data, types in ((ros2_types().serialize(scan), ros2_types()),
                        (ros1_types().serialize(scan, 3), ros1_types())):
        back = types.deserialize(data, LaserScan)
        assert back.header == scan.header
        assert back.angle_max == scan.angle_max or math.isnan(scan.angle_max)
        assert back.ranges.dtype == np.float32
        np.testing.assert_array_equal(back.ranges, scan.ranges)
        np.testing.assert_array_equal(back.intensities, scan.intensities)
