"""Wheel odometry from the VESC: measured ERPM and the servo position actually sent.

Speed v (m/s, rear axle, negative in reverse) = :meth:`AckermannConversion.erpm_to_speed`;
steering delta (rad, positive left) = :meth:`AckermannConversion.servo_to_steering` of the
commanded servo value (the VESC does not measure the steering); yaw rate = v tan(delta) / wheelbase,
or the IMU's gyro z when the driver passes one (``vesc.odometry_yaw_rate: imu``).
So moving forward with the wheels turned left gives a positive (counter-clockwise) yaw rate, and
reversing with the wheels turned left a negative one.

Integration is midpoint (second order): over each interval the velocities are the mean of both
ends, and the heading used for the translation is the heading at mid-interval. The pose is in
``odom`` (REP-105), the twist in ``base_link``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from racecar_hw.base.clock import seconds
from racecar_hw.base.messages import (
    Header,
    Odometry,
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    TFMessage,
    Time,
    Transform,
    TransformStamped,
    Twist,
    TwistWithCovariance,
    Vector3,
)
from vesc.ackermann import AckermannConversion
from vesc.params import VescParams

#: Variance for axes a planar car cannot move in (z, roll, pitch): large, "unknown".
_UNUSED_AXIS_VARIANCE = 1e6


@dataclass
class Pose2D:
    """x, y in metres and yaw in radians, in the odom frame."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0


class OdometryIntegrator:
    """Integrates (ERPM, servo) samples into a planar pose."""

    def __init__(self, conversion: AckermannConversion, wheelbase_m: float = 0.25,
                 odom_frame_id: str = "odom", base_frame_id: str = "base_link",
                 pose_covariance: tuple[float, float] = (0.2, 0.4),
                 twist_covariance: tuple[float, float] = (0.05, 0.1)) -> None:
        self.conversion = conversion
        self.wheelbase_m = wheelbase_m
        self.odom_frame_id = odom_frame_id
        self.base_frame_id = base_frame_id
        self.pose = Pose2D()
        self.speed = 0.0
        self.yaw_rate = 0.0
        self._last_ns: int | None = None
        self._pose_cov = _covariance(pose_covariance[0], pose_covariance[1])
        self._twist_cov = _covariance(twist_covariance[0], twist_covariance[1])

    @classmethod
    def from_params(cls, p: VescParams) -> OdometryIntegrator:
        """An integrator configured from the driver parameters."""
        return cls(AckermannConversion.from_params(p), p.wheelbase_m, p.odom_frame_id, p.base_frame_id,
                   (p.pose_covariance_xy, p.pose_covariance_yaw),
                   (p.twist_covariance_speed, p.twist_covariance_yaw_rate))

    def reset(self) -> None:
        """Back to the origin, forgetting the last sample time."""
        self.pose = Pose2D()
        self.speed = self.yaw_rate = 0.0
        self._last_ns = None

    def update(self, erpm: float, servo: float, t_ns: int, yaw_rate: float | None = None) -> Pose2D:
        """Add a sample taken at monotonic ``t_ns``; returns the new pose.

        ``yaw_rate`` (rad/s, a gyro's) replaces the steering model's when given. The first sample
        (and any sample not later than the previous one) only sets the velocities.
        """
        speed = self.conversion.erpm_to_speed(erpm)
        if yaw_rate is None:
            delta = self.conversion.servo_to_steering(servo)
            yaw_rate = speed * math.tan(delta) / self.wheelbase_m
        if self._last_ns is not None and t_ns > self._last_ns:
            dt = seconds(t_ns - self._last_ns)
            v = 0.5 * (self.speed + speed)
            w = 0.5 * (self.yaw_rate + yaw_rate)
            mid_yaw = self.pose.yaw + 0.5 * w * dt
            self.pose.x += v * math.cos(mid_yaw) * dt
            self.pose.y += v * math.sin(mid_yaw) * dt
            self.pose.yaw = _wrap(self.pose.yaw + w * dt)
        if self._last_ns is None or t_ns > self._last_ns:
            self._last_ns = t_ns
        self.speed, self.yaw_rate = speed, yaw_rate
        return self.pose

    def odometry(self, stamp_ns: int) -> Odometry:
        """nav_msgs/Odometry for the current state, stamped ``stamp_ns`` (wall clock)."""
        p = self.pose
        return Odometry(
            header=Header(Time.from_ns(stamp_ns), self.odom_frame_id),
            child_frame_id=self.base_frame_id,
            pose=PoseWithCovariance(Pose(Point(p.x, p.y, 0.0), Quaternion.from_yaw(p.yaw)),
                                    self._pose_cov.copy()),
            twist=TwistWithCovariance(Twist(Vector3(self.speed, 0.0, 0.0), Vector3(0.0, 0.0, self.yaw_rate)),
                                      self._twist_cov.copy()),
        )

    def transform(self, stamp_ns: int) -> TransformStamped:
        """The odom -> base_link transform for the current pose."""
        p = self.pose
        return TransformStamped(Header(Time.from_ns(stamp_ns), self.odom_frame_id), self.base_frame_id,
                                Transform(Vector3(p.x, p.y, 0.0), Quaternion.from_yaw(p.yaw)))

    def tf_message(self, stamp_ns: int) -> TFMessage:
        """A TFMessage carrying :meth:`transform`."""
        return TFMessage([self.transform(stamp_ns)])


def _covariance(linear: float, angular: float) -> np.ndarray:
    """Row-major 6x6 diagonal: x, y = ``linear``; z, roll, pitch unknown; yaw = ``angular``."""
    diag = [linear, linear, _UNUSED_AXIS_VARIANCE, _UNUSED_AXIS_VARIANCE, _UNUSED_AXIS_VARIANCE, angular]
    return np.diag(np.array(diag, dtype=np.float64)).reshape(36)


def _wrap(angle: float) -> float:
    """``angle`` in (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))
