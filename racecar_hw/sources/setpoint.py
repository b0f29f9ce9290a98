"""The CSE490R lab 0 set-point relay: hold a speed and a steering angle, stream them to the mux.

The relay keeps the last velocity (m/s, negative in reverse) and steering angle (rad, positive
left) it was given, through :meth:`SetpointRelay.set_velocity` and friends or on the bus topics
``/lab0/velocity`` and ``/lab0/steering_angle`` (``std_msgs/Float64``), and publishes them as an
``AckermannDriveStamped`` on ``/vesc/high_level/ackermann_cmd_mux/input/nav_0`` at ``rate_hz``
(20 Hz) on absolute deadlines. :meth:`SetpointRelay.reset` (the lab's ``/subscriber/reset``
service) zeroes both. An initial pose arrives as the text ``"x,y,theta"`` (metres, metres,
radians in the map frame) on ``/lab0/initialpose`` (``std_msgs/String``) or from the config; it is
parsed, validated and handed to the ``on_initial_pose`` callback (the daemon places the simulated
car there).

Set-points outside the configured limits or not finite are refused (ValueError from the setters;
logged and counted in :attr:`SetpointRelay.rejected` for bus input), never clamped silently.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Float64,
    Point,
    Pose,
    Quaternion,
    String,
    stamp_now,
)
from racecar_hw.base.params import param
from racecar_hw.runtime.ticker import Ticker

log = logging.getLogger(__name__)

NAV0_TOPIC = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"


@dataclass(frozen=True)
class Pose2D:
    """A planar pose in the map frame: ``x``, ``y`` in metres, heading ``theta`` in radians (CCW)."""

    x: float
    y: float
    theta: float

    def to_pose(self) -> Pose:
        """As a ``geometry_msgs/Pose`` (z = 0, rotation about z)."""
        return Pose(Point(self.x, self.y, 0.0), Quaternion.from_yaw(self.theta))


def parse_pose(text: str) -> Pose2D:
    """``"x,y,theta"`` (spaces allowed) as a :class:`Pose2D`; ValueError says what is wrong."""
    parts = text.split(",")
    if len(parts) != 3:
        raise ValueError(f"expected 'x,y,theta', got {text!r}")
    values = []
    for name, part in zip(("x", "y", "theta"), parts, strict=True):
        try:
            value = float(part.strip())
        except ValueError:
            raise ValueError(f"{name} is not a number in {text!r}") from None
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite in {text!r}")
        values.append(value)
    return Pose2D(values[0], values[1], values[2])


@dataclass
class SetpointParams:
    """The set-point relay's topics, rate and limits."""

    topic: str = param(NAV0_TOPIC, "where the AckermannDriveStamped commands go (a mux input)", topic=True)
    rate_hz: float = param(20.0, "publish rate", unit="Hz", min=1.0, max=200.0)
    frame_id: str = param("base_link", "frame_id of the published commands", nonempty=True)
    max_speed_mps: float = param(2.0, "largest |velocity| accepted", unit="m/s", min=0.0, max=20.0)
    max_steering_rad: float = param(0.4189, "largest |steering angle| accepted", unit="rad",
                                    min=0.0, max=1.2)
    velocity_topic: str = param("/lab0/velocity", "std_msgs/Float64 velocity set-points (m/s)", topic=True)
    steering_topic: str = param("/lab0/steering_angle", "std_msgs/Float64 steering set-points (rad)",
                                topic=True)
    initial_pose_topic: str = param("/lab0/initialpose", "std_msgs/String 'x,y,theta' initial poses",
                                    topic=True)
    initial_pose: str | None = param(None, "initial pose 'x,y,theta' (m, m, rad, map frame)")

    def __post_init__(self) -> None:
        if self.initial_pose is not None:
            try:
                parse_pose(self.initial_pose)
            except ValueError as err:
                raise ConfigError("initial_pose", str(err)) from err


