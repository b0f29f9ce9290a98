"""The obstacle memory alone: scans of a known world fed with odometry poses, no simulator.

The world is wall segments in the odom frame; a UST-10LX (270 degrees) sits 0.265 m ahead of
base_link. Each test drives the car along a path of poses at 40 Hz and looks at what the memory
holds, in odom, against the true geometry.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scans import LASER_X, Segment, base_points, left_arc, scan_at, square, straight

from safety.controller import planar_transform
from safety.memory import MIN_ANGLE_INCREMENT_RAD, ObstacleMemory, _window_min

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

MS = 1_000_000
PERIOD_NS = 25 * MS  # 40 Hz
TO_BASE = planar_transform((LASER_X, 0.0, 0.0))
BODY = (0.45, 0.10, 0.15)  # front, rear, half width of the default car


def feed(memory: ObstacleMemory, pose: tuple[float, float, float], world: list[Segment],
         now_ns: int) -> None:
    scan = scan_at(pose, world)
    x, y = base_points(scan)
    memory.update(pose, TO_BASE, scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min,
                  scan.range_max, x, y, now_ns, footprint=BODY)


def drive(memory: ObstacleMemory, poses: list[tuple[float, float, float]], world: list[Segment],
          t0_ns: int = 0) -> int:
    """Feed one scan per pose, 25 ms apart; returns the time after the last."""
    now = t0_ns
    for pose in poses:
        feed(memory, pose, world, now)
        now += PERIOD_NS
    return now


def near(memory: ObstacleMemory, x: float, y: float, within: float = 0.1) -> int:
    """How many remembered cells lie within ``within`` m of (x, y)."""
    cx, cy, _ = memory.cells()
    return int(np.count_nonzero(np.hypot(cx - x, cy - y) <= within))


def to_base(pose: tuple[float, float, float], x: np.ndarray,
            y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Odom points in base_link at ``pose``."""
    px, py, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return c * (x - px) + s * (y - py), -s * (x - px) + c * (y - py)


POST = (2.0, 0.6)  # a 10 cm post ahead and to the left


def test_a_post_driven_past_stays_where_it_is_in_odom_and_behind_the_car_in_base_link():
    world = square(*POST)
    memory = ObstacleMemory()
    poses = straight((0.0, 0.0, 0.0), 4.0)
    drive(memory, poses, world)
    # 2 m past it the post is behind the car, in the lidar's blind sector (bearing about 165 deg)
    assert near(memory, *POST) > 0
    bx, by = to_base(poses[-1], memory.points().real, memory.points().imag)
    close = np.hypot(bx - (POST[0] - 4.0), by - POST[1]) <= 0.1
    assert close.any()
    # every remembered cell of the post lies on it, within half a cell diagonal plus the post size
    x, y, _ = memory.cells()
    mine = np.hypot(x - POST[0], y - POST[1]) < 0.5
    assert np.all(np.abs(x[mine] - POST[0]) <= 0.05 + 0.036)
    assert np.all(np.abs(y[mine] - POST[1]) <= 0.05 + 0.036)


def test_reversing_back_towards_the_post_keeps_it_in_odom():
    world = square(*POST)
    memory = ObstacleMemory()
    forward = straight((0.0, 0.0, 0.0), 4.0)
    now = drive(memory, forward, world)
    back = straight(forward[-1], -1.5, speed=0.5)
    drive(memory, back, world, now)
    assert back[-1][0] == pytest.approx(2.5)
    # the post is now 0.5 m behind base_link, 0.6 m to the left: still blind, still remembered
    assert near(memory, *POST) > 0
    bx, by = to_base(back[-1], memory.points().real, memory.points().imag)
    on_post = np.hypot(bx + 0.5, by - 0.6) <= 0.1
    assert on_post.any()


def test_turning_moves_the_remembered_wall_round_the_car():
    # a wall 1.2 m ahead; the car turns left through 180 degrees on a 0.6 m circle; the wall ends
    # up behind the car, where the lidar cannot see it
    wall: list[Segment] = [((1.2 + LASER_X, -5.0), (1.2 + LASER_X, 5.0))]
    memory = ObstacleMemory()
    turn = left_arc((0.0, 0.0, 0.0), 0.6, math.pi)
    drive(memory, turn, wall)
    end = turn[-1]
    assert end[0] == pytest.approx(0.0, abs=1e-6) and end[1] == pytest.approx(1.2)
    assert abs(abs(end[2]) - math.pi) < 1e-6
    bx, by = to_base(end, memory.points().real, memory.points().imag)
    behind = (np.abs(by) <= 0.3) & (bx < 0)
    assert behind.any()
    # the wall's x in odom is 1.465 m: behind the car it is 1.465 m back from base_link
    assert np.median(-bx[behind]) == pytest.approx(1.2 + LASER_X, abs=0.05)


