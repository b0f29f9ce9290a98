"""The DDS interface at nominal load: what it adds to the scan path and the CPU, and a round trip
through a stock rclpy node.

The nominal-load daemon of ``bench_daemon.py`` (UST-10LX at 40 Hz, VESC at 50 Hz, figure-8 source,
safety, recorder), one run per setting:

(a) DDS off; on with nobody; on with one rclpy node (the PyPI Kilted wheels, Fast DDS, from
    ``.ros-venv``) subscribed to every topic the car publishes whose type has a wheel (/scan with
    the sensor-data QoS, /odom, the servo position, the mux's active source): the daemon's own
    scan-to-VESC-command p50/p99 and its CPU share;
(b) the round trip: an rclpy node answers every /scan with a /cmd_vel Twist (the turn rate
    alternating, so each answer changes the servo position); the time from the fake lidar handing a
    scan frame to its socket until the fake VESC reads the servo position that answers it
    (``bench_zenoh._round_trip``), next to the same through the Zenoh client.

Each run uses a DDS domain of its own (``ROS_DOMAIN_ID`` for the rclpy node). ``python
benchmarks/bench_dds.py [SECONDS]``; ``run()`` returns the rows.
"""

from __future__ import annotations

import os
import random
import sys
from pathlib import Path

from bench_daemon import run as run_daemon
from bench_zenoh import CLIENT, _free_port, _pick, _round_trip
from table import print_rows

ROS_PYTHON = str(Path(os.environ.get("RACECAR_ROS_VENV", Path(__file__).resolve().parents[1] / ".ros-venv"))
                 / "bin" / "python")

SUBSCRIBER = '''
import importlib, rclpy
from rclpy.qos import qos_profile_sensor_data
rclpy.init()
node = rclpy.create_node("bench_subscriber")
topics = [("/scan", "sensor_msgs.msg", "LaserScan"), ("/odom", "nav_msgs.msg", "Odometry"),
          ("/vesc/sensors/servo_position_command", "std_msgs.msg", "Float64"),
          ("/vesc/low_level/ackermann_cmd_mux/active", "std_msgs.msg", "String")]
for topic, module, name in topics:
    cls = getattr(importlib.import_module(module), name)
    node.create_subscription(cls, topic, lambda m: None,
                             qos_profile_sensor_data if topic == "/scan" else 10)
rclpy.spin(node)
'''

ANSWER = '''
import rclpy
from geometry_msgs.msg import Twist
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import LaserScan
rclpy.init()
node = rclpy.create_node("bench_driver")
pub = node.create_publisher(Twist, "/cmd_vel", 10)
sign = [1.0]
def answer(scan):
    sign[0] = -sign[0]
    t = Twist()
    t.linear.x = 0.3
    t.angular.z = 0.2 * sign[0]
    pub.publish(t)
node.create_subscription(LaserScan, "/scan", answer, qos_profile_sensor_data)
rclpy.spin(node)
'''

P99 = "scan to VESC command p99 (in daemon)"
P50 = "scan to VESC command p50 (in daemon)"
CPU = "daemon CPU share of one core"


def _dds(domain: int) -> dict:
    return {"dds": {"enabled": True, "domain_id": domain}}


def run(seconds: float = 20.0) -> list[dict]:
    if not Path(ROS_PYTHON).exists():
        raise SystemExit(f"no ROS 2 environment at {ROS_PYTHON} (.ci/run makes it)")
    env_domain = random.randrange(100, 200)
    os.environ["ROS_DOMAIN_ID"] = str(env_domain)  # the rclpy helpers inherit it
    off = run_daemon(seconds)
    nobody = run_daemon(seconds, config_extra=_dds(env_domain))
    one = run_daemon(seconds, config_extra=_dds(env_domain), helpers=[[ROS_PYTHON, "-c", SUBSCRIBER]])
    trip = run_daemon(seconds, config_extra=_dds(env_domain),
                      helpers=[[ROS_PYTHON, "-c", ANSWER, "--drives"]], on_results=_round_trip)
    port = _free_port()
    ztrip = run_daemon(seconds, zenoh_port=port,
                       helpers=[[sys.executable, "-c", CLIENT, str(port), "--drives"]],
                       on_results=_round_trip)
    rows = []
    every = "on, one rclpy subscriber of every topic"
    for label, result in (("off", off), ("on, nobody", nobody), (every, one)):
        rows.append({"name": f"DDS {label}: scan to VESC command p50", "value": _pick(result, P50),
                     "unit": "ms", "target": None})
        rows.append({"name": f"DDS {label}: scan to VESC command p99", "value": _pick(result, P99),
                     "unit": "ms", "target": 2.0})
        rows.append({"name": f"DDS {label}: daemon CPU share", "value": _pick(result, CPU), "unit": "%",
                     "target": None})
    for label, result in (("on, nobody", nobody), (every, one)):
        rows.append({"name": f"(a) p99 added, DDS {label}", "value": _pick(result, P99) - _pick(off, P99),
                     "unit": "ms", "target": 0.05})
        rows.append({"name": f"(a) CPU added, DDS {label}", "value": _pick(result, CPU) - _pick(off, CPU),
                     "unit": "% of a core", "target": None})
    for label, result in (("rclpy over DDS", trip), ("racecar_hw.client over Zenoh", ztrip)):
        for row in result:
            if row["name"].startswith("(b)"):
                rows.append({**row, "name": row["name"].replace("(b)", f"(b) {label}:")})
        rows.append({"name": f"(b) {label}: daemon CPU share", "value": _pick(result, CPU), "unit": "%",
                     "target": None})
    return rows


def main() -> None:
    print_rows(run(float(sys.argv[1]) if len(sys.argv) > 1 else 20.0))


if __name__ == "__main__":
    main()
