"""The topic table: which bus topics the network interfaces offer, under which ROS 2 name, type and QoS.

One table for every live interface (the Zenoh bridge in rmw_zenoh's format, the Foxglove server):
each row says what a bus topic is to the outside world. ``OUT`` rows go from the car to clients
(``/scan``, ``/odom``, ...); ``IN`` rows come from clients into the daemon (mux inputs, locks, the
e-stop and its release). Payloads are serialized by :mod:`racecar_hw.rosmsg`, the serializer the
recorder uses, so a live message and a recorded one are the same bytes.

The ROS name of a row is its bus topic unless a profile or remap changes it (see the bridge); QoS
follows the drivers the daemon replaces: the sensor-data profile for ``/scan`` (best effort, depth
5), transient local depth 1 for ``/tf_static`` (late joiners get it), reliable depth 10 otherwise.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from mux.params import MuxParams
from racecar_hw.base.messages import (
    AckermannDriveStamped,
    Bool,
    DiagnosticArray,
    Float64,
    LaserScan,
    Message,
    Odometry,
    OpenSpace,
    ScanRange,
    String,
    TFMessage,
    VescStateStamped,
)
from safety.params import SafetyParams
from vesc.driver import TOPIC_CORE, TOPIC_ODOM, TOPIC_SERVO, TOPIC_TF


class Direction(enum.Enum):
    """Which way a topic crosses the network."""

    OUT = "out"  #: the car publishes, clients subscribe
    IN = "in"    #: clients publish, the car subscribes


class Reliability(enum.IntEnum):
    """ROS 2 ``rmw_qos_reliability_policy_e`` values."""

    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):
    """ROS 2 ``rmw_qos_durability_policy_e`` values."""

    TRANSIENT_LOCAL = 1
    VOLATILE = 2


@dataclass(frozen=True)
class Qos:
    """The QoS a topic is offered with (history is always KEEP_LAST ``depth``)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    depth: int = 10

    @property
    def latched(self) -> bool:
        """Late joiners get the last ``depth`` messages (ROS 2 TRANSIENT_LOCAL, ROS 1 latching)."""
        return self.durability is Durability.TRANSIENT_LOCAL


#: rclcpp's ``SensorDataQoS``: what real lidar drivers offer ``/scan`` with.
SENSOR_DATA = Qos(Reliability.BEST_EFFORT, Durability.VOLATILE, 5)
#: What ``static_transform_publisher`` offers ``/tf_static`` with.
LATCHED = Qos(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, 1)
#: rclcpp's default QoS with depth 10.
DEFAULT = Qos()


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

    def __post_init__(self) -> None:
        if not self.ros:
            object.__setattr__(self, "ros", self.bus)


def topic_table(mux: MuxParams, safety: SafetyParams, *, scan_topic: str = "/scan",
                scan_range_topic: str | None = "/scan_range",
                open_space_topic: str | None = "/open_space") -> list[Topic]:
    """The default rows for a daemon with these mux and safety parameters.

    ``scan_topic`` is the lidar's topic; the scan summary topics are left out when ``None`` (their
    publisher is off).
    """
    out = Direction.OUT
    rows = [
        Topic(scan_topic, LaserScan, out, SENSOR_DATA, "lidar scan, frame laser"),
        Topic(TOPIC_ODOM, Odometry, out, DEFAULT, "wheel odometry, odom -> base_link"),
        Topic(TOPIC_TF, TFMessage, out, DEFAULT, "odom -> base_link transform"),
        Topic("/tf_static", TFMessage, out, LATCHED, "static transforms (base_link -> laser ...)"),
        Topic(TOPIC_CORE, VescStateStamped, out, DEFAULT, "VESC telemetry"),
        Topic(TOPIC_SERVO, Float64, out, DEFAULT, "servo position command (0..1)"),
        Topic(mux.output_topic, AckermannDriveStamped, out, DEFAULT, "mux output: the drive command"),
        Topic(mux.active_topic, String, out, LATCHED, "the mux's active source"),
        Topic(mux.diagnostics_topic, DiagnosticArray, out, DEFAULT, "diagnostics"),
        Topic(safety.state_topic, DiagnosticArray, out, DEFAULT, "safety controller state"),
    ]
    if scan_range_topic:
        rows.append(Topic(scan_range_topic, ScanRange, out, DEFAULT, "closest and farthest return"))
    if open_space_topic:
        rows.append(Topic(open_space_topic, OpenSpace, out, DEFAULT, "longest range and its angle"))
    into = Direction.IN
    for source in mux.inputs:
        rows.append(Topic(source.topic, AckermannDriveStamped, into, DEFAULT,
                          f"mux input {source.name} (priority {source.priority})"))
    for lock in mux.locks:
        rows.append(Topic(lock.topic, Bool, into, DEFAULT, f"mux lock {lock.name}"))
    rows.append(Topic(mux.estop_topic, Bool, into, DEFAULT, "e-stop: true engages (latched)"))
    rows.append(Topic(mux.estop_release_topic, Bool, into, DEFAULT, "e-stop release: true releases"))
    return rows
