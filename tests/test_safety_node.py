"""SafetyNode and ConeSafety on the in-process bus."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from conftest import async_wait_for

from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    LaserScan,
    Odometry,
    Quaternion,
    Time,
)
from racecar_hw.base.params import build
from safety import ConeSafety, SafetyNode, SafetyParams
from safety.node import sweep_ns
from safety.params import MUX_SAFETY_TOPIC, ConeParams

MS = 1_000_000


class ManualClock:
    """Test time, in monotonic nanoseconds."""

    def __init__(self) -> None:
        self.now = 10_000 * MS

    def __call__(self) -> int:
        return self.now


def scan_with(ranges: np.ndarray, stamp_ns: int = 123 * MS) -> LaserScan:
    """A UST-10LX-like scan: 1081 beams over -135..135 degrees."""
    n = ranges.size
    angle_min, angle_max = -math.radians(135), math.radians(135)
    return LaserScan(header=Header(Time.from_ns(stamp_ns), "laser"), angle_min=angle_min,
                     angle_max=angle_max, angle_increment=(angle_max - angle_min) / (n - 1),
                     scan_time=0.025, range_min=0.06, range_max=30.0,
                     ranges=ranges.astype(np.float32))


def open_scan() -> LaserScan:
    """Open space: walls 25 m away, beyond any path (a scan without a single return is refused as a
    blinded lidar: safety.min_return_fraction)."""
    return scan_with(np.full(1081, 25.0))


def blocked_ahead(distance: float) -> LaserScan:
    """Open space except an object straight ahead of the laser, 20 beams wide."""
    r = np.full(1081, np.inf)
    r[530:551] = distance
    return scan_with(r)


def odom(speed: float) -> Odometry:
    msg = Odometry()
    msg.twist.twist.linear.x = speed
    return msg


def states(bus: Bus, topic: str = "/safety/state") -> list[DiagnosticStatus]:
    got: list[DiagnosticStatus] = []
    bus.subscribe(topic, lambda m: got.append(m.status[0]))
    return got


def values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_node_filters_commands_with_scans_and_odometry_from_the_bus() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, SafetyParams(), clock=clock)
    published = states(bus)
    out = node.filter(AckermannDrive(speed=1.0, steering_angle=0.1), "nav")
    assert out.speed == 0.0 and node.state.reason == "no_scan"
    bus.publish("/scan", blocked_ahead(1.0))
    out = node.filter(AckermannDrive(speed=3.0, steering_angle=0.05), "nav")
    assert 0.0 < out.speed < 3.0 and out.steering_angle == 0.05
    assert node.state.intervening and node.interventions == 1
    last = values(published[-1])
    assert published[-1].level == DiagnosticStatus.WARN and published[-1].message == "obstacle"
    assert last["intervening"] == "true"
    assert float(last["allowed_speed"]) == pytest.approx(out.speed, abs=1e-3)
    assert float(last["obstacle_x"]) > 1.0 and last["source"] == "nav"
    # the car is measured going fast although the command is slow: still an intervention
    bus.publish("/scan", blocked_ahead(1.0))
    bus.publish("/odom", odom(5.0))
    node.filter(AckermannDrive(speed=0.1), "nav")
    assert node.state.intervening
    node.close()
    node.close()


def test_node_brakes_when_scans_stop() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, SafetyParams(), clock=clock)
    published = states(bus)
    bus.publish("/scan", open_scan())
    assert node.filter(AckermannDrive(speed=2.0), "nav").speed == 2.0
    clock.now += 150 * MS
    assert node.filter(AckermannDrive(speed=2.0), "nav").speed == 0.0
    assert published[-1].message == "stale_scan" and published[-1].level == DiagnosticStatus.ERROR


def test_node_publishes_on_change_and_at_a_low_rate() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, build(SafetyParams, {"state_rate_hz": 2.0}), clock=clock)
    published = states(bus)
    for _ in range(20):  # 20 commands within 200 ms, nothing changes: one message
        bus.publish("/scan", open_scan())
        node.filter(AckermannDrive(speed=1.0), "nav")
        clock.now += 10 * MS
    assert len(published) == 1 and published[0].message == "clear"
    bus.publish("/scan", blocked_ahead(0.5))
    node.filter(AckermannDrive(speed=1.0), "nav")
    assert len(published) == 2 and published[-1].message == "obstacle"
    clock.now += 600 * MS
    node.tick()  # no command for a while: the state is refreshed and republished
    assert len(published) == 3


def test_limit_leaves_the_state_to_be_published_after_the_motor_command() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, SafetyParams(), clock=clock)
    published = states(bus)
    bus.publish("/scan", blocked_ahead(1.0))
    out = node.limit(AckermannDrive(speed=3.0), "nav", clock.now)
    assert 0.0 < out.speed < 3.0 and node.state.intervening
    assert published == []
    node.publish_state_if_due(clock.now)
    assert [s.message for s in published] == ["obstacle"]
    assert values(published[0])["commanded_speed"] == "3.000"
    assert float(values(published[0])["output_speed"]) == pytest.approx(out.speed, abs=1e-3)


def test_node_run_publishes_periodically() -> None:
    bus = Bus()
    node = SafetyNode(bus, build(SafetyParams, {"state_rate_hz": 50.0}))
    published = states(bus)

    async def main() -> None:
        task = asyncio.create_task(node.run())
        try:
            await async_wait_for(lambda: len(published) >= 3, timeout=20.0)
        finally:
            task.cancel()

    asyncio.run(main())
    assert all(s.message == "no_scan" for s in published)


def test_node_latches_a_fault_and_brakes() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, SafetyParams(), clock=clock)
    bus.publish("/scan", open_scan())
    broken = AckermannDrive(speed="fast", steering_angle=0.2)  # type: ignore[arg-type]
    out = node.filter(broken, "nav")
    assert out.speed == 0.0 and out.steering_angle == 0.2
    assert node.state.reason == "fault" and node.faults == 1
    assert node.filter(AckermannDrive(speed=1.0), "nav").speed == 0.0
    node.reset_fault()
    assert node.filter(AckermannDrive(speed=1.0), "nav").speed == 1.0


def test_a_scan_the_controller_cannot_take_in_latches_a_fault_too() -> None:
    for deferred in (False, True):
        bus, clock = Bus(), ManualClock()
        node = SafetyNode(bus, SafetyParams(), clock=clock, defer_memory=deferred)
        bus.publish("/odom", odom_at(0.0, 0.0, 0.0))
        bus.publish("/scan", open_scan())
        assert node.filter(AckermannDrive(speed=1.0), "nav").speed == 1.0
        garbled = open_scan()
        garbled.ranges = np.array(["far"] * 1081)  # a publisher in the same process got it wrong
        bus.publish("/scan", garbled)
        assert node.fault is not None and node.fault.startswith("ValueError") and node.faults == 1
        assert node.filter(AckermannDrive(speed=1.0), "nav").speed == 0.0
        assert node.state.reason == "fault"


def test_stale_odometry_is_ignored() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, SafetyParams(), clock=clock)
    bus.publish("/odom", odom(4.0))
    assert node.measured_speed(clock.now) == 4.0
    assert node.measured_speed(clock.now + 600 * MS) == 0.0


def odom_at(x: float, y: float, yaw: float, speed: float = 0.0, yaw_rate: float = 0.0) -> Odometry:
    msg = odom(speed)
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    msg.pose.pose.orientation = Quaternion.from_yaw(yaw)
    msg.twist.twist.angular.z = yaw_rate
    return msg


def test_the_pose_at_a_scan_is_the_odometry_carried_forward_by_its_twist() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, SafetyParams(), clock=clock)
    assert node.pose_at(clock.now) is None
    bus.publish("/odom", odom_at(1.0, 2.0, 0.5, speed=2.0))
    assert node.pose_at(clock.now) == pytest.approx((1.0, 2.0, 0.5))
    x, y, yaw = node.pose_at(clock.now + 20 * MS)
    assert (x, y, yaw) == pytest.approx((1.0 + 0.04 * math.cos(0.5), 2.0 + 0.04 * math.sin(0.5), 0.5))
    bus.publish("/odom", odom_at(0.0, 0.0, 0.0, speed=1.0, yaw_rate=1.0))
    _, _, yaw = node.pose_at(clock.now + 100 * MS)
    assert yaw == pytest.approx(0.1)
    assert node.pose_at(clock.now + 600 * MS) is None  # older than odom_timeout_s


def test_the_node_remembers_each_scan_at_once_or_when_the_daemon_says() -> None:
    for deferred in (False, True):
        bus, clock = Bus(), ManualClock()
        node = SafetyNode(bus, SafetyParams(), clock=clock, defer_memory=deferred)
        published = states(bus)
        bus.publish("/odom", odom_at(0.0, 0.0, 0.0))
        bus.publish("/scan", blocked_ahead(1.0))
        memory = node.controller.memory
        assert memory is not None
        assert memory.updates == (0 if deferred else 1)
        node.remember()
        assert memory.updates == 1 and len(memory) > 0
        node.filter(AckermannDrive(speed=0.5), "nav")
        last = values(published[-1])
        assert last["memory"] == "on" and last["obstacle_source"] in ("", "scan")
        clock.now += 600 * MS  # odometry gone stale
        bus.publish("/scan", blocked_ahead(1.0))
        node.remember()
        node.tick()
        assert values(published[-1])["memory"] == "no_odometry" and len(memory) == 0


def test_a_scan_with_beams_a_subnormal_angle_apart_brakes_without_a_fault() -> None:
    # it once made the memory raise IndexError: a latched fault, or with the memory following
    # each scan an exception out of the bus callback
    for deferred in (False, True):
        bus, clock = Bus(), ManualClock()
        node = SafetyNode(bus, SafetyParams(), clock=clock, defer_memory=deferred)
        bus.publish("/odom", odom_at(0.0, 0.0, 0.0))
        bus.publish("/scan", blocked_ahead(1.0))
        node.remember()
        memory = node.controller.memory
        assert memory is not None and len(memory) > 0
        remembered = len(memory)
        broken = open_scan()
        broken.angle_increment = 1e-300
        clock.now += 100 * MS  # past the memory's update period: it takes this scan in
        bus.publish("/scan", broken)
        node.remember()
        assert memory.updates == 2 and len(memory) == remembered
        assert node.filter(AckermannDrive(speed=1.0), "nav").speed == 0.0
        assert node.state.reason == "bad_scan" and node.fault is None and node.faults == 0


def test_the_memory_can_be_switched_off() -> None:
    bus = Bus()
    node = SafetyNode(bus, build(SafetyParams, {"memory": {"enabled": False}}))
    published = states(bus)
    node.tick()
    assert node.controller.memory is None and values(published[-1])["memory"] == "off"


def cone_bus(**cone: object) -> tuple[Bus, ConeSafety, list[AckermannDriveStamped]]:
    bus = Bus()
    safety = ConeSafety(bus, build(ConeParams, cone, "cone"))
    got: list[AckermannDriveStamped] = []
    bus.subscribe(MUX_SAFETY_TOPIC, got.append)
    return bus, safety, got


def test_cone_publishes_zero_on_the_mux_safety_input_at_the_scan_rate() -> None:
    bus, cone, got = cone_bus(stop_distance_m=0.5)
    for _ in range(3):
        bus.publish("/scan", blocked_ahead(0.3))
    assert len(got) == 3
    assert all(m.drive.speed == 0.0 and m.drive.steering_angle == 0.0 for m in got)
    assert got[0].header.stamp == Time.from_ns(123 * MS)
    assert cone.stopping and cone.closest == np.float32(0.3)


def test_cone_stays_silent_when_clear_or_obstacle_outside_the_cone() -> None:
    bus, cone, got = cone_bus(stop_distance_m=0.5, half_angle_rad=0.35)
    bus.publish("/scan", open_scan())
    bus.publish("/scan", blocked_ahead(0.8))
    side = np.full(1081, np.inf)
    side[900:920] = 0.2  # about 90 degrees to the left
    bus.publish("/scan", scan_with(side))
    nan_ahead = np.full(1081, np.inf)
    nan_ahead[530:551] = np.nan
    bus.publish("/scan", scan_with(nan_ahead))
    assert got == [] and not cone.stopping


def test_cone_hysteresis_on_noisy_ranges() -> None:
    bus, cone, got = cone_bus(stop_distance_m=0.5, release_margin_m=0.05)
    rng = np.random.default_rng(5)
    flips, last = 0, False
    for _ in range(200):
        bus.publish("/scan", blocked_ahead(0.5 + rng.uniform(-0.02, 0.02)))
        flips += cone.stopping != last
        last = cone.stopping
    assert flips == 1
    bus.publish("/scan", blocked_ahead(0.56))
    assert not cone.stopping
    cone.close()
    cone.close()


def test_node_in_cone_mode_runs_the_cone_and_still_brakes_when_blind() -> None:
    bus, clock = Bus(), ManualClock()
    node = SafetyNode(bus, build(SafetyParams, {"mode": "cone"}), clock=clock)
    got: list[AckermannDriveStamped] = []
    bus.subscribe(MUX_SAFETY_TOPIC, got.append)
    bus.publish("/scan", blocked_ahead(0.3))
    assert len(got) == 1
    assert node.filter(AckermannDrive(speed=2.0), "teleop").speed == 2.0
    assert values(node.state_message().status[0])["cone_stopping"] == "true"
    clock.now += 200 * MS
    assert node.filter(AckermannDrive(speed=2.0), "teleop").speed == 0.0
    assert node.state.reason == "stale_scan"
    assert isinstance(node.state_message(), DiagnosticArray)


def test_a_scans_returns_are_placed_with_the_pose_at_its_first_beam_not_at_its_arrival() -> None:
    """A UST-10LX's 1081 beams take 18.75 ms; its frame arrives after the last. Placed with the pose
    at arrival, a return was remembered 18.75 ms of driving too far ahead (9 cm at 5 m/s; in a
    full-lock turn a pole ended up 0.28 m from where it was, lockstep)."""
    def nearest_remembered(time_increment: float) -> float:
        bus, clock = Bus(), ManualClock()
        node = SafetyNode(bus, SafetyParams(), clock=clock)  # the laser at base_link
        scan = blocked_ahead(2.0)
        scan.time_increment = time_increment
        bus.publish("/odom", odom_at(0.0, 0.0, 0.0, speed=5.0))  # just now, driving along x
        bus.publish("/scan", scan)
        memory = node.controller.memory
        assert memory is not None and len(memory) > 0
        return float(np.min(memory.points().real))

    ust = 0.025 / 1440  # the UST-10LX's beam time: 1440 steps a turn
    scan = blocked_ahead(2.0)
    scan.time_increment = ust
    assert sweep_ns(scan) == round(1080 * ust * 1e9)  # 18.75 ms
    at_arrival = nearest_remembered(0.0)  # no beam timing: placed at its arrival, as before
    at_first_beam = nearest_remembered(ust)
    # the car was 5 m/s * 18.75 ms = 9.4 cm back when the lidar measured (the memory's cells are
    # 5 cm: the same cell edge moves by one or two cells)
    assert at_arrival - at_first_beam == pytest.approx(5.0 * 0.01875, abs=0.05)
    assert at_first_beam < at_arrival
