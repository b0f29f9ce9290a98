"""Message classes mirror ROS: type names, field order, stamps, quaternions."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from racecar_hw.base import messages as m

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


def _message_classes():
    return [c for c in vars(m).values()
            if isinstance(c, type) and issubclass(c, m.Message) and c is not m.Message]


@pytest.mark.parametrize("cls", _message_classes(), ids=lambda c: c.__name__)
def test_fields_match_msgdef(cls):
    assert cls.ROS_TYPE.count("/msg/") == 1
    declared = [line.split()[1] for line in cls.MSGDEF.splitlines()
                if line and "=" not in line.split()[1]]
    assert declared == [f.name for f in dataclasses.fields(cls)]


@given(st.integers(min_value=0, max_value=2**62))
def test_time_round_trip(ns):
    t = m.Time.from_ns(ns)
    assert 0 <= t.nanosec < 1_000_000_000
    assert t.to_ns() == ns


@given(st.floats(min_value=-math.pi + 1e-9, max_value=math.pi))
def test_quaternion_yaw_round_trip(yaw):
    assert m.Quaternion.from_yaw(yaw).yaw() == pytest.approx(yaw, abs=1e-9)


def test_laser_scan_angles():
    scan = m.LaserScan(angle_min=-1.0, angle_max=1.0, angle_increment=0.5)
    scan.ranges = np.array([1, 2, 3, 4, 5], dtype=np.float32)
    assert list(scan.angles()) == [-1.0, -0.5, 0.0, 0.5, 1.0]
