"""The world: driving, collisions, obstacles, lidar range sources, real-time stepping."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from conftest import wait_for

from racecar_hw.base.clock import monotonic_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.runtime.devicethread import DeviceThread
from racecar_hw.sim.car import CarParams
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.world import World

P = CarParams()
ROOM = load_shipped_map("room")
CORRIDOR = load_shipped_map("corridor")


class Motor:
    """Stands in for the fake VESC's thread-safe ``erpm``/``servo`` and its stall flag."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._erpm = 0.0
        self._servo = P.steering_angle_to_servo_offset
        self.stalls = 0

    def drive(self, speed: float, steering: float = 0.0) -> None:
        with self._lock:
            self._erpm = P.speed_to_erpm_gain * speed + P.speed_to_erpm_offset
            self._servo = P.steering_angle_to_servo_gain * steering + P.steering_angle_to_servo_offset

    @property
    def erpm(self) -> float:
        with self._lock:
            return self._erpm

    @property
    def servo(self) -> float:
        with self._lock:
            return self._servo

    def stall(self) -> None:
        with self._lock:
            self.stalls += 1
            self._erpm = 0.0


def make_world(occ_map=ROOM, motor: Motor | None = None, **kw) -> tuple[World, Motor]:  # noqa: ANN001
    motor = motor or Motor()
    world = World(occ_map, P, (0.0, 0.0, 0.0), lambda: motor.erpm, lambda: motor.servo,
                  on_collision=motor.stall, **kw)
    return world, motor


def drive(world: World, seconds: float, dt: float = 0.005) -> None:
    for _ in range(round(seconds / dt)):
        world.step(dt)


def test_driving_into_a_wall_stops_the_car_and_stalls_the_motor() -> None:
    world, motor = make_world()
    motor.drive(4.0)
    drive(world, 3.0)  # the far wall is 8 m ahead: contact after 7.55 m, 1.9 s
    assert world.collided
    assert motor.stalls == 1
    assert world.speed == 0.0
    x, y, yaw = world.pose
    assert x + 0.45 == pytest.approx(8.0, abs=0.03) and y == pytest.approx(0.0) and yaw == 0.0
    assert world.min_clearance == 0.0
    [hit] = world.collisions
    assert hit.x == pytest.approx(8.0, abs=0.03) and hit.t == pytest.approx(7.55 / 4.0, abs=0.02)
    # it stays put even though the command still says 4 m/s
    motor.drive(4.0)
    drive(world, 0.5)
    assert world.pose.x == x and world.speed == 0.0 and motor.stalls == 1
    assert world.distance_travelled == pytest.approx(x, abs=1e-6)


def test_corridor_centre_run_is_collision_free() -> None:
    world, motor = make_world(CORRIDOR)
    motor.drive(4.0)
    drive(world, 6.0)
    assert not world.collided
    assert world.pose.x == pytest.approx(24.0, abs=0.01)
    assert world.min_clearance == pytest.approx(0.6, abs=1e-6)
    assert world.distance_travelled == pytest.approx(24.0, abs=0.01)
    t = [s[0] for s in world.trajectory]
    assert t[0] == 0.0 and t[-1] == pytest.approx(6.0) and np.all(np.diff(t) > 0)


def test_circle_in_the_room_and_reverse() -> None:
    world, motor = make_world()
    motor.drive(2.0, 0.2)
    radius = P.wheelbase / math.tan(0.2)
    drive(world, 2 * math.pi * radius / 2.0)  # one lap
    x, y, yaw = world.pose
    assert math.hypot(x, y) < 0.02 and not world.collided
    assert max(s[2] for s in world.trajectory) == pytest.approx(2 * radius, abs=0.02)
    motor.drive(-1.0)
    drive(world, 1.0)
    assert world.speed == pytest.approx(-1.0)
    assert world.pose.x == pytest.approx(x - 1.0 * math.cos(yaw), abs=0.01)


def test_obstacle_appearing_ahead() -> None:
    world, motor = make_world()
    motor.drive(2.0)
    drive(world, 0.5)
    ident = world.add_obstacle_ahead(1.5, radius=0.2)
    rng = world.true_ranges(np.array([0.0]))[0]
    # from the laser (0.265 m ahead of the rear axle) to the obstacle: bumper at 0.45 m, then 1.5 m
    assert rng == pytest.approx(0.45 - 0.265 + 1.5, abs=1e-6)
    assert world.clearance() == pytest.approx(1.5, abs=1e-6)
    drive(world, 1.0)
    assert world.collided and motor.stalls == 1
    assert world.collisions[0].t == pytest.approx(0.5 + 0.75, abs=0.02)
    world.remove_obstacle(ident)
    world.reset()
    motor.drive(2.0)
    assert not world.collided and world.pose == (0.0, 0.0, 0.0) and world.sim_time == 0.0
    assert world.trajectory == [(0.0, 0.0, 0.0, 0.0, 0.0)]
    drive(world, 1.0)
    assert not world.collided and world.pose.x == pytest.approx(2.0)


