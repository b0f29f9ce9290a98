"""The safety controller on synthetic scans: closed-form speeds, paths, staleness, hysteresis."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scans import LASER_X, Segment, left_arc, scan_at, square, straight, ust10lx_scan

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDrive, LaserScan
from racecar_hw.base.params import build
from safety.controller import BLIND, SafetyController, planar_transform
from safety.params import SafetyParams

MS = 1_000_000
FRONT = 0.45  # default base_link -> front bumper
LATENCY = 0.025 + 0.01 + 0.02
DECEL = 4.0
MARGIN = 0.25

def closed_form(free: float) -> float:
    """The largest v with v * latency + v^2 / (2 a) <= free - margin, solved with numpy's roots."""
    d = free - MARGIN
    if d <= 0:
        return 0.0
    roots = np.roots([1.0 / (2 * DECEL), LATENCY, -d])
    return float(max(roots.real))


def wall_ahead(x: float) -> list[Segment]:
    return [((x, -5.0), (x, 5.0))]


def corridor(half_width: float = 0.75) -> list[Segment]:
    return [((-2.0, half_width), (30.0, half_width)), ((-2.0, -half_width), (30.0, -half_width))]


def controller(**overrides: object) -> SafetyController:
    return SafetyController(build(SafetyParams, overrides, "safety"))


def drive(speed: float, steering: float = 0.0) -> AckermannDrive:
    return AckermannDrive(steering_angle=steering, speed=speed, acceleration=1.5, jerk=0.5)


@pytest.mark.parametrize("wall_x", [0.6, 0.8, 1.0, 1.5, 3.0, 6.0, 9.0])
def test_wall_ahead_allowed_speed_matches_closed_form(wall_x: float) -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(wall_x)), now_ns=0)
    out, state = c.limit(drive(20.0), "nav", 0.0, now_ns=0)
    free = wall_x - FRONT
    assert state.free_distance == pytest.approx(free, abs=1e-5)
    assert state.allowed_speed == pytest.approx(closed_form(free), abs=1e-4)
    assert out.speed == pytest.approx(closed_form(free), abs=1e-4)
    assert state.intervening and state.reason == "obstacle"
    assert state.obstacle is not None and state.obstacle.x == pytest.approx(wall_x, abs=1e-5)
    assert abs(state.obstacle.y) <= 0.2


def test_nothing_within_lookahead_allows_the_lookahead_speed() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(25.0)), now_ns=0)
    out, state = c.limit(drive(20.0), "nav", 0.0, now_ns=0)
    assert state.free_distance == 10.0 and state.obstacle is None
    assert out.speed == pytest.approx(closed_form(10.0), abs=1e-4)


def test_scan_age_adds_to_the_latency() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(2.0)), now_ns=0)
    _, fresh = c.limit(drive(20.0), "nav", 0.0, now_ns=0)
    _, older = c.limit(drive(20.0), "nav", 0.0, now_ns=50 * MS)
    d = 2.0 - FRONT - MARGIN
    t = LATENCY + 0.05
    assert older.allowed_speed < fresh.allowed_speed
    v = older.allowed_speed
    assert v * t + v * v / (2 * DECEL) == pytest.approx(d, abs=1e-5)


def test_a_slower_lidar_sweep_lengthens_the_latency() -> None:
    c = controller()
    slow = ust10lx_scan(wall_ahead(2.0))
    slow.scan_time = 0.1  # a 10 Hz RPLIDAR
    c.on_scan(slow, now_ns=0)
    v = c.limit(drive(20.0), "nav", 0.0, now_ns=0)[1].allowed_speed
    t = 0.1 + 0.01 + 0.02
    assert v * t + v * v / (2 * DECEL) == pytest.approx(2.0 - FRONT - MARGIN, abs=1e-5)


def test_corridor_walls_beside_the_path_do_not_intervene() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(corridor(0.75)), now_ns=0)
    for steering in (0.0, 0.02, -0.02):
        out, state = c.limit(drive(3.0, steering), "nav", 3.0, now_ns=0)
        assert out.speed == 3.0
        assert not state.intervening and state.reason == "clear"
    assert c.interventions == 0


def test_obstacle_inside_the_turn_only_when_steering_toward_it() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(corridor(2.0) + square(1.0, 0.45)), now_ns=0)
    out, state = c.limit(drive(2.0, 0.3), "nav", 0.0, now_ns=0)
    assert state.intervening and out.speed < 2.0
    assert state.obstacle is not None and state.obstacle.y > 0.3
    for steering in (0.0, -0.3):
        c = controller()
        c.on_scan(ust10lx_scan(corridor(2.0) + square(1.0, 0.45)), now_ns=0)
        out, state = c.limit(drive(2.0, steering), "nav", 0.0, now_ns=0)
        assert out.speed == 2.0 and not state.intervening


def test_no_scan_yet_allows_nothing() -> None:
    c = controller()
    out, state = c.limit(drive(1.0), "nav", 0.0, now_ns=5 * MS)
    assert out.speed == 0.0 and state.reason == "no_scan" and state.allowed_speed == 0.0


def test_stale_scan_allows_nothing() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(corridor()), now_ns=0)
    out, state = c.limit(drive(1.0), "nav", 0.0, now_ns=100 * MS)
    assert out.speed == 1.0 and state.reason == "clear"
    out, state = c.limit(drive(1.0), "nav", 0.0, now_ns=101 * MS)
    assert out.speed == 0.0 and state.reason == "stale_scan" and state.intervening
    out, _ = c.limit(drive(-0.3), "nav", 0.0, now_ns=102 * MS)
    assert out.speed == 0.0
    assert c.interventions == 1 and c.interventions_by_reason == {"stale_scan": 1}


