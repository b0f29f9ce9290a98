"""Lap progress around a loop track: how far the car went round a point in the track's infield.

Progress is counted in laps (1.0 = once round) as the unwrapped turn of the car's position (map
frame, x and y in metres) about a centre inside the infield, from where the car started. Its sign
follows the start: forwards is the way the car faced at the start, so on the shipped ``track``
(started heading +x along the bottom corridor) counter-clockwise laps count up. A lap is complete
when the car has gone once round: crossed the line from the centre through the start again.

The centre defaults to the middle of the map's free space (the bounding box of its free cells);
that is the infield on a loop track. On a map whose middle is free (an open room) the count means
nothing, and :func:`infield_centre` gives None: no lap progress is counted there.
"""

from __future__ import annotations

import math

import numpy as np

from racecar_hw.sim.occupancy import OccupancyMap


def infield_centre(occ_map: OccupancyMap) -> tuple[float, float] | None:
    """The middle of the free space's bounding box (map frame, m) when it is not free itself (a
    loop's infield); None otherwise (no loop round it)."""
    free = ~occ_map.occupied
    rows = np.flatnonzero(free.any(axis=1))
    cols = np.flatnonzero(free.any(axis=0))
    if rows.size == 0:
        return None
    gx = (cols[0] + cols[-1] + 1) / 2.0
    gy = (rows[0] + rows[-1] + 1) / 2.0
    x, y = occ_map.grid_frame_to_world(gx, gy)
    centre = (float(x), float(y))
    return centre if bool(occ_map.is_occupied(*centre)) else None


class LapProgress:
    """Progress (laps) round ``centre`` of a car that started at ``start`` (x, y, yaw in the map
    frame); feed it every new position with :meth:`update`."""

    def __init__(self, centre: tuple[float, float], start: tuple[float, float, float]) -> None:
        self.centre = centre
        x, y, yaw = start
        rx, ry = x - centre[0], y - centre[1]
        # forwards: the way round that the start heading points (its cross product with the radius)
        cross = rx * math.sin(yaw) - ry * math.cos(yaw)
        self.direction = 1.0 if cross >= 0 else -1.0
        self._last = math.atan2(ry, rx)
        self._turned = 0.0

    @property
    def progress(self) -> float:
        """Laps driven forwards (negative backwards of the start)."""
        return self.direction * self._turned / (2 * math.pi)

    @property
    def laps(self) -> int:
        """Whole laps completed (0 until the car first comes round to the start line again)."""
        return max(0, math.floor(self.progress))

    def update(self, x: float, y: float) -> float:
        """Take the car's position (map frame, m); returns :attr:`progress`."""
        angle = math.atan2(y - self.centre[1], x - self.centre[0])
        self._turned += math.remainder(angle - self._last, 2 * math.pi)
        self._last = angle
        return self.progress


__all__ = ["LapProgress", "infield_centre"]
