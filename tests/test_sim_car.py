"""The kinematic bicycle, the ERPM/servo conversions, footprint collisions and clearance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build
from racecar_hw.sim.car import (
    CLEARANCE_RANGE_M,
    CarParams,
    Collider,
    Pose2D,
    advance,
    footprint,
    speed_from_erpm,
    steering_from_servo,
)
from racecar_hw.sim.obstacles import Box, Circle, polygon_distance
from racecar_hw.sim.occupancy import OccupancyMap, load_shipped_map

P = CarParams()


def test_defaults_match_the_f1tenth_stack() -> None:
    assert (P.speed_to_erpm_gain, P.speed_to_erpm_offset) == (4614.0, 0.0)
    # the stack's offset 0.5304 as the VESC receives it (thousandths): see the test on "straight"
    assert (P.steering_angle_to_servo_gain, P.steering_angle_to_servo_offset) == (-1.2135, 0.530)
    assert (P.wheelbase, P.length, P.width, P.rear_overhang) == (0.25, 0.55, 0.30, 0.10)
    assert P.max_steering_angle == 0.4189
    assert build(CarParams, {"wheelbase": 0.33}).wheelbase == 0.33
    with pytest.raises(ConfigError, match="car.wheelbase"):
        build(CarParams, {"wheelbase": -1.0}, "car")


def test_conversions() -> None:
    assert speed_from_erpm(4614.0 * 2, P) == pytest.approx(2.0)
    assert speed_from_erpm(-4614.0, P) == pytest.approx(-1.0)
    assert steering_from_servo(0.530, P) == 0.0
    # a servo below the centre steers left (the gain is negative)
    assert steering_from_servo(0.530 - 1.2135 * 0.2, P) == pytest.approx(0.2)
    assert steering_from_servo(0.0, P) == P.max_steering_angle
    assert steering_from_servo(1.0, P) == pytest.approx((1.0 - 0.530) / -1.2135)  # within the limit
    assert speed_from_erpm(math.nan, P) == 0.0 and steering_from_servo(math.inf, P) == 0.0


def test_straight_line_forward_and_reverse() -> None:
    pose = Pose2D(1.0, 2.0, math.pi / 6)
    ahead = advance(pose, 2.0, 0.0, 1.5, P.wheelbase)
    assert ahead.x == pytest.approx(1.0 + 3.0 * math.cos(math.pi / 6))
    assert ahead.y == pytest.approx(2.0 + 3.0 * math.sin(math.pi / 6))
    assert ahead.yaw == pytest.approx(math.pi / 6)
    back = advance(ahead, -2.0, 0.0, 1.5, P.wheelbase)
    assert back == pytest.approx(pose)


@given(st.floats(0.05, 0.4189), st.floats(-5.0, 5.0).filter(lambda v: abs(v) > 0.1))
def test_constant_steering_drives_a_circle_of_radius_wheelbase_over_tan(delta: float, speed: float) -> None:
    radius = P.wheelbase / math.tan(delta)
    centre = (0.0, radius)  # turning left from the origin heading +x
    pose = Pose2D(0.0, 0.0, 0.0)
    for _ in range(37):
        pose = advance(pose, speed, delta, 0.013, P.wheelbase)
        assert math.hypot(pose.x - centre[0], pose.y - centre[1]) == pytest.approx(radius, rel=1e-9)
    # the heading stays tangent: yaw grew by distance / radius
    travelled = speed * 37 * 0.013
    expected = (travelled / radius + math.pi) % (2 * math.pi) - math.pi
    assert math.remainder(pose.yaw - expected, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_one_step_equals_many_steps() -> None:
    pose = Pose2D(0.5, -0.5, 1.0)
    one = advance(pose, 3.0, -0.3, 0.8, P.wheelbase)
    many = pose
    for _ in range(80):
        many = advance(many, 3.0, -0.3, 0.01, P.wheelbase)
    assert one == pytest.approx(many, abs=1e-9)


def test_footprint_corners() -> None:
    corners = footprint((1.0, 1.0, math.pi / 2), P)
    xs, ys = sorted(corners[:, 0]), sorted(corners[:, 1])
    assert xs[0] == pytest.approx(0.85) and xs[-1] == pytest.approx(1.15)
    assert ys[0] == pytest.approx(0.9) and ys[-1] == pytest.approx(1.45)


def wall_map() -> OccupancyMap:
    """Free space with a wall whose face is at x = 3.0 m."""
    occ = np.zeros((80, 100), dtype=bool)
    occ[:, 60:64] = True
    return OccupancyMap.from_occupied(occ, 0.05, image_order=False)


def test_clearance_to_a_wall() -> None:
    col = Collider(wall_map(), P)
    # the front bumper is 0.45 m ahead of the rear axle
    assert col.clearance((2.0, 2.0, 0.0)) == pytest.approx(0.55, abs=1e-9)
    assert col.clearance((2.5, 2.0, 0.0)) == pytest.approx(0.05, abs=1e-9)
    assert col.collides((2.56, 2.0, 0.0))
    assert not col.collides((2.54, 2.0, 0.0))
    # facing away, the rear overhang (0.10 m) is what comes close
    assert col.clearance((2.7, 2.0, math.pi)) == pytest.approx(0.2, abs=1e-9)
    # sideways the half-width counts
    assert col.clearance((2.5, 2.0, math.pi / 2)) == pytest.approx(0.35, abs=1e-9)
    assert col.clearance((0.5, 2.0, math.pi)) == CLEARANCE_RANGE_M


def test_corridor_centre_clearance_is_0_6_m() -> None:
    col = Collider(load_shipped_map("corridor"), P)
    for x in np.linspace(0.0, 20.0, 9):
        assert col.clearance((x, 0.0, 0.0)) == pytest.approx(0.6, abs=1e-9)


def test_clearance_asked_again_answers_as_measuring_again() -> None:
    """A car at rest is asked its clearance at every step: the answer (and the anchor the map bound
    works from) is the same as measuring each time, whatever the running minimum and obstacles."""
    pole = Circle(2.2, 2.4, 0.1)
    remembered, measured = Collider(wall_map(), P), Collider(wall_map(), P)
    searches = {"remembered": 0, "measured": 0}
    for name, collider in (("remembered", remembered), ("measured", measured)):
        search = collider._map_clearance

        def counted(*args, name=name, search=search):  # noqa: ANN002, ANN202
            searches[name] += 1
            return search(*args)

        collider._map_clearance = counted  # type: ignore[method-assign]
    least = math.inf
    poses = [(2.0, 2.0, 0.0)] * 4 + [(2.1, 2.0, 0.1)] * 3 + [(2.0, 2.0, 0.0)] * 3 + [(2.3, 1.9, 0.2)] * 2
    for k, pose in enumerate(poses):
        shapes = [pole] if k % 5 else []
        for exact_below in (least, least, math.inf) if k % 3 == 0 else (least, least):
            measured._last = None  # (measures every time)
            got = remembered.clearance(pose, shapes, exact_below=exact_below)
            assert got == measured.clearance(pose, shapes, exact_below=exact_below)
            assert remembered._anchor is not None and measured._anchor is not None
            assert np.array_equal(remembered._anchor[0], measured._anchor[0])
            assert remembered._anchor[1] == measured._anchor[1]
            least = min(least, got)
    assert searches["remembered"] < searches["measured"]


def test_obstacles() -> None:
    col = Collider(wall_map(), P)
    pole = Circle(1.5, 2.0, 0.1)  # near edge at x = 1.4; the bumper of a car at x = 0.5 is at 0.95
    assert col.clearance((0.5, 2.0, 0.0), [pole]) == pytest.approx(0.45, abs=1e-9)
    assert col.collides((1.0, 2.0, 0.0), [pole])
    box = Box(1.5, 2.5, 0.2, 0.2)
    assert box.distance_to(footprint((0.5, 2.0, 0.0), P)) == pytest.approx(
        math.hypot(1.4 - 0.95, 2.4 - 2.15))
    assert col.collides((1.3, 2.35, 0.0), [box])
    assert polygon_distance(box.corners(), box.corners()) == 0.0


def test_obstacle_ray_ranges() -> None:
    angles = np.array([0.0, math.pi, 0.09])
    c, s = np.cos(angles), np.sin(angles)
    r = Circle(3.0, 0.0, 0.5).ray_ranges(0.0, 0.0, c, s)
    assert r[0] == pytest.approx(2.5) and math.isinf(r[1])
    off = 3.0 * math.sin(0.09)
    assert r[2] == pytest.approx(3.0 * math.cos(0.09) - math.sqrt(0.25 - off * off))
    b = Box(3.0, 0.0, 1.0, 2.0, yaw=math.pi / 2).ray_ranges(0.0, 0.0, c, s)
    assert b[0] == pytest.approx(2.0) and math.isinf(b[1])
    assert b[2] == pytest.approx(2.0 / math.cos(0.09))
    inside = Box(0.0, 0.0, 1.0, 1.0).ray_ranges(0.0, 0.0, c, s)
    assert np.all(inside == 0.0)


def test_the_daemon_and_the_simulated_car_agree_on_straight() -> None:
    """The servo position the daemon sends for steering 0 steers the simulated car straight: the
    shipped offset 0.5304 reaches the VESC as 0.530 (thousandths), and a car straight at 0.5304
    drifted 0.27 m over 20 m."""
    from racecar_hw.base.messages import AckermannDrive
    from racecar_hw.config import load_config, shipped_config
    from racecar_hw.sim.car import CarParams, steering_from_servo
    from racecar_hw.sim.loopback import Loopback
    from vesc.ackermann import AckermannConversion
    from vesc.codec import Role, SetServoPosition, VescCodec, servo_on_wire
    from vesc.params import VescParams

    for name in ("sim", "car"):
        config = load_config(shipped_config(name))
        sent = AckermannConversion.from_params(config.vesc).to_vesc(AckermannDrive()).servo
        device = VescCodec(Role.DEVICE)  # the fake VESC's end of the serial line
        device.receive_data(VescCodec(Role.HOST).send(SetServoPosition(sent)))
        (packet,) = device.events()
        received = packet.position
        assert received == servo_on_wire(sent) == 0.530
        car = Loopback._car_params(config)
        assert steering_from_servo(received, car) == 0.0
    assert CarParams().steering_angle_to_servo_offset == servo_on_wire(
        VescParams().steering_angle_to_servo_offset)


def test_the_simulated_car_is_wired_as_the_config_says_unless_the_scenario_says_otherwise():
    """A config with ``invert_motor`` and ``invert_servo`` describes a car whose motor is wired
    backwards and whose servo is mirrored: the simulated car is that car (it once ignored both flags,
    so such a config drove the simulated car backwards and steered it the wrong way), so a command
    drives it as the config means; the scenario's ``car`` can say the flags are wrong for it."""
    from racecar_hw.base.messages import AckermannDrive
    from racecar_hw.config import load_config, shipped_config
    from racecar_hw.sim.car import speed_from_erpm, steering_from_servo
    from racecar_hw.sim.rig import car_params
    from racecar_hw.sim.scenario import CarSpec
    from vesc.ackermann import AckermannConversion

    config = load_config(shipped_config("sim"), ["vesc.invert_motor=true", "vesc.invert_servo=true"])
    sent = AckermannConversion.from_params(config.vesc).to_vesc(AckermannDrive(speed=1.0, steering_angle=0.1))
    assert sent.erpm < 0 and sent.servo > config.vesc.steering_angle_to_servo_offset  # mirrored on the wire
    car = car_params(config)
    assert speed_from_erpm(sent.erpm, car) == pytest.approx(1.0)
    assert steering_from_servo(sent.servo, car) == pytest.approx(0.1, abs=1e-3)  # (the wire's thousandths)
    wrong = car_params(config, CarSpec(invert_motor=False, invert_servo=False))
    assert speed_from_erpm(sent.erpm, wrong) == pytest.approx(-1.0)
    assert steering_from_servo(sent.servo, wrong) == pytest.approx(-0.1, abs=1e-3)