def test_only_reduces_magnitude_and_keeps_sign_steering_and_limits() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(2.0)), now_ns=0)
    slow = drive(0.4, 0.1)
    out, _ = c.limit(slow, "nav", 0.0, now_ns=0)
    assert out == slow
    out, _ = c.limit(drive(9.0, 0.1), "nav", 0.0, now_ns=0)
    assert 0.0 < out.speed < 9.0
    assert (out.steering_angle, out.acceleration, out.jerk) == (0.1, 1.5, 0.5)
    out, _ = c.limit(drive(0.0, -0.2), "nav", 0.0, now_ns=0)
    assert out.speed == 0.0 and out.steering_angle == -0.2


def test_reverse_is_capped_because_the_lidar_cannot_see_behind() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(corridor()), now_ns=0)
    out, state = c.limit(drive(-2.0, 0.2), "nav", 0.0, now_ns=0)
    assert out.speed == -0.5 and out.steering_angle == 0.2
    assert state.reason == "reverse_cap" and state.intervening
    c = controller()
    c.on_scan(ust10lx_scan(corridor()), now_ns=0)
    out, state = c.limit(drive(-0.3), "nav", 0.0, now_ns=0)
    assert out.speed == -0.3 and not state.intervening


def test_reverse_with_a_360_lidar_sees_the_wall_behind() -> None:
    c = controller(reverse_uses_scan=True, reverse_speed_cap_mps=5.0)
    c.on_scan(ust10lx_scan(wall_ahead(-1.0), fov_deg=359.0, n=1000), now_ns=0)
    out, state = c.limit(drive(-5.0), "nav", 0.0, now_ns=0)
    free = 1.0 - 0.10  # the rear bumper is 0.10 m behind base_link
    assert state.free_distance == pytest.approx(free, abs=1e-4)
    assert out.speed == pytest.approx(-closed_form(free), abs=1e-4)
    assert state.reason == "obstacle"


def drive_along(c: SafetyController, poses: list, world: list[Segment], t0_ns: int = 0) -> int:
    """Scans of ``world`` (odom) from each pose at 40 Hz, each folded into the memory as the daemon
    does after the motor write; returns the time of the last scan."""
    now = t0_ns
    for pose in poses:
        now += 25 * MS
        c.on_scan(scan_at(pose, world, stamp_ns=now), now, pose)
        c.remember()
    return now


# a wall 1.2 m ahead of the laser at the start; a U-turn on a 0.6 m circle puts it behind the car
U_TURN_WALL: list[Segment] = [((1.2 + LASER_X, -5.0), (1.2 + LASER_X, 5.0))]


def test_reversing_towards_a_wall_seen_before_the_turn_stops_before_it() -> None:
    c = controller()
    now = drive_along(c, left_arc((0.0, 0.0, 0.0), 0.6, math.pi), U_TURN_WALL)
    end = (0.0, 1.2, math.pi)
    now = drive_along(c, [end] * 2, U_TURN_WALL, now)
    out, state = c.limit(drive(-0.5), "nav", 0.0, now)
    # behind the car: the wall 1.465 m from base_link, the rear bumper 0.10 m behind base_link; a
    # remembered point is its cell's centre, within half a cell diagonal of the return
    free = 1.2 + LASER_X - 0.10
    assert state.obstacle is not None and state.obstacle.source == "memory"
    assert state.free_distance == pytest.approx(free, abs=0.036)
    assert state.reason == "clear" and out.speed == -0.5  # far enough: the crawl cap, not reached
    # backing up until the wall is 0.26 m behind the bumper: now the memory limits
    now = drive_along(c, straight(end, -(free - 0.26), speed=0.5), U_TURN_WALL, now)
    out, state = c.limit(drive(-0.5), "nav", -0.5, now)
    assert state.obstacle is not None and state.obstacle.source == "memory"
    assert state.free_distance == pytest.approx(0.26, abs=0.036)
    assert state.reason == "obstacle" and state.intervening
    assert -0.5 < out.speed <= 0.0
    assert out.speed == pytest.approx(-closed_form(state.free_distance), abs=1e-3)
    # the same drive with the memory off: reverse is only capped, the wall unknown
    blind = controller(memory={"enabled": False})
    drive_along(blind, left_arc((0.0, 0.0, 0.0), 0.6, math.pi) + [end] * 2
                + straight(end, -(free - 0.26), speed=0.5), U_TURN_WALL)
    out, state = blind.limit(drive(-0.5), "nav", -0.5, now)
    assert out.speed == -0.5 and state.reason == "clear" and math.isnan(state.free_distance)


def test_without_odometry_the_memory_stays_out_and_reverse_is_capped_as_before() -> None:
    c = controller()
    drive_along(c, left_arc((0.0, 0.0, 0.0), 0.6, math.pi), U_TURN_WALL)
    assert c.memory is not None and len(c.memory) > 0 and c.memory_active
    scan = scan_at((0.0, 1.2, math.pi), U_TURN_WALL)
    c.on_scan(scan, 10_000 * MS, None)  # odometry lost
    out, state = c.limit(drive(-2.0), "nav", 0.0, 10_000 * MS)
    assert not c.memory_active
    assert out.speed == -0.5 and state.reason == "reverse_cap" and math.isnan(state.free_distance)
    c.remember()
    assert len(c.memory) == 0  # it cannot place anything without a pose: forgotten


