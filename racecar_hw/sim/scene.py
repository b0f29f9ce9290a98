"""What the car drives among: the occupancy map's walls and the obstacles placed on it.

Obstacles are fixed (a disc or a box, :meth:`Scene.add_obstacle`) or movers
(:class:`~racecar_hw.sim.movers.Mover`, :meth:`Scene.add_mover`), which appear, move and disappear
on sim time ``t`` (s). Positions are in the map frame (m), angles in radians. Thread-safe: the
world's stepping thread, the fake lidars' threads and the scenario read and change it at once.
"""

from __future__ import annotations

import threading

import numpy as np

from racecar_hw.sim.movers import Mover
from racecar_hw.sim.obstacles import Box, Circle, Obstacle, rectangle
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.raycast import RayCaster


class Scene:
    """The map and its obstacles, by id; ray-cast and asked what is where."""

    def __init__(self, occ_map: OccupancyMap) -> None:
        self.map = occ_map
        self._raycaster = RayCaster(occ_map)
        self._last_cast: tuple[tuple[float, float, float, float], np.ndarray, np.ndarray] | None = None
        self._lock = threading.Lock()
        self._obstacles: dict[int, Obstacle | Mover] = {}
        self._next_obstacle = 1

    def add_obstacle(self, x: float, y: float, radius: float | None = None,
                     box: tuple[float, float] | None = None, yaw: float = 0.0) -> int:
        """Place a disc (``radius`` m) or a box (``box`` = (length, width) m, rotated by ``yaw``)
        centred at map-frame (``x``, ``y``). Returns an id for :meth:`remove`."""
        if (radius is None) == (box is None):
            raise ValueError("give exactly one of radius or box")
        obstacle: Obstacle
        if radius is not None:
            if not radius > 0:
                raise ValueError(f"radius must be > 0, got {radius}")
            obstacle = Circle(float(x), float(y), float(radius))
        else:
            assert box is not None
            if not (box[0] > 0 and box[1] > 0):
                raise ValueError(f"box sides must be > 0, got {box}")
            obstacle = Box(float(x), float(y), float(box[0]), float(box[1]), float(yaw))
        return self._add(obstacle)

    def add_mover(self, mover: Mover) -> int:
        """Add an obstacle that appears, moves and disappears on sim time. Returns an id."""
        return self._add(mover)

    def _add(self, entry: Obstacle | Mover) -> int:
        with self._lock:
            ident = self._next_obstacle
            self._next_obstacle += 1
            self._obstacles[ident] = entry
        return ident

    def remove(self, ident: int) -> None:
        """Take away an obstacle; unknown ids are ignored."""
        with self._lock:
            self._obstacles.pop(ident, None)

    def clear(self) -> None:
        """Take away every obstacle."""
        with self._lock:
            self._obstacles.clear()

    def shapes_at(self, t: float) -> tuple[Obstacle, ...]:
        """The obstacles present at sim time ``t``, where they are then."""
        with self._lock:
            entries = list(self._obstacles.values())
        return tuple(shape for entry in entries if (shape := _shape_at(entry, t)) is not None)

    def by_id_at(self, t: float) -> dict[int, Obstacle]:
        """The obstacles present at sim time ``t``, by id, where they are then."""
        with self._lock:
            entries = list(self._obstacles.items())
        return {ident: shape for ident, entry in entries
                if (shape := _shape_at(entry, t)) is not None}

    def named_at(self, t: float) -> list[tuple[str, Obstacle]]:
        """(name, shape) of every obstacle present at sim time ``t`` (s), where it is then; an
        obstacle without a name is called ``obstacle <id>``."""
        with self._lock:
            entries = list(self._obstacles.items())
        out = []
        for ident, entry in entries:
            shape = _shape_at(entry, t)
            if shape is not None:
                name = entry.name if isinstance(entry, Mover) and entry.name else f"obstacle {ident}"
                out.append((name, shape))
        return out

    def what_is_at(self, x: float, y: float, t: float, within: float = 0.15) -> str | None:
        """What occupies map point (``x``, ``y``) at sim time ``t``, within ``within`` metres: the
        nearest obstacle's name, ``"map"`` for an occupied map cell, or None."""
        best, name = within, None
        probe = rectangle(x, y, 0.0, -1e-3, 1e-3, -1e-3, 1e-3)
        for label, shape in self.named_at(t):
            gap = shape.distance_to(probe)
            if gap <= best:
                best, name = gap, label
        if name is not None:
            return name
        res = self.map.resolution
        dx, dy = np.meshgrid(np.arange(-within, within + res, res), np.arange(-within, within + res, res))
        disc = np.hypot(dx, dy) <= within + res / 2
        return "map" if bool(np.any(self.map.is_occupied(x + dx[disc], y + dy[disc]))) else None

    def _walls(self, x: float, y: float, yaw: float, angles: np.ndarray, max_range: float) -> np.ndarray:
        """The walls' ranges from the ray caster; the last cast again (a copy) when the laser has
        not moved (a car at rest scans the same walls: only the noise and the obstacles change)."""
        last = self._last_cast
        if (last is not None and last[0] == (x, y, yaw, max_range)
                and (last[1] is angles or np.array_equal(last[1], angles))):
            return last[2].copy()
        ranges = self._raycaster.cast(x, y, yaw, angles, max_range)
        # kept as is when nothing can change it (read-only and its own data: the fake lidar's
        # angles of a sweep, the same array every scan), so the next scan's test is `is`
        kept = angles if not angles.flags.writeable and angles.base is None else angles.copy()
        self._last_cast = ((x, y, yaw, max_range), kept, ranges.copy())
        return ranges

    def ranges(self, laser_pose: tuple[float, float, float], angles: np.ndarray, max_range: float,
               t: float) -> np.ndarray:
        """Noise-free ranges (m) along ``angles`` (rad, laser frame) from ``laser_pose`` (x, y, yaw
        in the map frame): walls and the obstacles where they are at sim time ``t``; ``inf``
        beyond ``max_range``."""
        x, y, yaw = laser_pose
        angles = np.asarray(angles, dtype=np.float64)
        ranges = self._walls(x, y, yaw, angles, max_range)
        obstacles = self.shapes_at(t)
        if obstacles:
            theta = angles + yaw
            c, s = np.cos(theta), np.sin(theta)
            for obstacle in obstacles:
                np.minimum(ranges, obstacle.ray_ranges(x, y, c, s), out=ranges)
            ranges[ranges > max_range] = np.inf
        return ranges


def _shape_at(entry: Obstacle | Mover, t: float) -> Obstacle | None:
    """A fixed obstacle, or a mover where it is at sim time ``t`` (None while it is absent)."""
    return entry.at(t) if isinstance(entry, Mover) else entry


__all__ = ["Scene"]
