"""The calibration procedure's checks on a straight leg (:class:`StraightLeg`), as numbers: the
runs against the simulated car are in tests/test_calibrate.py."""

from __future__ import annotations

import math

import pytest

from racecar_hw.sources.calibration import MAX_HEADING_DEG, WRONG_WAY_M, CalibrationAborted, StraightLeg

GAIN = 4614.0
TACH_PER_M = GAIN / 10.0


@pytest.mark.parametrize(("direction", "step"), [(1.0, "toward the wall"), (-1.0, "back from the wall")])
def test_the_wall_moving_the_way_the_car_was_told_passes(direction, step):
    leg = StraightLeg(step, direction, 3.0, GAIN)
    for k in range(50):
        moved = 0.01 * k
        leg.check(3.0 - direction * moved, 0.0, moved * TACH_PER_M)


@pytest.mark.parametrize(("direction", "step", "text"), [
    (1.0, "toward the wall", "drove away from the wall when told to drive toward it"),
    (-1.0, "back from the wall", "drove toward the wall when told to drive away from it"),
])
def test_the_wall_moving_the_other_way_names_invert_motor(direction, step, text):
    leg = StraightLeg(step, direction, 3.0, GAIN)
    leg.check(3.0 + direction * WRONG_WAY_M * 0.9, 0.0, 0.0)  # scan-to-scan scatter: not yet
    with pytest.raises(CalibrationAborted) as err:
        leg.check(3.0 + direction * WRONG_WAY_M * 1.1, 0.0, 0.0)
    assert str(err.value).startswith(f"stopped during {step}: the car {text}")
    assert str(err.value).endswith("check vesc.invert_motor")


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_heading_running_off_names_invert_servo(sign):
    leg = StraightLeg("toward the wall", 1.0, 3.0, GAIN)
    leg.check(2.9, sign * math.radians(MAX_HEADING_DEG * 0.9), 0.1 * TACH_PER_M)
    with pytest.raises(CalibrationAborted, match=r"vesc\.invert_servo \(or the sign of "
                                                 r"vesc\.steering_angle_to_servo_gain\)$"):
        leg.check(2.9, sign * math.radians(MAX_HEADING_DEG * 1.1), 0.1 * TACH_PER_M)


def test_a_wall_that_stops_agreeing_with_the_distance_driven_still_aborts():
    leg = StraightLeg("toward the wall", 1.0, 3.0, GAIN, first=(0.0, 2.9))
    leg.check(2.5, 0.0, 0.4 * TACH_PER_M)
    with pytest.raises(CalibrationAborted, match="the wall is not where it should be"):
        leg.check(2.8, 0.0, 1.5 * TACH_PER_M)  # 1.5 m driven, the wall 0.1 m nearer