def test_reverse_with_nothing_remembered_behind_is_capped_to_the_crawl() -> None:
    c = controller()
    now = drive_along(c, [(0.0, 0.0, 0.0)] * 3, corridor())
    out, state = c.limit(drive(-2.0), "nav", 0.0, now)
    assert c.memory_active
    assert out.speed == -0.5 and state.reason == "reverse_cap" and state.obstacle is None


def test_a_remembered_post_in_the_blind_sector_limits_a_tight_forward_turn() -> None:
    # a post behind and left of the car, on the circle a full-lock left turn drives: the live scan
    # cannot see it (bearing from the laser about 146 degrees), the memory saw it on the way in
    post = square(-0.6, 0.59, 0.05)
    c = controller(min_return_fraction=0.0)  # open space of no return at all: trusted here
    now = drive_along(c, straight((-1.6, 0.0, 0.0), 1.6, speed=1.0), post)
    steering = math.atan(0.25 / 0.6)  # a 0.6 m turn radius
    out, state = c.limit(drive(5.0, steering), "nav", 0.0, now)
    assert state.obstacle is not None and state.obstacle.source == "memory"
    assert state.free_distance < 4.0  # three quarters of the 3.8 m circle, less the body
    sighted = controller(memory={"enabled": False}, min_return_fraction=0.0)
    now = drive_along(sighted, straight((-1.6, 0.0, 0.0), 1.6, speed=1.0), post)
    _, blind = sighted.limit(drive(5.0, steering), "nav", 0.0, now)
    assert blind.free_distance == 10.0 and out.speed < 5.0


def test_the_memory_is_updated_only_when_asked_or_before_the_next_scan() -> None:
    c = controller()
    assert c.memory is not None
    pose = (0.0, 0.0, 0.0)
    c.on_scan(scan_at(pose, U_TURN_WALL), 25 * MS, pose)
    assert c.memory.updates == 0  # the scan's command is decided first
    c.remember()
    c.remember()  # once per scan
    assert c.memory.updates == 1
    c.on_scan(scan_at(pose, U_TURN_WALL), 200 * MS, pose)
    c.on_scan(scan_at(pose, U_TURN_WALL), 225 * MS, pose)  # nobody called remember(): folded in now
    assert c.memory.updates == 2


def test_the_memory_takes_a_scan_in_at_most_once_per_update_period() -> None:
    c = controller()  # update_period_s 0.1: every fourth scan of a 40 Hz lidar
    assert c.memory is not None
    drive_along(c, [(0.0, 0.0, 0.0)] * 8, U_TURN_WALL)
    assert c.memory.updates == 2
    half = controller(memory={"update_period_s": 0.05})
    drive_along(half, [(0.0, 0.0, 0.0)] * 8, U_TURN_WALL)
    assert half.memory is not None and half.memory.updates == 4
    every = controller(memory={"update_period_s": 0.0})
    drive_along(every, [(0.0, 0.0, 0.0)] * 8, U_TURN_WALL)
    assert every.memory is not None and every.memory.updates == 8


def test_interventions_are_recorded_with_their_obstacle() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(1.0)), now_ns=5 * MS)
    c.limit(drive(3.0), "nav", 0.0, now_ns=6 * MS)
    (event,) = c.events
    assert event.t_ns == 6 * MS and event.scan_ns == 5 * MS and event.reason == "obstacle"
    assert event.commanded_speed == 3.0 and event.allowed_speed < 3.0
    assert event.obstacle is not None and event.obstacle.source == "scan"
    assert event.obstacle.x == pytest.approx(1.0, abs=1e-5)


def test_an_intervention_for_a_late_scan_that_becomes_an_obstacle_stop_gets_a_second_entry() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(9.0)), now_ns=0)
    c.limit(drive(2.0), "nav", 2.0, now_ns=200 * MS)  # the scan is 0.2 s old: stale_scan
    # a fresh scan with the path free far enough for 2 m/s: held by the hysteresis, no obstacle stop
    c.on_scan(ust10lx_scan(wall_ahead(9.0)), now_ns=205 * MS)
    _, state = c.limit(drive(2.0), "nav", 2.0, now_ns=206 * MS)
    assert state.intervening and len(c.events) == 1
    # a wall 1 m ahead now cuts the command: from here on it is a stop for the wall
    c.on_scan(ust10lx_scan(wall_ahead(1.0)), now_ns=210 * MS)
    _, state = c.limit(drive(2.0), "nav", 2.0, now_ns=211 * MS)
    assert state.reason == "obstacle" and state.intervening
    # the reason flipping back and forth on a loaded machine adds nothing more
    c.limit(drive(2.0), "nav", 1.5, now_ns=400 * MS)  # stale again
    c.on_scan(ust10lx_scan(wall_ahead(1.0)), now_ns=405 * MS)
    c.limit(drive(2.0), "nav", 1.0, now_ns=406 * MS)
    start, stop = c.events
    assert start.reason == "stale_scan" and start.obstacle is None and not start.continues
    assert start.t_ns == 200 * MS and start.end_ns == 211 * MS
    assert stop.continues and stop.reason == "obstacle" and stop.t_ns == 211 * MS
    assert stop.end_ns is None and stop.scan_ns == 210 * MS and stop.allowed_speed < 2.0
    assert stop.obstacle is not None and stop.obstacle.source == "scan"
    assert stop.obstacle.x == pytest.approx(1.0, abs=1e-5)
    # still one intervention, counted by what started it
    assert c.interventions == 1 and c.interventions_by_reason == {"stale_scan": 1}
    # when it ends, the entry that continues it ends
    c.on_scan(ust10lx_scan(wall_ahead(9.0)), now_ns=500 * MS)
    c.limit(drive(2.0), "nav", 0.0, now_ns=500 * MS)
    c.on_scan(ust10lx_scan(wall_ahead(9.0)), now_ns=900 * MS)
    _, state = c.limit(drive(2.0), "nav", 0.0, now_ns=900 * MS)
    assert not state.intervening and c.events[-1].end_ns == 900 * MS and len(c.events) == 2


