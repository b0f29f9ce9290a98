"""The rate limiter: acceleration, braking, zero crossing, steering rate, fixed period."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mux.limiter import RateLimiter
from mux.params import MuxParams
from racecar_hw.base.messages import AckermannDrive

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

TOL = 1e-9


def _limiter(accel: float = 2.5, decel: float = 8.0, steer: float = 3.2, rate: float = 50.0,
             enabled: bool = True) -> RateLimiter:
    return RateLimiter(accel, decel, steer, 1.0 / rate, enabled)


def test_from_params_uses_the_output_rate_as_its_fixed_period():
    lim = RateLimiter.from_params(MuxParams(rate_hz=40.0, max_accel_mps2=3.0))
    assert lim.period_s == 1.0 / 40.0
    assert lim.max_accel_mps2 == 3.0
    assert lim.max_decel_mps2 == 8.0
    assert lim.max_steering_rate_radps == 3.2


def test_step_from_0_to_5_accelerates_at_exactly_the_configured_limit():
    lim = _limiter(accel=2.5, rate=50.0)
    speeds = [lim.step(5.0, 0.0)[0] for _ in range(150)]
    for n, v in enumerate(speeds, start=1):
        t = n / 50.0
        assert v == pytest.approx(min(5.0, 2.5 * t), abs=TOL)
    assert speeds[99] == pytest.approx(5.0, abs=TOL)  # 2 s at 2.5 m/s^2
    assert speeds[-1] == 5.0


def _buggy_ros1_throttle_interpolator_speed(t_s: float, gain: float, max_accel: float,
                                            rate: float, target: float) -> float:
    """Speed reached after ``t_s`` by ROS 1's throttle_interpolator, whose timer period is
    1 / max_delta_rpm seconds (the bug) while each firing still moves max_delta_rpm."""
    max_delta_rpm = abs(gain) * max_accel / rate
    firings = math.floor(t_s * max_delta_rpm)
    return min(target, firings * max_delta_rpm / abs(gain))


@pytest.mark.parametrize(("car", "gain", "accel", "rate"), [
    ("MIT", 4614.0, 3.5, 75.0),
    ("MuSHR", -3500.0, 2.5, 75.0),
])
def test_no_throttle_interpolator_period_bug(car, gain, accel, rate):
    """The ROS 1 throttle_interpolator let through ~|gain| * a^2 / rate^2; ours realizes a."""
    bug_factor = abs(gain) * accel / rate**2  # buggy realized / configured
    assert bug_factor > 1.5, car  # the bug really is large for these cars
    lim = _limiter(accel=accel, rate=rate)
    target = 5.0
    steps = int(0.5 * rate)  # half a second, well before either reaches 5 m/s
    for _ in range(steps):
        ours, _steering = lim.step(target, 0.0)
    t = steps / rate
    assert ours == pytest.approx(accel * t, abs=TOL)
    realized = ours / t
    assert realized == pytest.approx(accel, rel=1e-9)
    buggy = _buggy_ros1_throttle_interpolator_speed(t, gain, accel, rate, target) / t
    assert buggy > 1.4 * accel  # what the old node did, for contrast
    assert buggy == pytest.approx(accel * bug_factor, rel=0.05)


def test_braking_to_zero_uses_max_decel_and_is_never_slower():
    lim = _limiter(decel=8.0, rate=50.0)
    lim.reset(speed=5.0)
    previous = 5.0
    for n in range(1, 40):
        v, _ = lim.step(0.0, 0.0)
        expected = max(0.0, 5.0 - 8.0 * n / 50.0)
        assert v == pytest.approx(expected, abs=TOL)
        assert previous - v == pytest.approx(min(previous, 8.0 / 50.0), abs=TOL)
        previous = v
    assert v == 0.0  # exactly stopped, no creeping residue


def test_braking_in_reverse_and_to_a_lower_speed_use_max_decel():
    lim = _limiter()
    lim.reset(speed=-3.0)
    assert lim.step(0.0, 0.0)[0] == pytest.approx(-3.0 + 0.16, abs=TOL)
    lim.reset(speed=5.0)
    assert lim.step(2.0, 0.0)[0] == pytest.approx(5.0 - 0.16, abs=TOL)
    lim.reset(speed=2.1)
    assert lim.step(2.0, 0.0)[0] == 2.0


def test_accelerating_in_reverse_uses_max_accel():
    lim = _limiter()
    for n in range(1, 11):
        assert lim.step(-2.0, 0.0)[0] == pytest.approx(-0.05 * n, abs=TOL)


def test_zero_crossing_brakes_to_zero_then_accelerates_within_one_step():
    lim = _limiter(accel=2.5, decel=8.0, rate=50.0)
    lim.reset(speed=1.0)
    speeds = [lim.step(-1.0, 0.0)[0] for _ in range(6)]
    assert speeds[-1] == pytest.approx(1.0 - 6 * 0.16, abs=TOL)  # 0.04 m/s left
    # step 7: 0.005 s braking the last 0.04 m/s, then 0.015 s accelerating backwards
    v = lim.step(-1.0, 0.0)[0]
    assert v == pytest.approx(-2.5 * 0.015, abs=TOL)
    v = lim.step(-1.0, 0.0)[0]
    assert v == pytest.approx(-2.5 * 0.015 - 0.05, abs=TOL)
    for _ in range(100):
        v = lim.step(-1.0, 0.0)[0]
    assert v == -1.0


def test_skipped_periods_advance_the_limits_by_whole_periods():
    lim = _limiter()
    lim.reset(speed=5.0)
    assert lim.step(0.0, 0.0, periods=5)[0] == pytest.approx(5.0 - 8.0 * 0.1, abs=TOL)
    lim.reset()
    assert lim.step(5.0, 0.0, periods=3)[0] == pytest.approx(2.5 * 0.06, abs=TOL)
    # periods below 1 count as 1
    lim.reset()
    assert lim.step(5.0, 0.0, periods=0)[0] == pytest.approx(0.05, abs=TOL)


def test_steering_rate_limit_both_ways():
    lim = _limiter(steer=3.2, rate=50.0)
    angles = [lim.step(0.0, 0.34)[1] for _ in range(7)]
    assert angles[:5] == pytest.approx([0.064 * n for n in range(1, 6)], abs=TOL)
    assert angles[5:] == [0.34, 0.34]
    assert lim.step(0.0, -0.34)[1] == pytest.approx(0.34 - 0.064, abs=TOL)


def test_disabled_limiter_passes_targets_through():
    lim = _limiter(enabled=False)
    assert lim.step(5.0, 0.3) == (5.0, 0.3)
    assert lim.step(-5.0, -0.3) == (-5.0, -0.3)


def test_limit_returns_a_new_command_and_copies_other_fields():
    lim = _limiter()
    drive = AckermannDrive(steering_angle=0.3, steering_angle_velocity=1.0, speed=4.0,
                           acceleration=2.0, jerk=3.0)
    out = lim.limit(drive)
    assert out is not drive
    assert drive.speed == 4.0  # untouched
    assert out == AckermannDrive(0.064, 1.0, 0.05, 2.0, 3.0)


def test_rejects_non_positive_limits():
    with pytest.raises(ValueError, match="max_decel_mps2"):
        RateLimiter(2.5, 0.0, 3.2, 0.02)
    with pytest.raises(ValueError, match="period_s"):
        RateLimiter(2.5, 8.0, 3.2, math.nan)


_speed = st.floats(min_value=-10.0, max_value=10.0)
_angle = st.floats(min_value=-0.5, max_value=0.5)


@given(st.lists(st.tuples(_speed, _angle, st.integers(1, 4)), min_size=1, max_size=60))
def test_every_step_respects_the_limits(targets):
    accel, decel, rate_radps, period = 2.5, 8.0, 3.2, 0.02
    lim = RateLimiter(accel, decel, rate_radps, period)
    for target, angle, periods in targets:
        v0, a0 = lim.speed, lim.steering_angle
        v, a = lim.step(target, angle, periods)
        dt = period * periods
        assert abs(a - a0) <= rate_radps * dt + TOL
        assert min(a0, angle) - TOL <= a <= max(a0, angle) + TOL  # never overshoots
        assert min(v0, target) - TOL <= v <= max(v0, target) + TOL
        assert abs(v) - abs(v0) <= accel * dt + TOL  # never faster than max_accel away from 0
        assert abs(v - v0) <= max(accel, decel) * dt + TOL
        if target == 0.0:
            # a stop is never slowed beyond the configured deceleration
            assert abs(v) == pytest.approx(max(0.0, abs(v0) - decel * dt), abs=TOL)


def test_clamp_lowers_the_held_speed_keeping_its_direction_and_the_next_steps_ramp_from_there():
    for sign in (1.0, -1.0):
        lim = _limiter(accel=2.5, rate=50.0)
        lim.reset(speed=sign * 2.0, steering_angle=0.1)
        lim.clamp(0.5)  # a safety cut to 0.5 m/s (its sign does not matter: the magnitude is held)
        assert lim.speed == sign * 0.5 and lim.steering_angle == 0.1
        lim.clamp(sign * 1.5)  # never raises the held speed
        assert lim.speed == sign * 0.5
        speed, _ = lim.step(sign * 2.0, 0.1)  # back up at the acceleration limit, not at once
        assert speed == pytest.approx(sign * (0.5 + 2.5 / 50.0), abs=TOL)
    lim = _limiter()
    lim.clamp(0.0)
    assert lim.speed == 0.0


def test_a_steering_target_beyond_the_cars_reach_is_held_at_full_lock_not_wound_up():
    """A car that steers 0.26 rad each way, commanded 1 rad left for a second and then 1 rad right:
    the held angle stops at 0.26, so the first step of the turn back already moves the wheels."""
    lim = RateLimiter(2.5, 8.0, 3.2, 0.02, steering_range=(-0.26, 0.26))
    for _ in range(50):
        _, steering = lim.step(1.0, 1.0)
    assert steering == pytest.approx(0.26, abs=TOL)
    _, steering = lim.step(1.0, -1.0)
    assert steering == pytest.approx(0.26 - 3.2 * 0.02, abs=TOL)
    # without the range, the same commands wind the limiter up to 1 rad (what the mux had before)
    free = RateLimiter(2.5, 8.0, 3.2, 0.02)
    for _ in range(50):
        free.step(1.0, 1.0)
    assert free.step(1.0, -1.0)[1] == pytest.approx(1.0 - 3.2 * 0.02, abs=TOL)
    # and with the limits off the output is still within what the car drives
    off = RateLimiter(2.5, 8.0, 3.2, 0.02, enabled=False, steering_range=(-0.3, 0.2))
    assert off.step(1.0, -1.0)[1] == -0.3
    assert off.step(1.0, 1.0)[1] == 0.2


def test_a_speed_target_beyond_the_cars_top_speed_is_held_at_it_not_wound_up():
    """A command of 100 m/s for 3 s on a car sent at most 5 m/s, then a stop: the held speed stops
    at 5, so the stop brakes from 5 at once (it once ramped down from 7.5 while the VESC still got 5)."""
    lim = RateLimiter(2.5, 8.0, 3.2, 0.02, speed_max_mps=5.0)
    for _ in range(150):
        speed, _ = lim.step(100.0, 0.0)
    assert speed == pytest.approx(5.0, abs=TOL)
    assert lim.step(0.0, 0.0)[0] == pytest.approx(5.0 - 8.0 * 0.02, abs=TOL)
    for _ in range(150):
        speed, _ = lim.step(-100.0, 0.0)
    assert speed == pytest.approx(-5.0, abs=TOL)
    # without the bound the same commands wind it up (what the mux had before)
    free = RateLimiter(2.5, 8.0, 3.2, 0.02)
    for _ in range(150):
        speed, _ = free.step(100.0, 0.0)
    assert speed == pytest.approx(7.5, abs=1e-6)