def _clearance_over_every_cell(occ_map: OccupancyMap, pose: tuple[float, float, float]) -> float:
    """The map gap the collider measures, over every occupied cell of the map (no window)."""
    res = occ_map.resolution
    gx, gy = (float(v) for v in occ_map.world_to_grid_frame(pose[0], pose[1]))
    jj, ii = np.nonzero(occ_map.occupied)
    if jj.size == 0:
        return math.inf
    cx, cy = ii + 0.5 - gx, jj + 0.5 - gy
    yaw = pose[2] - occ_map.origin[2]
    c, s = math.cos(yaw), math.sin(yaw)
    lx, ly = c * cx + s * cy, -s * cx + c * cy
    dx = np.maximum(np.maximum(-P.rear_overhang / res - lx, lx - (P.length - P.rear_overhang) / res), 0)
    dy = np.maximum(np.abs(ly) - P.width / 2 / res, 0)
    return max(float(np.sqrt(np.min(dx * dx + dy * dy))) - 0.5, 0.0) * res


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 6.0), st.floats(0.0, 4.0), st.floats(-math.pi, math.pi),
       st.sampled_from([0.0, 0.002, 0.02, 0.2]))
def test_the_clearance_window_finds_what_a_search_of_the_whole_map_finds(seed, x, y, yaw, density) -> None:
    occ = np.random.default_rng(seed).random((80, 120)) < density
    occ_map = OccupancyMap.from_occupied(occ, 0.05, image_order=False)
    everywhere = min(_clearance_over_every_cell(occ_map, (x, y, yaw)), CLEARANCE_RANGE_M)
    assert Collider(occ_map, P).clearance((x, y, yaw)) == everywhere
