"""The simulated car: a kinematic bicycle driven by motor ERPM and servo position, with a footprint.

Frames (REP-103/105): the car's pose is ``base_link``, the centre of the REAR axle, in the map
frame: x forward, y left, yaw counter-clockwise from the map's x axis, metres and radians.

Model: the wheels do not slip. The speed of the rear axle centre is the motor's speed,
``v = (erpm - speed_to_erpm_offset) / speed_to_erpm_gain`` (m/s, negative in reverse), and the
front-wheel steering angle is the servo's,
``delta = (servo - steering_angle_to_servo_offset) / steering_angle_to_servo_gain`` (rad, positive
= left), clipped to +-``max_steering_angle``. The servo reaches its position at once (the fake VESC
reports the commanded position) and the motor's ERPM is whatever the fake VESC reports (its motor
model owns acceleration). Over a step with constant ``v`` and ``delta`` the car follows an arc of
curvature ``tan(delta) / wheelbase`` exactly.

The footprint is a rectangle ``length`` x ``width`` whose rear edge is ``rear_overhang`` behind the
rear axle. Clearance is measured from that rectangle to occupied map cells (each cell taken as a
disc of half a cell around its centre) and to dynamic obstacles.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from racecar_hw.base.params import param
from racecar_hw.sim.obstacles import Obstacle, rectangle
from racecar_hw.sim.occupancy import OccupancyMap

#: Clearances beyond this are reported as this value (metres).
CLEARANCE_RANGE_M = 2.0


class Pose2D(NamedTuple):
    """A planar pose in the map frame: metres, metres, radians (CCW)."""

    x: float
    y: float
    yaw: float


@dataclass
class CarParams:
    """The physical car the simulator drives: its true gains (the F1TENTH defaults) and its size."""

    speed_to_erpm_gain: float = param(4614.0, "motor ERPM per m/s of car speed", unit="ERPM/(m/s)")
    speed_to_erpm_offset: float = param(0.0, "ERPM added to a non-zero speed (0 ERPM is standing)",
                                        unit="ERPM")
    steering_angle_to_servo_gain: float = param(-1.2135, "servo position per radian of steering",
                                                unit="1/rad")
    steering_angle_to_servo_offset: float = param(0.530, "servo position that steers straight ahead "
                                                         "(F1TENTH's 0.5304 as the VESC receives it, in "
                                                         "thousandths)",
                                                  min=0.0, max=1.0)
    steering_angle_to_servo_gain_right: float | None = param(
        None, "servo position per radian of right turn; none: steering_angle_to_servo_gain", unit="1/rad")
    wheelbase: float = param(0.25, "rear axle to front axle", unit="m", min=0.05, max=2.0)
    length: float = param(0.55, "footprint length, bumper to bumper", unit="m", min=0.05, max=3.0)
    width: float = param(0.30, "footprint width", unit="m", min=0.05, max=2.0)
    rear_overhang: float = param(0.10, "footprint behind the rear axle (base_link)", unit="m", min=0.0,
                                 max=2.0)
    max_steering_angle: float = param(0.4189, "mechanical steering limit either side", unit="rad",
                                      min=0.0, max=1.5)

    def __post_init__(self) -> None:
        if self.speed_to_erpm_gain == 0 or self.steering_angle_to_servo_gain == 0:
            raise ValueError("speed_to_erpm_gain and steering_angle_to_servo_gain must be non-zero")


def speed_from_erpm(erpm: float, params: CarParams) -> float:
    """Car speed (m/s) for a motor ERPM; 0 for 0 ERPM (the driver's stop, whatever the offset) and
    for a non-finite reading."""
    if erpm == 0.0 or not math.isfinite(erpm):
        return 0.0
    return (erpm - params.speed_to_erpm_offset) / params.speed_to_erpm_gain


def steering_from_servo(servo: float, params: CarParams) -> float:
    """Steering angle (rad, + left) for a servo position, clipped to the mechanical limit;
    straight ahead for a non-finite reading."""
    if not math.isfinite(servo):
        return 0.0
    delta = (servo - params.steering_angle_to_servo_offset) / params.steering_angle_to_servo_gain
    if delta < 0 and params.steering_angle_to_servo_gain_right is not None:
        delta = (servo - params.steering_angle_to_servo_offset) / params.steering_angle_to_servo_gain_right
    return max(-params.max_steering_angle, min(params.max_steering_angle, delta))


def wrap_angle(a: float) -> float:
    """An angle in [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def advance(pose: Pose2D, speed: float, steering: float, dt: float, wheelbase: float) -> Pose2D:
    """The rear-axle pose after ``dt`` seconds at constant ``speed`` (m/s) and ``steering`` (rad)."""
    x, y, yaw = pose
    distance = speed * dt
    curvature = math.tan(steering) / wheelbase
    turn = distance * curvature
    if abs(turn) < 1e-9:
        # straight (or nearly): second-order chord, exact in the limit
        heading = yaw + turn / 2
        return Pose2D(x + distance * math.cos(heading), y + distance * math.sin(heading),
                      wrap_angle(yaw + turn))
    new_yaw = yaw + turn
    return Pose2D(x + (math.sin(new_yaw) - math.sin(yaw)) / curvature,
                  y - (math.cos(new_yaw) - math.cos(yaw)) / curvature, wrap_angle(new_yaw))


def footprint(pose: Pose2D | tuple[float, float, float], params: CarParams) -> np.ndarray:
    """Corners (CCW, shape (4, 2), map frame) of the car's footprint at ``pose``."""
    x, y, yaw = pose
    return rectangle(x, y, yaw, -params.rear_overhang, params.length - params.rear_overhang,
                     -params.width / 2, params.width / 2)


class Collider:
    """Measures the gap between the car's footprint and the map's occupied cells and obstacles.

    The map does not move, so a gap measured once bounds the gaps nearby: from a footprint whose
    gap to the map is ``g``, a footprint whose corners moved at most ``d`` has a gap of at least
    ``g - d`` (a rigid motion moves no point of a rectangle further than its furthest corner).
    :meth:`clearance` with ``exact_below`` and :meth:`collides` use that bound to skip the map
    search where it cannot change the answer.
    """

    def __init__(self, occ_map: OccupancyMap, params: CarParams) -> None:
        self.map = occ_map
        self.params = params
        self._occ = occ_map.occupied
        #: the last exact map gap (capped at CLEARANCE_RANGE_M) and the footprint it was measured at
        self._anchor: tuple[np.ndarray, float] | None = None
        #: the last :meth:`clearance`: its arguments, the anchor it left, and its answer
        self._last: tuple[tuple[Any, ...], tuple[Obstacle, ...], Any, float] | None = None

    def clearance(self, pose: Pose2D | tuple[float, float, float], obstacles: Iterable[Obstacle] = (),
                  max_distance: float = CLEARANCE_RANGE_M, exact_below: float = math.inf) -> float:
        """Smallest gap (m) from the footprint at ``pose`` to any obstacle; 0 on contact. Gaps of
        ``max_distance`` or more are reported as ``max_distance``. With ``exact_below``, a gap
        known to be at least ``exact_below`` may be reported as a lower bound that is itself at
        least ``exact_below`` (enough for a running minimum).

        Asked the same again (a car at rest: the world asks at every step), with the same obstacle
        objects and nothing measured in between, it answers what it answered, without measuring:
        measuring again would give that answer (the anchor it left is at this very footprint, or
        was not moved by it) and leave an equal anchor."""
        key = (*pose, max_distance, exact_below)
        shapes = tuple(obstacles)
        last = self._last
        if (last is not None and last[0] == key and last[2] is self._anchor and len(last[1]) == len(shapes)
                and all(a is b for a, b in zip(last[1], shapes, strict=True))):
            return last[3]
        corners = footprint(pose, self.params)
        if max_distance == CLEARANCE_RANGE_M:
            gap = self._map_gap(pose, corners, exact_below)
        else:
            gap = min(self._map_clearance(pose, max_distance), max_distance)
        if gap > 0:
            for obstacle in shapes:
                gap = min(gap, obstacle.distance_to(corners))
        self._last = (key, shapes, self._anchor, gap)
        return gap

    def collides(self, pose: Pose2D | tuple[float, float, float],
                 obstacles: Iterable[Obstacle] = ()) -> bool:
        """Whether the footprint at ``pose`` touches an occupied cell or an obstacle."""
        corners = footprint(pose, self.params)
        if self._map_bound(corners) <= 0.0 and self._map_clearance(pose, self.map.resolution) <= 0.0:
            return True
        return any(obstacle.distance_to(corners) <= 0.0 for obstacle in obstacles)

    def _map_bound(self, corners: np.ndarray) -> float:
        """A lower bound of the map gap of the footprint ``corners`` (-inf before any measure)."""
        if self._anchor is None:
            return -math.inf
        at, gap = self._anchor
        shift = float(np.sqrt(((corners - at) ** 2).sum(axis=1).max()))
        return gap - shift

    def _map_gap(self, pose: Pose2D | tuple[float, float, float], corners: np.ndarray,
                 exact_below: float) -> float:
        bound = self._map_bound(corners)
        if bound >= exact_below:
            return min(bound, CLEARANCE_RANGE_M)
        gap = min(self._map_clearance(pose, CLEARANCE_RANGE_M), CLEARANCE_RANGE_M)
        self._anchor = (corners, gap)
        return gap

    def sweep(self, pose: Pose2D, speed: float, steering: float, dt: float,
              obstacles: Iterable[Obstacle] = ()) -> tuple[Pose2D, float, bool]:
        """Drive from ``pose`` at ``speed`` (m/s) and ``steering`` (rad) for ``dt`` s in sub-steps
        short enough that a collision is found within half a cell (and 0.05 rad of turn): the pose
        reached, the path length driven (m), and whether the car hit something (then the pose is
        the last one before the contact)."""
        p = self.params
        travelled = 0.0
        turn = abs(speed * dt * math.tan(steering) / p.wheelbase)
        n = max(1, math.ceil(abs(speed) * dt / (self.map.resolution / 2)), math.ceil(turn / 0.05))
        h = dt / n
        for _ in range(n):
            nxt = advance(pose, speed, steering, h, p.wheelbase)
            if self.collides(nxt, obstacles):
                return pose, travelled, True
            pose = nxt
            travelled += abs(speed) * h
        return pose, travelled, False

    def _map_clearance(self, pose: Pose2D | tuple[float, float, float], max_distance: float) -> float:
        m, p = self.map, self.params
        res = m.resolution
        x, y, yaw = pose
        gx, gy = m.world_to_grid_frame(x, y)
        gx, gy = float(gx), float(gy)
        gyaw = yaw - m.origin[2]
        corners = rectangle(gx, gy, gyaw, -p.rear_overhang / res, (p.length - p.rear_overhang) / res,
                            -p.width / 2 / res, p.width / 2 / res)
        reach = max_distance / res + 1
        i0 = max(int(math.floor(corners[:, 0].min() - reach)), 0)
        i1 = min(int(math.ceil(corners[:, 0].max() + reach)), m.width)
        j0 = max(int(math.floor(corners[:, 1].min() - reach)), 0)
        j1 = min(int(math.ceil(corners[:, 1].max() + reach)), m.height)
        if i0 >= i1 or j0 >= j1:
            return math.inf
        # the window's occupied cells, row by row: the same indices in the same order as np.nonzero
        # of the 2-D slice, at an eighth of its cost (a strided slice's nonzero walks it slowly)
        jj, ii = np.divmod(self._occ[j0:j1, i0:i1].ravel().nonzero()[0], i1 - i0)
        if jj.size == 0:
            return math.inf
        # occupied cell centres in the car frame, in cells
        cx = ii + (i0 + 0.5) - gx
        cy = jj + (j0 + 0.5) - gy
        c, s = math.cos(gyaw), math.sin(gyaw)
        lx, ly = c * cx + s * cy, -s * cx + c * cy
        dx = np.maximum(np.maximum(-p.rear_overhang / res - lx, lx - (p.length - p.rear_overhang) / res), 0)
        dy = np.maximum(np.abs(ly) - p.width / 2 / res, 0)
        nearest = float(np.sqrt(np.min(dx * dx + dy * dy)))
        return max(nearest - 0.5, 0.0) * res
