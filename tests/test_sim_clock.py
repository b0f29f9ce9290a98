"""``/clock`` in simulation (issue 27): ROS 2 nodes with ``use_sim_time`` and the Python client follow it.

* A stock rclpy node (the PyPI Kilted wheels, Fast DDS, in .ros-venv: tests/netns.py) started with
  ``use_sim_time:=true`` in the namespace ``/car1``, beside ``racecar-hw sim`` whose interfaces are in
  that namespace, in a private network namespace over DDS (tests/ros2_clock_peer.py): its time is
  exactly the /clock values the sim publishes, stands still while it takes none, and its timer
  fires on that time.
* The Python client over Zenoh with ``use_sim_time=True`` (a car in a namespace: /clock is not in
  it): ``now()``, ``sleep()`` and ``on_clock`` follow /clock.
* The row, its QoS against ClockQoS, the type hash against ROS 2's own, the rate parameter.
"""

from __future__ import annotations

import asyncio
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import QUIET_NET, wait_for
from netns import ROOT, NetNs, netns, ros_python
from zenoh_util import endpoint, free_port, start_sim

from racecar_hw.base import clock
from racecar_hw.base.clock import NS_PER_S, SIM_EPOCH_NS
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import Clock, Time
from racecar_hw.base.topics import CLOCK_TOPIC, SCAN_TOPIC
from racecar_hw.client import AsyncCar, Car, ClientError
from racecar_hw.net import rmw
from racecar_hw.net.topics import CLOCK_QOS, CLOCK_ROW, CLOCK_SUBSCRIPTION, Reliability
from racecar_hw.rosmsg.typestore import ros1_types, ros2_types
from racecar_hw.runtime import lockstep
from racecar_hw.sim.clock_topic import clock_message
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.scenario import WorldSpec, load_scenario

PEER = str(ROOT / "tests" / "ros2_clock_peer.py")


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1.0):
            return True
    except OSError:
        return False


def _wait_listening(port: int) -> None:
    wait_for(lambda: _listening(port), timeout=60.0, interval=0.1)
SHARE = Path(sys.prefix) / "share"


# --- the row, the type, the parameter --------------------------------------------------------


def test_the_clock_row_is_absolute_and_its_qos_matches_clockqos_readers():
    assert CLOCK_ROW.ros == "/clock" and CLOCK_ROW.absolute and CLOCK_ROW.msgtype is Clock
    # DDS's request-offered rule: a writer matches a reader that asks for no more than it offers
    assert CLOCK_QOS.reliability is Reliability.RELIABLE  # >= ClockQoS's best effort, and reliable readers
    assert CLOCK_SUBSCRIPTION.reliability is Reliability.BEST_EFFORT and CLOCK_SUBSCRIPTION.depth == 1
    assert not CLOCK_QOS.latched and CLOCK_QOS.depth == 1


def test_the_clock_type_hash_is_ros2s_and_humble_peers_get_theirs():
    path = SHARE / "rosgraph_msgs" / "msg" / "Clock.json"
    if not path.exists():
        pytest.skip(f"{path} absent: install the test extra (ros-rosgraph-msgs)")
    official = json.loads(path.read_text())["type_hashes"][0]
    assert official["type_name"] == "rosgraph_msgs/msg/Clock"
    assert rmw.type_hash(Clock.ROS_TYPE) == official["hash_string"] == ros2_types().digest(Clock.ROS_TYPE)
    # Jazzy, Kilted and later put the hash in keys; Humble's rmw_zenoh the literal placeholder
    assert rmw.wire_type_hash(Clock.ROS_TYPE, "jazzy") == official["hash_string"]
    assert rmw.wire_type_hash(Clock.ROS_TYPE, "humble") == rmw.HUMBLE_TYPE_HASH
    assert rmw.dds_type(Clock.ROS_TYPE) == "rosgraph_msgs::msg::dds_::Clock_"


def test_clock_messages_carry_the_time_in_both_bag_formats():
    msg = clock_message(1_700_000_000 * NS_PER_S + 5)
    assert msg.clock == Time(1_700_000_000, 5)
    for types in (ros1_types(), ros2_types()):
        raw = types.serialize(msg)
        assert raw == types.serialize_generic(msg)
        assert types.deserialize(raw, Clock) == msg


def test_the_rate_is_a_scenario_parameter_and_zero_turns_clock_off():
    assert WorldSpec().clock_rate_hz == 100.0 == load_scenario("wall").world.clock_rate_hz
    assert load_scenario("wall", ["world.clock_rate_hz=0"]).world.clock_rate_hz == 0.0
    with pytest.raises(ConfigError, match="clock_rate_hz"):
        load_scenario("wall", ["world.clock_rate_hz=-1"])


# --- lockstep: /clock is the virtual clock ------------------------------------------------------


