"""A four-process rclpy chain doing what the daemon and one remote client do: the yardstick.

The ROS 2 way of running this car with Python nodes, against the same fakes as ``bench_daemon.py``
(a UST-10LX streaming 1081 beams at 40 Hz over TCP, a VESC on a pty, the world simulation):

1. ``lidar``: reads the fake lidar's SCIP stream (this project's sans-I/O codec) and publishes
   ``sensor_msgs/LaserScan`` on ``/scan`` (sensor-data QoS), as ``urg_node`` would;
2. ``nav``: subscribes ``/scan`` and ``/odom`` and answers every scan on ``/nav`` (speed 0.3 m/s,
   steering alternating +-0.03 rad, as ``bench_zenoh.py``'s client does);
3. ``mux``: forwards its one input to ``/drive`` at once, as ``ackermann_cmd_mux`` does for the
   winning input;
4. ``vesc``: turns ``/drive`` into SET_RPM and SET_SERVO_POS frames on the pty (the shipped
   gains), polls GET_VALUES at 50 Hz and publishes ``nav_msgs/Odometry`` from the replies.

No ackermann_msgs wheel exists on PyPI, so the drive commands are ``geometry_msgs/Twist``
(``linear.x`` m/s, ``angular.z`` the steering angle in rad); a Twist and an
AckermannDriveStamped cost the same to a middleware. The four processes run the Python given
(``--chain-python``: a virtual environment with ``ros-rclpy[fastrtps]``, ``ros-sensor-msgs``,
``ros-geometry-msgs``, ``ros-nav-msgs`` and this project installed) over its default RMW
(Fast DDS), with default discovery.

Measured as in ``bench_zenoh.py``'s far-side rows: the round trip from the fake lidar handing a
frame to its socket until the fake VESC reads the servo position that answers it, and the four
processes' CPU share together ("helpers' CPU share of one core").

``python benchmarks/bench_rclpy_chain.py PYTHON [SECONDS]``; ``run()`` for ``bench_zenoh.py --far-side``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bench_daemon import _cpu_s, _host_ticks
from fakes import room_fakes
from table import print_rows

from vesc.codec import SetRpm

COMMON = '''
import os, sys, rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.executors import SingleThreadedExecutor
rclpy.init()
'''

LIDAR = COMMON + '''
import array, math, socket
from sensor_msgs.msg import LaserScan
from lidar_drivers.scip import ResponseDecoder, ScanCommand, ScanReply
host, port = sys.argv[1], int(sys.argv[2])
node = Node("lidar")
pub = node.create_publisher(LaserScan, "/scan", qos_profile_sensor_data)
sock = socket.create_connection((host, port))
sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
sock.sendall(ScanCommand(name="MD", start=0, end=1080, cluster=1, interval=0, count=0).encode())
decoder = ResponseDecoder()
msg = LaserScan()
msg.header.frame_id = "laser"
step = 2 * math.pi / 1440
msg.angle_min, msg.angle_max, msg.angle_increment = -540 * step, 540 * step, step
msg.scan_time, msg.range_min, msg.range_max = 0.025, 0.02, 10.0
while rclpy.ok():
    data = sock.recv(65536)
    if not data:
        break
    decoder.receive_data(data)
    while (event := decoder.next_event()) is not None:
        if isinstance(event, ScanReply) and event.distances.size:
            msg.header.stamp = node.get_clock().now().to_msg()
            msg.ranges = array.array("f", (event.distances * 0.001).astype("<f4").tobytes())
            pub.publish(msg)
'''

NAV = COMMON + '''
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan
node = Node("nav")
pub = node.create_publisher(Twist, "/nav", 10)
sign = [1.0]
def on_scan(scan):
    sign[0] = -sign[0]
    out = Twist()
    out.linear.x = 0.3
    out.angular.z = 0.03 * sign[0]
    pub.publish(out)
odom = [None]
node.create_subscription(LaserScan, "/scan", on_scan, qos_profile_sensor_data)
node.create_subscription(Odometry, "/odom", lambda m: odom.__setitem__(0, m), 10)
rclpy.spin(node)
'''

MUX = COMMON + '''
from geometry_msgs.msg import Twist
node = Node("mux")
pub = node.create_publisher(Twist, "/drive", 10)
node.create_subscription(Twist, "/nav", pub.publish, 10)
rclpy.spin(node)
'''

VESC = COMMON + '''
import threading, tty
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from vesc.codec import GetValuesRequest, Role, SetRpm, SetServoPosition, Values, VescCodec
from vesc.params import VescParams
p = VescParams()
fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY)
tty.setraw(fd)
codec = VescCodec(Role.HOST, firmware=(6, 2))
lock = threading.Lock()
node = Node("vesc")
pub = node.create_publisher(Odometry, "/odom", 10)
def write(*packets):
    data = b"".join(codec.send(packet) for packet in packets)
    with lock:
        os.write(fd, data)
def on_drive(msg):
    servo = p.steering_angle_to_servo_offset + p.steering_angle_to_servo_gain * msg.angular.z
    write(SetRpm(round(p.speed_to_erpm_gain * msg.linear.x)), SetServoPosition(min(max(servo, 0.0), 1.0)))
def reader():
    while True:
        codec.receive_data(os.read(fd, 4096))
        for event in codec.events():
            if isinstance(event, Values):
                odom = Odometry()
                odom.header.stamp = node.get_clock().now().to_msg()
                odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
                odom.twist.twist.linear.x = event.rpm / p.speed_to_erpm_gain
                pub.publish(odom)
threading.Thread(target=reader, daemon=True).start()
node.create_subscription(Twist, "/drive", on_drive, 10)
node.create_timer(0.02, lambda: write(GetValuesRequest()))
rclpy.spin(node)
'''


def run(seconds: float, python: str, on_results: Callable[[np.ndarray, list], list[dict]] | None = None
        ) -> list[dict]:
    """One run of the chain against fresh fakes; rows as ``bench_daemon.run``'s (the chain's CPU
    in "helpers' CPU share of one core"), plus what ``on_results(sent_ns, commands)`` returns."""
    sys.setswitchinterval(0.0002)
    with tempfile.TemporaryDirectory() as tmp, room_fakes(tmp, open_vesc=True) as (vesc, lidar):
        host, port = lidar.tcp_address
        env = {**os.environ, "ROS_DOMAIN_ID": str(os.getpid() % 200 + 20)}  # apart from other runs
        # the chain's nodes import this project's codecs from this tree, whatever the working directory
        env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
        nodes = [[python, "-c", VESC, f"{tmp}/vesc"], [python, "-c", MUX], [python, "-c", NAV],
                 [python, "-c", LIDAR, host, str(port)]]
        logs = [open(f"{tmp}/node{i}.log", "w") for i in range(len(nodes))]  # noqa: SIM115
        procs = [subprocess.Popen(n, env=env, stdout=subprocess.DEVNULL, stderr=log)
                 for n, log in zip(nodes, logs, strict=True)]
        try:
            deadline = time.monotonic() + 90
            while lidar.clients == 0 or sum(isinstance(c.packet, SetRpm) for c in vesc.commands) < 40:
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                    errors = [Path(f"{tmp}/node{i}.log").read_text()[-1500:] for i in range(len(nodes))]
                    raise RuntimeError(f"the rclpy chain did not start: {errors}")
                time.sleep(0.1)
            time.sleep(3.0)  # warm up
            lidar.frames_sent_ns.clear()
            vesc.clear_commands()
            host0 = _host_ticks()
            cpu0, t0 = sum(_cpu_s(p.pid) for p in procs), time.monotonic()
            time.sleep(seconds)
            cpu1, t1 = sum(_cpu_s(p.pid) for p in procs), time.monotonic()
            host1 = _host_ticks()
            sent = np.array(lidar.frames_sent_ns, dtype=np.int64)
            commands = list(vesc.commands)
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
            for log in logs:
                log.close()
    rows = [
        {"name": "helpers' CPU share of one core", "value": 100.0 * (cpu1 - cpu0) / (t1 - t0),
         "unit": "%", "target": None},
        {"name": "scans during measurement", "value": len(sent), "unit": "scans", "target": None},
        {"name": "host: CPU time stolen by the hypervisor", "unit": "% of busy",
         "value": 100.0 * (host1[1] - host0[1]) / max(1, host1[0] - host0[0]), "target": None},
    ]
    return rows + (on_results(sent, commands) if on_results else [])


def main() -> None:
    from bench_zenoh import _latencies, _percentiles  # noqa: PLC0415

    python = sys.argv[1]
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 20.0

    def trip(sent: np.ndarray, commands: list) -> list[dict]:
        p50, p99 = _percentiles(_latencies(sent, commands))
        return [{"name": "round trip scan frame out -> answer at the VESC, p50", "value": p50,
                 "unit": "ms", "target": None},
                {"name": "round trip, p99", "value": p99, "unit": "ms", "target": None}]

    print_rows(run(seconds, python, trip))


if __name__ == "__main__":
    main()
