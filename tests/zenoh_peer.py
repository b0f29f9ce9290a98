"""An independent ROS 2 peer for the tests: zenoh-ros2-sdk in a process of its own.

It knows nothing of racecar-hw: message definitions come from the official ROS 2 packages' ``.msg``
files (the PyPI ``ros-*-msgs`` wheels install them under ``<prefix>/share``) and the type hashes
from their JSON type descriptions, injected because zenoh-ros2-sdk computes wrong ones offline.
ackermann_msgs has no wheel: its two definitions (ros-drivers/ackermann_msgs, ros2 branch) are
below, with the hash ROS 2's own generator gives them (tests/test_net_rmw.py checks it).

    python tests/zenoh_peer.py PORT drive [--namespace /car1] [--input TOPIC] [--twist-topic T] [--humble]
    python tests/zenoh_peer.py PORT latched TOPIC
    python tests/zenoh_peer.py PORT node [--node /racecar_hw]
    python tests/zenoh_peer.py PORT imu [--count N]

``drive``: wait for /scan and /odom, then publish AckermannDriveStamped on the input topic at
20 Hz for 1.5 s (0.6 m/s, steering 0), pause 1.5 s, then Twist on /cmd_vel for 1.5 s (0.5 m/s,
0.6 rad/s), pause; print a JSON line of what it saw, with each stream's length on its own clock
and on the simulation's (``/clock``, where the daemon publishes it). ``--humble`` makes it a
Humble rmw_zenoh node: ``TypeHashNotSupported`` instead of every RIHS01 hash, in its keys and
liveliness tokens.
``latched``: subscribe TRANSIENT_LOCAL to a TFMessage topic and print the frames of the first
message (or none after 10 s). ``node``: what ``ros2 node info`` and ``ros2 param`` see of the node:
its services and publishers in the graph, ``list_parameters``, ``get_parameters`` (of
``mux.rate_hz`` and ``zenoh.listen``), ``get_parameter_types``, ``describe_parameters`` and a refused
``set_parameters``, all with the SDK's service client on the official ``rcl_interfaces``
definitions and hashes; then it subscribes to ``/rosout``, engages the e-stop (``/estop`` true,
which the mux logs as a warning) and reports the Log records it got. ``imu``: subscribe to /imu and
/odom until ``--count`` IMU messages came (or 60 s) and print each with the odometry before it.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import threading
import time
from pathlib import Path

import numpy as np
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber
from zenoh_ros2_sdk.session import ZenohSession

SHARE = Path(sys.prefix) / "share"
HUMBLE_HASH = "TypeHashNotSupported"
ACKERMANN = {
    "ackermann_msgs/msg/AckermannDrive": "float32 steering_angle\nfloat32 steering_angle_velocity\n"
                                         "float32 speed\nfloat32 acceleration\nfloat32 jerk\n",
    "ackermann_msgs/msg/AckermannDriveStamped": "std_msgs/Header header\nAckermannDrive drive\n",
}
ACKERMANN_HASH = "RIHS01_48ca7612a08d3bb72744fd98b71b7cf2ea24c6ad50fa4e1aa0bbad963c90d8cf"
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
TF_DEF = "geometry_msgs/TransformStamped[] transforms\n"
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string", "wstring"}


def definition(name: str) -> str:
    if name in ACKERMANN:
        return ACKERMANN[name]
    if name == "tf2_msgs/msg/TFMessage":
        return TF_DEF
    pkg, _, short = name.split("/")
    return (SHARE / pkg / "msg" / f"{short}.msg").read_text()


def srv_definitions(srv: str) -> tuple[str, str]:
    """The request and response definitions of a service type, from its official ``.srv`` file, with
    the package's own types named in full (the SDK would look for ``pkg/srv/msg/Type`` otherwise)."""
    pkg, _, short = srv.split("/")
    text = (SHARE / pkg / "srv" / f"{short}.srv").read_text()
    lines = []
    for raw in text.splitlines():
        parts = raw.split("#", 1)[0].split()
        base = re.sub(r"\[.*\]", "", parts[0]).split("<=")[0] if parts else ""
        if len(parts) >= 2 and "=" not in raw.split("#", 1)[0] and "/" not in base \
                and base not in _PRIMITIVES:
            raw = raw.replace(parts[0], f"{pkg}/{parts[0]}", 1)
        lines.append(raw)
    request, response = "\n".join(lines).split("---", 1)
    return request, response


def official_hash(name: str) -> str:
    if name.startswith("ackermann_msgs/"):
        return ACKERMANN_HASH
    if name == "tf2_msgs/msg/TFMessage":
        return TF_HASH
    pkg, kind, short = name.split("/")
    return json.loads((SHARE / pkg / kind / f"{short}.json").read_text())["type_hashes"][0]["hash_string"]


