"""The topic table: which bus topics the network interfaces offer, under which ROS 2 name, type and QoS.

One table for every live interface (the Zenoh bridge in rmw_zenoh's format, the Foxglove server):
each row says what a bus topic is to the outside world. ``OUT`` rows go from the car to clients
(``/scan``, ``/odom``, ...); ``IN`` rows come from clients into the daemon (mux inputs, locks, the
e-stop and its release). A mux input with ``network: false`` (``safety`` and ``teleop`` by default:
the operator's) is an ``IN`` row that every interface subscribes and refuses (:attr:`Topic.refused`):
a sample on it is counted and logged with the key to change, never handed over. Payloads are
serialized by :mod:`racecar_hw.rosmsg`, the serializer the recorder uses, so a live message and a
recorded one are the same bytes.

The ROS name of a row is its bus topic unless a profile or remap changes it (:func:`named`):
``racecar`` keeps the MIT/MuSHR ROS 1 names of the bus, ``f1tenth`` offers the F1TENTH ROS 2 names
(autonomy on ``/drive``, the joystick on ``/teleop``, ``/sensors/core``, ...). QoS follows the
drivers the daemon replaces: the sensor-data profile for ``/scan`` (best effort,
depth 5), transient local for the latched topics of :data:`racecar_hw.base.topics.LATCHED_TOPICS`
(``/tf_static``, the mux's active source, ``/rosout``, the simulator's ``/map``: late joiners get
them; the recorder takes the same table), reliable depth 10 otherwise. The QoS classes live in
:mod:`racecar_hw.base.qos` (re-exported here).
"""

from __future__ import annotations

import dataclasses
import enum
import os
from collections.abc import Mapping
from dataclasses import dataclass

from mux.params import MuxParams
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import (
    AckermannDriveStamped,
    Bool,
    Clock,
    DiagnosticArray,
    Float64,
    Imu,
    LaserScan,
    Log,
    Message,
    Odometry,
    OpenSpace,
    ScanRange,
    String,
    TFMessage,
    Twist,
    VescStateStamped,
)
from racecar_hw.base.qos import CLOCK_QOS as CLOCK_QOS
from racecar_hw.base.qos import CLOCK_SUBSCRIPTION as CLOCK_SUBSCRIPTION
from racecar_hw.base.qos import DEFAULT as DEFAULT
from racecar_hw.base.qos import LATCHED as LATCHED
from racecar_hw.base.qos import ROSOUT as ROSOUT
from racecar_hw.base.qos import SENSOR_DATA as SENSOR_DATA
from racecar_hw.base.qos import Durability as Durability
from racecar_hw.base.qos import Qos as Qos
from racecar_hw.base.qos import Reliability as Reliability
from racecar_hw.base.topics import CLOCK_TOPIC, LATCHED_TOPICS, MUX_ACTIVE_TOPIC, TOPIC_TF_STATIC
from racecar_hw.base.topics import ROSOUT_TOPIC as ROSOUT_TOPIC
from safety.params import SafetyParams
from vesc.driver import TOPIC_CORE, TOPIC_IMU, TOPIC_ODOM, TOPIC_SERVO, TOPIC_TF


class Direction(enum.Enum):
    """Which way a topic crosses the network."""

    OUT = "out"  #: the car publishes, clients subscribe
    IN = "in"    #: clients publish, the car subscribes


@dataclass(frozen=True)
class Topic:
    """One row: a bus topic as the outside world sees it."""

    bus: str                     #: the daemon's bus topic
    msgtype: type[Message]       #: its message class (ROS type: ``msgtype.ROS_TYPE``)
    direction: Direction
    qos: Qos = DEFAULT
    #: what the topic is, for ``topic list``, docs and panels
    what: str = ""
    #: the ROS 2 name offered outside; the bus topic unless a profile or remap renames it
    ros: str = ""
    #: the ROS name is used as is, without the interface's namespace (``/rosout``, as rcl does)
    absolute: bool = False
    #: an ``IN`` row closed to the network: why every sample on it is refused (counted and logged
    #: by each interface, never handed over); empty: open
    refused: str = ""

    def __post_init__(self) -> None:
        if not self.ros:
            object.__setattr__(self, "ros", self.bus)


#: The simulator's ``/clock`` row (:mod:`racecar_hw.sim.clock_topic`): absolute, as ROS 2's time
#: source subscribes ``/clock`` whatever the node's namespace.
CLOCK_ROW = Topic(CLOCK_TOPIC, Clock, Direction.OUT, CLOCK_QOS,
                  "simulation time (use_sim_time), in the time base of every stamp", absolute=True)