def test_what_the_lidar_sees_through_now_is_forgotten():
    memory = ObstacleMemory()
    now = drive(memory, [(0.0, 0.0, 0.0)] * 3, square(*POST))
    assert near(memory, *POST) > 0
    # the post is taken away: the next scan sees the wall behind where it stood
    far_wall: list[Segment] = [((4.0, -5.0), (4.0, 5.0))]
    feed(memory, (0.0, 0.0, 0.0), far_wall, now)
    assert near(memory, *POST) == 0
    assert near(memory, 4.0, 0.6) > 0


def test_what_is_hidden_or_out_of_view_is_kept_until_it_ages_out():
    memory = ObstacleMemory(max_age_s=2.0)
    now = drive(memory, [(0.0, 0.0, 0.0)] * 3, square(*POST))
    # a wall between the car and the post hides it: not seen through, kept
    screen: list[Segment] = [((1.0, 0.2), (1.0, 1.0))]
    now = drive(memory, [(0.0, 0.0, 0.0)] * 3, screen, now)
    assert near(memory, *POST) > 0
    # turned away (the post in the blind sector) and the post gone: nothing can clear it but age
    behind = (0.0, 0.0, math.pi + math.atan2(POST[1], POST[0]))
    now = drive(memory, [behind] * 40, [], now)  # 1 s
    assert near(memory, *POST) > 0
    drive(memory, [behind] * 45, [], now)  # another 1.1 s: last seen over 2 s ago
    assert near(memory, *POST) == 0 and len(memory) == 0


def test_a_wall_seen_at_grazing_angles_is_not_cleared_by_its_own_cells():
    # driving 4 m down a 1.5 m corridor: the walls behind the car stay remembered without gaps,
    # although beams meet them at a few degrees and cell centres sit off the wall's surface
    corridor: list[Segment] = [((-3.0, 0.75), (30.0, 0.75)), ((-3.0, -0.75), (30.0, -0.75))]
    memory = ObstacleMemory()
    drive(memory, straight((0.0, 0.0, 0.0), 4.0, speed=3.0), corridor)
    x, y, _ = memory.cells()
    for side in (0.75, -0.75):
        on_wall = x[np.abs(y - side) < 0.06]
        columns = set(np.floor(on_wall / 0.05).astype(int))
        # every 5 cm column from 0.3 m behind the start (the edge of the lidar's view there) to the car
        expected = set(range(int(-0.3 / 0.05), int(4.0 / 0.05)))
        assert expected <= columns, sorted(expected - columns)[:10]


def test_the_cars_own_footprint_holds_nothing():
    memory = ObstacleMemory()
    now = drive(memory, [(0.0, 0.0, 0.0)] * 2, square(1.0, 0.0, 0.05))
    assert near(memory, 1.0, 0.0, 0.1) > 0
    # odometry says the car now stands where the post was (it moved, or odometry drifted)
    poses = straight((0.0, 0.0, 0.0), 0.8, speed=1.0)
    drive(memory, poses, [], now)
    assert near(memory, 1.0, 0.0, 0.1) == 0


def test_an_odometry_jump_forgets_everything():
    memory = ObstacleMemory()
    now = drive(memory, [(0.0, 0.0, 0.0)] * 2, square(*POST))
    assert len(memory) > 0
    feed(memory, (5.0, 0.0, 0.0), [], now)  # 5 m in 25 ms: a reset, not motion
    assert len(memory) == 0 and memory.resets == 1


def test_the_window_follows_the_car_and_forgets_what_it_leaves():
    memory = ObstacleMemory(size_m=10.0)
    now = drive(memory, [(0.0, 0.0, 0.0)], square(*POST))
    assert near(memory, *POST) > 0
    drive(memory, straight((0.0, 0.0, 0.0), 9.0, speed=3.0), [], now)
    x_min, y_min, x_max, y_max = memory.window()
    assert x_min <= 9.0 <= x_max and y_min <= 0.0 <= y_max
    assert x_min > POST[0]  # 7 m behind: out of the window, forgotten
    assert near(memory, *POST) == 0


