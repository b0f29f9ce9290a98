"""The node surface ROS 2 tools expect, and Humble's rmw_zenoh, against ``racecar-hw sim`` in its own
process and an independent ROS 2 peer (zenoh-ros2-sdk, tests/zenoh_peer.py) in another.

* ``ros2 node info`` / ``ros2 param``: the peer finds the six parameter services and the /rosout
  publisher of /racecar_hw in the graph, lists and reads parameters with the SDK's service client
  (the official rcl_interfaces definitions and hashes), and is refused a set.
* ``/rosout``: the peer engages the e-stop; the mux's warning reaches its /rosout subscriber.
* Humble: with ``zenoh.ros_distro: humble`` a Humble-style peer (``TypeHashNotSupported`` in its
  keys and tokens) reads /scan and /odom and drives the car; the default (Jazzy and later) keys are
  the other acceptance run's (tests/test_net_zenoh_sim.py).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ahead_of_ordinary_load
from zenoh_util import ROOT, free_port, start_sim, switch_times, switches, wait_until_stopped

from racecar_hw.sim.trajectory import read_csv

pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk (the test extra) is not installed")
SHARE = Path(sys.prefix) / "share"
for _need in ("sensor_msgs/msg/LaserScan.msg", "rcl_interfaces/srv/ListParameters.srv"):
    if not (SHARE / _need).exists():
        pytest.skip(f"{SHARE / _need} is absent: the official ROS 2 message packages (ros-*-msgs and "
                    "ros-rcl-interfaces wheels, x86_64 only) are not installed; the independent peer "
                    "reads its definitions from them", allow_module_level=True)

PEER = str(ROOT / "tests" / "zenoh_peer.py")
#: no default ports in tests: the sim's Foxglove server and status page stay off
QUIET = ("foxglove.enabled=false", "web.enabled=false")


def _peer(port: int, *args: str, timeout: float = 150, ahead: bool = False) -> dict:
    """``ahead``: run the peer ahead of the ordinary load of a shared machine, for a peer that
    drives: what is checked is the daemon's handling of its 20 Hz stream (the mux's 0.2 s timeout),
    not how long another tenant of the machine holds the peer's process up."""
    proc = subprocess.run([sys.executable, PEER, str(port), *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, preexec_fn=ahead_of_ordinary_load if ahead else None)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_ros2_tools_see_the_node_its_parameters_and_its_log(tmp_path):
    port = free_port()
    sim = start_sim(tmp_path, port, *QUIET, duration=120.0)
    try:
        seen = _peer(port, "node")
    finally:
        sim.interrupt()
    # ros2 node info /racecar_hw: the parameter services and the /rosout publisher
    assert [name for name, _ in seen["services"]] == [
        f"/racecar_hw/{s}" for s in ("describe_parameters", "get_parameter_types", "get_parameters",
                                     "list_parameters", "set_parameters", "set_parameters_atomically")]
    assert all(types == [f"rcl_interfaces/srv/{_camel(name)}"] for name, types in seen["services"])
    assert seen["rosout_publishers"] == ["/racecar_hw"]
    assert seen["rosout_qos"] == [":1:,1000:,:,:,,"]  # reliable, transient local, depth 1000 (rcl's)
    # ros2 param list / get / set: the effective config, read-only
    assert {"mux.rate_hz", "zenoh.listen", "zenoh.ros_distro", "rosout.level"} <= set(seen["names"])
    assert seen["values"] == [{"type": 3, "double": 50.0, "strings": []},
                              {"type": 9, "double": 0.0, "strings": [f"tcp/127.0.0.1:{port}"]}]
    assert seen["types"] == [3, 9]  # PARAMETER_DOUBLE, PARAMETER_STRING_ARRAY
    assert seen["read_only"] == [True]
    (refused,) = seen["set"]
    assert refused["ok"] is False
    assert "read-only" in refused["reason"] and "--set mux.rate_hz" in refused["reason"]
    # /rosout: the mux's warning, as rcl_interfaces/msg/Log at WARN (30), named after the node
    engaged = [log for log in seen["logs"] if "e-stop engaged" in log["msg"]]
    assert engaged, seen["logs"]
    assert engaged[0]["level"] == 30 and engaged[0]["name"] == "racecar_hw.mux.node"
    assert all(log["level"] >= 30 for log in seen["logs"])  # rosout.level: WARNING by default


def _camel(service_path: str) -> str:
    return "".join(part.capitalize() for part in service_path.rsplit("/", 1)[1].split("_"))


@pytest.mark.slow
def test_a_humble_peer_reads_the_car_and_drives_it_when_the_daemon_is_set_for_humble(tmp_path):
    port = free_port()
    # ended (SIGINT) once the peer is done and the car stands still, not after a fixed duration;
    # in lockstep paced at real time, as tests/test_net_zenoh_sim.py's acceptance runs (the brake
    # after the mux's timeout on the world's clock, whatever the machine's load)
    sim = start_sim(tmp_path, port, *QUIET, "zenoh.ros_distro=humble", duration=180.0, speed=1)
    try:
        seen = _peer(port, "drive", "--humble", ahead=True)
        wait_until_stopped(port, ros_distro="humble")
        report = sim.interrupt()
    finally:
        sim.kill()
    assert seen["scan_before_driving"] >= 5 and seen["odom_before_driving"] >= 5
    assert seen["scan_beams"] == 1081 and seen["odom_frame"] == "odom"
    order = switches(report)
    assert "nav_0" in order and "cmd_vel" in order, report["mux_switches"]
    samples = read_csv(report["trajectory_csv"])
    # on a loaded machine a gap in the peer's 20 Hz stream can outlast the mux's 0.2 s timeout: nav_0
    # may come back; the run is from its first switch to the idle after its last, before cmd_vel
    nav, (twist_on, *_) = switch_times(report, "nav_0"), switch_times(report, "cmd_vel")
    nav_on = nav[0]
    nav_off = min(t for t in switch_times(report, "idle") if nav[-1] < t < twist_on)
    assert 0.5 < max(s.speed for s in samples if nav_on <= s.t <= nav_off + 0.05) < 0.7
    # 30 commands 50 ms apart, then the timeout: the stream's length on the sim's clock, as the peer
    # read it on /clock (a paced sim's clock can fall behind the peer's, docs/tests.md)
    stream = seen["drive_sim_s"] + 0.05
    assert stream <= nav_off - nav_on <= stream + 0.2 + 0.6
    # then it stopped (the first sample 0.4 s on: a loaded machine may hold the sim up, and the
    # sample nearest that time may be one from before the switch)
    assert abs(next((s for s in samples if s.t >= nav_off + 0.4), samples[-1]).speed) < 0.05
    assert report["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
