"""Ray casting against occupancy grids, checked against analytic geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from racecar_hw.sim.occupancy import OccupancyMap, load_shipped_map
from racecar_hw.sim.raycast import RayCaster, distance_field

RES = 0.05


def box_room(width_m: float = 8.0, depth_m: float = 6.0, wall_m: float = 0.2,
             origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> OccupancyMap:
    """A closed room whose inner faces are at x = 0, x = width, y = 0, y = depth (grid frame)."""
    wall = round(wall_m / RES)
    w, h = round(width_m / RES) + 2 * wall, round(depth_m / RES) + 2 * wall
    occ = np.zeros((h, w), dtype=bool)
    occ[:wall], occ[-wall:], occ[:, :wall], occ[:, -wall:] = True, True, True, True
    ox, oy, oyaw = origin
    c, s = math.cos(oyaw), math.sin(oyaw)
    # shift the origin so the inner lower-left corner is at (ox, oy) whatever the yaw
    return OccupancyMap.from_occupied(occ, RES, (ox - c * wall_m + s * wall_m,
                                                 oy - s * wall_m - c * wall_m, oyaw), image_order=False)


def room_truth(x: float, y: float, angles: np.ndarray, width: float, depth: float) -> np.ndarray:
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tx = np.where(c > 0, (width - x) / c, np.where(c < 0, -x / c, np.inf))
        ty = np.where(s > 0, (depth - y) / s, np.where(s < 0, -y / s, np.inf))
    return np.minimum(tx, ty)


ANGLES = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 1081)


@pytest.mark.parametrize(("x", "y", "yaw"), [(4.0, 3.0, 0.0), (1.0, 0.7, 0.3), (7.3, 5.6, -2.5),
                                             (0.3, 3.0, math.pi), (2.2, 2.2, math.pi / 4)])
def test_room_ranges_match_geometry_within_a_cell(x: float, y: float, yaw: float) -> None:
    caster = RayCaster(box_room())
    got = caster.cast(x, y, yaw, ANGLES, 30.0)
    want = room_truth(x, y, ANGLES + yaw, 8.0, 6.0)
    assert np.all(np.isfinite(got))
    assert np.max(np.abs(got - want)) < RES


def test_rotated_map_origin() -> None:
    yaw0 = 0.7
    caster = RayCaster(box_room(origin=(2.0, -1.0, yaw0)))
    # the pose (4, 3, 0) in the room's own frame
    c, s = math.cos(yaw0), math.sin(yaw0)
    x, y = 2.0 + c * 4.0 - s * 3.0, -1.0 + s * 4.0 + c * 3.0
    got = caster.cast(x, y, yaw0, ANGLES, 30.0)
    assert np.max(np.abs(got - room_truth(4.0, 3.0, ANGLES, 8.0, 6.0))) < RES


def test_max_range_gives_inf() -> None:
    caster = RayCaster(box_room())
    got = caster.cast(1.0, 3.0, 0.0, np.array([0.0, math.pi, math.pi / 2]), 5.0)
    assert math.isinf(got[0])  # far wall 7 m away
    assert got[1] == pytest.approx(1.0, abs=RES)
    assert got[2] == pytest.approx(3.0, abs=RES)


def test_open_map_and_outside_sensor() -> None:
    occ = np.zeros((40, 40), dtype=bool)
    occ[18:22, 30:34] = True  # a 0.2 m block whose near face is at x = 1.5 m
    caster = RayCaster(OccupancyMap.from_occupied(occ, RES, image_order=False))
    got = caster.cast(1.0, 1.0, 0.0, np.array([0.0, math.pi, math.pi / 2]), 30.0)
    assert got[0] == pytest.approx(0.5, abs=RES)
    assert np.isinf(got[1:]).all()  # nothing but the map edge: empty space
    # a sensor off the grid still sees the block, and rays never entering the grid see nothing
    got = caster.cast(-3.0, 1.0, 0.0, np.array([0.0, math.pi]), 30.0)
    assert got[0] == pytest.approx(4.5, abs=RES) and math.isinf(got[1])


def test_sensor_inside_a_wall_reads_zero() -> None:
    caster = RayCaster(box_room())
    got = caster.cast(-0.1, 3.0, 0.0, ANGLES, 30.0)
    assert np.all(got < RES)


def test_corridor_is_1_5_m_wide() -> None:
    caster = RayCaster(load_shipped_map("corridor"))
    left, right = caster.cast(0.0, 0.0, 0.0, np.array([math.pi / 2, -math.pi / 2]), 10.0)
    assert left == pytest.approx(0.75, abs=RES) and right == pytest.approx(0.75, abs=RES)
    assert left + right == pytest.approx(1.5, abs=0.02)
    # beams at a slant hit the side walls at 0.75 / sin(angle)
    angles = np.radians([10.0, 30.0, -45.0, 120.0])
    got = caster.cast(0.0, 0.0, 0.0, angles, 30.0)
    assert np.max(np.abs(got - 0.75 / np.abs(np.sin(angles)))) < RES
    ahead = caster.cast(0.0, 0.0, 0.0, np.array([0.0]), 30.0)[0]
    assert ahead == pytest.approx(28.0, abs=RES)


@settings(max_examples=40, deadline=None)
@given(arrays(bool, st.tuples(st.integers(1, 12), st.integers(1, 12)), elements=st.booleans()),
       st.integers(1, 6), st.booleans())
def test_distance_field_matches_brute_force(occ: np.ndarray, cap: int, squares: bool) -> None:
    got = distance_field(occ, cap, between_squares=squares)
    jj, ii = np.nonzero(occ)
    shrink = 1.0 if squares else 0.0
    for (r, c), value in np.ndenumerate(got):
        if occ[r, c]:
            assert value == 0.0
            continue
        if jj.size == 0:
            assert value == cap
            continue
        dr = np.maximum(np.abs(jj - r) - shrink, 0.0)
        dc = np.maximum(np.abs(ii - c) - shrink, 0.0)
        assert value == pytest.approx(min(float(np.sqrt(dr * dr + dc * dc).min()), cap))


@settings(max_examples=60, deadline=None)
@given(st.floats(0.2, 7.8), st.floats(0.2, 5.8), st.floats(-math.pi, math.pi))
def test_any_pose_in_the_room(x: float, y: float, yaw: float) -> None:
    got = _ROOM.cast(x, y, yaw, ANGLES[::20], 30.0)
    assert np.max(np.abs(got - room_truth(x, y, ANGLES[::20] + yaw, 8.0, 6.0))) < RES


_ROOM = RayCaster(box_room())
