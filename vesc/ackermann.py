"""Ackermann commands to VESC set points and back, as the ROS ackermann_to_vesc / vesc_to_odom do.

::

    erpm  = speed_to_erpm_gain * speed + speed_to_erpm_offset                  (speed in m/s)
    servo = steering_angle_to_servo_gain * steering_angle + steering_angle_to_servo_offset
            (steering_angle_to_servo_gain_right for negative angles, when set)

Speed is first clamped to +-speed_max_mps and the steering angle (rad, positive left) to
+-steering_max_rad, so the limits are symmetric in SI units; the servo value is then clamped to
[servo_min, servo_max] as a last guard for the mechanical stops. A speed of exactly 0 (a stop: the
mux's e-stop, fault and idle outputs, a disarmed car) is 0 ERPM whatever the offset, and 0 ERPM reads
back as 0 m/s: the ROS formula would send ``speed_to_erpm_offset`` (up to 10,000 ERPM) to a car that
should stand, and a real VESC turns its motor at any non-zero set RPM. Nor does the offset reverse
a command: where it would flip the sign of a small speed (-0.1 m/s with an offset of +2,000 ERPM
would be +1,539 ERPM, forward), 0 ERPM is sent. ``invert_motor`` and
``invert_servo`` negate the respective gain. NaN or infinite input is refused with
:class:`~racecar_hw.base.errors.LocalProtocolError`; the caller brakes instead.

Defaults are those of the F1TENTH stack (``f1tenth_stack/config/vesc.yaml``): gain 4614,
offset 0, servo gain -1.2135, servo offset 0.5304, servo range 0.15..0.85.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from racecar_hw.base.errors import LocalProtocolError
from racecar_hw.base.messages import AckermannDrive
from vesc.params import VescParams


@dataclass(frozen=True)
class VescSetpoint:
    """What goes to the VESC for one drive command: ``erpm`` (electrical RPM) and ``servo`` (0..1)."""

    erpm: int
    servo: float


@dataclass(frozen=True)
class AckermannConversion:
    """The linear maps between (speed m/s, steering rad) and (ERPM, servo 0..1), with limits."""

    speed_to_erpm_gain: float = 4614.0
    speed_to_erpm_offset: float = 0.0
    steering_angle_to_servo_gain: float = -1.2135
    steering_angle_to_servo_offset: float = 0.5304
    servo_min: float = 0.15
    servo_max: float = 0.85
    speed_max_mps: float = 5.0
    steering_max_rad: float = 0.26
    invert_motor: bool = False
    invert_servo: bool = False
    steering_angle_to_servo_gain_right: float | None = None

    @classmethod
    def from_params(cls, p: VescParams) -> AckermannConversion:
        """The conversion configured in ``p``."""
        return cls(p.speed_to_erpm_gain, p.speed_to_erpm_offset, p.steering_angle_to_servo_gain,
                   p.steering_angle_to_servo_offset, p.servo_min, p.servo_max, p.speed_max_mps,
                   p.steering_max_rad, p.invert_motor, p.invert_servo,
                   p.steering_angle_to_servo_gain_right)

    @property
    def erpm_gain(self) -> float:
        """ERPM per m/s, sign included (inverted motors have a negative gain)."""
        return -self.speed_to_erpm_gain if self.invert_motor else self.speed_to_erpm_gain

    @property
    def servo_gain(self) -> float:
        """Servo units per radian of left turn, sign included."""
        gain = self.steering_angle_to_servo_gain
        return -gain if self.invert_servo else gain

    @property
    def servo_gain_right(self) -> float:
        """Servo units per radian of right turn, sign included."""
        gain = self.steering_angle_to_servo_gain_right
        if gain is None:
            return self.servo_gain
        return -gain if self.invert_servo else gain

    def speed_to_erpm(self, speed: float) -> int:
        """ERPM for ``speed`` m/s after the speed limit; refuses NaN/inf."""
        _finite(speed, "speed")
        if speed == 0.0:
            return 0  # stand: never the offset alone
        v = min(max(speed, -self.speed_max_mps), self.speed_max_mps)
        base = self.erpm_gain * v
        erpm = round(base + self.speed_to_erpm_offset)
        return erpm if (erpm > 0) == (base > 0) else 0  # the offset never reverses the direction

    def steering_to_servo(self, angle: float) -> float:
        """Servo position for ``angle`` rad (positive left) after both limits; refuses NaN/inf."""
        _finite(angle, "steering_angle")
        a = min(max(angle, -self.steering_max_rad), self.steering_max_rad)
        gain = self.servo_gain if a >= 0 else self.servo_gain_right
        servo = gain * a + self.steering_angle_to_servo_offset
        return min(max(servo, self.servo_min), self.servo_max)

    def to_vesc(self, drive: AckermannDrive) -> VescSetpoint:
        """The set point for a drive command (acceleration and jerk are ignored); any real number
        is taken (a numpy float32 too), anything else is refused as a NaN is."""
        speed, angle = _real(drive.speed, "speed"), _real(drive.steering_angle, "steering_angle")
        return VescSetpoint(self.speed_to_erpm(speed), self.steering_to_servo(angle))

    @property
    def servo_centre(self) -> float:
        """The servo position for straight ahead (clamped to the servo range)."""
        return self.steering_to_servo(0.0)

    def erpm_to_speed(self, erpm: float) -> float:
        """Rear-axle speed (m/s) from a measured ERPM: the inverse of :meth:`speed_to_erpm` (0 ERPM
        is standing)."""
        if erpm == 0.0:
            return 0.0
        return (erpm - self.speed_to_erpm_offset) / self.erpm_gain

    def steering_range(self) -> tuple[float, float]:
        """The steering angles (rad, right negative, left positive) the car drives at full right
        and full left: ``steering_max_rad`` each way, unless ``servo_min``/``servo_max`` clip a side
        further (a calibrated servo offset moves the centre toward one limit)."""
        right = self.servo_to_steering(self.steering_to_servo(-self.steering_max_rad))
        left = self.servo_to_steering(self.steering_to_servo(self.steering_max_rad))
        return min(right, left, 0.0), max(right, left, 0.0)

    def servo_to_steering(self, servo: float) -> float:
        """Steering angle (rad, positive left) from a servo position: the inverse map."""
        if self.servo_gain == 0.0:
            return 0.0
        angle = (servo - self.steering_angle_to_servo_offset) / self.servo_gain
        return angle if angle >= 0 else (servo - self.steering_angle_to_servo_offset) / self.servo_gain_right


def _real(value: object, what: str) -> float:
    """``value`` as a Python float (a numpy scalar's type would not pass the codec's checks)."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError) as err:
        raise LocalProtocolError(f"{what} {value!r} refused: not a number") from err


def _finite(value: float, what: str) -> None:
    if not math.isfinite(value):
        raise LocalProtocolError(f"{what} {value} refused: not a finite number")
