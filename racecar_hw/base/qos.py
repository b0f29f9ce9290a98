"""The QoS a topic is offered with, for every layer: the live interfaces (Zenoh, DDS, Foxglove) offer
it, the recorder writes it into bags (ROS 2: ``offered_qos_profiles``; ROS 1: ``latching=1`` for a
latched one). Which topics are latched is :data:`racecar_hw.base.topics.LATCHED_TOPICS`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


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
#: rcl's ``/rosout`` publisher (``rcl_qos_profile_rosout_default``, less its 10 s lifespan): a late
#: rqt_console still gets the recent records, and a TRANSIENT_LOCAL reader matches it over DDS.
ROSOUT = Qos(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, 1000)
#: What the simulator offers ``/clock`` with: reliable, volatile, keep last 1. ROS 2 nodes read it
#: with ``ClockQoS`` (:data:`CLOCK_SUBSCRIPTION`); a reliable writer matches best-effort readers and
#: reliable ones alike (a best-effort writer only the former), and only the newest time matters.
CLOCK_QOS = Qos(Reliability.RELIABLE, Durability.VOLATILE, 1)
#: rclcpp's and rclpy's ``ClockQoS``, the QoS ROS 2's time source subscribes ``/clock`` with.
CLOCK_SUBSCRIPTION = Qos(Reliability.BEST_EFFORT, Durability.VOLATILE, 1)
