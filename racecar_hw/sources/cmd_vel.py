"""``geometry_msgs/Twist`` velocity commands (Nav2 and most planners) as an Ackermann mux input.

For a car with wheelbase ``L`` (m), a Twist asking for forward speed ``v = linear.x`` (m/s) and yaw
rate ``w = angular.z`` (rad/s, + left) becomes::

    speed = v
    steering_angle = atan(L * w / v)     (0 when |v| < 1 mm/s: a car cannot turn on the spot)

clamped to the steering limit. Each Twist becomes one AckermannDriveStamped (frame ``base_link``)
on the mux input's topic, so the mux's timeout applies as to any input: a planner that stops
publishing stops the car. A Twist with a NaN or infinite value is dropped and counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Twist, stamp_now

#: Below this speed (m/s) the steering is centred rather than computed.
MIN_SPEED_MPS = 1e-3


def twist_to_ackermann(twist: Twist, wheelbase_m: float, steering_max_rad: float) -> AckermannDrive | None:
    """The Ackermann command for ``twist``, or None when a value is not finite."""
    v, w = float(twist.linear.x), float(twist.angular.z)
    if not (math.isfinite(v) and math.isfinite(w)):
        return None
    steering = 0.0 if abs(v) < MIN_SPEED_MPS else math.atan(wheelbase_m * w / v)
    steering = max(-steering_max_rad, min(steering_max_rad, steering))
    return AckermannDrive(steering_angle=steering, speed=v)


@dataclass
class CmdVelParams:
    """Where Twists come from and go, and the car's geometry."""

    twist_topic: str
    input_topic: str
    wheelbase_m: float
    steering_max_rad: float


class CmdVelConverter:
    """Subscribes to Twists on the bus and publishes Ackermann commands on a mux input."""

    def __init__(self, bus: Bus, params: CmdVelParams) -> None:
        self.bus = bus
        self.params = params
        self.converted = 0
        self.rejected = 0
        bus.declare(params.twist_topic, Twist)
        self._sub: Subscription | None = bus.subscribe(params.twist_topic, self._on_twist)

    def _on_twist(self, twist: Twist) -> None:
        p = self.params
        drive = twist_to_ackermann(twist, p.wheelbase_m, p.steering_max_rad)
        if drive is None:
            self.rejected += 1
            return
        self.converted += 1
        self.bus.publish(p.input_topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()), drive))

    def close(self) -> None:
        """Stop converting (safe twice)."""
        if self._sub is not None:
            self._sub.close()
            self._sub = None
