"""The fake VESC's IMU: what a board on a moving car would report, in the firmware's units.

The simulation supplies the car's planar motion at the rear axle (:class:`PlanarMotion`: speed,
yaw rate, and their rates of change over its last step). :class:`ImuModel` turns it into what an
IMU mounted at ``mount`` (x, y in metres from base_link, yaw in radians) measures, as
COMM_GET_IMU_DATA reports it (:class:`~vesc.codec.ImuData`: deg/s, g, quaternion):

- specific force: gravity (+1 g on z), plus the acceleration of the mounting point, which for a
  rigid body in the plane is ``a_base + alpha x r - omega^2 r`` with ``a_base`` = (dv/dt, v·omega)
  (longitudinal, and the centripetal v²·tan(delta)/L), rotated into the board's axes. dv/dt and
  d(omega)/dt are the means since the previous sample, (v - v_prev) / (t - t_prev), as a real
  accelerometer's low-pass filter averages them: the world's speed rises in steps at the command
  rate, so its acceleration over its last step is 0 most of the time and a spike in between, and a
  50 Hz poll would mostly read 0 while the car speeds up. The first sample takes the world's own
  value, and a second sample at the same instant repeats the previous mean;
- angular rate: omega on z (a yaw-only mounting leaves it unchanged);
- orientation: the integrated yaw since the model started (the firmware's yaw is relative to the
  heading at boot), roll and pitch 0 on a flat floor;
- errors: a constant gyro bias (deg/s), white noise on the rates and accelerations, and motor
  vibration on the accelerations (a sine at ``vibration_hz_per_mps`` times the speed, amplitude
  ``vibration_g``), all seeded for repeatable runs.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

from vesc.codec import IMU_FIELDS, ImuData


class PlanarMotion(NamedTuple):
    """The car's motion at the rear axle (base_link), in base_link axes.

    ``speed`` m/s (negative in reverse), ``yaw_rate`` rad/s (counter-clockwise positive),
    ``accel`` dv/dt in m/s², ``yaw_accel`` d(yaw_rate)/dt in rad/s².
    """

    speed: float = 0.0
    yaw_rate: float = 0.0
    accel: float = 0.0
    yaw_accel: float = 0.0


AT_REST = PlanarMotion()


@dataclass
class ImuErrors:
    """How far the fake IMU is from the truth (BMI160-like defaults).

    ``gyro_bias_dps`` deg/s on z; ``gyro_noise_dps`` and ``accel_noise_g`` standard deviations of
    white noise per sample; ``vibration_g`` amplitude of the motor's vibration on x, y, z while
    moving, at ``vibration_hz_per_mps`` Hz per m/s of speed.
    """

    gyro_bias_dps: float = 0.5
    gyro_noise_dps: float = 0.07
    accel_noise_g: float = 0.002
    vibration_g: float = 0.02
    vibration_hz_per_mps: float = 30.0


class ImuModel:
    """An IMU mounted at ``mount`` = (x m, y m, yaw rad) in base_link, read at monotonic times."""

    def __init__(self, motion: Callable[[], PlanarMotion] = lambda: AT_REST,
                 mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 errors: ImuErrors | None = None, seed: int = 0) -> None:
        self.motion = motion
        self.mount = mount
        self.errors = errors if errors is not None else ImuErrors()
        self._rng = random.Random(seed)
        self._yaw = 0.0
        self._phase = 0.0
        self._last_s: float | None = None
        #: the motion at the previous sample, and the mean (dv/dt, d(omega)/dt) reported then
        self._prev: PlanarMotion | None = None
        self._mean = (0.0, 0.0)

    def sample(self, t_s: float, mask: int = 0xFFFF) -> ImuData:
        """The reply at time ``t_s`` (seconds, any monotonic origin) with the fields of ``mask``."""
        m = self.motion()
        dt = 0.0 if self._last_s is None else max(0.0, t_s - self._last_s)
        self._last_s = t_s
        if self._prev is None:
            self._mean = (m.accel, m.yaw_accel)
        elif dt > 0.0:
            self._mean = ((m.speed - self._prev.speed) / dt, (m.yaw_rate - self._prev.yaw_rate) / dt)
        self._prev = m
        self._yaw = math.remainder(self._yaw + m.yaw_rate * dt, math.tau)
        e, rng = self.errors, self._rng
        self._phase = math.remainder(self._phase + math.tau * e.vibration_hz_per_mps * abs(m.speed) * dt,
                                     math.tau)
        x, y, mount_yaw = self.mount
        w = m.yaw_rate
        accel, alpha = self._mean
        ax = accel - alpha * y - w * w * x
        ay = m.speed * w + alpha * x - w * w * y
        c, s = math.cos(mount_yaw), math.sin(mount_yaw)
        bx, by = c * ax + s * ay, -s * ax + c * ay  # into the board's axes
        shake = e.vibration_g * math.sin(self._phase) if m.speed else 0.0
        g = 9.80665
        half = 0.5 * self._yaw  # heading since boot, whatever the mounting
        values = {
            "roll": 0.0, "pitch": 0.0, "yaw": -self._yaw,  # the firmware negates yaw
            "acc_x": bx / g + shake + rng.gauss(0.0, e.accel_noise_g),
            "acc_y": by / g + 0.5 * shake + rng.gauss(0.0, e.accel_noise_g),
            "acc_z": 1.0 + 0.7 * shake + rng.gauss(0.0, e.accel_noise_g),
            "gyro_x": rng.gauss(0.0, e.gyro_noise_dps), "gyro_y": rng.gauss(0.0, e.gyro_noise_dps),
            "gyro_z": math.degrees(w) + e.gyro_bias_dps + rng.gauss(0.0, e.gyro_noise_dps),
            "mag_x": 0.0, "mag_y": 0.0, "mag_z": 0.0,  # BMI160 boards have no magnetometer
            "q0": math.cos(half), "q1": 0.0, "q2": 0.0, "q3": math.sin(half),
        }
        return ImuData(**{name: values[name] for i, name in enumerate(IMU_FIELDS) if mask >> i & 1})