def test_an_intervention_that_starts_for_an_obstacle_has_one_entry() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(1.0)), now_ns=0)
    c.limit(drive(2.0), "nav", 0.0, now_ns=1 * MS)
    c.limit(drive(2.0), "nav", 0.0, now_ns=200 * MS)  # stale
    c.on_scan(ust10lx_scan(wall_ahead(0.9)), now_ns=205 * MS)
    c.limit(drive(2.0), "nav", 0.0, now_ns=206 * MS)  # an obstacle again
    (event,) = c.events
    assert event.reason == "obstacle" and not event.continues and event.end_ns is None


def test_teleop_exempt_only_when_configured() -> None:
    scan = ust10lx_scan(wall_ahead(1.0))
    strict = controller()
    strict.on_scan(scan, now_ns=0)
    out, _ = strict.limit(drive(3.0), "teleop", 0.0, now_ns=0)
    assert out.speed < 3.0
    lax = controller(exempt_teleop=True, exempt_sources=["bag_follower"])
    lax.on_scan(scan, now_ns=0)
    for source in ("teleop", "bag_follower"):
        out, state = lax.limit(drive(3.0), source, 0.0, now_ns=0)
        assert out.speed == 3.0 and state.reason == "exempt" and not state.intervening
    out, state = lax.limit(drive(3.0), "nav", 0.0, now_ns=0)
    assert out.speed < 3.0 and state.intervening


def test_mode_off_passes_everything() -> None:
    c = controller(mode="off")
    out, state = c.limit(drive(7.0), "nav", 0.0, now_ns=0)
    assert out.speed == 7.0 and state.reason == "off"


def noisy_run(c: SafetyController, base_wall: float, speed: float, ticks: int = 400) -> int:
    """Scans at 40 Hz with +-2 cm range noise and occasional dropouts; count intervention flips."""
    rng = np.random.default_rng(3)
    clean = ust10lx_scan(wall_ahead(base_wall))
    flips, last = 0, False
    for k in range(ticks):
        now = k * 25 * MS
        scan = ust10lx_scan(wall_ahead(base_wall))
        noisy = clean.ranges + rng.uniform(-0.02, 0.02, clean.ranges.size).astype(np.float32)
        if k % 17 == 0:  # a sweep where the wall's returns drop out
            noisy = np.where(np.abs(scan.angles()) < 0.6, np.inf, noisy).astype(np.float32)
        scan.ranges = noisy
        c.on_scan(scan, now)
        out, state = c.limit(drive(speed), "nav", speed, now)
        assert out.speed <= speed
        flips += state.intervening != last
        last = state.intervening
    return flips


def test_hysteresis_prevents_chatter_on_noisy_ranges() -> None:
    wall = 2.0
    threshold_speed = closed_form(wall - FRONT)
    without = noisy_run(controller(release_margin_mps=0.0, release_hold_s=0.0), wall, threshold_speed)
    with_hysteresis = noisy_run(controller(), wall, threshold_speed)
    assert without > 20, "the scenario must actually sit on the threshold"
    assert with_hysteresis <= 1


def test_release_needs_margin_held_for_the_hold_time() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(1.2)), now_ns=0)
    out, state = c.limit(drive(2.0), "nav", 0.0, now_ns=0)
    capped = out.speed
    assert state.intervening and capped < 2.0
    # the obstacle is gone: the cap holds for release_hold_s, then the command passes
    for t in range(10, 300, 10):
        c.on_scan(ust10lx_scan(corridor()), now_ns=t * MS)
        out, state = c.limit(drive(2.0), "nav", 0.0, now_ns=t * MS)
        assert state.intervening and out.speed == pytest.approx(capped)
    c.on_scan(ust10lx_scan(corridor()), now_ns=310 * MS)
    out, state = c.limit(drive(2.0), "nav", 0.0, now_ns=310 * MS)
    assert not state.intervening and out.speed == 2.0 and state.reason == "clear"
    assert c.interventions == 1


def test_measured_speed_above_allowed_intervenes_immediately() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(1.5)), now_ns=0)
    allowed = closed_form(1.5 - FRONT)
    # commanded speed is below the allowed one, but the car is already going much faster
    out, state = c.limit(drive(allowed - 0.2), "nav", allowed + 1.0, now_ns=0)
    assert state.intervening and c.interventions == 1
    assert out.speed == pytest.approx(allowed - 0.2)
    # while a release is pending, a fast measured speed cuts the command at once
    c2 = controller()
    c2.on_scan(ust10lx_scan(wall_ahead(1.5)), now_ns=0)
    c2.limit(drive(3.0), "nav", 0.0, now_ns=0)
    c2.on_scan(ust10lx_scan(wall_ahead(4.0)), now_ns=10 * MS)
    wide = c2.limit(drive(1.0), "nav", 0.0, now_ns=10 * MS)[1].allowed_speed
    c2.on_scan(ust10lx_scan(wall_ahead(1.5)), now_ns=20 * MS)
    out, state = c2.limit(drive(3.0), "nav", 3.0, now_ns=20 * MS)
    assert state.intervening and out.speed == pytest.approx(state.allowed_speed) and wide > allowed


