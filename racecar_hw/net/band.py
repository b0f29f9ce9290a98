"""The band the car's footprint sweeps along the commanded arc, in base_link.

Geometry (the model of :mod:`safety.arc`): base_link, the centre of the rear axle, moves on a circle
of radius ``R = wheelbase / tan(steering)`` (straight when the steering is 0). Over the stopping
distance the car's rectangle sweeps a band whose inner edge is traced by the inner end of the rear
axle (radius ``R - half_width``, the point nearest the turn centre) and whose outer edge by the
leading outer corner (the front one, the rear one in reverse). Straight ahead the band is the
rectangle from the leading bumper on. Metres, base_link (x forward, y left).

Both live views draw it: the status page (:mod:`racecar_hw.net.web`) and the Foxglove scene
(:mod:`racecar_hw.net.scene`); apart from the latter so that the status page runs without the
Foxglove SDK (the ``foxglove`` extra).
"""

from __future__ import annotations

import math

import numpy as np

from racecar_hw.net.control import CarShape
from safety.arc import SweptFootprint

#: Samples along the arc.
STATIONS = 24


def body_corners(shape: CarShape) -> np.ndarray:
    """The footprint's corners (4, 2) in base_link, counter-clockwise from the front left."""
    f, r, w = shape.front_m, shape.rear_m, shape.half_width_m
    return np.array([[f, w], [-r, w], [-r, -w], [f, -w]])


def swept_band(shape: CarShape, steering_rad: float, length_m: float,
               reverse: bool = False, stations: int = STATIONS) -> tuple[np.ndarray, np.ndarray]:
    """The band the footprint sweeps over ``length_m`` of path: (inner edge, outer edge), each (n, 2).

    The edges run side by side from the car outwards: point k of each is where the car's edge points
    are after the same stretch of path, so consecutive pairs make the band's quads.
    """
    sweep = SweptFootprint(shape.front_m, shape.rear_m, shape.half_width_m, shape.wheelbase_m)
    radius = sweep.turn_radius(steering_rad if math.isfinite(steering_rad) else 0.0)
    lead = -shape.rear_m if reverse else shape.front_m
    s = np.linspace(0.0, max(length_m, 0.0), stations) * (-1.0 if reverse else 1.0)
    if math.isinf(radius):
        x = lead + s
        w = shape.half_width_m
        return np.column_stack([x, np.full_like(x, w)]), np.column_stack([x, np.full_like(x, -w)])
    turn = math.copysign(1.0, radius)
    theta = s / radius
    px, py = radius * np.sin(theta), radius * (1.0 - np.cos(theta))
    c, sn = np.cos(theta), np.sin(theta)

    def carried(bx: float, by: float) -> np.ndarray:
        return np.column_stack([px + bx * c - by * sn, py + bx * sn + by * c])

    return carried(0.0, turn * shape.half_width_m), carried(lead, -turn * shape.half_width_m)


def band_polygon(inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """The band's outline: the inner edge out, the outer edge back."""
    return np.vstack([inner, outer[::-1]])


__all__ = ["STATIONS", "band_polygon", "body_corners", "swept_band"]
