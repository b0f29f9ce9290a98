"""Dynamic obstacles a scenario places in the world: circles, oriented boxes and convex polygons,
in the map frame.

Each obstacle answers two questions: how far a lidar beam travels before hitting it
(:meth:`ray_ranges`) and how far it is from the car's footprint polygon (:meth:`distance_to`).
:func:`place` moves a shape given around the origin to a pose. Metres and radians, map frame
(REP-103).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
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


@dataclass(frozen=True)
class Polygon:
    """A convex polygon: its corners (x, y) in metres, counter-clockwise. Build with :meth:`convex`."""

    points: tuple[tuple[float, float], ...]

    @classmethod
    def convex(cls, points: Sequence[Sequence[float]]) -> Polygon:
        """The polygon through ``points`` (either winding); ValueError unless they make a convex one.

        A concave outline is several convex polygons side by side.
        """
        corners = [(float(x), float(y)) for x, y in points]
        if len(corners) < 3:
            raise ValueError(f"a polygon needs at least 3 corners, got {len(corners)}")
        a = np.asarray(corners)
        b = np.roll(a, -1, axis=0)
        edges = b - a
        after = np.roll(edges, -1, axis=0)
        turns = edges[:, 0] * after[:, 1] - edges[:, 1] * after[:, 0]  # + at a left turn
        area = 0.5 * float(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]))  # shoelace, + if CCW
        if not np.all(np.isfinite(a)) or abs(area) < 1e-9:
            raise ValueError(f"polygon {corners} has no area")
        if not (np.all(turns >= -1e-12) or np.all(turns <= 1e-12)):
            raise ValueError(f"polygon {corners} is not convex (split it into convex ones)")
        return cls(tuple(corners) if area > 0 else tuple(reversed(corners)))

    def corners(self) -> np.ndarray:
        """The corners, counter-clockwise, shape (N, 2)."""
        return np.asarray(self.points, dtype=np.float64)

    def ray_ranges(self, x0: float, y0: float, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Distance along unit directions (c, s) from (x0, y0) to the polygon; inf on a miss, 0 inside."""
        corners = self.corners()
        if point_polygon_distance(x0, y0, corners) == 0.0:
            return np.zeros(np.shape(c))
        best = np.full(np.shape(c), np.inf)
        for (ax, ay), (bx, by) in zip(corners, np.roll(corners, -1, axis=0), strict=True):
            ex, ey = bx - ax, by - ay
            den = c * ey - s * ex
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((ax - x0) * ey - (ay - y0) * ex) / den
                u = ((ax - x0) * s - (ay - y0) * c) / den
            hit = (np.abs(den) > 1e-12) & (t >= 0) & (u >= 0) & (u <= 1)
            best = np.where(hit & (t < best), t, best)
        return best

    def distance_to(self, polygon: np.ndarray) -> float:
        """Gap (m) between this polygon and a convex polygon (N x 2 corners, CCW); 0 when they overlap."""
        return polygon_distance(self.corners(), polygon)


Obstacle = Circle | Box | Polygon


def place(shape: Obstacle, x: float, y: float, yaw: float = 0.0) -> Obstacle:
    """``shape``, given around the origin, turned by ``yaw`` and moved to (``x``, ``y``)."""
    if isinstance(shape, Circle):
        return Circle(shape.x + x, shape.y + y, shape.radius)
    c, s = math.cos(yaw), math.sin(yaw)
    if isinstance(shape, Box):
        return Box(x + c * shape.x - s * shape.y, y + s * shape.x + c * shape.y, shape.length,
                   shape.width, shape.yaw + yaw)
    return Polygon(tuple((x + c * px - s * py, y + s * px + c * py) for px, py in shape.points))


def rectangle(x: float, y: float, yaw: float, x_min: float, x_max: float, y_min: float,
              y_max: float) -> np.ndarray:
    """Corners (CCW, shape (4, 2)) of the body-frame box [x_min, x_max] x [y_min, y_max] placed at
    pose (x, y, yaw)."""
    c, s = math.cos(yaw), math.sin(yaw)
    # four points: plain arithmetic, then one array (numpy's per-call cost dominates at this size)
    return np.array([(x + c * px - s * py, y + s * px + c * py)
                     for px, py in ((x_min, y_min), (x_max, y_min), (x_max, y_max), (x_min, y_max))])


def point_polygon_distance(px: float, py: float, polygon: np.ndarray | list[list[float]]) -> float:
    """Distance from a point to a convex CCW polygon; 0 inside."""
    # plain arithmetic over a handful of corners: numpy's per-call cost dominates at this size
    pts = polygon.tolist() if isinstance(polygon, np.ndarray) else polygon
    n = len(pts)
    inside = True
    best = math.inf
    for i in range(n):
        ax, ay = pts[i]
        bx, by = pts[(i + 1) % n]
        ex, ey = bx - ax, by - ay
        rx, ry = px - ax, py - ay
        if ex * ry - ey * rx < 0:
            inside = False
        u = min(max((rx * ex + ry * ey) / (ex * ex + ey * ey), 0.0), 1.0)
        best = min(best, math.hypot(px - (ax + u * ex), py - (ay + u * ey)))
    return 0.0 if inside else best


def polygon_distance(p: np.ndarray, q: np.ndarray) -> float:
    """Distance between two convex CCW polygons; 0 when they overlap (separating-axis test)."""
    pts_p = p.tolist() if isinstance(p, np.ndarray) else p
    pts_q = q.tolist() if isinstance(q, np.ndarray) else q
    if not _separated(pts_p, pts_q) and not _separated(pts_q, pts_p):
        return 0.0
    return min(min(point_polygon_distance(x, y, pts_q) for x, y in pts_p),
               min(point_polygon_distance(x, y, pts_p) for x, y in pts_q))


def _separated(poly: list[list[float]], other: list[list[float]]) -> bool:
    """Whether an edge normal of ``poly`` separates the two polygons."""
    n = len(poly)
    for i in range(n):
        ax, ay = poly[i]
        bx, by = poly[(i + 1) % n]
        nx, ny = by - ay, ax - bx
        pp = [x * nx + y * ny for x, y in poly]
        qq = [x * nx + y * ny for x, y in other]
        if max(pp) < min(qq) or max(qq) < min(pp):
            return True
    return False
