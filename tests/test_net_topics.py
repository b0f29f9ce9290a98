"""The topic table shared by the network interfaces."""

from __future__ import annotations

import pytest

from mux.params import InputParams, LockParams, MuxParams
from racecar_hw.base.messages import AckermannDriveStamped, Bool, LaserScan, TFMessage
from racecar_hw.net.topics import (
    LATCHED,
    SENSOR_DATA,
    Direction,
    Durability,
    Reliability,
    topic_table,
)
from safety.params import SafetyParams

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


def _rows(**kwargs):
    return {row.bus: row for row in topic_table(MuxParams(), SafetyParams(), **kwargs)}


def test_the_car_offers_its_sensors_and_state():
    rows = _rows()
    for topic in ("/scan", "/odom", "/tf", "/tf_static", "/vesc/sensors/core",
                  "/vesc/sensors/servo_position_command", "/vesc/low_level/ackermann_cmd_mux/output",
                  "/vesc/low_level/ackermann_cmd_mux/active", "/diagnostics", "/safety/state",
                  "/scan_range", "/open_space"):
        assert rows[topic].direction is Direction.OUT, topic
    assert rows["/scan"].msgtype is LaserScan and rows["/tf_static"].msgtype is TFMessage


def test_every_mux_input_lock_and_the_estop_come_in():
    mux = MuxParams(locks=[LockParams("pause", "/pause", 95)])
    rows = {row.bus: row for row in topic_table(mux, SafetyParams())}
    for source in mux.inputs:
        assert rows[source.topic].direction is Direction.IN
        assert rows[source.topic].msgtype is AckermannDriveStamped
        assert source.name in rows[source.topic].what
    for topic in ("/pause", "/estop", "/estop_release"):
        assert rows[topic].direction is Direction.IN and rows[topic].msgtype is Bool


def test_an_input_closed_to_the_network_is_subscribed_and_refused_naming_its_key():
    """One table, two wires: the row says why its samples are refused, and every interface reads it."""
    rows = _rows()
    for name, index in (("safety", 0), ("teleop", 1)):
        row = rows[f"/vesc/low_level/ackermann_cmd_mux/input/{name}"]
        assert row.direction is Direction.IN
        assert row.refused == (f"mux input {name} takes no network commands "
                               f"(mux.inputs[{index}].network: false)")
    assert not rows["/vesc/high_level/ackermann_cmd_mux/input/nav_0"].refused
    assert not rows["/estop"].refused and not rows["/estop_release"].refused  # stop is for anyone
    opened = MuxParams(inputs=[InputParams("teleop", "/t", 90, network=True)])
    assert not {row.bus: row for row in topic_table(opened, SafetyParams())}["/t"].refused


def test_qos_follows_the_drivers_the_daemon_replaces():
    rows = _rows()
    assert rows["/scan"].qos == SENSOR_DATA
    assert (SENSOR_DATA.reliability, SENSOR_DATA.depth) == (Reliability.BEST_EFFORT, 5)
    assert rows["/tf_static"].qos == LATCHED and rows["/tf_static"].qos.latched
    assert LATCHED.durability is Durability.TRANSIENT_LOCAL and LATCHED.depth == 1
    assert not rows["/odom"].qos.latched and rows["/odom"].qos.reliability is Reliability.RELIABLE


def test_names_are_unique_and_default_to_the_bus_topic():
    table = topic_table(MuxParams(), SafetyParams())
    assert len({row.ros for row in table}) == len(table)
    assert all(row.ros == row.bus for row in table)


def test_summary_topics_are_left_out_when_their_publisher_is_off():
    rows = _rows(scan_range_topic=None, open_space_topic=None)
    assert "/scan_range" not in rows and "/open_space" not in rows
