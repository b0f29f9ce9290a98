"""The DDS acceptance runs against a real ROS 2: ``racecar-hw sim`` on its shipped config, and a stock
rclpy node (the PyPI Kilted wheels, Fast DDS, in .ros-venv: tests/netns.py) in a private network
namespace with only loopback. The node, with its default discovery and with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, receives /scan (sensor-data QoS) and /odom, gets the
mux's active source as a late joiner, finds racecar_hw in the node graph as the publisher of /scan,
drives the car with /cmd_vel, engages /estop and reads the daemon's warning about it on /rosout
(tests/ros2_rclpy_peer.py). The sim's report and
trajectory say whether the car moved as commanded and stopped once the publisher stopped."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest
from netns import ROOT, NetNs, netns, ros_python
from zenoh_util import switch_times, switches

from racecar_hw.sim.trajectory import read_csv

pytest.importorskip("cyclonedds", reason="cyclonedds (a dependency) is not installed")

PEER = str(ROOT / "tests" / "ros2_rclpy_peer.py")
ACTIVE = "/vesc/low_level/ackermann_cmd_mux/active"
#: The sim's static transforms and its map -> odom, as the Zenoh acceptance test lists them.
STATIC_FRAMES = ["imu", "laser", "left_cam", "odom", "right_cam"]


def _start_sim(ns: NetNs, out, *sets: str, duration: float = 40.0) -> subprocess.Popen[str]:
    out.mkdir(parents=True, exist_ok=True)
    # lockstep paced at real time (the peer's stream stays real time): the brake after the mux's
    # timeout comes on the world's clock whatever the machine's load (tests/test_net_zenoh_sim.py)
    command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--scenario", "wall", "--speed", "1",
               "--scenario-set", "drivers=[]", "--duration", str(duration), "--no-status",
               "--no-plot", "--out", str(out), "--report", str(out / "report.json"),
               "--set", "zenoh.enabled=false", "--set", "foxglove.port=0", "--set", "web.port=0"]
    for item in sets:
        command += ["--set", item]
    # its log goes to a file: a pipe nobody reads until the end fills and stops the sim
    log = (out / "sim.log").open("w")
    return ns.popen(command, stdout=subprocess.DEVNULL, stderr=log, text=True, cwd=ROOT)


def _report(sim: subprocess.Popen[str], out) -> tuple[dict, str]:
    sim.send_signal(2)  # as Ctrl-C: the report is written
    try:
        sim.wait(timeout=120)
    except subprocess.TimeoutExpired:
        sim.kill()
        sim.wait()
        raise AssertionError(f"sim did not finish: {(out / 'sim.log').read_text()[-3000:]}") from None
    err = (out / "sim.log").read_text()
    assert (out / "report.json").exists(), err[-3000:]
    return json.loads((out / "report.json").read_text()), err


def _late_tf_static(ns: NetNs) -> list[str]:
    """/tf_static's frames read by a Cyclone reader that starts now (no tf2_msgs wheel for rclpy)."""
    script = (
        "import sys, time, json\n"
        "from cyclonedds.domain import DomainParticipant\nfrom cyclonedds.topic import Topic\n"
        "from cyclonedds.sub import DataReader\n"
        "from racecar_hw.net.dds_bridge import qos_of\nfrom racecar_hw.net.topics import LATCHED\n"
        "from racecar_hw.net.dds_types import ros2_factory\n"
        "from racecar_hw.rosmsg.typestore import ros2_types\nfrom racecar_hw.base.messages import TFMessage\n"
        "from cyclonedds.domain import Domain\nfrom racecar_hw.net.dds_config import DdsParams, cyclone_xml\n"
        "d = Domain(0, cyclone_xml(DdsParams()))\np = DomainParticipant(0)\n"
        "r = DataReader(p, Topic(p, 'rt/tf_static', ros2_factory().topic_type('tf2_msgs/msg/TFMessage')),"
        " qos_of(LATCHED))\n"
        "frames = []\nend = time.monotonic() + 30\n"
        "while not frames and time.monotonic() < end:\n"
        "    for s in r.take(10):\n"
        "        tf = ros2_types().deserialize(s.data, TFMessage)\n"
        "        frames += [t.child_frame_id for t in tf.transforms]\n"
        "    time.sleep(0.1)\n"
        "print(json.dumps(sorted(frames)))\n")
    proc = ns.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=90, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _speed_near(samples, t: float) -> float:
    return min(samples, key=lambda s: abs(s.t - t)).speed