def test_measured_speed_against_the_command_direction_is_no_reason_to_cut() -> None:
    c = controller()
    c.on_scan(ust10lx_scan(wall_ahead(1.5)), now_ns=0)
    out, state = c.limit(drive(0.3), "nav", -3.0, now_ns=0)
    assert out.speed == 0.3 and not state.intervening


def test_nan_inf_and_short_beams_are_ignored() -> None:
    clean = ust10lx_scan(wall_ahead(2.0))
    dirty = ust10lx_scan(wall_ahead(2.0))
    r = dirty.ranges.copy()
    r[::7] = np.nan
    r[1::11] = np.inf
    r[2::13] = -np.inf
    r[3::29] = 0.01  # below range_min: dust on the window
    dirty.ranges = r
    a, b = controller(), controller()
    a.on_scan(clean, 0)
    b.on_scan(dirty, 0)
    va = a.limit(drive(9.0), "nav", 0.0, 0)[1].allowed_speed
    vb = b.limit(drive(9.0), "nav", 0.0, 0)[1].allowed_speed
    assert vb == pytest.approx(va, abs=1e-4)


@pytest.mark.parametrize("no_return", [np.inf, 45.0])  # none, or past range_max (30 m)
def test_a_scan_without_a_return_is_a_blind_lidar_not_open_space(no_return: float) -> None:
    """An RPLIDAR blinded or failing reports every beam as no return (distance 0, published inf):
    the car cannot tell that from open space, and drove on at full speed. Refused as a bad scan
    below safety.min_return_fraction (1 % of the beams); a sparse view above it still drives, and
    0 trusts even an empty view."""
    empty = ust10lx_scan([])
    empty.ranges = np.full(empty.ranges.size, no_return, dtype=np.float32)
    c = controller()
    c.on_scan(empty, 0)
    out, state = c.limit(drive(2.0), "nav", 0.0, 0)
    assert out.speed == 0.0 and state.reason == "bad_scan"
    sparse = ust10lx_scan([])
    sparse.ranges = np.full(sparse.ranges.size, np.inf, dtype=np.float32)
    sparse.ranges[:11] = 25.0  # a far wall on 11 of 1081 beams, behind the car's right
    c.on_scan(sparse, 25 * MS)
    assert c.limit(drive(2.0), "nav", 0.0, 25 * MS)[1].allowed_speed > 2.0
    trusting = controller(min_return_fraction=0.0)
    trusting.on_scan(empty, 0)
    assert trusting.limit(drive(2.0), "nav", 0.0, 0)[0].speed == 2.0


def test_a_blind_lidar_brakes_and_centres_the_steering() -> None:
    """A stale scan (the lidar stalled or unplugged) stopped the car with its steering held at the
    command (0.15 rad on the VESC's servo for seconds): the fail-safe rule is brake and centre.
    ``centre_when_blind: false`` keeps the commanded steering while the car brakes."""
    for centre, expected in ((True, 0.0), (False, 0.15)):
        c = controller(centre_when_blind=centre)
        c.on_scan(ust10lx_scan(corridor()), 0)
        assert c.limit(drive(1.0, 0.15), "nav", 0.0, 0)[0] == drive(1.0, 0.15)
        out, state = c.limit(drive(1.0, 0.15), "nav", 1.0, 150 * MS)  # older than scan_timeout_s
        assert state.reason == "stale_scan" and out.speed == 0.0 and out.steering_angle == expected
    fresh = controller()
    out, state = fresh.limit(drive(1.0, -0.2), "teleop", 0.0, 0)  # no scan yet
    assert state.reason == "no_scan" and (out.speed, out.steering_angle) == (0.0, 0.0)


def test_mostly_invalid_scan_is_refused() -> None:
    scan = ust10lx_scan(corridor())
    scan.ranges = np.where(np.arange(scan.ranges.size) % 4 == 0, scan.ranges, np.nan).astype(np.float32)
    c = controller()
    c.on_scan(scan, 0)
    out, state = c.limit(drive(1.0), "nav", 0.0, 0)
    assert out.speed == 0.0 and state.reason == "bad_scan"
    covered = ust10lx_scan(corridor())
    covered.ranges = np.full(covered.ranges.size, 0.02, dtype=np.float32)  # a hand over the lidar
    c.on_scan(covered, 0)
    assert c.limit(drive(1.0), "nav", 0.0, 0)[0].speed == 0.0


def test_scan_with_broken_geometry_is_refused_or_read_safely() -> None:
    c = controller()
    no_angles = ust10lx_scan(wall_ahead(1.0))
    no_angles.angle_increment = math.nan
    c.on_scan(no_angles, 0)
    assert c.limit(drive(1.0), "nav", 0.0, 0)[1].reason == "bad_scan"
    no_max = ust10lx_scan(wall_ahead(1.0))
    no_max.range_max = math.nan  # the wall must still be seen
    c.on_scan(no_max, 0)
    out, state = c.limit(drive(3.0), "nav", 0.0, 0)
    assert state.free_distance == pytest.approx(1.0 - FRONT, abs=1e-5) and out.speed < 3.0


def test_interventions_are_counted_once_per_start(caplog: pytest.LogCaptureFixture) -> None:
    c = controller()
    caplog.set_level("WARNING", logger="safety.controller")
    c.on_scan(ust10lx_scan(wall_ahead(1.0)), now_ns=0)
    for t in range(0, 50, 5):
        c.limit(drive(3.0), "nav", 0.0, now_ns=t * MS)
    assert c.interventions == 1
    assert len([r for r in caplog.records if "intervening" in r.getMessage()]) == 1


