"""Obstacle memory: what the lidar saw recently, kept in the odom frame, for where it cannot see now.

A front lidar is blind behind the car (a UST-10LX sees 270 degrees; the rear quarter is dark) and
right beside the rear wheels. The car has seen most of what is there moments before, when it
drove past or away from it. :class:`ObstacleMemory` keeps those returns.

Structure: a square grid of ``size_m`` on a side at ``resolution_m`` (200 x 200 cells by default)
in the ``odom`` frame (REP-105), following the car. Each cell holds the monotonic time (integer
ns) at which the lidar last saw a return in it, 0 when empty. Cells are fixed in odom, so as the
car moves they move relative to it exactly as its odometry says. The grid is allocated once, so
the memory is bounded whatever the run's length.

One :meth:`update` per scan, with the car's odom pose at that scan:

1. The window follows the car: when the car is more than a quarter of the window from its
   centre, the grid shifts so the car is central again, and cells that leave the window are
   forgotten.
2. Remembered cells older than ``max_age_s`` are forgotten: odometry drifts.
3. Remembered cells inside the lidar's field of view are checked against the scan: a cell is
   forgotten when every beam across its width reaches ``see_through_m`` beyond it, because the
   lidar now sees through it (the live scan wins: what moved away is not remembered where it was).
4. The scan's returns are written in, stamped with the update's time.

:meth:`points` then gives the remembered cells the scan cannot vouch for: outside its field of view
(shrunk by ``fov_margin_rad`` at each edge, as the car turns between scans), beyond its range, or
hidden behind a nearer return. Those, with the live scan, are what the safety controller sweeps.

Pure numpy, no clock, no bus: times are the caller's monotonic nanoseconds, poses the caller's
odometry. Metres, radians; x forward, y left (REP-103).
"""

from __future__ import annotations

import math

import numpy as np

#: An odom pose that moves farther than this between two updates is a reset or a jump of the
#: odometry, not motion (40 m/s at 40 Hz): everything remembered is forgotten.
MAX_JUMP_M = 1.0

#: The widest window of beams (either side of a cell's bearing) checked for a see-through. Beyond
#: it a cell is so close that it is as wide as many beams, and only its central ones are checked.
MAX_HALF_WINDOW = 31

_TWO_PI = 2.0 * math.pi