@pytest.mark.parametrize(("discovery", "host"), [
    # ROS 2's default discovery (multicast), on loopback with multicast as in a container
    ("default", "multicast loopback"),
    # ... and as on a laptop: lo without multicast, a LAN interface where multicast goes
    ("default", "LAN"),
    ("LOCALHOST", "LAN"),
])
def test_a_stock_rclpy_node_reads_the_car_finds_it_and_drives_it_over_dds(tmp_path, discovery, host):
    python = ros_python()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    if discovery == "LOCALHOST":
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    out = tmp_path / "out"
    lan = host == "LAN"
    with netns(multicast=not lan, lan="10.77.0.1/24" if lan else None) as ns:
        # the node graph of Fast DDS 3 (Kilted): see dds.ros_distro
        sim = _start_sim(ns, out, "dds.ros_distro=kilted")
        try:
            started = time.monotonic()
            peer = ns.run([python, PEER, "check", "--active", ACTIVE, "--timeout", "45"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
            assert peer.returncode == 0, peer.stderr[-3000:]
            seen = json.loads(peer.stdout.strip().splitlines()[-1])
            assert time.monotonic() - started > 3.0
            frames = _late_tf_static(ns)
        finally:
            report, log = _report(sim, out) if sim.poll() is None else ({}, "")
            if sim.poll() is None:
                sim.kill()
    assert seen["scan_and_odom"], seen
    assert seen["scan_beams"] == 1081 and seen["scan_frame"] == "laser" and seen["odom_frame"] == "odom"
    # late joiners: the active source (std_msgs/String) with rclpy, /tf_static with Cyclone
    assert seen["active"][:1] == ["idle"], seen["active"]
    assert frames == STATIC_FRAMES
    assert seen["tf_static_publishers"] == [{"node": "racecar_hw", "durability": 1, "reliability": 1}]
    # the node graph: ros_discovery_info names the car's node and its endpoints; best effort /scan
    assert "/racecar_hw" in seen["nodes"]
    scan_pub, = seen["scan_publishers"]
    assert scan_pub["node"] == "racecar_hw" and scan_pub["type"] == "sensor_msgs/msg/LaserScan"
    assert scan_pub["reliability"] == 2  # BEST_EFFORT
    assert scan_pub["hash"].startswith("RIHS01_64c191398013af96509d518dac71d5164f93")
    assert seen["cmd_vel_subscribers"] == ["racecar_hw"]
    # the drive: Twist 0.5 m/s, 0.6 rad/s, then silence; then the e-stop
    assert seen["estop_seen"], seen["active"]
    # /rosout: the mux's warning, from the daemon's node logger
    engaged = [log for log in seen["logs"] if "e-stop engaged" in log["msg"]]
    assert engaged, seen["logs"]
    assert engaged[0]["level"] == 30 and engaged[0]["name"] == "racecar_hw.mux.node"
    order = switches(report)
    assert "cmd_vel" in order and "estop" in order, report["mux_switches"]
    assert order[order.index("cmd_vel") + 1] == "idle"
    samples = read_csv(report["trajectory_csv"])
    twist_on, = switch_times(report, "cmd_vel")
    twist_off = min(t for t in switch_times(report, "idle") if t > twist_on)
    during = [s for s in samples if twist_on <= s.t <= twist_off]
    assert 0.4 < max(s.speed for s in during) < 0.6
    assert during[-1].yaw - during[0].yaw > 0.3
    assert abs(_speed_near(samples, twist_off + 0.4)) < 0.05
    assert report["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
    assert "dds interface up" in log
    # /imu: SI units, its frame and covariances; while turning, the gyro's yaw rate is the
    # kinematics' (the odometry's v tan(delta) / L) within 5 %
    imu = seen["imu"]
    assert len(imu) > 50 and {m["frame"] for m in imu} == {"imu"}
    assert imu[0]["cov_w"] > 0 and imu[0]["cov_a"] > 0
    acc_z = sorted(m["acc_z"] for m in imu)
    assert acc_z[len(acc_z) // 2] == pytest.approx(9.81, abs=0.3)
    ratios = sorted(m["gyro_z"] / m["odom_yaw_rate"] for m in imu
                    if m["odom_yaw_rate"] is not None and abs(m["odom_yaw_rate"]) > 0.3)
    assert len(ratios) > 10, len(ratios)
    assert ratios[len(ratios) // 2] == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("allowed", [False, True])
def test_beyond_loopback_dds_publishes_but_takes_commands_only_when_explicitly_allowed(tmp_path, allowed):
    """dds.interface on a LAN address: the car's topics reach a node there; its /cmd_vel is
    refused (counted, the start notice says why) unless dds.accept_unauthenticated_commands."""
    python = ros_python()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    out = tmp_path / "out"
    with netns(multicast=False, lan="10.77.0.1/24") as ns:
        sim = _start_sim(ns, out, "dds.interface=10.77.0.1", "dds.multicast=true", "dds.peers=[10.77.0.1]",
                         f"dds.accept_unauthenticated_commands={str(allowed).lower()}")
        try:
            peer = ns.run([python, PEER, "drive", "--drive-s", "2.0", "--timeout", "45"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
            assert peer.returncode == 0, peer.stderr[-3000:]
            seen = json.loads(peer.stdout.strip().splitlines()[-1])
        finally:
            report, log = _report(sim, out) if sim.poll() is None else ({}, "")
            if sim.poll() is None:
                sim.kill()
    assert seen["scan"] and seen["matched"], seen  # it publishes, and its reader is there
    order = switches(report)
    if allowed:
        assert "cmd_vel" in order, report["mux_switches"]
        assert "anyone on that network can drive the car" in log
    else:
        assert "cmd_vel" not in order, report["mux_switches"]
        assert "publishing only. Commands from DDS" in log
        assert "unauthenticated interface" in log  # the refusal, counted and logged