def test_an_absurd_commanded_speed_is_logged_in_a_short_line(caplog: pytest.LogCaptureFixture) -> None:
    """1e300 m/s from a client (clamped before the wire) once wrote a 509-character line."""
    c = controller()
    caplog.set_level("WARNING", logger="safety.controller")
    c.on_scan(ust10lx_scan(wall_ahead(1.0)), now_ns=0)
    c.limit(drive(1e300), "nav", 0.0, now_ns=0)
    (line,) = [r.getMessage() for r in caplog.records if "intervening" in r.getMessage()]
    assert "commanded 1e+300 m/s" in line and len(line) < 200


def test_laser_transform_forms_agree_and_upside_down_lidar_mirrors() -> None:
    yaw = 0.3
    m = np.eye(4)
    m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    m[:2, 3] = [0.2, 0.05]
    np.testing.assert_allclose(planar_transform(m), planar_transform((0.2, 0.05, yaw)))
    # upside down (roll pi): the laser's +angles point to base_link's right
    flipped = np.diag([1.0, -1.0, -1.0, 1.0])
    flipped[0, 3] = LASER_X
    scan = ust10lx_scan(square(1.0, -0.45))  # the scan is cast as if upright, so the box ends up left
    verdicts = {}
    for steering in (0.3, -0.3):
        c = SafetyController(SafetyParams(), flipped)
        c.on_scan(scan, 0)
        verdicts[steering] = c.limit(drive(2.0, steering), "nav", 0.0, 0)[1].intervening
    assert verdicts == {0.3: True, -0.3: False}
    with pytest.raises(ValueError):
        planar_transform(np.eye(3))


def test_params_validate_footprint() -> None:
    with pytest.raises(ConfigError, match="safety.footprint"):
        build(SafetyParams, {"footprint": {"length_m": 0.3, "rear_overhang_m": 0.3}}, "safety")
    with pytest.raises(ConfigError, match="safety.mode"):
        build(SafetyParams, {"mode": "panic"}, "safety")


finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=32)
range_values = st.one_of(st.floats(0.0, 40.0, width=32), st.just(math.inf), st.just(math.nan),
                         st.just(-math.inf))


@pytest.mark.filterwarnings("error::RuntimeWarning")
@settings(max_examples=300, deadline=None)
@given(ranges=st.lists(range_values, min_size=0, max_size=300),
       angle_min=st.floats(-4.0, 0.0), span=st.floats(0.0, 6.3),
       range_min=st.floats(0.0, 1.0), range_max=st.floats(0.0, 40.0),
       speed=finite, steering=st.floats(-1.6, 1.6), measured=finite,
       age_ms=st.integers(-5, 200), reverse_uses_scan=st.booleans(),
       source=st.sampled_from(["nav", "teleop"]))
def test_property_output_never_exceeds_input(ranges: list[float], angle_min: float, span: float,
                                             range_min: float, range_max: float, speed: float,
                                             steering: float, measured: float, age_ms: int,
                                             reverse_uses_scan: bool, source: str) -> None:
    c = controller(reverse_uses_scan=reverse_uses_scan)
    n = len(ranges)
    scan = LaserScan(angle_min=angle_min, angle_max=angle_min + span,
                     angle_increment=span / max(n - 1, 1), range_min=range_min, range_max=range_max,
                     ranges=np.array(ranges, dtype=np.float32))
    c.on_scan(scan, now_ns=1000 * MS)
    command = drive(speed, steering)
    out, state = c.limit(command, source, measured, now_ns=(1000 + age_ms) * MS)
    assert math.isfinite(out.speed)
    assert abs(out.speed) <= abs(speed)
    assert out.speed == 0.0 or math.copysign(1.0, out.speed) == math.copysign(1.0, speed)
    if state.reason in BLIND:  # nothing to trust: a stop with the steering centred
        assert out.speed == 0.0 and out.steering_angle == 0.0
    else:
        assert out.steering_angle == steering
    assert state.allowed_speed >= 0.0 and not math.isnan(state.allowed_speed)


coordinate = st.floats(-50.0, 50.0, allow_nan=False)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # a numeric warning is a bug on this path
@settings(max_examples=150, deadline=None)
@given(scans=st.lists(st.tuples(st.lists(range_values, min_size=0, max_size=200),
                                st.tuples(coordinate, coordinate, st.floats(-7.0, 7.0))),
                      min_size=1, max_size=6),
       angle_min=st.floats(-4.0, 0.0), span=st.floats(0.0, 6.3), speed=finite,
       steering=st.floats(-1.6, 1.6))
# beams a subnormal angle apart (drawn once in CI): the memory's beam indices overflowed
@example(scans=[([1.0] * 3, (0.0, 0.0, 0.0)), ([5.0] * 3, (0.0, 0.0, 0.0))], angle_min=-1.0,
         span=1e-323, speed=1.0, steering=0.0)
def test_property_with_the_memory_output_never_exceeds_input(scans: list, angle_min: float,
                                                             span: float, speed: float,
                                                             steering: float) -> None:
    # any scans at any poses (jumps, turns, empty and broken scans) folded into the memory
    c = controller(memory={"update_period_s": 0.0})
    now = 1000 * MS
    for ranges, pose in scans:
        n = len(ranges)
        scan = LaserScan(angle_min=angle_min, angle_max=angle_min + span,
                         angle_increment=span / max(n - 1, 1), range_min=0.05, range_max=30.0,
                         ranges=np.array(ranges, dtype=np.float32))
        now += 25 * MS
        c.on_scan(scan, now, pose)
        out, state = c.limit(drive(speed, steering), "nav", 0.0, now)
        c.remember()
        assert math.isfinite(out.speed) and abs(out.speed) <= abs(speed)
        assert out.speed == 0.0 or math.copysign(1.0, out.speed) == math.copysign(1.0, speed)
        assert state.allowed_speed >= 0.0 and not math.isnan(state.allowed_speed)
    assert c.memory is not None and len(c.memory) <= c.memory.cells_per_side ** 2