class SetpointRelay:
    """Holds a velocity and steering set-point and streams them to the mux at a fixed rate."""

    def __init__(self, bus: Bus, params: SetpointParams | None = None, *,
                 on_initial_pose: Callable[[Pose2D], None] | None = None) -> None:
        self.bus = bus
        self.params = params if params is not None else SetpointParams()
        self.on_initial_pose = on_initial_pose
        self.velocity = 0.0
        self.steering_angle = 0.0
        self.initial_pose: Pose2D | None = None
        self.published = 0
        self.rejected = 0
        self.ticker = Ticker(self.params.rate_hz)
        self._subs: list[Subscription] = []
        bus.declare(self.params.topic, AckermannDriveStamped)
        if self.params.initial_pose is not None:
            self.set_initial_pose(self.params.initial_pose)

    # --- set-points ---------------------------------------------------------------------------

    def set_velocity(self, velocity: float) -> None:
        """Hold ``velocity`` (m/s); ValueError if not finite or beyond ``max_speed_mps``."""
        self.velocity = self._checked("velocity", velocity, self.params.max_speed_mps, "m/s")

    def set_steering_angle(self, angle: float) -> None:
        """Hold ``angle`` (rad, positive left); ValueError if not finite or beyond the limit."""
        self.steering_angle = self._checked("steering angle", angle, self.params.max_steering_rad, "rad")

    def set_initial_pose(self, pose: str | Pose2D) -> Pose2D:
        """Parse (if text), remember and hand on an initial pose; ValueError if malformed."""
        parsed = parse_pose(pose) if isinstance(pose, str) else pose
        self.initial_pose = parsed
        if self.on_initial_pose is not None:
            self.on_initial_pose(parsed)
        return parsed

    def reset(self) -> None:
        """Zero the velocity and steering set-points (the lab's reset service)."""
        self.velocity = 0.0
        self.steering_angle = 0.0

    def command(self, stamp_ns: int | None = None) -> AckermannDriveStamped:
        """The command for the current set-points, stamped ``stamp_ns`` (Unix ns; now by default)."""
        return AckermannDriveStamped(
            stamp_now(self.params.frame_id, wall_ns() if stamp_ns is None else stamp_ns),
            AckermannDrive(steering_angle=self.steering_angle, speed=self.velocity))

    # --- bus ----------------------------------------------------------------------------------

    def start(self) -> None:
        """Listen to the set-point topics on the bus (idempotent)."""
        if self._subs:
            return
        p = self.params
        self._subs = [
            self.bus.subscribe(p.velocity_topic, self._from_bus(self.set_velocity, "velocity")),
            self.bus.subscribe(p.steering_topic, self._from_bus(self.set_steering_angle, "steering")),
            self.bus.subscribe(p.initial_pose_topic, self._from_bus(self.set_initial_pose, "initial pose")),
        ]

    def close(self) -> None:
        """Stop listening; safe to call twice."""
        for sub in self._subs:
            sub.close()
        self._subs = []

    def publish(self) -> None:
        """Publish the current command once."""
        self.bus.publish(self.params.topic, self.command())
        self.published += 1

    async def run(self) -> None:
        """Listen and publish at ``rate_hz`` until cancelled; a last zero command is sent on exit."""
        self.start()
        self.ticker.reset()
        try:
            while True:
                await self.ticker.tick()
                self.publish()
        finally:
            self.close()
            self.reset()
            self.publish()

    def _checked(self, what: str, value: float, limit: float, unit: str) -> float:
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"{what} must be finite, got {value!r}")
        if abs(v) > limit:
            raise ValueError(f"{what} {v} {unit} is beyond the limit of {limit} {unit}")
        return v

    def _from_bus(self, setter: Callable[[Any], object], what: str) -> Callable[[Any], None]:
        def take(msg: Float64 | String) -> None:
            try:
                setter(msg.data)
            except (ValueError, TypeError) as err:
                self.rejected += 1
                log.warning("set-point relay: refused %s: %s", what, err)

        return take
