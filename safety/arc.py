"""Free distance along the path a car's rectangular footprint sweeps at a fixed steering angle.

Frame: ``base_link``, the centre of the rear axle (x forward, y left, metres). The car follows the
bicycle model: at steering angle ``delta`` (radians, + left) base_link moves on a circle of radius
``R = wheelbase / tan(delta)`` about the instantaneous centre of rotation (ICR) ``(0, R)``; at
``delta = 0`` it moves straight. Path lengths are arc lengths travelled by base_link.

The footprint is the rectangle ``x in [-rear, front]``, ``|y| <= half_width`` (lateral margin
included). On a circle, a point at distance ``rho`` from the ICR is hit when the footprint's
leading edge at that radius (the front face or the inner side; beyond ``R + half_width`` also the
rear outer corner, which swings outwards) has turned onto it; points whose ``rho`` lies outside
the swept annulus ``[R - half_width, hypot(max(front, rear), R + half_width)]`` are never hit.
Reverse motion is the same problem mirrored front to back. Everything is vectorised over the points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Beyond this turn radius the path is treated as straight: over 10 m of path the arc leaves
#: the straight corridor by at most 10^2 / (2 * 1e4) = 5 mm.
STRAIGHT_RADIUS_M = 1.0e4

#: Radii closer than this to the footprint's half width are widened to it: the ICR would sit
#: inside the car, which no Ackermann car can steer (it needs |delta| near 90 degrees).
MIN_RADIUS_CLEARANCE_M = 0.05

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class SweptFootprint:
    """The rectangle swept along the path, in base_link.

    ``front_m``: base_link to the front bumper; ``rear_m``: base_link to the rear bumper;
    ``half_width_m``: half the width plus any lateral margin; ``wheelbase_m``: rear to front axle.
    """

    front_m: float
    rear_m: float
    half_width_m: float
    wheelbase_m: float

    def turn_radius(self, steering_rad: float) -> float:
        """The signed turn radius (m, + left) at ``steering_rad``; ``inf`` when straight."""
        t = math.tan(steering_rad)
        if t == 0.0 or abs(self.wheelbase_m / t) > STRAIGHT_RADIUS_M:
            return math.inf
        radius = self.wheelbase_m / t
        least = self.half_width_m + MIN_RADIUS_CLEARANCE_M
        if abs(radius) < least:
            return math.copysign(least, radius)
        return radius


@dataclass(frozen=True)
class PathHit:
    """The nearest point on the path: ``distance_m`` (capped), ``index`` into the points or -1."""

    distance_m: float
    index: int


def path_lengths(x: np.ndarray, y: np.ndarray, steering_rad: float, footprint: SweptFootprint,
                 reverse: bool = False) -> np.ndarray:
    """For every point (base_link, metres), how far base_link travels before the footprint touches it.

    ``inf`` for points the footprint never sweeps, 0 for points already inside it. ``reverse``
    means driving backwards at the same steering angle. ``x`` and ``y`` must be finite.
    """
    scale, band, values = _sweep(x, y, steering_rad, footprint, reverse)
    out = np.full(np.shape(x), np.inf)
    out[band] = values * scale
    return out


def free_distance(x: np.ndarray, y: np.ndarray, steering_rad: float, footprint: SweptFootprint,
                  max_path_m: float, reverse: bool = False) -> PathHit:
    """The free path length (m, at most ``max_path_m``) and which point limits it.

    ``index`` is -1 when nothing within ``max_path_m`` is on the path.
    """
    return free_distances(x, y, steering_rad, footprint, max_path_m, reverse, 0)[0]


def free_distances(x: np.ndarray, y: np.ndarray, steering_rad: float, footprint: SweptFootprint,
                   max_path_m: float, reverse: bool, first: int) -> tuple[PathHit, PathHit]:
    """:func:`free_distance` over all the points and over the ``first`` ones only, from one sweep.

    The second is what sweeping ``x[:first]``, ``y[:first]`` alone gives (the same point, the
    same distance), without sweeping them again: each point's path length depends on that point
    only. It is the first when that one's index is below ``first``.
    """
    miss = PathHit(max_path_m, -1)
    if len(x) == 0:
        return miss, miss
    scale, band, values = _sweep(x, y, steering_rad, footprint, reverse)
    hit = _nearest(band, values, scale, max_path_m)
    if hit.index < first:  # -1 too: nothing on the path, nor among the first points
        return hit, hit
    k = int(np.searchsorted(band, first))  # band is in increasing order: its first k are < first
    return hit, _nearest(band[:k], values[:k], scale, max_path_m)


def _nearest(band: np.ndarray, values: np.ndarray, scale: float, max_path_m: float) -> PathHit:
    """The nearest of the swept points ``band`` (see :func:`_sweep`) within ``max_path_m``."""
    if band.size == 0:
        return PathHit(max_path_m, -1)
    i = int(np.argmin(values))
    nearest = float(values[i] * scale)
    if nearest >= max_path_m:
        return PathHit(max_path_m, -1)
    return PathHit(nearest, int(band[i]))


def _sweep(x: np.ndarray, y: np.ndarray, steering_rad: float, footprint: SweptFootprint,
           reverse: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, band, values): the indices of the points the footprint may sweep, and for each of
    them path length / scale (inf where never hit); every other point is never hit.

    Straight: values are path lengths, scale 1. On an arc: values are rotations about the ICR
    (radians), scale the turn radius. Runs on every scan, so it sticks to a few numpy operations,
    each used many times (see :func:`lidar_drivers.scip.decode_data_lines` for why).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    front, rear = footprint.front_m, footprint.rear_m
    if reverse:
        x = -x
        front, rear = rear, front
    radius = footprint.turn_radius(steering_rad)
    hw = footprint.half_width_m
    if math.isinf(radius):
        band = ((np.abs(y) <= hw) & (x >= -rear)).nonzero()[0]
        return 1.0, band, np.maximum(x[band] - front, 0.0)
    if radius < 0.0:
        y = -y
        radius = -radius
    # u: the point's coordinate along the ICR -> base_link direction; rho: distance from the ICR
    u = radius - y
    rho2 = x * x + u * u
    inner, outer = radius - hw, radius + hw
    front_reach2 = front * front + outer * outer  # the front outer corner's radius, squared
    rear_reach2 = rear * rear + outer * outer
    band = ((rho2 >= inner * inner) & (rho2 <= max(front_reach2, rear_reach2))).nonzero()[0]
    if band.size == 0:
        return radius, band, np.zeros(0)
    xb, ub, r2 = x[band], u[band], rho2[band]
    # Leading end of the front part of the body at radius rho: the point with the smallest u
    # whose x stays within the front face, u = clip(sqrt(rho^2 - front^2), inner, outer).
    u_lead = np.minimum(np.maximum(np.sqrt(np.maximum(r2 - front * front, 0.0)), inner), outer)
    x_lead = np.sqrt(np.maximum(r2 - u_lead * u_lead, 0.0))
    turn = _turn(x_lead, u_lead, xb, ub)
    turn[r2 > front_reach2] = np.inf
    # Past radius R + hw the body at that radius splits in two arcs: the front one above, and
    # the rear outer corner region, which swings outwards (tail swing) and leads at u = R + hw.
    tail = ((r2 > outer * outer) & (r2 <= rear_reach2)).nonzero()[0]
    if tail.size:
        x_tail = -np.sqrt(r2[tail] - outer * outer)
        turn[tail] = np.minimum(turn[tail], _turn(x_tail, outer, xb[tail], ub[tail]))
    inside = (xb >= -rear) & (xb <= front) & (np.abs(y[band]) <= hw)
    # A point on the leading edge can round to a turn of about a full circle: it is a hit.
    turn[inside | (turn > _TWO_PI - 1e-9)] = 0.0
    return radius, band, turn


def _turn(x_from: np.ndarray, u_from: np.ndarray | float, x_to: np.ndarray,
          u_to: np.ndarray) -> np.ndarray:
    """Counter-clockwise rotation about the ICR, radians in [0, 2 pi], taking one point onto another.

    Points are (x, u) with angle ``atan2(x, u)``; both lie on the same circle about the ICR. The
    angle of the negated (cross, dot) vector plus pi is the rotation already in [0, 2 pi].
    """
    minus_cross = x_from * u_to - u_from * x_to
    minus_dot = 0.0 - (u_from * u_to + x_from * x_to)
    return np.arctan2(minus_cross, minus_dot) + math.pi


def stopping_speed(free_m: float, latency_s: float, max_decel_mps2: float) -> float:
    """The largest speed v (m/s) with ``v * latency + v^2 / (2 * decel) <= free_m``; 0 if free_m <= 0.

    Solves ``v^2 / (2a) + v t - d = 0`` for its positive root ``-a t + sqrt((a t)^2 + 2 a d)``,
    written as ``2 a d / (a t + sqrt((a t)^2 + 2 a d))`` to avoid cancellation.
    """
    if not free_m > 0.0:
        return 0.0
    at = max_decel_mps2 * latency_s
    twice_ad = 2.0 * max_decel_mps2 * free_m
    if twice_ad == 0.0:  # free_m so small it underflows
        return 0.0
    return twice_ad / (at + math.sqrt(at * at + twice_ad))
