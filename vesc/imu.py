"""The VESC's IMU reply as ``sensor_msgs/Imu``, and the gyro bias estimated at standstill.

COMM_GET_IMU_DATA (:class:`~vesc.codec.ImuData`) carries the firmware's units: angular rate in
deg/s, acceleration in g (specific force: +1 g on z when the board lies flat and still), the
orientation as a quaternion (w, x, y, z) whose yaw is relative to the heading at boot (no
magnetometer fusion). The firmware has already rotated the axes for the board and applied VESC
Tool's mounting rotation, so the reply is in the IMU frame (``imu_frame_id``, REP-103: x forward,
y left, z up when mounted as configured); where the IMU sits on the car is the static transform
``base_link -> imu`` in the config, like the laser's.

:func:`imu_message` converts to SI (rad/s, m/s², REP-145's convention that the acceleration
includes gravity) and sets the covariances from the datasheet figures
(:class:`ImuCovariances`). The firmware's roll/pitch/yaw fields are not used (roll and yaw are
negated relative to the quaternion); the quaternion is.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from racecar_hw.base.clock import seconds
from racecar_hw.base.messages import Header, Imu, Quaternion, Time, Vector3
from vesc.codec import ImuData

#: Standard gravity (m/s² per g), the unit the firmware's accelerometer reports in.
G = 9.80665
DEG = math.pi / 180.0
#: Norms of the reply's quaternion taken as an orientation (the firmware sends a unit quaternion;
#: float32 rounding moves it by far less).
QUATERNION_NORM_RANGE = (0.9, 1.1)
#: A covariance that says "not provided" (sensor_msgs/Imu: element 0 is -1).
_NOT_PROVIDED = np.zeros(9)
_NOT_PROVIDED[0] = -1.0


@dataclass(frozen=True)
class ImuCovariances:
    """Diagonal variances of the published message.

    ``orientation_rp`` roll and pitch (rad²), ``orientation_yaw`` yaw (rad², large: no
    magnetometer, so heading drifts from the boot heading), ``angular_velocity`` ((rad/s)²),
    ``linear_acceleration`` ((m/s²)²).
    """

    orientation_rp: float
    orientation_yaw: float
    angular_velocity: float
    linear_acceleration: float

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The three row-major 3x3 covariance arrays of sensor_msgs/Imu (new copies each call: a
        message owns its arrays)."""
        o, w, a = self._diagonals
        return o.copy(), w.copy(), a.copy()

    @functools.cached_property
    def _diagonals(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The arrays, built once (the IMU is read at 50 Hz)."""
        def diag(a: float, b: float, c: float) -> np.ndarray:
            return np.diag(np.array([a, b, c], dtype=np.float64)).reshape(9)
        return (diag(self.orientation_rp, self.orientation_rp, self.orientation_yaw),
                diag(*(self.angular_velocity,) * 3), diag(*(self.linear_acceleration,) * 3))


def imu_message(data: ImuData, stamp_ns: int, frame_id: str, cov: ImuCovariances,
                gyro_bias_z: float = 0.0) -> Imu:
    """``data`` as sensor_msgs/Imu stamped ``stamp_ns`` (wall ns) in ``frame_id``.

    A group the reply does not carry whole (the mask left out any of its fields) is "not
    provided" as sensor_msgs/Imu defines it: zeros, and a covariance of zeros with element 0 at
    -1: the acceleration (``acc_x..z``), the angular velocity (``gyro_x..z``), or the orientation
    (``q0..q3``; also a quaternion whose norm is not about 1, :data:`QUATERNION_NORM_RANGE`: all
    zeros from an IMU not yet running, damaged bytes). ``gyro_bias_z`` (rad/s) is subtracted from
    the z rate.
    """
    o_cov, w_cov, a_cov = cov.arrays()
    rates = (data.gyro_x, data.gyro_y, data.gyro_z)
    accelerations = (data.acc_x, data.acc_y, data.acc_z)
    quat = (data.q0, data.q1, data.q2, data.q3)
    norm = (math.sqrt(sum(float(q) * float(q) for q in quat))  # type: ignore[arg-type]
            if all(q is not None for q in quat) else 0.0)
    lo, hi = QUATERNION_NORM_RANGE
    if not lo <= norm <= hi:
        orientation, o_cov = Quaternion(), _NOT_PROVIDED.copy()
    else:
        w, x, y, z = (float(q) for q in quat)  # type: ignore[arg-type]
        orientation = Quaternion(x / norm, y / norm, z / norm, w / norm)
    if None in rates:
        angular_velocity, w_cov = Vector3(), _NOT_PROVIDED.copy()
    else:
        wx, wy, wz = (float(r) * DEG for r in rates)  # type: ignore[arg-type]
        angular_velocity = Vector3(wx, wy, wz - gyro_bias_z)
    if None in accelerations:
        linear_acceleration, a_cov = Vector3(), _NOT_PROVIDED.copy()
    else:
        linear_acceleration = Vector3(*(float(a) * G for a in accelerations))  # type: ignore[arg-type]
    return Imu(header=Header(Time.from_ns(stamp_ns), frame_id),
               orientation=orientation, orientation_covariance=o_cov,
               angular_velocity=angular_velocity, angular_velocity_covariance=w_cov,
               linear_acceleration=linear_acceleration, linear_acceleration_covariance=a_cov)


def imu_provides(msg: Imu) -> bool:
    """Whether ``msg`` carries anything: an orientation, angular velocity or acceleration."""
    return any(cov[0] != -1.0 for cov in (msg.orientation_covariance, msg.angular_velocity_covariance,
                                          msg.linear_acceleration_covariance))


class GyroBias:
    """The gyro's z offset (rad/s), learned while the car stands still.

    A first-order average with time constant ``tau_s`` over the rates seen at standstill (the
    caller says when: zero ERPM); while moving the estimate is held. BMI160s are off by up to
    ±3 °/s before calibration, which alone would turn 20 m of straight driving into a 0.5 rad
    heading error, so the yaw rate from the gyro is only used once ``settled``.
    """

    def __init__(self, tau_s: float = 2.0) -> None:
        self.tau_s = tau_s
        self.bias = 0.0
        self.still_s = 0.0
        self._last_ns: int | None = None

    @property
    def settled(self) -> bool:
        """Whether the car has stood still for at least one time constant since start."""
        return self.still_s >= self.tau_s

    def update(self, rate_z: float, still: bool, t_ns: int) -> None:
        """Take a z rate (rad/s, bias included) measured at monotonic ``t_ns``."""
        dt = seconds(t_ns - self._last_ns) if self._last_ns is not None and t_ns > self._last_ns else 0.0
        self._last_ns = t_ns
        if not still or dt <= 0.0:
            return
        # while still settling, average over all the still time so far (no start-up lag from 0)
        weight = min(1.0, dt / max(self.still_s + dt, 1e-9)) if not self.settled else dt / self.tau_s
        self.bias += min(1.0, weight) * (rate_z - self.bias)
        self.still_s += dt