def register(session: ZenohSession, name: str, done: set[str], text: str | None = None) -> None:
    """Register ``name`` (with ``text``, else its definition) and every type it nests, dependencies first."""
    if name in done:
        return
    pkg = name.split("/")[0]
    text = definition(name) if text is None else text
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        parts = line.split()
        if len(parts) < 2 or "=" in line[len(parts[0]):]:  # blank, comment or constant
            continue
        ftype = re.sub(r"\[.*\]", "", parts[0]).split("<=")[0]
        if ftype in _PRIMITIVES:
            continue
        nested = ftype if "/" in ftype else f"{pkg}/{ftype}"
        if nested.count("/") == 1:
            nested = nested.replace("/", "/msg/")
        register(session, nested, done)
    session.register_message_type(text, name)
    done.add(name)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("port", type=int)
    parser.add_argument("mode", choices=("drive", "latched", "node", "imu"))
    parser.add_argument("--count", type=int, default=300)
    parser.add_argument("topic", nargs="?", default="/tf_static")
    parser.add_argument("--namespace", default="")
    parser.add_argument("--input", default="/vesc/high_level/ackermann_cmd_mux/input/nav_0")
    parser.add_argument("--twist-topic", default="/cmd_vel")
    parser.add_argument("--humble", action="store_true", help="be a Humble rmw_zenoh node")
    parser.add_argument("--node", default="/racecar_hw")
    args = parser.parse_args()
    session = ZenohSession.get_instance("127.0.0.1", args.port)
    done: set[str] = set()
    common = dict(router_ip="127.0.0.1", router_port=args.port)
    if args.mode == "node":
        return node_info(session, args.port, args.node, done)
    type_hash = (lambda name: HUMBLE_HASH) if args.humble else official_hash
    if args.mode == "latched":
        register(session, "tf2_msgs/msg/TFMessage", done)
        got: list = []
        arrived = threading.Event()

        def on_tf(msg) -> None:  # noqa: ANN001 - a rosbags message of the SDK's own store
            got.append([t.child_frame_id for t in msg.transforms])
            arrived.set()

        sub = ROS2Subscriber(args.topic, "tf2_msgs/msg/TFMessage", on_tf, msg_definition=TF_DEF,
                             type_hash=TF_HASH, qos=":1:,1:,:,:,,", **common)
        arrived.wait(10)
        print(json.dumps({"frames": got[0] if got else None}), flush=True)
        sub.close()
        return 0
    if args.mode == "imu":
        return imu(session, done, common, args.namespace, args.count)
    for name in ("sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry", "geometry_msgs/msg/Twist",
                 "ackermann_msgs/msg/AckermannDriveStamped", "rosgraph_msgs/msg/Clock"):
        register(session, name, done)
    seen = {"scan": 0, "odom": 0, "scan_beams": 0, "odom_frame": ""}

    def on_scan(msg) -> None:  # noqa: ANN001
        seen["scan"] += 1
        seen["scan_beams"] = len(msg.ranges)

    def on_odom(msg) -> None:  # noqa: ANN001
        seen["odom"] += 1
        seen["odom_frame"] = msg.header.frame_id

    clock_ns: list[int] = []  # the newest /clock (the simulation's time), as a node on sim time reads it

    def on_clock(msg) -> None:  # noqa: ANN001
        clock_ns[:] = [msg.clock.sec * 10**9 + msg.clock.nanosec]

    ns = args.namespace
    subs = [ROS2Subscriber(f"{ns}/scan", "sensor_msgs/msg/LaserScan", on_scan,
                           msg_definition=definition("sensor_msgs/msg/LaserScan"),
                           type_hash=type_hash("sensor_msgs/msg/LaserScan"), **common),
            ROS2Subscriber(f"{ns}/odom", "nav_msgs/msg/Odometry", on_odom,
                           msg_definition=definition("nav_msgs/msg/Odometry"),
                           type_hash=type_hash("nav_msgs/msg/Odometry"), **common),
            ROS2Subscriber("/clock", "rosgraph_msgs/msg/Clock", on_clock,
                           msg_definition=definition("rosgraph_msgs/msg/Clock"),
                           type_hash=type_hash("rosgraph_msgs/msg/Clock"), **common)]
    deadline = time.monotonic() + 30
    while (seen["scan"] < 5 or seen["odom"] < 5) and time.monotonic() < deadline:
        time.sleep(0.02)
    seen["scan_before_driving"], seen["odom_before_driving"] = seen["scan"], seen["odom"]
    store = session.store.types
    drive_pub = ROS2Publisher(f"{ns}{args.input}", "ackermann_msgs/msg/AckermannDriveStamped",
                              msg_definition=ACKERMANN["ackermann_msgs/msg/AckermannDriveStamped"],
                              type_hash=type_hash("ackermann_msgs/msg/AckermannDriveStamped"), **common)
    twist_pub = ROS2Publisher(f"{ns}{args.twist_topic}", "geometry_msgs/msg/Twist",
                              msg_definition=definition("geometry_msgs/msg/Twist"),
                              type_hash=type_hash("geometry_msgs/msg/Twist"), **common)
    time.sleep(0.5)  # let the daemon's subscriber see the new publishers' session
    Time, Header = store["builtin_interfaces/msg/Time"], store["std_msgs/msg/Header"]
    Drive, Vector3 = store["ackermann_msgs/msg/AckermannDrive"], store["geometry_msgs/msg/Vector3"]
    sent = {"drive": 0, "twist": 0}
    # how long each stream took from its first command to its last (1.45 s at 20 Hz; longer where a
    # loaded machine held this process up), for the test to compare the mux's switches with; and the
    # same on the simulation's clock as /clock gave it (absent where no /clock came)
    spread = {}

    def measure(name: str, first: float, first_clock: list[int]) -> None:
        spread[f"{name}_s"] = time.monotonic() - first
        if first_clock and clock_ns:
            spread[f"{name}_sim_s"] = (clock_ns[0] - first_clock[0]) / 1e9

    first, first_clock = time.monotonic(), list(clock_ns)
    for _ in range(30):
        measure("drive", first, first_clock)
        now = time.time_ns()
        stamp = Time(sec=now // 10**9, nanosec=now % 10**9)
        drive_pub.publish(header=Header(stamp=stamp, frame_id="base_link"),
                          drive=Drive(steering_angle=0.0, steering_angle_velocity=0.0, speed=0.6,
                                      acceleration=0.0, jerk=0.0))
        sent["drive"] += 1
        time.sleep(0.05)
    time.sleep(1.5)
    first, first_clock = time.monotonic(), list(clock_ns)
    for _ in range(30):
        measure("twist", first, first_clock)
        twist_pub.publish(linear=Vector3(x=0.5, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=0.6))
        sent["twist"] += 1
        time.sleep(0.05)
    time.sleep(1.0)
    print(json.dumps({**seen, **sent, **spread}), flush=True)
    for entity in (*subs, drive_pub, twist_pub):
        entity.close()
    return 0


def imu(session: ZenohSession, done: set[str], common: dict, ns: str, count: int) -> int:
    """/imu with the odometry's speed and yaw rate just before each message, as one JSON line."""
    for name in ("sensor_msgs/msg/Imu", "nav_msgs/msg/Odometry"):
        register(session, name, done)
    last_odom: dict = {}
    rows: list[dict] = []

    def on_odom(msg) -> None:  # noqa: ANN001
        last_odom.update(speed=msg.twist.twist.linear.x, yaw_rate=msg.twist.twist.angular.z)

    def on_imu(msg) -> None:  # noqa: ANN001
        rows.append({"frame": msg.header.frame_id, "gyro": [msg.angular_velocity.x, msg.angular_velocity.y,
                                                             msg.angular_velocity.z],
                     "acc": [msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z],
                     "q": [msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w],
                     "cov_o": list(map(float, msg.orientation_covariance)),
                     "cov_w": list(map(float, msg.angular_velocity_covariance)),
                     "cov_a": list(map(float, msg.linear_acceleration_covariance)),
                     "odom": dict(last_odom)})

    subs = [ROS2Subscriber(f"{ns}/odom", "nav_msgs/msg/Odometry", on_odom,
                           msg_definition=definition("nav_msgs/msg/Odometry"),
                           type_hash=official_hash("nav_msgs/msg/Odometry"), **common),
            ROS2Subscriber(f"{ns}/imu", "sensor_msgs/msg/Imu", on_imu,
                           msg_definition=definition("sensor_msgs/msg/Imu"),
                           type_hash=official_hash("sensor_msgs/msg/Imu"), **common)]
    deadline = time.monotonic() + 60
    while len(rows) < count and time.monotonic() < deadline:
        time.sleep(0.05)
    print(json.dumps({"imu": rows[:count]}), flush=True)
    for entity in subs:
        entity.close()
    return 0


def node_info(session: ZenohSession, port: int, node: str, done: set[str]) -> int:
    """The ``node`` mode (see the module documentation)."""
    from zenoh_ros2_sdk import ROS2ServiceClient  # noqa: PLC0415
    from zenoh_ros2_sdk.discovery import get_service_names_and_types, get_topic_info  # noqa: PLC0415

    common = dict(router_ip="127.0.0.1", router_port=port)
    out: dict = {}
    for name in ("rcl_interfaces/msg/Log", "std_msgs/msg/Bool", "rcl_interfaces/msg/ParameterValue",
                 "rcl_interfaces/msg/Parameter", "rcl_interfaces/msg/ParameterDescriptor",
                 "rcl_interfaces/msg/ListParametersResult", "rcl_interfaces/msg/SetParametersResult"):
        register(session, name, done)
    # the graph: ros2 node info lists the node's services and publishers from these tokens
    deadline = time.monotonic() + 60
    services: list = []
    while time.monotonic() < deadline and len(services) < 6:
        services = [(name, types) for name, types in get_service_names_and_types(timeout=1.0, **common)
                    if name.startswith(node + "/")]
    out["services"] = services
    rosout = None  # asked again until it answers with the publisher: one query may time out under load
    while time.monotonic() < deadline and (rosout is None or not rosout.publishers):
        rosout = get_topic_info("/rosout", timeout=1.0, verbose=True, **common)
    out["rosout_publishers"] = ([f"{p.node_namespace.rstrip('/')}/{p.node_name}" for p in rosout.publishers]
                                if rosout is not None else [])
    out["rosout_qos"] = [p.qos for p in rosout.publishers] if rosout is not None else []

    def client(service: str, srv: str) -> ROS2ServiceClient:
        request, response = srv_definitions(srv)
        register(session, f"{srv}_Request", done, request)
        register(session, f"{srv}_Response", done, response)
        return ROS2ServiceClient(f"{node}/{service}", srv, request_definition=request,
                                 response_definition=response, type_hash=official_hash(srv),
                                 timeout=10.0, **common)

    listed = client("list_parameters", "rcl_interfaces/srv/ListParameters").call(prefixes=[], depth=0)
    out["names"] = list(listed.result.names) if listed is not None else None
    names = ["mux.rate_hz", "zenoh.listen"]
    got = client("get_parameters", "rcl_interfaces/srv/GetParameters").call(names=names)
    out["values"] = ([{"type": v.type, "double": v.double_value, "strings": list(v.string_array_value)}
                      for v in got.values] if got is not None else None)
    types = client("get_parameter_types", "rcl_interfaces/srv/GetParameterTypes").call(names=names)
    out["types"] = [int(t) for t in types.types] if types is not None else None
    described = client("describe_parameters", "rcl_interfaces/srv/DescribeParameters").call(names=names[:1])
    out["read_only"] = ([d.read_only for d in described.descriptors] if described is not None else None)
    store = session.store.types
    Parameter, Value = store["rcl_interfaces/msg/Parameter"], store["rcl_interfaces/msg/ParameterValue"]
    value = Value(type=3, bool_value=False, integer_value=0, double_value=10.0, string_value="",
                  byte_array_value=np.zeros(0, np.uint8), bool_array_value=np.zeros(0, np.bool_),
                  integer_array_value=np.zeros(0, np.int64), double_array_value=np.zeros(0, np.float64),
                  string_array_value=[])
    refused = client("set_parameters", "rcl_interfaces/srv/SetParameters").call(
        parameters=[Parameter(name="mux.rate_hz", value=value)])
    out["set"] = ([{"ok": r.successful, "reason": r.reason} for r in refused.results]
                  if refused is not None else None)
    # /rosout: a warning the daemon logs reaches a ROS 2 subscriber
    logs: list = []

    def on_log(m) -> None:  # noqa: ANN001 - a rosbags message of the SDK's own store
        logs.append({"level": int(m.level), "name": m.name, "msg": m.msg})

    sub = ROS2Subscriber("/rosout", "rcl_interfaces/msg/Log", on_log,
                         msg_definition=definition("rcl_interfaces/msg/Log"),
                         type_hash=official_hash("rcl_interfaces/msg/Log"), qos=":1:,1000:,:,:,,", **common)
    estop = ROS2Publisher("/estop", "std_msgs/msg/Bool", msg_definition=definition("std_msgs/msg/Bool"),
                          type_hash=official_hash("std_msgs/msg/Bool"), **common)
    time.sleep(0.5)  # let the daemon's subscriber see the new publisher's session
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and not any("e-stop" in log["msg"] for log in logs):
        estop.publish(data=True)
        time.sleep(0.2)
    out["logs"] = logs
    print(json.dumps(out), flush=True)
    sub.close()
    estop.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