def _lockstep_clock(tmp_path: Path, *sets: str) -> tuple[list[tuple[int, int]], list[int]]:
    """A 2 s lockstep run of the wall scenario: (/clock ns, the process's clock at publish) for
    every /clock, and every /scan stamp (ns)."""
    clocks: list[tuple[int, int]] = []
    scans: list[int] = []

    def setup(loopback: Loopback) -> None:
        assert loopback.daemon is not None
        bus = loopback.daemon.bus
        bus.subscribe(CLOCK_TOPIC, lambda msg: clocks.append((msg.clock.to_ns(), clock.monotonic_ns())))
        bus.subscribe(SCAN_TOPIC, lambda msg: scans.append(msg.header.stamp.to_ns()))

    scenario = load_scenario("wall", ["drivers=[]"])
    overrides = [*QUIET_NET, "foxglove.enabled=false", "web.enabled=false", *sets]
    loopback = Loopback(scenario, overrides=overrides, lockstep=True, setup=setup, duration_s=2.0,
                        out_dir=tmp_path / "out")
    lockstep.run(loopback.run())
    return clocks, scans


def test_in_lockstep_clock_carries_the_virtual_clock_every_10_ms_and_bags_record_it(tmp_path):
    from rosbags.highlevel import AnyReader  # noqa: PLC0415 - the test extra

    bags = tmp_path / "bags"
    clocks, scans = _lockstep_clock(tmp_path, "recorder.enabled=true", f"recorder.path={bags}")
    values = [value for value, _ in clocks]
    # sim time from the virtual epoch (1 s), not 1970; what every stamp uses, published at its tick
    assert all(value == now for value, now in clocks)
    assert SIM_EPOCH_NS <= values[0] < values[-1] < SIM_EPOCH_NS + 60 * NS_PER_S
    assert scans[0] >= SIM_EPOCH_NS and scans[-1] <= values[-1] + 25_000_000
    # 100 Hz of sim time, on the ticker's grid: exactly 10 ms apart, however loaded the machine
    assert {b - a for a, b in zip(values, values[1:], strict=False)} == {10_000_000}
    assert len(values) >= 200
    (bag,) = [p for p in bags.iterdir() if p.is_dir()]
    with AnyReader([bag]) as reader:
        (connection,) = [c for c in reader.connections if c.topic == "/clock"]
        assert connection.msgtype == "rosgraph_msgs/msg/Clock"
        recorded = [reader.deserialize(raw, connection.msgtype).clock
                    for _, _, raw in reader.messages(connections=[connection])]
    assert [t.sec * NS_PER_S + t.nanosec for t in recorded] == values


def test_nothing_publishes_clock_when_nothing_carries_it(tmp_path):
    # the step API's episodes: every interface and the recorder off
    clocks, scans = _lockstep_clock(tmp_path)
    assert clocks == [] and len(scans) > 40


# --- a real rclpy node on simulation time, over DDS ----------------------------------------------


def _start_sim(ns: NetNs, out: Path, *sets: str, clock_rate_hz: float) -> subprocess.Popen[str]:
    out.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--scenario", "wall",
               "--scenario-set", "drivers=[]", "--scenario-set", f"world.clock_rate_hz={clock_rate_hz}",
               "--duration", "60", "--no-status", "--no-plot", "--out", str(out),
               "--report", str(out / "report.json"), "--set", "zenoh.enabled=false",
               "--set", "foxglove.port=0", "--set", "web.port=0"]
    for item in sets:
        command += ["--set", item]
    log = (out / "sim.log").open("w")  # a pipe nobody reads would fill and stop the sim
    return ns.popen(command, stdout=subprocess.DEVNULL, stderr=log, text=True, cwd=ROOT)


def _stop(sim: subprocess.Popen[str]) -> None:
    sim.send_signal(2)
    try:
        sim.wait(timeout=120)
    except subprocess.TimeoutExpired:
        sim.kill()
        sim.wait()


