"""A trivial policy for the step API (:mod:`racecar_hw.sim.env`): something to drive the car with in
tests, benchmarks and as a starting point, not a racing line.

Inputs are a scan's ranges (m) and their beam angles (rad, laser frame, CCW, 0 ahead); the result
is an Ackermann command, (speed m/s, steering rad, + left).
"""

from __future__ import annotations

import math

import numpy as np

#: The sim config's ``vesc.steering_max_rad``.
STEERING_MAX_RAD = 0.26


def range_at(ranges: np.ndarray, angles: np.ndarray, angle: float, width: float = 0.04) -> float:
    """The median finite range within ``width`` rad of ``angle``, inf if none."""
    values = ranges[np.abs(angles - angle) <= width]
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else math.inf


def follow_right_wall(ranges: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """Keep 0.8 m from the right-hand wall (two beams, as examples/wall_follower.py does, P only),
    turn left where a wall comes up ahead, slow down for it and for the steering."""
    theta = math.radians(50.0)
    b = range_at(ranges, angles, -math.pi / 2)
    a = range_at(ranges, angles, -math.pi / 2 + theta)
    front = range_at(ranges, angles, 0.0, 0.15)
    b = b if math.isfinite(b) else 3.0
    a = a if math.isfinite(a) else b / math.cos(theta)
    alpha = math.atan2(a * math.cos(theta) - b, a * math.sin(theta))
    distance = b * math.cos(alpha) + 0.6 * math.sin(alpha)
    steering = 1.2 * (0.8 - distance)
    if front < 2.5:
        steering += 0.6 * (2.5 - front)
    steering = max(-STEERING_MAX_RAD, min(STEERING_MAX_RAD, steering))
    speed = min(2.0, max(0.6, 0.7 * (front - 0.8)))
    return speed * (1.0 - 0.5 * abs(steering) / STEERING_MAX_RAD), steering


__all__ = ["STEERING_MAX_RAD", "follow_right_wall", "range_at"]
