"""The CSE490R lab 0 analytical figure-8: one full loop left, then one full loop right.

With steering angle ``delta`` the kinematic bicycle turns on a circle of radius
``R = wheelbase / tan(|delta|)`` about a centre beside the rear axle, so at speed ``v`` one full
loop takes ``T = 2 pi R / |v|`` seconds. Steering ``+delta`` for ``T``, then ``-delta`` for ``T``,
brings the car back to its start pose and heading with the two circles touching there: a figure 8.
A negative speed drives the same figure backwards. The path is only as good as the car's
steering calibration and wheel slip allow; it is an open-loop manoeuvre.

:func:`figure8_command` gives the command at any time (pure); :class:`Figure8Driver` publishes it
on a mux input at ``rate_hz`` (20 Hz) on absolute deadlines, for ``figure8s`` figures (0 = until
cancelled), then publishes one zero command and returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.base.params import param
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.sources.setpoint import NAV0_TOPIC

#: The smallest |steering angle| accepted: below it a loop would be tens of metres across.
MIN_STEERING_RAD = 0.01


@dataclass
class Figure8Params:
    """The figure-8's speed, steering, car geometry, count, rate and output topic."""

    speed_mps: float = param(1.0, "speed along the figure; negative drives it backwards", unit="m/s",
                             min=-5.0, max=5.0)
    steering_angle_rad: float = param(0.3, "steering of the first loop (positive: left first); the "
                                           "second loop uses the opposite", unit="rad", min=-0.8, max=0.8)
    wheelbase_m: float = param(0.25, "rear axle to front axle", unit="m", min=0.05, max=2.0)
    figure8s: int = param(1, "figure-8s to drive, then stop; 0 drives until cancelled", min=0, max=1000)
    rate_hz: float = param(20.0, "command rate", unit="Hz", min=1.0, max=200.0)
    topic: str = param(NAV0_TOPIC, "mux input the commands go to", topic=True)
    frame_id: str = param("base_link", "frame_id of the published commands", nonempty=True)

    def __post_init__(self) -> None:
        if self.speed_mps == 0.0 or not math.isfinite(self.speed_mps):
            raise ConfigError("speed_mps", "must be a non-zero finite speed")
        if not abs(self.steering_angle_rad) >= MIN_STEERING_RAD:
            raise ConfigError("steering_angle_rad", f"|steering| must be at least {MIN_STEERING_RAD} rad")

    @property
    def radius_m(self) -> float:
        """Radius of each loop at the rear axle, metres."""
        return turn_radius_m(self.steering_angle_rad, self.wheelbase_m)

    @property
    def loop_s(self) -> float:
        """Duration of one loop (half a figure-8), seconds."""
        return loop_duration_s(self.speed_mps, self.steering_angle_rad, self.wheelbase_m)

    @property
    def duration_s(self) -> float | None:
        """Duration of all the figure-8s, seconds; None when driving until cancelled."""
        return 2.0 * self.loop_s * self.figure8s if self.figure8s else None


def turn_radius_m(steering_angle_rad: float, wheelbase_m: float) -> float:
    """``wheelbase / tan(|steering|)``: the kinematic bicycle's turn radius at the rear axle, m."""
    return wheelbase_m / math.tan(abs(steering_angle_rad))


def loop_duration_s(speed_mps: float, steering_angle_rad: float, wheelbase_m: float) -> float:
    """``2 pi R / |v|``: seconds for one full loop."""
    return 2.0 * math.pi * turn_radius_m(steering_angle_rad, wheelbase_m) / abs(speed_mps)


def figure8_command(t_s: float, p: Figure8Params) -> AckermannDrive:
    """The command ``t_s`` seconds after the start: left loop, right loop, repeat; zero when done.

    Before the start (negative time) and from ``duration_s`` on, the command is a stop.
    """
    if t_s < 0.0 or (p.duration_s is not None and t_s >= p.duration_s):
        return AckermannDrive()
    loop = int(t_s // p.loop_s)
    steering = p.steering_angle_rad if loop % 2 == 0 else -p.steering_angle_rad
    return AckermannDrive(steering_angle=steering, speed=p.speed_mps)


class Figure8Driver:
    """Publishes the figure-8 on a mux input at a fixed rate; ``run()`` returns when it is done."""

    def __init__(self, bus: Bus, params: Figure8Params | None = None) -> None:
        self.bus = bus
        self.params = params if params is not None else Figure8Params()
        self.published = 0
        self.finished = False
        self.ticker = Ticker(self.params.rate_hz)
        bus.declare(self.params.topic, AckermannDriveStamped)

    async def run(self) -> None:
        """Drive the configured figure-8s (or until cancelled), then publish one stop command."""
        self.finished = False
        self.ticker.reset()
        start_ns: int | None = None
        try:
            while True:
                due_ns = await self.ticker.tick()
                if start_ns is None:
                    start_ns = due_ns
                t_s = (due_ns - start_ns) / NS_PER_S
                duration = self.params.duration_s
                if duration is not None and t_s >= duration:
                    self.finished = True
                    return
                self._publish(figure8_command(t_s, self.params))
        finally:
            self._publish(AckermannDrive())

    def _publish(self, drive: AckermannDrive) -> None:
        self.bus.publish(self.params.topic,
                         AckermannDriveStamped(stamp_now(self.params.frame_id, wall_ns()), drive))
        self.published += 1