def test_an_rclpy_node_with_use_sim_time_follows_clock_and_its_timer_fires_on_it(tmp_path):
    pytest.importorskip("cyclonedds", reason="cyclonedds (a dependency) is not installed")
    python = ros_python()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    out = tmp_path / "out"
    # /clock at 20 Hz and a 100 Hz timer: on the wall clock the timer would fire about five times
    # between two /clock messages (and see the same now() each time); on simulation time it can fire
    # once per /clock at most (rcl skips the periods a jump of time passes over)
    period_s, clock_rate_hz = 0.01, 20.0
    with netns() as ns:
        # the car in a namespace: /clock stays /clock, as ROS's time source wants it
        sim = _start_sim(ns, out, "dds.ros_distro=kilted", "zenoh.namespace=car1",
                         clock_rate_hz=clock_rate_hz)
        try:
            peer = ns.run([python, PEER, "--ns", "/car1", "--period-s", str(period_s), "--timer-calls", "40",
                           "--timeout", "90"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
        finally:
            _stop(sim)
    log = (out / "sim.log").read_text()
    assert peer.returncode == 0, peer.stderr[-3000:] + log[-2000:]
    seen = json.loads(peer.stdout.strip().splitlines()[-1])
    assert seen["use_sim_time"] is True and seen["ros_time_active"] is True and seen["namespace"] == "/car1"
    # the sim's writer, as the graph shows it: the car's node, reliable, volatile, keep last 1
    assert seen["publishers"] == [{"node": "racecar_hw", "namespace": "/car1", "reliability": 1,
                                   "durability": 2, "depth": 1}]
    clocks = [c for c, _ in seen["clocks"]]
    assert len(clocks) >= 40 and clocks == sorted(clocks)
    # the real-time sim's /clock is its stamps' time base, the wall clock: published before it arrived
    for value, received in seen["clocks"]:
        assert seen["started_wall_ns"] - 60 * NS_PER_S < value <= received
    # every now() the timer saw is a /clock value: the node's time is /clock's, not its own clock's
    calls = seen["calls"]
    assert len(calls) >= 40
    assert set(calls) <= set(clocks), sorted(set(calls) - set(clocks))
    # a periodic timer on that time: at most one call per /clock taken, so never twice at one time ...
    assert len(set(calls)) == len(calls) and calls == sorted(calls)
    # ... and /clock steps by 50 ms, so the calls are that far apart (not the timer's 10 ms)
    steps = [b - a for a, b in zip(clocks, clocks[1:], strict=False)]
    assert min(b - a for a, b in zip(calls, calls[1:], strict=False)) >= min(steps)
    assert (calls[-1] - calls[0]) / (len(calls) - 1) > 2 * period_s * NS_PER_S
    # while the node takes no /clock its time stands still; with the next it moves to that value
    held, still = seen["held"]
    assert held == still and held in clocks
    assert seen["after_spin"] > held and seen["after_spin"] in clocks


# --- the Python client over Zenoh ---------------------------------------------------------------


def test_the_python_client_with_use_sim_time_follows_clock_over_zenoh(tmp_path):
    port = free_port()
    sim = start_sim(tmp_path / "sim", port, "zenoh.namespace=car1", "dds.enabled=false", duration=30.0)
    try:
        _wait_listening(port)
        with Car(endpoint(port), namespace="car1", use_sim_time=True) as car, \
                Car(endpoint(port), namespace="car1") as wall:
            assert car.use_sim_time and not wall.use_sim_time
            first = car.wait_clock(timeout=60)
            assert first > 0
            ticks: list[float] = []
            got = threading.Condition()

            def on_clock(t: float) -> None:
                with got:
                    ticks.append(t)
                    got.notify_all()

            car.on_clock(on_clock)
            start = car.now()
            car.sleep(0.5)
            after = car.now()
            assert after - start >= 0.5
            # now() is a /clock value the client took (each one is called back), not its own clock
            with got:
                assert got.wait_for(lambda: len(ticks) >= 20, 30)
                assert after in ticks
            # sleep_until counts the same time; the scans' stamps are in its base (in the real-time
            # sim both are the wall clock: the same seconds since 1970)
            target = car.now() + 0.2
            car.sleep_until(target)
            assert car.now() >= target
            scan = car.next_scan(timeout=30)
            assert abs(scan.stamp_s - car.now()) < 5.0
            with pytest.raises(ClientError, match="use_sim_time"):
                wall.on_clock(print)
            assert abs(wall.now() - time.time()) < 1.0

        async def use() -> tuple[float, float]:  # the same for asyncio
            async with AsyncCar(endpoint(port), namespace="car1", use_sim_time=True) as car:
                first = await car.wait_clock(30)
                await car.sleep(0.2)
                return first, car.now()

        first, after = asyncio.run(use())
        assert after - first >= 0.2
    finally:
        sim.kill()
    assert ticks == sorted(ticks)


def test_sleep_raises_when_no_clock_comes(tmp_path):
    port = free_port()
    sim = start_sim(tmp_path / "sim", port, "dds.enabled=false", scenario_sets=("drivers=[]",
                    "world.clock_rate_hz=0"), duration=30.0)
    try:
        _wait_listening(port)
        with Car(endpoint(port), use_sim_time=True) as car:
            assert car.next_scan(timeout=60).ranges.size == 1081  # the daemon is up and reached
            assert car.now() == 0.0  # as a ROS 2 node's sim time before any /clock
            with pytest.raises(ClientError, match="no /clock for 1 s"):
                car.sleep(0.1, timeout=1.0)
    finally:
        sim.kill()
