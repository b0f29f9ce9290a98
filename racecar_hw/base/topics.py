"""The bus's well-known topic names, defined once for every layer (the mux, the drivers, teleop,
bags, the network bridges, the client).

Names follow the MIT/F1TENTH racecar stack (``vesc/``, ``ackermann_cmd_mux``) and REP-105 for
odometry and transforms. They are defaults: where a topic is a configuration value, the parameter's
default is the constant here, and the configured value wins.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from racecar_hw.base.qos import LATCHED, ROSOUT, Qos

#: The low-level mux's inputs (safety, teleop and the ground station's operator inputs).
MUX_LOW = "/vesc/low_level/ackermann_cmd_mux"
#: The high-level mux's inputs (navigation code, /cmd_vel).
MUX_HIGH = "/vesc/high_level/ackermann_cmd_mux"

#: std_msgs/String: the mux's current source.
MUX_ACTIVE_TOPIC = f"{MUX_LOW}/active"
#: geometry_msgs/Twist from Foxglove's Teleop panel (the panel's topic in the shipped layouts).
FOXGLOVE_TELEOP_TOPIC = "/foxglove/cmd_vel"

#: ackermann_msgs/AckermannDriveStamped from a person at the controls (gamepad, keyboard, GCS).
TELEOP_TOPIC = f"{MUX_LOW}/input/teleop"
#: The safety controller's braking commands.
MUX_SAFETY_TOPIC = f"{MUX_LOW}/input/safety"
#: Foxglove's teleop panel, once the daemon has turned its Twist into a mux command.
FOXGLOVE_INPUT_TOPIC = f"{MUX_LOW}/input/foxglove"
#: The first (highest-priority) navigation input.
NAV0_TOPIC = f"{MUX_HIGH}/input/nav_0"
#: The mux input of /cmd_vel Twists (geometry_msgs/Twist turned into AckermannDriveStamped).
CMD_VEL_BUS_TOPIC = f"{MUX_HIGH}/input/cmd_vel"

#: sensor_msgs/LaserScan from the lidar (``laser`` frame, metres, radians CCW).
SCAN_TOPIC = "/scan"
#: vesc_msgs/VescStateStamped, every telemetry reply.
TOPIC_CORE = "/vesc/sensors/core"
#: std_msgs/Float64, every servo position written (0..1).
TOPIC_SERVO = "/vesc/sensors/servo_position_command"
#: nav_msgs/Odometry, wheel odometry (``odom`` -> ``base_link``).
TOPIC_ODOM = "/odom"
#: tf2_msgs/TFMessage, dynamic transforms (``odom`` -> ``base_link``).
TOPIC_TF = "/tf"
#: tf2_msgs/TFMessage, latched static transforms.
TOPIC_TF_STATIC = "/tf_static"
#: sensor_msgs/Imu from the VESC's IMU (SI units, ``imu`` frame).
TOPIC_IMU = "/imu"
#: rosgraph_msgs/Clock, the simulation's time (ROS 2 ``use_sim_time``); outside any namespace.
CLOCK_TOPIC = "/clock"
#: nav_msgs/OccupancyGrid, the simulator's map (latched).
MAP_TOPIC = "/map"
#: rcl_interfaces/Log, the daemon's log (:mod:`racecar_hw.net.rosout`); outside any namespace.
ROSOUT_TOPIC = "/rosout"

#: The latched topics (ROS 2 transient local, ROS 1 latching) and their QoS: the one table the live
#: topic table (:mod:`racecar_hw.net.topics`, :mod:`racecar_hw.sim.live`) and the recorder
#: (:mod:`racecar_hw.bags.record`) read. A late joiner gets the latest; every bag split starts with it.
LATCHED_TOPICS: Mapping[str, Qos] = MappingProxyType({
    TOPIC_TF_STATIC: LATCHED,   # what static_transform_publisher offers
    MUX_ACTIVE_TOPIC: LATCHED,  # the mux's active source, published on change
    MAP_TOPIC: LATCHED,         # what map_server offers
    ROSOUT_TOPIC: ROSOUT,       # rcl's rosout publisher: the recent records
})