def test_a_scan_whose_beams_are_not_spread_out_brakes_and_clears_nothing_remembered() -> None:
    # beams 0 or a subnormal angle apart all lie along one ray: the rest of the field is unknown,
    # not free, so the scan is refused (bad_scan, braking) and the memory keeps what it saw
    c = controller(memory={"update_period_s": 0.0})
    pose = (0.0, 0.0, 0.0)
    now = 1000 * MS
    c.on_scan(ust10lx_scan(wall_ahead(1.5)), now, pose)
    c.remember()
    assert c.memory is not None
    remembered = len(c.memory)
    assert remembered > 0
    for increment in (0.0, 1e-323, 1e-300, 1e-7, 7.0):
        now += 25 * MS
        broken = LaserScan(angle_min=0.0, angle_max=1080 * increment, angle_increment=increment,
                           range_min=0.06, range_max=30.0, ranges=np.full(1081, 9.0, dtype=np.float32))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            c.on_scan(broken, now, pose)
            out, state = c.limit(drive(2.0), "nav", 0.0, now)
            c.remember()
        assert out.speed == 0.0 and state.reason == "bad_scan", increment
        assert len(c.memory) == remembered
    # one beam has no spacing to get wrong: a single-beam scan is judged as before
    c = controller()
    c.on_scan(LaserScan(angle_min=0.0, angle_max=0.0, angle_increment=0.0, range_min=0.06,
                        range_max=30.0, ranges=np.full(1, 9.0, dtype=np.float32)), now_ns=0)
    assert c.limit(drive(2.0), "nav", 0.0, now_ns=0)[1].reason == "clear"


def test_a_non_finite_pose_counts_as_no_odometry() -> None:
    c = controller(memory={"update_period_s": 0.0})
    c.on_scan(ust10lx_scan(wall_ahead(1.5)), 1000 * MS, (0.0, 0.0, 0.0))
    c.remember()
    assert c.memory is not None and len(c.memory) > 0
    c.on_scan(ust10lx_scan(wall_ahead(1.5)), 1025 * MS, (math.nan, 0.0, 0.0))
    assert not c.memory_active
    out, state = c.limit(drive(-1.0), "nav", 0.0, 1025 * MS)  # reverse: capped, as without memory
    assert out.speed == -0.5 and state.reason == "reverse_cap"
    c.remember()  # the memory cannot place anything: it forgets, as with stale odometry
    assert len(c.memory) == 0


def test_a_command_beyond_the_steering_limit_is_swept_along_the_arc_the_car_drives() -> None:
    """The VESC clamps steering to its steering_max_rad: a 0.6 rad command drives the 0.26 rad arc,
    and that arc (not the sharper one commanded) is what must be free."""
    # a post on the 0.26 rad arc (radius 0.94 m, 60 degrees round), outside the 0.6 rad one's sweep
    post = [((0.81, 0.42), (0.81, 0.52))]
    scan = ust10lx_scan(post)
    free_run = controller()
    free_run.on_scan(scan, now_ns=0)
    _, unlimited = free_run.limit(drive(3.0, 0.6), "nav", 0.0, now_ns=0)
    limited = SafetyController(build(SafetyParams, {}, "safety"), steering_limit_rad=0.26)
    limited.on_scan(scan, now_ns=0)
    out, state = limited.limit(drive(3.0, 0.6), "nav", 0.0, now_ns=0)
    _, driven = limited.limit(drive(3.0, 0.26), "nav", 0.0, now_ns=0)
    assert state.free_distance == pytest.approx(driven.free_distance)
    assert state.free_distance < unlimited.free_distance
    assert out.speed < 3.0 and state.intervening
    assert out.steering_angle == 0.6  # the command itself is left to the VESC's clamp


def test_where_the_servo_limit_clips_a_side_the_arc_the_car_drives_is_swept() -> None:
    """With the servo offset calibrated to 0.5804, full right (-0.26 rad) drives only -0.222 rad:
    a post on that wider arc must cut the command, which the -0.26 rad sweep missed."""
    from vesc.ackermann import AckermannConversion

    steer = AckermannConversion(steering_angle_to_servo_offset=0.5804).steering_range()
    assert steer[0] == pytest.approx(-0.2222, abs=1e-4)
    radius = 0.25 / math.tan(0.2222)  # the rear axle's turning radius on the driven arc
    angle = 0.55  # rad round the circle: about 0.6 m along the arc
    x, y = radius * math.sin(angle), -radius * (1 - math.cos(angle))
    post = [((x, y - 0.05), (x, y + 0.05))]
    scan = ust10lx_scan(post)
    symmetric = SafetyController(build(SafetyParams, {}, "safety"), steering_limit_rad=0.26)
    clipped = SafetyController(build(SafetyParams, {}, "safety"), steering_limit_rad=steer)
    for c in (symmetric, clipped):
        c.on_scan(scan, now_ns=0)
    _, missed = symmetric.limit(drive(3.0, -0.26), "nav", 0.0, now_ns=0)
    out, seen = clipped.limit(drive(3.0, -0.26), "nav", 0.0, now_ns=0)
    _, driven = clipped.limit(drive(3.0, steer[0]), "nav", 0.0, now_ns=0)
    assert seen.free_distance == pytest.approx(driven.free_distance)
    assert seen.free_distance < missed.free_distance
    assert out.speed < 3.0 and seen.intervening