class ObstacleMemory:
    """A rolling grid of recently seen lidar returns in the odom frame. See the module docs."""

    def __init__(self, size_m: float = 10.0, resolution_m: float = 0.05, max_age_s: float = 10.0,
                 see_through_m: float = 0.1, fov_margin_rad: float = 0.05) -> None:
        if not (resolution_m > 0.0 and size_m >= 4 * resolution_m):
            raise ValueError(f"memory grid of {size_m} m at {resolution_m} m cells is not a grid")
        self.resolution_m = float(resolution_m)
        self.cells_per_side = 2 * int(math.ceil(size_m / resolution_m / 2.0))
        self.max_age_ns = int(round(max_age_s * 1e9))
        self.see_through_m = float(see_through_m)
        self.fov_margin_rad = float(fov_margin_rad)
        n = self.cells_per_side
        self._seen = np.zeros((n, n), dtype=np.int64)  # row: y cell, column: x cell
        self._origin: tuple[int, int] | None = None  # global (x, y) cell index of [0, 0]
        self._last_xy: tuple[float, float] | None = None
        self._unseen = np.zeros((3, 0))  # homogeneous odom points, for one matrix product
        self.updates = 0
        self.resets = 0

    # --- queries --------------------------------------------------------------------------------

    @property
    def cell_radius_m(self) -> float:
        """Half a cell's diagonal: how far a remembered return may lie from its cell's centre, m."""
        return self.resolution_m * math.sqrt(0.5)

    def __len__(self) -> int:
        """How many cells hold a remembered return."""
        return int(np.count_nonzero(self._seen))

    @property
    def nbytes(self) -> int:
        """Bytes held by the grid and the last set of unseen points."""
        return int(self._seen.nbytes + self._unseen.nbytes)

    def points(self) -> np.ndarray:
        """Cells the last scan could not vouch for, as homogeneous odom points, shape (3, k).

        Rows are x, y (cell centres, metres) and 1, so that ``T @ points`` with a 2 x 3 matrix
        ``T`` maps them into another frame in one product.
        """
        return self._unseen

    def cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every remembered cell: odom x, y of its centre (m) and when it was last seen (ns)."""
        if self._origin is None:
            empty = np.zeros(0)
            return empty, empty, np.zeros(0, dtype=np.int64)
        j, i = np.nonzero(self._seen)
        x, y = self._centres(i, j)
        return x, y, self._seen[j, i]

    def window(self) -> tuple[float, float, float, float] | None:
        """The grid's extent in odom, (x_min, y_min, x_max, y_max) metres; None before any update."""
        if self._origin is None:
            return None
        res, n = self.resolution_m, self.cells_per_side
        oi, oj = self._origin
        return oi * res, oj * res, (oi + n) * res, (oj + n) * res

    # --- updates --------------------------------------------------------------------------------

    def clear(self) -> None:
        """Forget everything (the odometry was lost or jumped); the next update starts afresh."""
        self._seen[:] = 0
        self._unseen = np.zeros((3, 0))
        self._origin = None
        self._last_xy = None
        self.resets += 1

    def update(self, pose: tuple[float, float, float], laser_to_base: np.ndarray, ranges: np.ndarray,
               angle_min: float, angle_increment: float, range_min: float, range_max: float,
               x: np.ndarray, y: np.ndarray, now_ns: int,
               footprint: tuple[float, float, float] | None = None) -> None:
        """Fold one scan into the memory.

        ``pose``: base_link in odom (x m, y m, yaw rad) when the scan was taken. ``laser_to_base``:
        the 2 x 3 planar laser -> base_link matrix. ``ranges`` and the angles and limits: the scan as
        ``sensor_msgs/LaserScan`` has them. ``x``, ``y``: the scan's returns in base_link (the
        points the safety controller uses). ``now_ns``: the time they count as seen.
        ``footprint``: (front, rear, half width) of the car's body around base_link, metres: the
        car stands there, so whatever is remembered inside it is gone (or was never there).
        """
        px, py, yaw = (float(v) for v in pose)
        last = self._last_xy
        if last is not None and math.hypot(px - last[0], py - last[1]) > MAX_JUMP_M:
            self.clear()
        self._last_xy = (px, py)
        self._follow(px, py)
        c, s = math.cos(yaw), math.sin(yaw)
        base_to_odom = np.array([[c, -s, px], [s, c, py]])
        self._forget(base_to_odom, laser_to_base, ranges, angle_min, angle_increment, range_min,
                     range_max, now_ns, footprint)
        self._insert(base_to_odom, x, y, now_ns)
        self.updates += 1

    def _forget(self, base_to_odom: np.ndarray, laser_to_base: np.ndarray, ranges: np.ndarray,
                angle_min: float, angle_increment: float, range_min: float, range_max: float,
                now_ns: int, footprint: tuple[float, float, float] | None) -> None:
        """Steps 2 and 3: drop old, seen-through and run-over cells; keep those the scan cannot see."""
        flat = self._seen.reshape(-1)
        occupied = flat.nonzero()[0]
        if occupied.size == 0:
            self._unseen = np.zeros((3, 0))
            return
        n = self.cells_per_side
        qx, qy = self._centres(occupied % n, occupied // n)
        old = flat[occupied] < now_ns - self.max_age_ns
        # the cells in the laser frame: odom -> laser is the inverse of laser -> base -> odom
        lin = base_to_odom[:, :2] @ laser_to_base[:, :2]
        origin = base_to_odom[:, :2] @ laser_to_base[:, 2] + base_to_odom[:, 2]
        inv = np.linalg.inv(lin)
        dx, dy = qx - origin[0], qy - origin[1]
        lx = inv[0, 0] * dx + inv[0, 1] * dy
        ly = inv[1, 0] * dx + inv[1, 1] * dy
        r = np.hypot(lx, ly)
        visible, through, hidden = self._against_scan(r, np.arctan2(ly, lx), ranges, angle_min,
                                                      angle_increment, range_min, range_max)
        gone = old | through
        if footprint is not None:
            front, rear, half_width = footprint
            (c, s), (px, py) = base_to_odom[:, 0], base_to_odom[:, 2]
            bx = c * (qx - px) + s * (qy - py)
            by = c * (qy - py) - s * (qx - px)
            gone |= (bx >= -rear) & (bx <= front) & (np.abs(by) <= half_width)
        flat[occupied[gone]] = 0
        keep = ~gone & (~visible | hidden)
        self._unseen = np.vstack((qx[keep], qy[keep], np.ones(int(np.count_nonzero(keep)))))

    def _against_scan(self, r: np.ndarray, bearing: np.ndarray, ranges: np.ndarray, angle_min: float,
                      angle_increment: float, range_min: float,
                      range_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For cells at range ``r`` and ``bearing`` (laser frame): (visible, seen through, hidden).

        Visible: inside the field of view less the margins, and within the lidar's range limits.
        Seen through: visible, and every beam across the cell's width reaches ``see_through_m``
        beyond the cell. Hidden: visible, and some beam across it stops ``see_through_m`` short.
        """
        count = len(ranges)
        nothing = np.zeros(r.shape, dtype=bool)
        if count == 0 or not (math.isfinite(angle_min) and math.isfinite(angle_increment)) \
                or angle_increment == 0.0:
            return nothing, nothing, nothing
        step = abs(angle_increment)
        sign = 1.0 if angle_increment > 0 else -1.0
        index = np.mod((bearing - angle_min) * sign, _TWO_PI) / step
        margin = self.fov_margin_rad / step
        tol = self.see_through_m
        far = range_max if range_max > range_min else math.inf
        visible = (index >= margin) & (index <= count - 1 - margin) & (r >= range_min) & (r + tol <= far)
        if not visible.any():
            return visible, nothing, nothing
        # What each beam tells: how far it saw free space. NaN and readings below range_min tell
        # nothing (0); no return within range_max (inf, or past range_max) is free up to range_max.
        free = np.asarray(ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            free = np.where(free >= range_min, free, 0.0)
            free[free > far] = math.inf
        centre = np.minimum(np.rint(index), count - 1).astype(np.intp)
        half = np.minimum(np.ceil(np.arctan2(0.75 * self.resolution_m, r) / step), MAX_HALF_WINDOW)
        half = half.astype(np.intp)
        lo = np.maximum(centre - half, 0)
        hi = np.minimum(centre + half, count - 1)
        nearest = _window_min(free, lo, hi)
        through = visible & (nearest > r + tol)
        hidden = visible & (nearest < r - tol)
        return visible, through, hidden

    def _insert(self, base_to_odom: np.ndarray, x: np.ndarray, y: np.ndarray, now_ns: int) -> None:
        """Step 4: stamp the cells of the scan's returns."""
        if len(x) == 0:
            return
        assert self._origin is not None
        res, n = self.resolution_m, self.cells_per_side
        ox = base_to_odom[0, 0] * x + base_to_odom[0, 1] * y + base_to_odom[0, 2]
        oy = base_to_odom[1, 0] * x + base_to_odom[1, 1] * y + base_to_odom[1, 2]
        i = np.floor(ox / res).astype(np.int64) - self._origin[0]
        j = np.floor(oy / res).astype(np.int64) - self._origin[1]
        inside = ((i >= 0) & (i < n) & (j >= 0) & (j < n)).nonzero()[0]
        self._seen.reshape(-1)[j[inside] * n + i[inside]] = max(now_ns, 1)  # 0 marks an empty cell

    def _follow(self, x: float, y: float) -> None:
        """Step 1: shift the window so that the car stays within its central half."""
        res, n = self.resolution_m, self.cells_per_side
        ci, cj = math.floor(x / res), math.floor(y / res)
        want = (ci - n // 2, cj - n // 2)
        if self._origin is None:
            self._origin = want
            return
        oi, oj = self._origin
        if abs(want[0] - oi) <= n // 4 and abs(want[1] - oj) <= n // 4:
            return
        di, dj = want[0] - oi, want[1] - oj
        shifted = np.zeros_like(self._seen)
        if abs(di) < n and abs(dj) < n:
            # new[j, i] = old[j + dj, i + di] where both are inside the grid
            shifted[max(-dj, 0):n - max(dj, 0), max(-di, 0):n - max(di, 0)] = \
                self._seen[max(dj, 0):n - max(-dj, 0), max(di, 0):n - max(-di, 0)]
        self._seen = shifted
        self._origin = want

    def _centres(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Odom centres (m) of grid cells at column ``i``, row ``j``."""
        assert self._origin is not None
        res = self.resolution_m
        return (i + (self._origin[0] + 0.5)) * res, (j + (self._origin[1] + 0.5)) * res


def _window_min(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``min(values[lo[k]:hi[k] + 1])`` for every k (lo <= hi, windows of at most 64 values).

    A sparse table: level L holds the minimum of each run of 2**L values; a window is covered by
    two runs of the largest level that fits, overlapping in the middle.
    """
    length = hi - lo + 1
    levels = int(length.max()).bit_length()
    table = np.full((levels, len(values)), np.inf)
    table[0] = values
    for level in range(1, levels):
        half = 1 << (level - 1)
        table[level, :-half] = np.minimum(table[level - 1, :-half], table[level - 1, half:])
    level = np.log2(length).astype(np.intp)  # exact for the small integers here
    return np.minimum(table[level, lo], table[level, hi - (1 << level) + 1])