def test_box_obstacle_and_start_pose_checks() -> None:
    world, motor = make_world()
    world.add_obstacle(2.0, 0.3, box=(0.4, 0.4), yaw=0.3)
    motor.drive(1.0)
    drive(world, 2.0)
    assert world.collided
    with pytest.raises(ConfigError, match="start_pose"):
        world.reset((2.0, 0.3, 0.0))
    with pytest.raises(ConfigError, match="start_pose"):
        World(ROOM, P, (7.9, 0.0, 0.0))  # the front bumper in the far wall
    with pytest.raises(ValueError):
        world.add_obstacle(1.0, 1.0)


def test_range_source_geometry_and_noise_statistics() -> None:
    world, _ = make_world(noise_std_m=0.05, seed=7)
    angles = np.linspace(-math.pi / 2, math.pi / 2, 181)
    truth = world.true_ranges(angles)
    # the laser is 0.265 m ahead of the rear axle: the far wall is 8.0 - 0.265 ahead
    assert truth[90] == pytest.approx(8.0 - 0.265, abs=0.01)
    assert truth[0] == pytest.approx(5.0, abs=0.01) and truth[180] == pytest.approx(5.0, abs=0.01)
    source = world.range_source(max_range=10.0)
    errors = np.concatenate([source.ranges(angles, world.time_ns) - truth for _ in range(200)])
    assert abs(errors.mean()) < 0.003  # 36 200 samples: the mean's standard error is 0.0003
    assert errors.std() == pytest.approx(0.05, rel=0.03)
    again = World(ROOM, P, noise_std_m=0.05, seed=7).range_source(max_range=10.0)
    assert np.array_equal(again.ranges(angles, 0), World(ROOM, P, noise_std_m=0.05, seed=7)
                          .range_source(max_range=10.0).ranges(angles, 0))
    short = world.range_source(max_range=6.0, noise_std_m=0.0)
    r = short.ranges(angles, world.time_ns)
    assert math.isinf(r[90]) and np.isfinite(r[0])
    assert np.array_equal(r[np.isfinite(r)], truth[np.isfinite(r)])


def test_range_source_sees_the_car_where_it_was_at_the_stamp() -> None:
    world, motor = make_world()
    start_ns = world.time_ns
    motor.drive(2.0)
    drive(world, 1.0)  # now 2 m further on
    source = world.range_source(noise_std_m=0.0)
    ahead = np.array([0.0])
    assert source.ranges(ahead, start_ns)[0] == pytest.approx(8.0 - 0.265, abs=0.01)
    halfway = start_ns + 500_000_000 + 2_500_000  # between two 5 ms steps
    assert world.pose_at(halfway).x == pytest.approx(1.005)
    assert source.ranges(ahead, halfway)[0] == pytest.approx(8.0 - 0.265 - 1.005, abs=0.01)
    # a stamp slightly after the last step is extrapolated at the current speed
    assert world.pose_at(world.time_ns + 20_000_000).x == pytest.approx(2.04)
    sideways = world.range_source(noise_std_m=0.0, laser_pose_in_base=(0.0, 0.0, math.pi / 2))
    assert sideways.ranges(ahead, world.time_ns)[0] == pytest.approx(5.0, abs=0.01)


def test_run_steps_on_real_time_in_the_device_thread(device_thread: DeviceThread) -> None:
    world, motor = make_world(CORRIDOR)
    stalled = threading.Event()
    world.on_collision = stalled.set
    future = device_thread.spawn(world.run(rate_hz=200))
    motor.drive(1.0)
    began = monotonic_ns()
    wait_for(lambda: world.pose.x > 0.5, timeout=20)
    elapsed = (monotonic_ns() - began) / 1e9
    # sim time is real time: half a metre at 1 m/s took at least half a second of wall time
    assert elapsed >= 0.45
    assert world.sim_time >= 0.45
    assert abs(world.time_ns - monotonic_ns()) < 2_000_000_000
    source = world.range_source(noise_std_m=0.0)
    left = source.ranges(np.array([math.pi / 2]), monotonic_ns())[0]
    assert left == pytest.approx(0.75, abs=0.05)
    world.add_obstacle_ahead(0.3, radius=0.1)
    assert stalled.wait(20)
    assert world.collided
    future.cancel()


def test_range_source_tells_when_a_beam_was_measured() -> None:
    # a scan's points are where the lidar saw them from when it measured them (the report places
    # an intervention's point with the car's pose then, not at the scan's arrival)
    world, _ = make_world()
    source = world.range_source(noise_std_m=0.0)
    before = monotonic_ns()
    source.ranges(np.linspace(-1.0, 1.0, 5), 111)  # a sweep
    between = monotonic_ns()
    source.ranges(np.array([2.0, 2.5]), 222)  # a batch of two beams
    after = monotonic_ns()
    assert source.measured_before(0.0, after) == 111  # the latest measurement with that beam
    assert source.measured_before(2.2, after) == 222
    assert source.measured_before(-1.0 - 2 * math.pi, after) == 111  # angles wrap
    assert source.measured_before(2.2, between) is None  # not measured yet then
    assert source.measured_before(0.0, before - 1) is None
    assert source.measured_before(3.0, after) is None  # no beam there