@pytest.mark.slow
def test_memory_stays_bounded_over_a_long_run():
    # a kilometre of driving down an endless corridor lined with posts, 10 minutes of scans at
    # 40 Hz would take long; 1 km at 10 m per second of scans shows the same bound
    posts = [seg for k in range(0, 1000, 3) for seg in square(float(k), 1.2 * (-1) ** k)]
    walls: list[Segment] = [((-5.0, 2.0), (1005.0, 2.0)), ((-5.0, -2.0), (1005.0, -2.0))]
    memory = ObstacleMemory(size_m=10.0, resolution_m=0.05, max_age_s=10.0)
    now, x = 0, 0.0
    counts, sizes = [], []
    while x < 1000.0:
        near_car = [((max(a[0], x - 12), a[1]), (min(b[0], x + 12), b[1])) for a, b in posts + walls
                    if min(a[0], b[0]) < x + 12 and max(a[0], b[0]) > x - 12]
        feed(memory, (x, 0.0, 0.0), near_car, now)
        now += PERIOD_NS
        x += 0.5  # 20 m/s: the bound does not depend on the speed, the test's time does
        counts.append(len(memory))
        sizes.append(memory.nbytes)
    # what it holds is what lies within the 10 m window, the same after 1 km as after 100 m
    assert max(counts[-200:]) <= max(counts[:200]) * 1.2
    assert max(sizes[-200:]) <= max(sizes[:200]) * 1.2
    assert max(counts) < 2 * 3 * (10.0 / 0.05) + 8 * 40  # two walls, a cell or three thick; posts
    x_min, _, x_max, _ = memory.window()
    xs, _, _ = memory.cells()
    assert xs.min() >= x_min and xs.max() <= x_max


def test_the_swept_points_are_the_cells_within_reach_of_the_car():
    corridor: list[Segment] = [((-5.0, 0.75), (30.0, 0.75)), ((-5.0, -0.75), (30.0, -0.75))]
    memory = ObstacleMemory(reach_m=2.0)
    poses = straight((0.0, 0.0, 0.0), 3.0, speed=3.0)
    drive(memory, poses, corridor + square(*POST))
    x, y, _ = memory.cells()
    px, py, _ = poses[-1]
    within = np.hypot(x - px, y - py) <= 2.0
    assert 0 < within.sum() < len(memory)
    got = memory.points()
    assert np.all(np.abs(got - complex(px, py)) <= 2.0)
    # one per cell (its last return, not its centre): as many as the cells within reach, give or
    # take those whose centre and return lie either side of the reach
    half_diagonal = 0.025 * math.sqrt(2.0)
    distance = np.hypot(x - px, y - py)
    assert (distance <= 2.0 - half_diagonal).sum() <= len(got) <= (distance <= 2.0 + half_diagonal).sum()
    centres = x + 1j * y
    for point in got:
        off = np.maximum(abs(centres.real - point.real), abs(centres.imag - point.imag))
        assert off.min() <= 0.025 + 1e-9


def test_returns_land_in_the_cells_that_hold_them():
    memory = ObstacleMemory(resolution_m=0.05)
    pose = (1.0, -2.0, 0.7)
    bx, by = np.array([0.5, 1.234, -2.0]), np.array([0.3, -0.77, 1.5])
    never = np.full(1081, np.inf)
    memory.update(pose, TO_BASE, never, -2.35, 0.004363, 0.06, 30.0, bx, by, 1)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    ox, oy = pose[0] + c * bx - s * by, pose[1] + s * bx + c * by
    x, y, seen = memory.cells()
    assert len(x) == 3 and set(seen) == {1}
    for px, py in zip(ox, oy, strict=True):  # each return is in the 5 cm cell around some centre
        assert np.any((np.abs(x - px) <= 0.025 + 1e-9) & (np.abs(y - py) <= 0.025 + 1e-9))
    # and the swept points are the returns themselves, not their cells' centres
    np.testing.assert_allclose(np.sort_complex(memory.points()), np.sort_complex(ox + 1j * oy), atol=1e-9)


def test_a_remembered_return_the_scan_now_reaches_gives_way_to_the_scans_returns():
    """A noisy return just inside a corridor is not kept once the lidar sees the wall behind it
    within the range noise (it kept a car stopped in a gap it fitted through): a cell the scan
    reaches is forgotten and what the scan sees there now is written in. A cell behind something
    nearer stays."""
    memory = ObstacleMemory(resolution_m=0.05, see_through_m=0.1)
    angles = -2.35 + 0.004363 * np.arange(1081)
    wall = np.full(1081, np.inf)
    ahead = np.abs(angles) < 0.3
    wall[ahead] = 2.0 / np.cos(angles[ahead])  # a wall 2 m ahead
    noisy = np.array([1.93]), np.array([0.0])  # one return 7 cm short of it
    memory.update((0.0, 0.0, 0.0), TO_BASE, wall, -2.35, 0.004363, 0.06, 30.0, *noisy, 1)
    assert np.allclose(memory.points(), [1.93])
    bx, by = 2.0 * np.ones(3), np.array([-0.1, 0.0, 0.1])  # the next scan: the wall, no noise
    memory.update((0.0, 0.0, 0.0), TO_BASE, wall, -2.35, 0.004363, 0.06, 30.0, bx, by, 2)
    assert np.allclose(np.sort_complex(memory.points()), bx + 1j * by)
    post = wall.copy()
    post[np.abs(angles) < 0.05] = 1.0  # a post 1 m ahead hides the wall's middle
    memory.update((0.0, 0.0, 0.0), TO_BASE, post, -2.35, 0.004363, 0.06, 30.0, np.array([1.0]),
                  np.array([0.0]), 3)
    assert 2.0 + 0.0j in np.round(memory.points(), 9) and 1.0 + 0.0j in np.round(memory.points(), 9)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 100.0), min_size=1, max_size=300), st.data())