def test_a_wall_in_view_and_in_the_memory_is_named_by_the_live_scan() -> None:
    """The remembered copy of a wall the lidar sees now may lie up to a cell's diagonal nearer (its
    cell's centre): the distance is the nearer one, the obstacle the live return."""
    for dx in (0.0, 0.015, 0.03, 0.07, 0.12):  # where the wall is across the grid's cells
        ahead = [((1.0 + LASER_X + dx, -5.0), (1.0 + LASER_X + dx, 5.0))]
        c = controller()
        now = drive_along(c, straight((0.0, 0.0, 0.0), 0.2, speed=0.5), ahead)
        out, state = c.limit(drive(3.0), "nav", 0.5, now)
        assert state.obstacle is not None and state.obstacle.source == "scan", dx
        assert state.reason == "obstacle" and out.speed < 3.0
        assert state.free_distance <= state.obstacle.x - FRONT + 1e-9


def test_a_command_sweeps_the_path_once_with_the_memory_too(monkeypatch: pytest.MonkeyPatch) -> None:
    """The live scan names an obstacle whose remembered copy limits the path (above) from the same
    sweep: the scan path pays for the remembered points, not for a second sweep of its own."""
    import safety.arc

    sweeps = []
    sweep = safety.arc._sweep

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        sweeps.append(1)
        return sweep(*args, **kwargs)

    monkeypatch.setattr(safety.arc, "_sweep", counted)
    ahead = [((1.0 + LASER_X + 0.03, -5.0), (1.0 + LASER_X + 0.03, 5.0))]
    c = controller()
    now = drive_along(c, straight((0.0, 0.0, 0.0), 0.2, speed=0.5), ahead)
    sweeps.clear()
    out, state = c.limit(drive(3.0), "nav", 0.5, now)
    assert state.obstacle is not None and state.obstacle.source == "scan" and out.speed < 3.0
    assert c.memory_active and len(sweeps) == 1


def _blinded(scan: LaserScan, half_width_rad: float, value: float) -> LaserScan:
    """``scan`` with the beams within ``half_width_rad`` of straight ahead set to ``value``."""
    angles = scan.angle_min + scan.angle_increment * np.arange(len(scan.ranges))
    ranges = np.asarray(scan.ranges, dtype=np.float32).copy()
    ranges[np.abs(angles) < half_width_rad] = value
    return LaserScan(angle_min=scan.angle_min, angle_max=scan.angle_max, angle_increment=scan.angle_increment,
                     time_increment=scan.time_increment, scan_time=scan.scan_time,
                     range_min=scan.range_min, range_max=scan.range_max, ranges=ranges)


@pytest.mark.parametrize("value", [math.nan, 0.01])  # a device fault; a hand or dust on the window
def test_a_blind_sector_ahead_is_not_free_space(value: float) -> None:
    """A wall 1.2 m ahead, then the front 103 degrees of the scan unusable (62 % of the beams still
    usable, above min_valid_fraction): the car stops (it was allowed 4 m/s, "clear", before)."""
    wall = ust10lx_scan(wall_ahead(1.2 + LASER_X))
    c = controller(memory={"enabled": False})
    c.on_scan(_blinded(wall, 0.9, value), now_ns=0)
    out, state = c.limit(drive(4.0), "nav", 0.0, now_ns=0)
    assert out.speed == 0.0 and state.reason == "obstacle" and state.obstacle.source == "blind"
    # reversing away from it is not blocked by the blind sector ahead
    fresh = controller(memory={"enabled": False})
    fresh.on_scan(_blinded(wall, 0.9, value), now_ns=0)
    assert fresh.limit(drive(-0.3), "nav", 0.0, now_ns=0)[0].speed == -0.3


def test_single_unusable_beams_are_ignored_and_blind_points_are_not_remembered() -> None:
    """Every fifth beam NaN (dropouts on a dark surface) changes nothing; a blind sector stops the
    car, and once the lidar sees again nothing of it is left in the obstacle memory."""
    empty = ust10lx_scan([])
    holey = np.asarray(empty.ranges, dtype=np.float32).copy()
    holey[::5] = np.nan
    c = controller(min_return_fraction=0.0)  # open space of no return at all: trusted here
    c.on_scan(LaserScan(angle_min=empty.angle_min, angle_max=empty.angle_max,
                        angle_increment=empty.angle_increment, scan_time=empty.scan_time,
                        range_min=empty.range_min, range_max=empty.range_max, ranges=holey), now_ns=0)
    out, _ = c.limit(drive(4.0), "nav", 0.0, now_ns=0)
    assert out.speed == 4.0
    pose = (0.0, 0.0, 0.0)
    c.on_scan(_blinded(empty, 0.9, math.nan), 25 * MS, pose)
    c.remember()
    assert c.limit(drive(4.0), "nav", 0.0, now_ns=25 * MS)[0].speed == 0.0
    now = 25 * MS
    while now < 500 * MS:  # past the intervention's release hold (0.3 s) with a clear view
        now += 25 * MS
        c.on_scan(empty, now, pose)
        c.remember()
        out, state = c.limit(drive(4.0), "nav", 0.0, now_ns=now)
    assert out.speed == 4.0 and state.reason == "clear" and len(c.memory) == 0
