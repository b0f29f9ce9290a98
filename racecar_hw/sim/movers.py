"""Obstacles that come and go and move: a person crossing, a box sliding in, a cart on a route.

A :class:`Mover` is a shape (a :mod:`racecar_hw.sim.obstacles` shape given around the origin) with
a path in the map frame: it appears at ``appear_s`` at ``start``, then moves at a constant
``velocity``, or along ``waypoints`` at ``speed`` (stopping at the last one), and is gone from
``disappear_s`` on. Its heading stays ``yaw``. Times are the world's sim time in seconds; metres,
m/s, radians, map frame (REP-103).

Movers are pure data: :meth:`Mover.at` says where the shape is at a time, and the world asks it at
every physics step (collisions) and at every lidar stamp (ray casting).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from racecar_hw.sim.obstacles import Obstacle, place


@dataclass(frozen=True)
class Mover:
    """An obstacle with a schedule and a path. See the module documentation."""

    shape: Obstacle
    start: tuple[float, float]
    yaw: float = 0.0
    appear_s: float = 0.0
    disappear_s: float | None = None
    velocity: tuple[float, float] = (0.0, 0.0)
    waypoints: tuple[tuple[float, float], ...] = ()
    speed: float = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        if self.waypoints and not self.speed > 0.0:
            raise ValueError(f"waypoints need a speed > 0, got {self.speed}")
        if self.waypoints and any(self.velocity):
            raise ValueError("give a velocity or waypoints, not both")
        if self.disappear_s is not None and self.disappear_s <= self.appear_s:
            raise ValueError(f"disappears at {self.disappear_s} s, not after it appears at {self.appear_s} s")

    def present(self, t: float) -> bool:
        """Whether the obstacle is in the world at sim time ``t``."""
        return t >= self.appear_s and (self.disappear_s is None or t < self.disappear_s)

    def position(self, t: float) -> tuple[float, float]:
        """Where its origin is at sim time ``t`` (its start before it appears)."""
        elapsed = max(t - self.appear_s, 0.0)
        x, y = self.start
        if not self.waypoints:
            return x + self.velocity[0] * elapsed, y + self.velocity[1] * elapsed
        left = self.speed * elapsed
        for wx, wy in self.waypoints:
            leg = math.hypot(wx - x, wy - y)
            if left <= leg:
                f = left / leg if leg > 0.0 else 1.0
                return x + f * (wx - x), y + f * (wy - y)
            left -= leg
            x, y = wx, wy
        return x, y

    def at(self, t: float) -> Obstacle | None:
        """The shape where it is at sim time ``t``; None while it is absent."""
        if not self.present(t):
            return None
        x, y = self.position(t)
        return place(self.shape, x, y, self.yaw)
