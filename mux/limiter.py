"""Acceleration, braking and steering-rate limits on the mux output, in fixed time steps.

The limiter advances by a FIXED period, ``1 / rate_hz``, per step: it never reads a clock, so
scheduler jitter cannot widen a step and let a larger change through. When the output loop
misses deadlines it says how many periods passed (``periods``), an integer count of its own
schedule, so a stop is not slowed down by a late loop either.

Speed: a change toward zero (braking) is limited by ``max_decel_mps2``, a change away from zero by
``max_accel_mps2``. A target on the other side of zero brakes to zero first and spends the rest of
the step accelerating the other way. Steering: the angle moves by at most
``max_steering_rate_radps`` per second, toward the target clamped to ``steering_range`` (the angles
the car can drive, the VESC conversion's): a target beyond the servo's reach is driven at the
limit, so the held angle never winds up past what the car steers. Speed targets are clamped
to ``speed_max_mps`` (the VESC conversion's) the same way: a command of 100 m/s held the limiter at
7.5 m/s after 3 s while the VESC drove 5, and a stop then spent 0.3 s ramping down from 7.5 at the
full 5 m/s before the car slowed at all. Otherwise a command of 1 rad on
a car that steers 0.26 held the limiter at 1 rad, and a turn the other way then waited
(1 - 0.26) / 3.2 s = 0.23 s before the wheels moved at all, off the arc the safety controller checked.

ROS 1's throttle_interpolator ran its speed timer at ``1 / max_delta_rpm`` instead of
``1 / rate``, which lets roughly ``gain * max_accel^2 / rate^2`` through (about 10 m/s^2 for a
configured 3.5 on the MIT car); here the step size and the step period come from the same
``rate_hz`` (``tests/test_mux_limiter.py`` checks the realized acceleration).

Targets are finite: the mux turns a non-finite command on one of its inputs into a stop before
arbitration (the one check on the way, docs/architecture.md "Finite commands"); the VESC
conversion refuses NaN/inf as the last guard before the hardware.
"""

from __future__ import annotations

import math

from mux.params import MuxParams
from racecar_hw.base.messages import AckermannDrive


class RateLimiter:
    """Rate limits for speed (m/s) and steering angle (rad), stepped at a fixed period (s)."""

    def __init__(self, max_accel_mps2: float, max_decel_mps2: float, max_steering_rate_radps: float,
                 period_s: float, enabled: bool = True,
                 steering_range: tuple[float, float] = (-math.inf, math.inf),
                 speed_max_mps: float = math.inf) -> None:
        for name, value in (("max_accel_mps2", max_accel_mps2), ("max_decel_mps2", max_decel_mps2),
                            ("max_steering_rate_radps", max_steering_rate_radps),
                            ("period_s", period_s)):
            if not value > 0.0:
                raise ValueError(f"{name} must be greater than 0, got {value!r}")
        self.max_accel_mps2 = max_accel_mps2
        self.max_decel_mps2 = max_decel_mps2
        self.max_steering_rate_radps = max_steering_rate_radps
        self.period_s = period_s
        self.enabled = enabled
        #: (right, left) steering angles (rad) the car drives at full lock; targets are clamped to it
        self.steering_range = (float(steering_range[0]), float(steering_range[1]))
        #: the fastest speed (m/s, either way) the car is sent; targets are clamped to it
        self.speed_max_mps = float(speed_max_mps)
        #: the last output speed, m/s
        self.speed = 0.0
        #: the last output steering angle, rad
        self.steering_angle = 0.0

    @classmethod
    def from_params(cls, params: MuxParams, steering_range: tuple[float, float] = (-math.inf, math.inf),
                    speed_max_mps: float = math.inf) -> RateLimiter:
        """The limiter configured by the mux parameters, stepping at ``1 / rate_hz``."""
        return cls(params.max_accel_mps2, params.max_decel_mps2, params.max_steering_rate_radps,
                   1.0 / params.rate_hz, params.limiter_enabled, steering_range, speed_max_mps)

    def reset(self, speed: float = 0.0, steering_angle: float = 0.0) -> None:
        """Forget the past output: the next step starts from ``speed`` and ``steering_angle``."""
        self.speed = float(speed)
        self.steering_angle = float(steering_angle)

    def clamp(self, speed: float) -> None:
        """Lower the held speed to at most ``|speed|`` (m/s), keeping its direction: a safety cut
        between steps. The next steps start from there, so they cannot raise the speed again faster
        than ``max_accel_mps2``. A held speed already at or below ``|speed|`` is unchanged."""
        self.speed = math.copysign(min(abs(self.speed), abs(speed)), self.speed)

    def step(self, speed: float, steering_angle: float, periods: int = 1) -> tuple[float, float]:
        """Move toward the target over ``periods`` fixed periods; returns (speed, steering)."""
        low, high = self.steering_range
        top = self.speed_max_mps
        speed, steering_angle = min(max(float(speed), -top), top), min(max(float(steering_angle), low), high)
        if self.enabled:
            dt = self.period_s * max(1, periods)
            speed = self._speed_toward(speed, dt)
            steering_angle = _toward(self.steering_angle, steering_angle,
                                     self.max_steering_rate_radps * dt)
        self.speed = speed
        self.steering_angle = steering_angle
        return speed, steering_angle

    def limit(self, drive: AckermannDrive, periods: int = 1) -> AckermannDrive:
        """A new command: ``drive`` with speed and steering limited, other fields copied."""
        speed, steering = self.step(drive.speed, drive.steering_angle, periods)
        return AckermannDrive(steering, drive.steering_angle_velocity, speed, drive.acceleration,
                              drive.jerk)

    def preview(self, drive: AckermannDrive, periods: int = 1) -> AckermannDrive:
        """What :meth:`limit` would return, without taking the step (the state is unchanged)."""
        speed, steering = self.speed, self.steering_angle
        try:
            return self.limit(drive, periods)
        finally:
            self.speed, self.steering_angle = speed, steering

    def _speed_toward(self, target: float, dt: float) -> float:
        v = self.speed
        if v == target:
            return v
        if (v > 0.0 and target < v) or (v < 0.0 and target > v):
            # Braking: toward zero, or toward a smaller speed on the same side.
            floor = max(target, 0.0) if v > 0.0 else min(target, 0.0)
            gap = abs(v - floor)
            if gap >= self.max_decel_mps2 * dt:
                return v - math.copysign(self.max_decel_mps2 * dt, v)
            dt -= gap / self.max_decel_mps2
            v = floor
            if v == target:
                return v
        return _toward(v, target, self.max_accel_mps2 * dt)


def _toward(value: float, target: float, max_change: float) -> float:
    if target > value:
        return min(target, value + max_change)
    return max(target, value - max_change)

