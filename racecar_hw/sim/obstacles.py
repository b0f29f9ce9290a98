"""Dynamic obstacles a scenario places in the world: circles and oriented boxes, in the map frame.

Each obstacle answers two questions: how far a lidar beam travels before hitting it
(:meth:`ray_ranges`) and how far it is from the car's footprint polygon (:meth:`distance_to`).
Metres and radians, map frame (REP-103).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Circle:
    """A disc of ``radius`` metres centred at (``x``, ``y``): a pole, a person's legs, a cone."""

    x: float
    y: float
    radius: float

    def ray_ranges(self, x0: float, y0: float, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Distance along unit directions (c, s) from (x0, y0) to the circle; inf on a miss, 0 inside."""
        dx, dy = self.x - x0, self.y - y0
        along = dx * c + dy * s
        d2 = dx * dx + dy * dy - along * along
        r2 = self.radius * self.radius
        half = np.sqrt(np.maximum(r2 - d2, 0.0))
        t = along - half
        out = np.where((d2 <= r2) & (along + half >= 0), np.maximum(t, 0.0), np.inf)
        if dx * dx + dy * dy <= r2:
            out[:] = 0.0
        return out

    def distance_to(self, polygon: np.ndarray) -> float:
        """Gap (m) between the disc and a convex polygon (N x 2 corners, CCW); 0 when they touch."""
        return max(point_polygon_distance(self.x, self.y, polygon) - self.radius, 0.0)


@dataclass(frozen=True)
class Box:
    """A rectangle ``length`` x ``width`` metres centred at (``x``, ``y``), ``length`` along ``yaw``."""

    x: float
    y: float
    length: float
    width: float
    yaw: float = 0.0

    def corners(self) -> np.ndarray:
        """The four corners, counter-clockwise, shape (4, 2)."""
        return rectangle(self.x, self.y, self.yaw, -self.length / 2, self.length / 2,
                         -self.width / 2, self.width / 2)

    def ray_ranges(self, x0: float, y0: float, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Distance along unit directions (c, s) from (x0, y0) to the box; inf on a miss, 0 inside."""
        cy, sy = math.cos(self.yaw), math.sin(self.yaw)
        # ray in the box frame
        px = cy * (x0 - self.x) + sy * (y0 - self.y)
        py = -sy * (x0 - self.x) + cy * (y0 - self.y)
        dx = cy * c + sy * s
        dy = -sy * c + cy * s
        hx, hy = self.length / 2, self.width / 2
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            tx1, tx2 = (-hx - px) / dx, (hx - px) / dx
            ty1, ty2 = (-hy - py) / dy, (hy - py) / dy
        in_x, in_y = abs(px) <= hx, abs(py) <= hy
        lo = np.maximum(np.where(dx != 0, np.minimum(tx1, tx2), -np.inf if in_x else np.inf),
                        np.where(dy != 0, np.minimum(ty1, ty2), -np.inf if in_y else np.inf))
        hi = np.minimum(np.where(dx != 0, np.maximum(tx1, tx2), np.inf if in_x else -np.inf),
                        np.where(dy != 0, np.maximum(ty1, ty2), np.inf if in_y else -np.inf))
        return np.where((lo <= hi) & (hi >= 0), np.maximum(lo, 0.0), np.inf)

    def distance_to(self, polygon: np.ndarray) -> float:
        """Gap (m) between the box and a convex polygon (N x 2 corners, CCW); 0 when they overlap."""
        return polygon_distance(self.corners(), polygon)


Obstacle = Circle | Box


def rectangle(x: float, y: float, yaw: float, x_min: float, x_max: float, y_min: float,
              y_max: float) -> np.ndarray:
    """Corners (CCW, shape (4, 2)) of the body-frame box [x_min, x_max] x [y_min, y_max] placed at
    pose (x, y, yaw)."""
    local = np.array([[x_min, y_min], [x_max, y_min], [x_max, y_max], [x_min, y_max]])
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack((x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1]))


def point_polygon_distance(px: float, py: float, polygon: np.ndarray) -> float:
    """Distance from a point to a convex CCW polygon; 0 inside."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    edge = b - a
    rel = np.array([px, py]) - a
    cross = edge[:, 0] * rel[:, 1] - edge[:, 1] * rel[:, 0]
    if np.all(cross >= 0):
        return 0.0
    u = np.clip((rel * edge).sum(axis=1) / (edge * edge).sum(axis=1), 0.0, 1.0)
    nearest = a + u[:, None] * edge
    return float(np.min(np.hypot(px - nearest[:, 0], py - nearest[:, 1])))


def polygon_distance(p: np.ndarray, q: np.ndarray) -> float:
    """Distance between two convex CCW polygons; 0 when they overlap (separating-axis test)."""
    for poly in (p, q):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.column_stack((edges[:, 1], -edges[:, 0]))
        pp, qq = p @ normals.T, q @ normals.T
        if np.any((pp.max(axis=0) < qq.min(axis=0)) | (qq.max(axis=0) < pp.min(axis=0))):
            break
    else:
        return 0.0
    return min(min(point_polygon_distance(x, y, q) for x, y in p),
               min(point_polygon_distance(x, y, p) for x, y in q))
