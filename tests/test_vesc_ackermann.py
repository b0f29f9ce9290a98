"""Ackermann <-> VESC conversion, its limits and refusals, the parameters, and odometry signs."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.errors import ConfigError, LocalProtocolError
from racecar_hw.base.messages import AckermannDrive
from racecar_hw.base.params import build, describe
from vesc.ackermann import AckermannConversion
from vesc.odometry import OdometryIntegrator
from vesc.params import VescParams

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

F1T = AckermannConversion()  # f1tenth_stack/config/vesc.yaml defaults


def test_f1tenth_defaults():
    p = VescParams()
    assert (p.speed_to_erpm_gain, p.speed_to_erpm_offset) == (4614.0, 0.0)
    assert (p.steering_angle_to_servo_gain, p.steering_angle_to_servo_offset) == (-1.2135, 0.5304)
    assert (p.servo_min, p.servo_max, p.wheelbase_m) == (0.15, 0.85, 0.25)
    assert AckermannConversion.from_params(p) == F1T


def test_forward_conversion():
    sp = F1T.to_vesc(AckermannDrive(speed=1.0, steering_angle=0.1))
    assert sp.erpm == 4614
    assert sp.servo == pytest.approx(-1.2135 * 0.1 + 0.5304)
    assert F1T.speed_to_erpm(-2.0) == -9228
    assert F1T.servo_centre == pytest.approx(0.5304)
    offset = AckermannConversion(speed_to_erpm_offset=100.0)
    assert offset.speed_to_erpm(1.0) == 4714 and offset.speed_to_erpm(-0.0) == 0
    assert offset.erpm_to_speed(4714) == pytest.approx(1.0)


def test_a_stop_is_zero_erpm_whatever_the_offset():
    """The ROS formula would send the offset alone (here 2,000 ERPM, 0.43 m/s) for speed 0, which
    is what the mux sends while e-stopped: the motor would turn."""
    conv = AckermannConversion(speed_to_erpm_offset=2000.0)
    assert conv.speed_to_erpm(0.0) == 0
    assert conv.to_vesc(AckermannDrive(speed=0.0, steering_angle=0.2)).erpm == 0
    assert conv.erpm_to_speed(0) == 0.0
    assert conv.speed_to_erpm(1e-9) == 2000  # a crawl command keeps the formula


def test_the_offset_never_reverses_a_command():
    """-0.4 and -0.1 m/s with an offset of +2,000 ERPM would be +154 and +1,539 ERPM: forward, on
    a path the safety controller never swept. They stand instead; beyond the offset they reverse."""
    conv = AckermannConversion(speed_to_erpm_offset=2000.0)
    assert conv.speed_to_erpm(-0.4) == 0 and conv.speed_to_erpm(-0.1) == 0
    assert conv.speed_to_erpm(-1.0) == -4614 + 2000
    assert conv.speed_to_erpm(0.1) == round(461.4 + 2000)
    low = AckermannConversion(speed_to_erpm_offset=-2000.0)
    assert low.speed_to_erpm(0.1) == 0 and low.speed_to_erpm(-0.1) == round(-461.4 - 2000)
    inverted = AckermannConversion(speed_to_erpm_offset=2000.0, invert_motor=True)
    assert inverted.speed_to_erpm(0.1) == 0 and inverted.speed_to_erpm(1.0) == -4614 + 2000


def test_symmetric_si_limits_then_servo_clamp():
    assert F1T.speed_to_erpm(50.0) == round(4614 * 5.0)
    assert F1T.speed_to_erpm(-50.0) == -round(4614 * 5.0)
    left, right = F1T.steering_to_servo(1.0), F1T.steering_to_servo(-1.0)
    assert left == pytest.approx(0.5304 - 1.2135 * 0.26)
    assert right == pytest.approx(0.5304 + 1.2135 * 0.26)
    # the same angle both ways at the default limit: neither side reaches servo_min/max
    assert F1T.servo_to_steering(left) == pytest.approx(-F1T.servo_to_steering(right))
    wide = AckermannConversion(steering_max_rad=0.6)
    assert wide.steering_to_servo(0.6) == 0.15
    assert wide.steering_to_servo(-0.6) == 0.85


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_input_is_refused(bad):
    with pytest.raises(LocalProtocolError):
        F1T.to_vesc(AckermannDrive(speed=bad))
    with pytest.raises(LocalProtocolError):
        F1T.to_vesc(AckermannDrive(steering_angle=bad))


def test_numpy_scalars_convert_as_floats_and_non_numbers_are_refused():
    """Code on numpy (float32 fields of a decoded message) drives as with Python floats."""
    import numpy as np

    want = F1T.to_vesc(AckermannDrive(speed=1.5, steering_angle=0.25))
    got = F1T.to_vesc(AckermannDrive(speed=np.float32(1.5), steering_angle=np.float32(0.25)))
    assert got.erpm == want.erpm and type(got.erpm) is int
    assert type(got.servo) is float and got.servo == pytest.approx(want.servo, abs=1e-6)
    for bad in ("fast", None, [1.0]):
        with pytest.raises(LocalProtocolError, match="not a number"):
            F1T.to_vesc(AckermannDrive(speed=bad))  # type: ignore[arg-type]
        with pytest.raises(LocalProtocolError, match="not a number"):
            F1T.to_vesc(AckermannDrive(steering_angle=bad))  # type: ignore[arg-type]


def test_invert_flags():
    inv = AckermannConversion(invert_motor=True, invert_servo=True)
    assert inv.speed_to_erpm(1.0) == -4614
    assert inv.steering_to_servo(0.1) == pytest.approx(0.5304 + 1.2135 * 0.1)
    assert inv.servo_centre == pytest.approx(F1T.servo_centre)
    assert inv.erpm_to_speed(-4614) == pytest.approx(1.0)
    assert inv.servo_to_steering(inv.steering_to_servo(0.1)) == pytest.approx(0.1)


@settings(deadline=None)
@given(st.floats(-5.0, 5.0), st.floats(-0.26, 0.26), st.booleans(), st.booleans())
def test_inverse_maps_round_trip(speed, angle, inv_motor, inv_servo):
    c = AckermannConversion(invert_motor=inv_motor, invert_servo=inv_servo)
    assert c.erpm_to_speed(c.speed_to_erpm(speed)) == pytest.approx(speed, abs=1 / 4614)
    assert c.servo_to_steering(c.steering_to_servo(angle)) == pytest.approx(angle, abs=1e-9)


@settings(deadline=None)
@given(st.floats(allow_nan=False), st.floats(allow_nan=False))
def test_servo_never_leaves_its_range(speed, angle):
    try:
        sp = F1T.to_vesc(AckermannDrive(speed=speed, steering_angle=angle))
    except LocalProtocolError:
        assert not (math.isfinite(speed) and math.isfinite(angle))
        return
    assert 0.15 <= sp.servo <= 0.85
    assert abs(sp.erpm) <= round(4614 * 5.0)


def test_params_validation_and_docs():
    p = build(VescParams, {"port": "auto", "brake_mode": "current", "usb_serial": "ABC"})
    assert p.usb_ids == (0x0483, 0x5740)
    with pytest.raises(ConfigError, match="brake_mode"):
        build(VescParams, {"brake_mode": "coast"})
    with pytest.raises(ConfigError, match="command_timeout_s"):
        build(VescParams, {"command_timeout_s": 0.5})
    with pytest.raises(ConfigError, match="servo_min"):
        build(VescParams, {"servo_min": 0.9})
    with pytest.raises(ConfigError, match="usb_vid_pid"):
        build(VescParams, {"usb_vid_pid": "vesc"})
    for name, _default, doc in describe(VescParams):
        assert doc, f"{name} is undocumented"


# --- odometry ----------------------------------------------------------------------------------


def _drive(odom: OdometryIntegrator, erpm: float, servo: float, seconds: float, hz: int = 50) -> None:
    n = int(seconds * hz)
    for i in range(n + 1):
        odom.update(erpm, servo, 1_000 + i * NS_PER_S // hz)


def test_odometry_forward_and_reverse_straight():
    fwd = OdometryIntegrator(F1T)
    _drive(fwd, 4614, F1T.servo_centre, 1.0)
    assert fwd.pose.x == pytest.approx(1.0, rel=1e-6)
    assert fwd.pose.y == pytest.approx(0.0, abs=1e-9) and fwd.pose.yaw == pytest.approx(0.0, abs=1e-9)
    rev = OdometryIntegrator(F1T)
    _drive(rev, -2 * 4614, F1T.servo_centre, 1.0)
    assert rev.pose.x == pytest.approx(-2.0, rel=1e-6)
    assert rev.speed == pytest.approx(-2.0)


def test_odometry_left_turn_is_positive_yaw():
    odom = OdometryIntegrator(F1T)
    left = F1T.steering_to_servo(0.2)
    _drive(odom, 4614, left, 1.0)
    expected_rate = 1.0 * math.tan(0.2) / 0.25
    assert odom.yaw_rate == pytest.approx(expected_rate)
    assert odom.pose.yaw == pytest.approx(expected_rate * 1.0, rel=1e-6)
    assert odom.pose.y > 0.0  # curving left
    # exact circle: midpoint integration keeps the car on the arc of radius L / tan(delta)
    r = 0.25 / math.tan(0.2)
    assert math.hypot(odom.pose.x, odom.pose.y - r) == pytest.approx(r, rel=1e-4)


def test_odometry_right_turn_and_reverse_left():
    right = OdometryIntegrator(F1T)
    _drive(right, 4614, F1T.steering_to_servo(-0.2), 0.5)
    assert right.yaw_rate < 0 and right.pose.y < 0
    back_left = OdometryIntegrator(F1T)
    _drive(back_left, -4614, F1T.steering_to_servo(0.2), 0.5)
    assert back_left.yaw_rate < 0  # reversing with wheels left turns clockwise
    assert back_left.pose.x < 0 and back_left.pose.y > 0


def test_odometry_inverted_servo_uses_the_inverse_map():
    inv = AckermannConversion(invert_servo=True)
    odom = OdometryIntegrator(inv)
    _drive(odom, 4614, inv.steering_to_servo(0.2), 0.5)
    assert odom.yaw_rate == pytest.approx(math.tan(0.2) / 0.25)


def test_odometry_messages():
    p = VescParams(pose_covariance_xy=0.3, pose_covariance_yaw=0.5, twist_covariance_speed=0.01)
    odom = OdometryIntegrator.from_params(p)
    _drive(odom, 4614, F1T.steering_to_servo(0.1), 0.2)
    msg = odom.odometry(1_700_000_000 * NS_PER_S)
    assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
    assert msg.header.stamp.sec == 1_700_000_000
    assert msg.pose.pose.position.x == odom.pose.x
    assert msg.pose.pose.orientation.yaw() == pytest.approx(odom.pose.yaw)
    assert msg.twist.twist.linear.x == pytest.approx(1.0)
    assert msg.twist.twist.angular.z == pytest.approx(odom.yaw_rate)
    cov = msg.pose.covariance.reshape(6, 6)
    assert cov[0, 0] == cov[1, 1] == 0.3 and cov[5, 5] == 0.5
    assert msg.twist.covariance.reshape(6, 6)[0, 0] == 0.01
    tf = odom.tf_message(0).transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "base_link")
    assert tf.transform.translation.y == odom.pose.y
    odom.reset()
    assert (odom.pose.x, odom.pose.y, odom.pose.yaw) == (0.0, 0.0, 0.0)


def test_the_steering_range_is_what_the_servo_limits_let_the_car_drive():
    """A calibrated servo offset of 0.5804 moves the centre toward servo_max: full right (-0.26 rad)
    asks for servo 0.896, clamped to 0.85, which steers -0.222 rad; full left is unclipped."""
    assert F1T.steering_range() == pytest.approx((-0.26, 0.26))
    right, left = AckermannConversion(steering_angle_to_servo_offset=0.5804).steering_range()
    assert right == pytest.approx((0.85 - 0.5804) / -1.2135) and left == pytest.approx(0.26)
    inverted = AckermannConversion(steering_angle_to_servo_offset=0.5804, invert_servo=True)
    assert inverted.steering_range() == pytest.approx((-0.26, (0.85 - 0.5804) / 1.2135))  # now left
