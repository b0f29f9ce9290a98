"""The simulated car's state as the world last stepped it, and how a step changes it.

Pose: the rear axle's (x, y, yaw) in the map frame (m, rad). Speed in m/s (negative in reverse,
0 after a collision: the car stays stopped until the world is reset), steering in rad (+ left),
path length and clearances in m, sim time in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from racecar_hw.sim.car import CarParams, Pose2D, wrap_angle
from vesc.imu_model import AT_REST, PlanarMotion


@dataclass(frozen=True)
class Collision:
    """A contact: sim time (s), the contact side's centre (front bumper forwards, rear in reverse)."""

    t: float
    x: float
    y: float


def compose(pose: tuple[float, float, float], local: tuple[float, float, float]) -> Pose2D:
    """``local`` (a pose in the frame of ``pose``) expressed in ``pose``'s parent frame."""
    x, y, yaw = pose
    lx, ly, lyaw = local
    c, s = math.cos(yaw), math.sin(yaw)
    return Pose2D(x + c * lx - s * ly, y + s * lx + c * ly, wrap_angle(yaw + lyaw))


@dataclass
class CarState:
    """The car at rest at ``pose`` until stepped; ``min_clearance`` is the smallest gap seen (m)."""

    pose: Pose2D
    min_clearance: float
    speed: float = 0.0
    steering: float = 0.0
    #: the motion at the rear axle over the last step (what the IMU feels)
    motion: PlanarMotion = AT_REST
    #: latched by the first contact
    collided: bool = False
    collisions: list[Collision] = field(default_factory=list)
    #: path length driven, forwards and backwards
    distance: float = 0.0

    def stepped(self, pose: Pose2D, speed: float, steering: float, dt: float, travelled: float,
                clearance: float, hit: bool, t: float, params: CarParams) -> None:
        """A step of ``dt`` s ending at sim time ``t`` moved the car to ``pose`` at ``speed`` and
        ``steering``, ``travelled`` m, with ``clearance`` m left; ``hit``: it touched something."""
        moving = not (hit or self.collided)
        self.pose = pose
        new_speed = speed if moving else 0.0
        yaw_rate = new_speed * math.tan(steering) / params.wheelbase
        before = self.motion
        self.motion = (PlanarMotion(new_speed, yaw_rate, (new_speed - before.speed) / dt,
                                    (yaw_rate - before.yaw_rate) / dt) if dt > 0 else before)
        self.speed = new_speed
        self.steering = steering
        self.distance += travelled
        self.min_clearance = min(self.min_clearance, clearance)
        if hit:
            self.collided = True
            self.min_clearance = 0.0
            side = params.length - params.rear_overhang if speed > 0 else -params.rear_overhang
            cx, cy, _ = compose(pose, (side, 0.0, 0.0))
            self.collisions.append(Collision(t, cx, cy))


__all__ = ["CarState", "Collision", "compose"]
