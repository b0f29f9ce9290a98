"""Scenario obstacles: convex polygons, obstacles that appear, move and disappear, the file format."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_sim_world import drive, make_world

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build
from racecar_hw.sim.movers import Mover
from racecar_hw.sim.obstacles import Box, Circle, Polygon, place
from racecar_hw.sim.plot import plot_world
from racecar_hw.sim.scenario import ObstacleSpec, Scenario, load_scenario, scenario_names

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


def test_a_polygon_is_convex_counter_clockwise_and_hit_where_geometry_says() -> None:
    square = Polygon.convex([(1, -1), (1, 1), (3, 1), (3, -1)])  # given clockwise
    assert square.points[0] == (3.0, -1.0)  # reversed to counter-clockwise
    angles = np.array([0.0, math.atan2(1, 1), math.atan2(0.5, 1.0), math.pi / 2, math.pi])
    ranges = square.ray_ranges(0.0, 0.0, np.cos(angles), np.sin(angles))
    assert ranges == pytest.approx([1.0, math.sqrt(2), math.hypot(1.0, 0.5), np.inf, np.inf])
    # the same square as a Box answers the same for any beam
    box = Box(2.0, 0.0, 2.0, 2.0)
    fan = np.linspace(-math.pi, math.pi, 721)
    np.testing.assert_allclose(square.ray_ranges(-0.5, 0.3, np.cos(fan), np.sin(fan)),
                               box.ray_ranges(-0.5, 0.3, np.cos(fan), np.sin(fan)), atol=1e-9)
    assert square.ray_ranges(2.0, 0.0, np.ones(3), np.zeros(3)).tolist() == [0.0, 0.0, 0.0]
    car = np.array([[-1.0, -0.5], [0.5, -0.5], [0.5, 0.5], [-1.0, 0.5]])
    assert square.distance_to(car) == pytest.approx(0.5)
    for bad in ([(0, 0), (1, 0)], [(0, 0), (1, 0), (2, 0)], [(0, 0), (2, 0), (1, 0.2), (1, 2)]):
        with pytest.raises(ValueError):
            Polygon.convex(bad)


def test_place_turns_and_moves_every_shape() -> None:
    assert place(Circle(0, 0, 0.2), 1.0, 2.0, 1.0) == Circle(1.0, 2.0, 0.2)
    box = place(Box(0, 0, 0.6, 0.4, 0.1), 1.0, 2.0, 0.2)
    assert (box.x, box.y, box.yaw) == (1.0, 2.0, pytest.approx(0.3))
    tri = place(Polygon(((0.0, 0.0), (1.0, 0.0), (0.0, 1.0))), 5.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(tri.corners(), [[5.0, 0.0], [5.0, 1.0], [4.0, 0.0]], atol=1e-12)


def test_a_mover_appears_moves_and_disappears_on_time() -> None:
    walker = Mover(Circle(0, 0, 0.2), (3.0, 2.0), appear_s=1.0, disappear_s=4.0, velocity=(0.0, -1.5))
    assert walker.at(0.9) is None and walker.at(4.0) is None
    assert walker.at(1.0) == Circle(3.0, 2.0, 0.2)
    assert walker.at(2.0) == Circle(3.0, 0.5, 0.2)
    route = Mover(Box(0, 0, 0.6, 0.4), (0.0, 0.0), yaw=0.3, waypoints=((3.0, 0.0), (3.0, 4.0)), speed=2.0)
    assert route.position(1.0) == pytest.approx((2.0, 0.0))
    assert route.position(2.0) == pytest.approx((3.0, 1.0))
    assert route.position(100.0) == pytest.approx((3.0, 4.0))  # stays at the last waypoint
    assert route.at(2.0).yaw == 0.3
    with pytest.raises(ValueError):
        Mover(Circle(0, 0, 1), (0, 0), velocity=(1.0, 0.0), waypoints=((1.0, 1.0),), speed=1.0)
    with pytest.raises(ValueError):
        Mover(Circle(0, 0, 1), (0, 0), appear_s=2.0, disappear_s=1.0)


def test_the_world_sees_and_hits_a_mover_where_it_is_at_the_time() -> None:
    world, motor = make_world()
    # a person crossing 2 m ahead from the left at 1.5 m/s: on the car's centre line at 1 s
    world.add_mover(Mover(Circle(0, 0, 0.2), (2.0, 1.5), velocity=(0.0, -1.5), name="person"))
    ahead = np.array([0.0])
    assert world.true_ranges(ahead, t=0.0)[0] > 3.0  # not in front yet: the far wall
    assert world.true_ranges(ahead, t=1.0)[0] == pytest.approx(2.0 - 0.2 - 0.265, abs=1e-9)
    assert world.what_is_at(1.8, 0.0, t=1.0) == "person"
    assert world.what_is_at(1.8, 0.0, t=0.0) is None
    assert world.what_is_at(7.96, 0.0) == "map"  # the far wall's face
    assert world.obstacles_at(0.5)[0][0] == "person"
    # the car drives into its path and hits it
    motor.drive(1.5)
    drive(world, 1.2)
    assert world.collided and motor.stalls == 1
    assert 0.5 < world.collisions[0].t < 1.2


def test_a_mover_that_is_gone_is_neither_seen_nor_hit() -> None:
    world, motor = make_world()
    world.add_mover(Mover(Box(0, 0, 0.4, 2.0), (1.5, 0.0), disappear_s=0.5))
    assert world.true_ranges(np.array([0.0]), t=0.2)[0] == pytest.approx(1.5 - 0.2 - 0.265)
    motor.drive(1.0)
    drive(world, 2.0)
    assert not world.collided and world.pose.x == pytest.approx(2.0)
    assert world.obstacles == {}


def test_scenario_obstacles_are_validated_with_their_key() -> None:
    spec = build(ObstacleSpec, {"shape": "polygon", "points": [[0, 0], [1, 0], [0, 1]], "at": [2, 3],
                                "waypoints": [[4, 3]], "speed_mps": 0.5, "appear_s": 1.0})
    mover = spec.mover(offset_s=0.25, name="obstacle 1")
    assert mover.appear_s == 1.25 and mover.name == "obstacle 1" and mover.waypoints == ((4.0, 3.0),)
    assert isinstance(mover.at(1.25), Polygon)
    bad = [
        ({"shape": "polygon", "points": [[0, 0], [2, 0], [1, 0.2], [1, 2]]}, "not convex"),
        ({"shape": "polygon"}, "at least 3"),
        ({"shape": "box", "size_m": [0.0, 1.0]}, "size_m"),
        ({"shape": "cone"}, "shape"),
        ({"velocity_mps": [1, 0], "waypoints": [[1, 1]]}, "not both"),
        ({"appear_s": 2.0, "disappear_s": 1.0}, "disappears"),
        ({"radius_m": -1.0}, "radius_m"),
    ]
    for data, message in bad:
        with pytest.raises(ConfigError, match=message):
            build(Scenario, {"obstacles": [data]}, "scenario")


def test_shipped_scenarios_with_obstacles_load() -> None:
    names = scenario_names()
    for name in ("crossing-person", "sliding-box", "lidar-dropout"):
        assert name in names
        scenario = load_scenario(name)
        (spec,) = scenario.obstacles
        mover = spec.mover()
        assert mover.at(0.0) is not None and mover.name


def test_the_plot_draws_every_shape(tmp_path: Path) -> None:
    world, _ = make_world()
    world.add_mover(Mover(Polygon.convex([(0, 0), (1, 0), (0.5, 0.8)]), (3.0, 1.0), yaw=0.4))
    world.add_mover(Mover(Box(0, 0, 0.6, 0.4), (2.0, -1.0), yaw=0.3))
    world.add_mover(Mover(Circle(0, 0, 0.2), (4.0, 0.0)))
    assert len(world.obstacles) == 3
    path = tmp_path / "shapes.png"
    plot_world(path, world)
    with Image.open(path) as img:
        pixels = np.asarray(img.convert("RGB"))
    grey = np.all(pixels == (120, 120, 120), axis=-1)  # the obstacle colour
    assert grey.sum() > 3 * 50  # three filled shapes, each many pixels
