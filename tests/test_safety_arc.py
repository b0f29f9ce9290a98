"""The swept-footprint geometry of safety.arc, checked against a brute-force simulation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safety.arc import (
    MIN_RADIUS_CLEARANCE_M,
    STRAIGHT_RADIUS_M,
    SweptFootprint,
    free_distance,
    free_distances,
    path_lengths,
    stopping_speed,
)

CAR = SweptFootprint(front_m=0.45, rear_m=0.10, half_width_m=0.20, wheelbase_m=0.25)
LONG_TAIL = SweptFootprint(front_m=0.20, rear_m=0.50, half_width_m=0.15, wheelbase_m=0.30)


def brute_force(px: float, py: float, steering: float, fp: SweptFootprint, reverse: bool = False,
                s_max: float = 8.0, ds: float = 2.5e-4) -> float:
    """Move the rectangle along the bicycle-model path in small steps; first step touching the point."""
    s = np.arange(0.0, s_max, ds)
    signed = -s if reverse else s
    radius = fp.turn_radius(steering)
    if math.isinf(radius):
        cx, cy, th = signed, np.zeros_like(s), np.zeros_like(s)
    else:
        th = signed / radius
        cx, cy = radius * np.sin(th), radius - radius * np.cos(th)
    dx, dy = px - cx, py - cy
    lx = np.cos(th) * dx + np.sin(th) * dy
    ly = -np.sin(th) * dx + np.cos(th) * dy
    touching = (lx >= -fp.rear_m) & (lx <= fp.front_m) & (np.abs(ly) <= fp.half_width_m)
    hits = np.flatnonzero(touching)
    return float(s[hits[0]]) if hits.size else math.inf


def one(px: float, py: float, steering: float, fp: SweptFootprint = CAR, reverse: bool = False) -> float:
    return float(path_lengths(np.array([px]), np.array([py]), steering, fp, reverse)[0])


@settings(max_examples=300, deadline=None)
@given(px=st.floats(-3.0, 3.0), py=st.floats(-3.0, 3.0),
       steering=st.one_of(st.just(0.0), st.floats(-0.6, 0.6)), reverse=st.booleans(),
       fp=st.sampled_from([CAR, LONG_TAIL]))
def test_path_length_matches_brute_force(px: float, py: float, steering: float, reverse: bool,
                                         fp: SweptFootprint) -> None:
    exact = one(px, py, steering, fp, reverse)
    simulated = brute_force(px, py, steering, fp, reverse)
    if math.isinf(simulated):
        # the simulation stops at 8 m of path; beyond that the analytic answer may be finite
        assert math.isinf(exact) or exact > 8.0 - 1e-3
    else:
        assert exact == pytest.approx(simulated, abs=1e-3)


@pytest.mark.parametrize(("fp", "px", "py", "steering"), [
    (CAR, 0.0, -0.203, 0.3),  # just outside the right side, by the rear axle
    (CAR, -0.02, -0.202, 0.3),
    (LONG_TAIL, 0.1, -0.2, 0.4),
    (LONG_TAIL, -0.2, 0.17, -0.4),
])
def test_rear_swings_out_on_the_outside_of_a_turn(fp: SweptFootprint, px: float, py: float,
                                                  steering: float) -> None:
    exact = one(px, py, steering, fp)
    simulated = brute_force(px, py, steering, fp, s_max=1.0, ds=1e-5)
    assert 0.0 < simulated < 0.5, "the scenario must be a tail-swing hit"
    assert exact == pytest.approx(simulated, abs=1e-4)


def test_straight_corridor_is_car_width_plus_margin() -> None:
    x = np.array([1.0, 1.0, 1.0, 1.0, 2.0, -0.5])
    y = np.array([0.0, 0.19, 0.21, -0.21, -0.2, 0.0])
    got = path_lengths(x, y, 0.0, CAR)
    assert got[0] == pytest.approx(1.0 - 0.45)
    assert got[1] == pytest.approx(1.0 - 0.45)
    assert math.isinf(got[2]) and math.isinf(got[3])
    assert got[4] == pytest.approx(2.0 - 0.45)
    assert math.isinf(got[5]), "a point behind the car is never reached driving forward"


def test_points_inside_the_footprint_block_at_zero() -> None:
    got = path_lengths(np.array([0.3, -0.05, 0.0]), np.array([0.1, -0.15, 0.0]), 0.2, CAR)
    assert got.tolist() == [0.0, 0.0, 0.0]


def test_turn_annulus_bounds() -> None:
    steering = 0.3
    radius = CAR.wheelbase_m / math.tan(steering)
    inner = radius - CAR.half_width_m
    outer = math.hypot(CAR.front_m, radius + CAR.half_width_m)
    # points straight "above" the ICR (x = 0 side, ahead after a quarter turn): (r, radius)
    for r, blocked in [(inner - 0.01, False), (inner + 0.01, True), (outer - 0.01, True),
                       (outer + 0.01, False)]:
        got = one(r, radius, steering)
        assert math.isfinite(got) == blocked, (r, got)


def test_steering_toward_and_away_from_a_point_on_the_inside() -> None:
    post = (1.0, 0.45)
    assert math.isinf(one(*post, 0.0))
    assert math.isfinite(one(*post, 0.3))
    assert math.isinf(one(*post, -0.3))


def test_left_right_mirror_symmetry() -> None:
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-4, 4, 500), rng.uniform(-4, 4, 500)
    left = path_lengths(x, y, 0.25, CAR)
    right = path_lengths(x, -y, -0.25, CAR)
    np.testing.assert_allclose(left, right)


def test_reverse_is_forward_mirrored_front_to_back() -> None:
    rng = np.random.default_rng(8)
    x, y = rng.uniform(-4, 4, 500), rng.uniform(-4, 4, 500)
    swapped = SweptFootprint(CAR.rear_m, CAR.front_m, CAR.half_width_m, CAR.wheelbase_m)
    np.testing.assert_allclose(path_lengths(x, y, 0.2, CAR, reverse=True),
                               path_lengths(-x, y, 0.2, swapped))


def test_turn_radius_limits() -> None:
    assert math.isinf(CAR.turn_radius(0.0))
    assert math.isinf(CAR.turn_radius(CAR.wheelbase_m / (2 * STRAIGHT_RADIUS_M)))
    assert CAR.turn_radius(0.3) == pytest.approx(0.25 / math.tan(0.3))
    assert CAR.turn_radius(1.5) == pytest.approx(CAR.half_width_m + MIN_RADIUS_CLEARANCE_M)
    assert CAR.turn_radius(-1.5) == pytest.approx(-(CAR.half_width_m + MIN_RADIUS_CLEARANCE_M))


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), steering=st.floats(-0.7, 0.7), reverse=st.booleans(),
       fp=st.sampled_from([CAR, LONG_TAIL]))
def test_free_distance_is_the_minimum_path_length(seed: int, steering: float, reverse: bool,
                                                  fp: SweptFootprint) -> None:
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-3, 6, 300), rng.uniform(-3, 3, 300)
    lengths = path_lengths(x, y, steering, fp, reverse)
    hit = free_distance(x, y, steering, fp, max_path_m=5.0, reverse=reverse)
    best = float(lengths.min())
    if best >= 5.0:
        assert hit.index == -1 and hit.distance_m == 5.0
    else:
        assert hit.distance_m == pytest.approx(best, abs=1e-9)
        assert lengths[hit.index] == pytest.approx(best, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), steering=st.floats(-0.7, 0.7), reverse=st.booleans(),
       n=st.integers(0, 60), first=st.integers(0, 70))
def test_the_nearest_of_the_first_points_is_what_sweeping_them_alone_gives(seed: int, steering: float,
                                                                          reverse: bool, n: int,
                                                                          first: int) -> None:
    # the live scan's points first, the remembered ones after them: one sweep names both
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-2, 4, n), rng.uniform(-2, 2, n)
    hit, nearest_first = free_distances(x, y, steering, CAR, 3.0, reverse, first)
    assert hit == free_distance(x, y, steering, CAR, 3.0, reverse)
    assert nearest_first == free_distance(x[:first], y[:first], steering, CAR, 3.0, reverse)


def test_free_distance_picks_the_nearest_point_and_caps() -> None:
    x, y = np.array([3.0, 1.5, 9.0]), np.array([0.0, 0.1, 0.0])
    hit = free_distance(x, y, 0.0, CAR, max_path_m=10.0)
    assert hit.index == 1 and hit.distance_m == pytest.approx(1.05)
    far = free_distance(np.array([20.0]), np.array([0.0]), 0.0, CAR, max_path_m=10.0)
    assert far.index == -1 and far.distance_m == 10.0
    empty = free_distance(np.zeros(0), np.zeros(0), 0.1, CAR, max_path_m=4.0)
    assert empty.index == -1 and empty.distance_m == 4.0


@given(d=st.floats(0.0, 50.0), t=st.floats(0.0, 0.5), a=st.floats(0.1, 20.0))
def test_stopping_speed_solves_the_stopping_equation(d: float, t: float, a: float) -> None:
    v = stopping_speed(d, t, a)
    assert v >= 0.0
    assert v * t + v * v / (2 * a) == pytest.approx(d, rel=1e-9, abs=1e-12)


def test_stopping_speed_is_zero_without_room() -> None:
    assert stopping_speed(0.0, 0.05, 4.0) == 0.0
    assert stopping_speed(-1.0, 0.05, 4.0) == 0.0
    assert stopping_speed(math.nan, 0.05, 4.0) == 0.0
