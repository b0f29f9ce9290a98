"""A stock rclpy node (the PyPI Kilted wheels, Fast DDS) that checks the car over DDS, as a user's
node would; run by tests/test_dds_ros2.py in the ROS 2 environment (.ros-venv), in a private network
namespace with the daemon. Prints one JSON line of what it saw.

    python ros2_rclpy_peer.py check --active TOPIC --estop TOPIC --drive-s 2.0
    python ros2_rclpy_peer.py drive --drive-s 2.0

``check``: receive /scan (sensor-data QoS) and /odom; subscribe to /tf_static and the mux's active
source only after that (a late joiner: TRANSIENT_LOCAL QoS); find racecar_hw in the node graph and
as the publisher of /scan; drive with /cmd_vel (Twist 0.5 m/s, 0.6 rad/s at 20 Hz for ``--drive-s``),
stop publishing and watch /odom come to rest; then engage the e-stop (std_msgs/Bool true) and read
the daemon's warning about it on /rosout (rcl_interfaces/msg/Log). Throughout, /imu
(sensor_msgs/Imu): its frame, acceleration, covariances, and its yaw rate next to the odometry's.
``drive``: receive /scan, then publish /cmd_vel (0.5 m/s) for ``--drive-s``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import rclpy
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Log
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Imu, LaserScan
from std_msgs.msg import Bool, String

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
try:
    from tf2_msgs.msg import TFMessage  # not in the PyPI wheels
except ImportError:
    TFMessage = None


def spin_until(node, predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        if predicate():
            return True
    return predicate()


def check(args: argparse.Namespace) -> dict:
    node = rclpy.create_node("dds_checker")
    seen: dict = {"scans": 0, "odoms": 0, "active": [], "odom_speeds": []}

    def on_scan(msg: LaserScan) -> None:
        seen["scans"] += 1
        seen["scan_beams"] = len(msg.ranges)
        seen["scan_frame"] = msg.header.frame_id

    def on_odom(msg: Odometry) -> None:
        seen["odoms"] += 1
        seen["odom_frame"] = msg.header.frame_id
        seen["odom_speeds"].append((time.monotonic(), msg.twist.twist.linear.x))
        seen["odom_yaw_rate"] = msg.twist.twist.angular.z

    seen["imu"] = []

    def on_imu(msg: Imu) -> None:
        seen["imu"].append({"frame": msg.header.frame_id, "gyro_z": msg.angular_velocity.z,
                            "acc_z": msg.linear_acceleration.z,
                            "cov_w": float(msg.angular_velocity_covariance[0]),
                            "cov_a": float(msg.linear_acceleration_covariance[0]),
                            "odom_yaw_rate": seen.get("odom_yaw_rate")})

    seen["logs"] = []
    rosout_qos = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(Log, "/rosout", lambda m: seen["logs"].append(
        {"name": m.name, "level": int(m.level), "msg": m.msg}) if m.level >= 30 else None, rosout_qos)
    node.create_subscription(LaserScan, "/scan", on_scan, qos_profile_sensor_data)
    node.create_subscription(Odometry, "/odom", on_odom, 10)
    node.create_subscription(Imu, "/imu", on_imu, 10)
    seen["scan_and_odom"] = spin_until(node, lambda: seen["scans"] >= 5 and seen["odoms"] >= 5, args.timeout)
    # late joiners: the daemon published these once, long before this subscription exists
    seen["tf_static_frames"] = []
    if TFMessage is not None:
        node.create_subscription(TFMessage, "/tf_static",
                                 lambda m: seen["tf_static_frames"].extend(
                                     t.child_frame_id for t in m.transforms),
                                 LATCHED)
    node.create_subscription(String, args.active, lambda m: seen["active"].append(m.data), LATCHED)
    spin_until(node, lambda: seen["active"] and (TFMessage is None or seen["tf_static_frames"]), args.timeout)
    # the node graph: ros_discovery_info names the car's participant's node and its endpoints
    spin_until(node, lambda: ("racecar_hw", args.namespace) in node.get_node_names_and_namespaces(),
               args.timeout)
    seen["nodes"] = sorted(f"{ns.rstrip('/')}/{name}" for name, ns in node.get_node_names_and_namespaces())
    pubs = node.get_publishers_info_by_topic("/scan")
    seen["scan_publishers"] = [{"node": p.node_name, "namespace": p.node_namespace, "type": p.topic_type,
                                "reliability": int(p.qos_profile.reliability),
                                "hash": str(getattr(p, "topic_type_hash", ""))} for p in pubs]
    seen["tf_static_publishers"] = [{"node": p.node_name, "durability": int(p.qos_profile.durability),
                                     "reliability": int(p.qos_profile.reliability)}
                                    for p in node.get_publishers_info_by_topic("/tf_static")]
    subs = node.get_subscriptions_info_by_topic("/cmd_vel")
    seen["cmd_vel_subscribers"] = [p.node_name for p in subs]
    # drive: a Twist stream, then silence
    cmd = node.create_publisher(Twist, "/cmd_vel", 10)
    spin_until(node, lambda: cmd.get_subscription_count() > 0, args.timeout)
    twist = Twist()
    twist.linear.x, twist.angular.z = 0.5, 0.6
    start = time.monotonic()
    seen["drive_start"] = start
    while time.monotonic() - start < args.drive_s:
        cmd.publish(twist)
        rclpy.spin_once(node, timeout_sec=0.05)
    seen["drive_stop"] = time.monotonic()
    spin_until(node, lambda: False, 1.5)
    # the e-stop
    estop = node.create_publisher(Bool, args.estop, 10)
    spin_until(node, lambda: estop.get_subscription_count() > 0, args.timeout)
    deadline = time.monotonic() + args.timeout
    while "estop" not in seen["active"] and time.monotonic() < deadline:
        # a sample written before the car's reader has matched this writer is lost (volatile)
        estop.publish(Bool(data=True))
        spin_until(node, lambda: "estop" in seen["active"], 0.2)
    seen["estop_seen"] = "estop" in seen["active"]
    # the daemon's warning about it, on /rosout
    spin_until(node, lambda: any("e-stop engaged" in log["msg"] for log in seen["logs"]), args.timeout)
    node.destroy_node()
    return seen


def drive(args: argparse.Namespace) -> dict:
    """Receive /scan, then publish /cmd_vel for ``--drive-s``: what a node beyond loopback does."""
    node = rclpy.create_node("dds_driver")
    seen: dict = {"scans": 0}
    node.create_subscription(LaserScan, "/scan", lambda m: seen.__setitem__("scans", seen["scans"] + 1),
                             qos_profile_sensor_data)
    seen["scan"] = spin_until(node, lambda: seen["scans"] >= 3, args.timeout)
    cmd = node.create_publisher(Twist, "/cmd_vel", 10)
    seen["matched"] = spin_until(node, lambda: cmd.get_subscription_count() > 0, args.timeout)
    twist = Twist()
    twist.linear.x = 0.5
    start = time.monotonic()
    while time.monotonic() - start < args.drive_s:
        cmd.publish(twist)
        rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()
    return seen


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("what", choices=["check", "drive"])
    parser.add_argument("--active", default="/vesc/low_level/ackermann_cmd_mux/active")
    parser.add_argument("--estop", default="/estop")
    parser.add_argument("--namespace", default="/")
    parser.add_argument("--drive-s", type=float, default=2.0)
    parser.add_argument("--timeout", type=float, default=30.0)
    args = parser.parse_args()
    rclpy.init()
    try:
        result = check(args) if args.what == "check" else drive(args)
    finally:
        rclpy.shutdown()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