def topic_table(mux: MuxParams, safety: SafetyParams, *, scan_topic: str = "/scan",
                scan_range_topic: str | None = "/scan_range",
                open_space_topic: str | None = "/open_space",
                cmd_vel_topic: str | None = None, rosout: bool = False) -> list[Topic]:
    """The default rows for a daemon with these mux and safety parameters.

    ``rosout`` adds the daemon's log on ``/rosout`` (rcl_interfaces/msg/Log, outside any namespace).
    ``scan_topic`` is the lidar's topic; the scan summary topics are left out when ``None`` (their
    publisher is off). ``cmd_vel_topic`` adds an ``IN`` row of geometry_msgs/Twist (Nav2's velocity
    commands), which :mod:`racecar_hw.sources.cmd_vel` turns into the mux input ``cmd_vel``.
    """
    out = Direction.OUT
    rows = [
        Topic(scan_topic, LaserScan, out, SENSOR_DATA, "lidar scan, frame laser"),
        Topic(TOPIC_ODOM, Odometry, out, DEFAULT, "wheel odometry, odom -> base_link"),
        Topic(TOPIC_TF, TFMessage, out, DEFAULT, "odom -> base_link transform"),
        Topic(TOPIC_TF_STATIC, TFMessage, out, LATCHED_TOPICS[TOPIC_TF_STATIC],
              "static transforms (base_link -> laser ...)"),
        Topic(TOPIC_CORE, VescStateStamped, out, DEFAULT, "VESC telemetry"),
        Topic(TOPIC_SERVO, Float64, out, DEFAULT, "servo position command (0..1)"),
        Topic(TOPIC_IMU, Imu, out, DEFAULT, "the VESC's IMU (SI units, frame imu)"),
        Topic(mux.output_topic, AckermannDriveStamped, out, DEFAULT, "mux output: the drive command"),
        Topic(mux.active_topic, String, out, LATCHED_TOPICS[MUX_ACTIVE_TOPIC], "the mux's active source"),
        Topic(mux.diagnostics_topic, DiagnosticArray, out, DEFAULT, "diagnostics"),
        Topic(safety.state_topic, DiagnosticArray, out, DEFAULT, "safety controller state"),
    ]
    if scan_range_topic:
        rows.append(Topic(scan_range_topic, ScanRange, out, DEFAULT, "closest and farthest return"))
    if open_space_topic:
        rows.append(Topic(open_space_topic, OpenSpace, out, DEFAULT, "longest range and its angle"))
    if rosout:
        rows.append(Topic(ROSOUT_TOPIC, Log, out, LATCHED_TOPICS[ROSOUT_TOPIC],
                          "the daemon's log (rosout.level and above)",
                          absolute=True))
    into = Direction.IN
    for i, source in enumerate(mux.inputs):
        rows.append(Topic(source.topic, AckermannDriveStamped, into, DEFAULT,
                          f"mux input {source.name} (priority {source.priority})",
                          refused="" if source.network else closed_input(source.name, i)))
    for lock in mux.locks:
        rows.append(Topic(lock.topic, Bool, into, DEFAULT, f"mux lock {lock.name}"))
    rows.append(Topic(mux.estop_topic, Bool, into, DEFAULT, "e-stop: true engages (latched)"))
    rows.append(Topic(mux.estop_release_topic, Bool, into, DEFAULT, "e-stop release: true releases"))
    if cmd_vel_topic:
        rows.append(Topic(cmd_vel_topic, Twist, into, DEFAULT,
                          "velocity commands (Nav2), into mux input cmd_vel"))
    return rows


def closed_input(name: str, index: int) -> str:
    """Why a network sample on mux input ``name`` (``mux.inputs[index]``) is refused."""
    return f"mux input {name} takes no network commands (mux.inputs[{index}].network: false)"


#: The mux input the /cmd_vel converter drives, and its priority (between nav_0 and nav_1).
CMD_VEL_INPUT = "cmd_vel"
CMD_VEL_PRIORITY = 18

#: F1TENTH's ROS 2 names (f1tenth_system): by mux input name, or by bus topic.
F1TENTH_INPUTS = {"nav_0": "/drive", "teleop": "/teleop"}
F1TENTH_TOPICS = {
    "/vesc/sensors/core": "/sensors/core",
    "/vesc/sensors/servo_position_command": "/sensors/servo_position_command",
    "/imu": "/sensors/imu/raw",
    "/vesc/low_level/ackermann_cmd_mux/output": "/ackermann_cmd",
}


def profile_names(profile: str, mux: MuxParams) -> dict[str, str]:
    """bus topic -> ROS name for a profile: ``racecar`` (none renamed) or ``f1tenth``."""
    if profile == "racecar":
        return {}
    if profile != "f1tenth":
        raise ValueError(f"unknown topic profile {profile!r}")
    names = dict(F1TENTH_TOPICS)
    for source in mux.inputs:
        if source.name in F1TENTH_INPUTS:
            names[source.topic] = F1TENTH_INPUTS[source.name]
    return names


def named(rows: list[Topic], mux: MuxParams, profile: str = "racecar",
          remap: Mapping[str, str] | None = None, key: str = "zenoh") -> list[Topic]:
    """``rows`` with their ROS names set by the profile, then by ``remap`` (bus topic -> ROS name).

    Raises :class:`ConfigError` naming ``key.remap.<topic>`` for a remap of a topic the table does
    not have, and ``key.remap`` or ``key.profile`` when two bus topics would share a ROS name.
    """
    remap = dict(remap or {})
    buses = {row.bus for row in rows}
    for bus in remap:
        if bus not in buses:
            raise ConfigError(f"{key}.remap.{bus}", "not a topic the car offers or takes; topics: "
                              + ", ".join(sorted(buses)))
    names = {**profile_names(profile, mux), **remap}
    out = [dataclasses.replace(row, ros=names.get(row.bus, row.bus)) for row in rows]
    seen: dict[str, str] = {}
    for row in out:
        if row.ros in seen:
            where = f"{key}.remap" if row.bus in remap or seen[row.ros] in remap else f"{key}.profile"
            raise ConfigError(where, f"{seen[row.ros]} and {row.bus} would both be {row.ros} (profile "
                                     f"{profile}); two topics cannot share a ROS name")
        seen[row.ros] = row.bus
    return out


def ros_domain_id(configured: int | None, key: str) -> int:
    """``configured``, else ``ROS_DOMAIN_ID`` from the environment, else 0 (as ROS 2 does); a bad
    environment value is a :class:`ConfigError` naming ``key``."""
    if configured is not None:
        return configured
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not env:
        return 0
    if not env.isdigit() or int(env) > 232:
        raise ConfigError(key, f"ROS_DOMAIN_ID={env!r} is not a domain id (0..232)")
    return int(env)
