"""A stock rclpy node on simulation time (the PyPI Kilted wheels, Fast DDS): run by
tests/test_sim_clock.py in the ROS 2 environment (.ros-venv), in a private network namespace with
``racecar-hw sim``. Prints one JSON line of what it saw.

    python ros2_clock_peer.py --ns /car1 --period-s 0.01 --timer-calls 30 --timeout 60

The node is started as a user would: ``--ros-args -p use_sim_time:=true -r __ns:=/car1``. Its
time source subscribes ``/clock`` (absolute, whatever the namespace) with ClockQoS; this node also
subscribes to ``/clock`` itself (best effort, deep enough to keep every sample), to know every
value published. A timer of ``--period-s`` on the node's clock records ``now()`` at each call.
It reports: the /clock values received, each with the wall clock at receipt; ``now()`` at each
timer call; the node's time while it stops spinning for a while (no callbacks: no /clock taken);
and the publishers of /clock as the graph shows them (node, namespace, QoS).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--ns", default="/")
    parser.add_argument("--period-s", type=float, default=0.01)
    parser.add_argument("--timer-calls", type=int, default=30)
    parser.add_argument("--timeout", type=float, default=60.0)
    args = parser.parse_args()
    rclpy.init(args=["--ros-args", "-p", "use_sim_time:=true", "-r", f"__ns:={args.ns}"])
    node = rclpy.create_node("sim_time_checker")
    started_wall_ns = time.time_ns()
    clocks: list[tuple[int, int]] = []  # (/clock ns, wall ns at receipt)
    calls: list[int] = []  # the node's now() at each timer call

    def on_clock(msg: Clock) -> None:
        clocks.append((_ns(msg.clock), time.time_ns()))

    node.create_subscription(Clock, "/clock", on_clock,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT))
    recording = [True]

    def on_timer() -> None:
        if recording[0]:
            calls.append(node.get_clock().now().nanoseconds)

    node.create_timer(args.period_s, on_timer)
    out: dict = {"use_sim_time": node.get_parameter("use_sim_time").value,
                 "ros_time_active": node.get_clock().ros_time_is_active,
                 "started_wall_ns": started_wall_ns, "namespace": node.get_namespace()}
    deadline = time.monotonic() + args.timeout
    while len(calls) < args.timer_calls and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    recording[0] = False
    # not spinning: no callback runs, so the node's time stands still while the wall clock goes on
    held = node.get_clock().now().nanoseconds
    wall = time.monotonic()
    while time.monotonic() - wall < 0.3:
        time.sleep(0.05)
    out["held"] = [held, node.get_clock().now().nanoseconds]
    # ... and moves again when the node spins (and takes /clock)
    while node.get_clock().now().nanoseconds == held and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    out["after_spin"] = after = node.get_clock().now().nanoseconds
    # our own subscription's backlog up to that sample (the time source's reader keeps only the newest)
    while all(c < after for c, _ in clocks) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    out["clocks"] = clocks
    out["calls"] = calls
    out["publishers"] = [{"node": p.node_name, "namespace": p.node_namespace,
                          "reliability": int(p.qos_profile.reliability),
                          "durability": int(p.qos_profile.durability), "depth": p.qos_profile.depth}
                         for p in node.get_publishers_info_by_topic("/clock")]
    node.destroy_node()
    rclpy.shutdown()
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
