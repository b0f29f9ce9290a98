"""The safety scene: the swept band follows the bicycle model, colours follow the safety state."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from racecar_hw.net.band import band_polygon, body_corners, swept_band
from racecar_hw.net.control import CLEAR, LIMITING, STOPPED, CarShape, LiveState
from racecar_hw.net.scene import label, scene_update
from safety.arc import SweptFootprint, free_distance, path_lengths

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

SHAPE = CarShape(front_m=0.45, rear_m=0.10, half_width_m=0.2, wheelbase_m=0.25, latency_s=0.055,
                 max_decel_mps2=4.0, margin_m=0.25, max_path_m=10.0)


def state(**changes: object) -> LiveState:
    base = LiveState(commanded_mps=1.0, output_mps=1.0, allowed_mps=3.0, measured_mps=1.0, steering_rad=0.0,
                     source="nav_0", mux_state="running", mux_reason="", armed=True, safety_reason="clear",
                     intervening=False, free_distance_m=10.0, obstacle=None, battery_v=16.0,
                     vesc_connected=True, vesc_reconnects=0, vesc_crc_errors=0, lidar_scan_age_s=0.01,
                     lidar_rate_hz=40.0, lidar_reconnects=0)
    return dataclasses.replace(base, **changes)


def test_stopping_distance_is_reaction_plus_braking_plus_margin():
    v = 2.0
    assert SHAPE.stopping_distance(v) == pytest.approx(v * 0.055 + v * v / 8.0 + 0.25)
    assert SHAPE.stopping_distance(-v) == SHAPE.stopping_distance(v)
    assert SHAPE.stopping_distance(100.0) == 10.0 and SHAPE.stopping_distance(math.nan) == 0.25


def test_straight_ahead_the_band_is_the_rectangle_from_the_bumper():
    inner, outer = swept_band(SHAPE, 0.0, 2.0)
    assert np.allclose(inner[[0, -1]], [[0.45, 0.2], [2.45, 0.2]])
    assert np.allclose(outer[[0, -1]], [[0.45, -0.2], [2.45, -0.2]])
    back_inner, _ = swept_band(SHAPE, 0.0, 1.0, reverse=True)
    assert np.allclose(back_inner[[0, -1]], [[-0.1, 0.2], [-1.1, 0.2]])


@pytest.mark.parametrize("steering", [0.3, -0.3])
def test_turning_the_band_edges_lie_on_the_swept_annulus(steering):
    radius = SweptFootprint(0.45, 0.10, 0.2, 0.25).turn_radius(steering)
    inner, outer = swept_band(SHAPE, steering, 3.0)
    centre = np.array([0.0, radius])
    assert np.allclose(np.hypot(*(inner - centre).T), abs(radius) - 0.2)
    assert np.allclose(np.hypot(*(outer - centre).T), math.hypot(0.45, abs(radius) + 0.2))
    # the band turns the way the car steers
    assert np.sign(inner[-1, 1]) == np.sign(steering)


def test_points_inside_the_band_are_on_the_controllers_path():
    """Anything the band covers past the car, the safety controller finds on its path."""
    from matplotlib.path import Path

    steering, length = 0.25, 2.0
    inner, outer = swept_band(SHAPE, steering, length)
    outline = Path(band_polygon(inner, outer))
    sweep = SweptFootprint(0.45, 0.10, 0.2, 0.25)
    xs, ys = np.meshgrid(np.linspace(-0.5, 3, 60), np.linspace(-1.5, 2.5, 60))
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    inside = outline.contains_points(pts)
    assert inside.sum() > 50
    along = path_lengths(pts[inside, 0], pts[inside, 1], steering, sweep)
    assert np.all(np.isfinite(along)) and np.all(along <= length + 1e-6)
    hit = free_distance(pts[inside, 0], pts[inside, 1], steering, sweep, 10.0)
    assert hit.index >= 0


def test_colours_follow_the_safety_state():
    assert state().safety_colour == CLEAR
    assert state(intervening=True, allowed_mps=0.5).safety_colour == LIMITING
    assert state(allowed_mps=0.0, safety_reason="stale_scan").safety_colour == STOPPED
    assert state(mux_state="estop", mux_reason="web").safety_colour == STOPPED
    assert state(armed=False).safety_colour == STOPPED


def test_the_scene_carries_body_band_obstacle_and_label():
    update = scene_update(state(intervening=True, allowed_mps=0.4, obstacle=(1.2, 0.1),
                                safety_reason="obstacle", steering_rad=0.2), SHAPE, 1_700_000_000_123_456_789)
    encoded = update.encode()
    assert b"safety" in encoded and b"obstacle" in encoded and b"base_link" in encoded
    assert b"limiting: obstacle, allowed 0.40 m/s" in encoded
    assert label(state(allowed_mps=math.inf, safety_reason="exempt")) == "clear: exempt, no limit"
    assert "(estop: web page)" in label(state(mux_state="estop", mux_reason="web page"))
    assert body_corners(SHAPE).tolist() == [[0.45, 0.2], [-0.1, 0.2], [-0.1, -0.2], [0.45, -0.2]]