def test_window_min_is_the_minimum_of_each_window(values, data):
    a = np.asarray(values)
    k = data.draw(st.integers(1, 50))
    lo = np.asarray(data.draw(st.lists(st.integers(0, len(a) - 1), min_size=k, max_size=k)))
    width = np.asarray(data.draw(st.lists(st.integers(0, 62), min_size=k, max_size=k)))
    hi = np.minimum(lo + width, len(a) - 1)
    expected = np.array([a[i:j + 1].min() for i, j in zip(lo, hi, strict=True)])
    assert np.array_equal(_window_min(a, lo, hi), expected)


def test_a_scan_with_no_usable_geometry_clears_nothing():
    memory = ObstacleMemory()
    now = drive(memory, [(0.0, 0.0, 0.0)], square(*POST))
    before = len(memory)
    nan = np.full(1081, np.nan, dtype=np.float32)
    memory.update((0.0, 0.0, 0.0), TO_BASE, nan, -2.35, 0.0, 0.06, 30.0, np.zeros(0), np.zeros(0), now)
    assert len(memory) == before
    memory.update((0.0, 0.0, 0.0), TO_BASE, nan, -2.35, 0.00436, 0.06, 30.0, np.zeros(0), np.zeros(0),
                  now + PERIOD_NS)
    assert len(memory) == before  # NaN beams tell nothing: nothing is seen through


# a cell 2 m out on the first beam and one centred on the laser (r = 0, bearing 0): r, bearing
ON_FIRST_BEAM = (np.array([2.0, 0.0]), np.array([0.0, 0.0]))


def seen_through(memory: ObstacleMemory, increment: float, range_min: float) -> np.ndarray:
    """The two cells judged against ten beams from bearing 0 that all reach 5 m, warnings raised."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return memory._seen_through(*ON_FIRST_BEAM, np.full(10, 5.0), 0.0, increment, range_min, 30.0)


@pytest.mark.parametrize("increment", [5e-324, 1e-323, -1e-300, 1e-20, 0.5 * MIN_ANGLE_INCREMENT_RAD,
                                       7.0, -math.inf, math.nan])
def test_a_scan_without_plausible_beam_spacing_sees_through_nothing(increment):
    # A subnormal increment (1e-323, as a property test drew) made bearing / increment overflow and
    # a cell's window of beams negative: an IndexError that latched the daemon's safety fault.
    memory = ObstacleMemory()
    assert not seen_through(memory, increment, 0.0).any()


def test_cells_on_the_first_beam_and_on_the_laser_are_judged_at_the_finest_plausible_spacing():
    memory = ObstacleMemory()
    # both cells are in view and every beam reaches 4.9 m beyond them: seen through
    assert seen_through(memory, MIN_ANGLE_INCREMENT_RAD, 0.0).tolist() == [True, True]
    assert seen_through(memory, -MIN_ANGLE_INCREMENT_RAD, 0.0).tolist() == [True, True]
    # r = 0 is below a real range_min: out of the lidar's range, kept (and no division by zero)
    assert seen_through(memory, 0.00436, 0.06).tolist() == [True, False]


def test_a_remembered_post_survives_scans_without_plausible_beam_spacing():
    memory = ObstacleMemory()
    now = drive(memory, [(0.0, 0.0, 0.0)], square(*POST))
    before = len(memory)
    beyond = np.full(1081, 5.0, dtype=np.float32)  # every beam past the post, were it spread out
    # the post's bearing from the laser: the first beam of the broken scans points at it
    first = math.atan2(POST[1], POST[0] - LASER_X)
    for increment in (1e-323, 1e-300, 0.0):
        now += PERIOD_NS
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            memory.update((0.0, 0.0, 0.0), TO_BASE, beyond, first, increment, 0.06, 30.0, np.zeros(0),
                          np.zeros(0), now)
        assert len(memory) == before
    # the same ranges over the UST-10LX's real 270 degrees: the lidar sees through where it stood
    memory.update((0.0, 0.0, 0.0), TO_BASE, beyond, -2.35, 0.00436, 0.06, 30.0, np.zeros(0),
                  np.zeros(0), now + PERIOD_NS)
    assert near(memory, *POST) == 0
