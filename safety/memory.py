"""Obstacle memory: what the lidar saw recently, kept in the odom frame, for where it cannot see now.

A front lidar is blind behind the car (a UST-10LX sees 270 degrees; the rear quarter is dark) and
right beside the rear wheels. The car has seen most of what is there moments before, when it
drove past or away from it. :class:`ObstacleMemory` keeps those returns.

Structure: a square grid of ``size_m`` on a side at ``resolution_m`` (200 x 200 cells by default)
in the ``odom`` frame (REP-105), following the car. Each cell holds the monotonic time (integer
ns) at which the lidar last saw a return in it, 0 when empty. Cells are fixed in odom, so as the
car moves they move relative to it exactly as its odometry says. The grid is allocated once, so
the memory is bounded whatever the run's length.

One :meth:`update` per scan (or every few scans), with the car's odom pose at that scan:

1. The window follows the car: when the car is more than a quarter of the window from its
   centre, the grid shifts so the car is central again, and cells that leave the window are
   forgotten.
2. Remembered cells older than ``max_age_s`` are forgotten: odometry drifts.
3. Remembered cells inside the lidar's field of view are checked against the scan: a cell is
   forgotten when every beam across its width reaches it, to within ``see_through_m``, or beyond,
   because the lidar now sees what is there (the live scan wins: what moved away is not remembered
   where it was, and a noisy return is replaced by the next ones, which step 4 writes in). Only a
   cell hidden behind something nearer stays. Cells inside the car's own footprint are forgotten
   too: the car stands there.
4. The scan's returns are written in, stamped with the update's time, each cell keeping the odom
   position of the last return in it.

:meth:`points` then gives the position of every remembered return within ``reach_m`` of the car
(the return itself, not its cell's centre: a centre is up to half a cell diagonal nearer, which put
a box's corner inside a corridor the car fitted through, and kept it stopped there). The safety
controller sweeps them with the live scan: where the lidar sees, they repeat what it saw at the last
update; where it does not (behind, beside the rear wheels, a point that left the field of view
between two updates), they are all there is. Farther ones only matter to a path longer than
that, which the lidar sees ahead, or to reversing faster than the crawl the controller allows.

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

#: The finest beam spacing a scan can have, radians. 2D lidars space their beams about 1e-3 rad
#: apart or more (a UST-10LX: 4.4e-3); a finer ``angle_increment`` is a broken message, whose beam
#: indices (bearing / increment) need not even fit an integer.
MIN_ANGLE_INCREMENT_RAD = 1e-6

#: A planar affine transform (a, b, tx, c, d, ty): x' = a x + b y + tx, y' = c x + d y + ty.
Affine = tuple[float, float, float, float, float, float]

# Sparse-table levels for windows of up to 2 * MAX_HALF_WINDOW + 1 beams: the level of a window
# of n values (the largest run length 2**level <= n), and each level's run length.
_LEVELS = (2 * MAX_HALF_WINDOW + 1).bit_length()
_LEVEL_OF = np.array([max(n.bit_length() - 1, 0) for n in range(2 * MAX_HALF_WINDOW + 2)], dtype=np.intp)
_RUN = 1 << np.arange(_LEVELS, dtype=np.intp)


def plausible_increment(angle_increment: float) -> bool:
    """Whether beams ``angle_increment`` apart (radians, either direction) can come from a lidar:
    at least :data:`MIN_ANGLE_INCREMENT_RAD` and at most a full turn (False for NaN and inf)."""
    return MIN_ANGLE_INCREMENT_RAD <= abs(angle_increment) <= _TWO_PI


class ObstacleMemory:
    """A rolling grid of recently seen lidar returns in the odom frame. See the module docs."""

    def __init__(self, size_m: float = 10.0, resolution_m: float = 0.05, max_age_s: float = 10.0,
                 see_through_m: float = 0.1, reach_m: float = 3.0) -> None:
        if not (resolution_m > 0.0 and size_m >= 4 * resolution_m):
            raise ValueError(f"memory grid of {size_m} m at {resolution_m} m cells is not a grid")
        self.resolution_m = float(resolution_m)
        self.cells_per_side = 2 * int(math.ceil(size_m / resolution_m / 2.0))
        self.max_age_ns = int(round(max_age_s * 1e9))
        self.see_through_m = float(see_through_m)
        self.reach_m = float(reach_m)
        n = self.cells_per_side
        self._seen = np.zeros((n, n), dtype=np.int64)  # row: y cell, column: x cell
        self._where = np.zeros((n, n), dtype=np.complex128)  # odom x + iy of each cell's last return
        self._origin: tuple[int, int] | None = None  # global (x, y) cell index of [0, 0]
        self._last_xy: tuple[float, float] | None = None
        self._points = np.zeros(0, dtype=np.complex128)  # odom cell centres as x + iy
        self.updates = 0
        self.resets = 0

    # --- queries --------------------------------------------------------------------------------

    def __len__(self) -> int:
        """How many cells hold a remembered return."""
        return int(np.count_nonzero(self._seen))

    @property
    def nbytes(self) -> int:
        """Bytes held by the grid and the remembered points."""
        return int(self._seen.nbytes + self._where.nbytes + self._points.nbytes)

    def points(self) -> np.ndarray:
        """The remembered returns within ``reach_m`` of the car at the last update: their odom
        positions as complex numbers x + iy (a cell's last return).

        Complex, because a planar rigid transform is then two numpy operations,
        ``points * exp(-i yaw) - p * exp(-i yaw)``, the cheapest way on the scan-to-command path.
        """
        return self._points

    def cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every remembered cell: odom x, y of its centre (m) and when it was last seen (ns)."""
        if self._origin is None:
            empty = np.zeros(0)
            return empty, empty, np.zeros(0, dtype=np.int64)
        j, i = np.nonzero(self._seen != 0)
        odom = np.array(self._cells_to_odom()).reshape(2, 3) @ np.array((i, j, np.ones(i.size)))
        return odom[0], odom[1], self._seen[j, i]

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
        self._where[:] = 0
        self._points = np.zeros(0, dtype=np.complex128)
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

        Runs once per scan, off the scan-to-command path but at the scan rate, so it sticks to
        few numpy calls (see :func:`safety.arc._sweep`): frames change by one matrix product each.
        """
        px, py, yaw = (float(v) for v in pose)
        last = self._last_xy
        if last is not None and math.hypot(px - last[0], py - last[1]) > MAX_JUMP_M:
            self.clear()
        self._last_xy = (px, py)
        self._follow(px, py)
        self._forget((px, py, yaw), laser_to_base, ranges, angle_min, angle_increment, range_min,
                     range_max, now_ns, footprint)
        self._insert((px, py, yaw), x, y, now_ns)
        occupied = (self._seen.reshape(-1) != 0).nonzero()[0]  # nonzero() of booleans: fast
        points = self._where.reshape(-1)[occupied]
        self._points = points[np.abs(points - complex(px, py)) <= self.reach_m]
        self.updates += 1

    def _forget(self, pose: tuple[float, float, float], laser_to_base: np.ndarray, ranges: np.ndarray,
                angle_min: float, angle_increment: float, range_min: float, range_max: float,
                now_ns: int, footprint: tuple[float, float, float] | None) -> None:
        """Steps 2 and 3: drop old, seen-through and run-over cells."""
        flat = self._seen.reshape(-1)
        occupied = (flat != 0).nonzero()[0]  # nonzero() on the booleans: 10x faster than on int64
        if occupied.size == 0:
            return
        # cells as homogeneous (column, row, 1), and the matrices taking them to the laser frame
        # and to base_link in one product
        cells = np.array((occupied % self.cells_per_side, occupied // self.cells_per_side,
                          np.ones(occupied.size)), dtype=np.float64)
        to_odom = self._cells_to_odom()
        base = _pose(pose)
        laser = _compose(base, tuple(float(v) for v in laser_to_base.ravel()))
        local = np.array(_compose(_inverse(laser), to_odom) + _compose(_inverse(base), to_odom)).reshape(4, 3)
        lx, ly, bx, by = local @ cells
        old = flat[occupied] < now_ns - self.max_age_ns
        through = self._seen_through(np.hypot(lx, ly), np.arctan2(ly, lx), ranges, angle_min,
                                     angle_increment, range_min, range_max)
        gone = old | through
        if footprint is not None:
            front, rear, half_width = footprint
            gone |= (np.abs(bx - 0.5 * (front - rear)) <= 0.5 * (front + rear)) & (np.abs(by) <= half_width)
        flat[occupied[gone]] = 0

    def _seen_through(self, r: np.ndarray, bearing: np.ndarray, ranges: np.ndarray, angle_min: float,
                      angle_increment: float, range_min: float, range_max: float) -> np.ndarray:
        """For cells at range ``r`` and ``bearing`` (laser frame): whether the scan sees through them.

        A cell is seen when it is inside the field of view and the lidar's range limits, and every
        beam across its width reaches it, to within ``see_through_m`` (range noise), or beyond:
        the scan then holds what is there now. A scan whose beams have no plausible directions (a
        non-finite angle, an increment below :data:`MIN_ANGLE_INCREMENT_RAD` or above a turn) sees
        nothing.
        """
        count = len(ranges)
        if count == 0 or not (math.isfinite(angle_min) and plausible_increment(angle_increment)):
            return np.zeros(r.shape, dtype=bool)
        step = abs(angle_increment)
        # the angle from the first beam, in the scan's direction, in [0, 2 pi): bearing is in
        # [-pi, pi] and the first beam's angle is brought into [-pi, pi) too
        first = (angle_min + math.pi) % _TWO_PI - math.pi
        turn = bearing - first if angle_increment > 0 else first - bearing
        index = np.where(turn < 0.0, turn + _TWO_PI, turn) / step
        tol = self.see_through_m
        far = range_max if range_max > range_min else math.inf
        visible = (index <= count - 1) & (r >= range_min) & (r <= far - tol)
        if not visible.any():
            return visible
        # What each beam tells: how far it saw free space. NaN and readings below range_min tell
        # nothing (0); no return within range_max (inf, or past range_max) is free up to range_max.
        free = np.asarray(ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            free = np.where(free >= range_min, free, 0.0)
            free[free > far] = math.inf
        # clamped as floats, then cast: a float beyond the integers casts to garbage
        centre = np.minimum(index + 0.5, count - 1).astype(np.intp)  # any beam for those out of view
        # beams either side across the cell: its half width over the range, an upper bound of the
        # angle it spans (atan(w) <= w); a cell centred on the laser (r = 0) spans them all
        with np.errstate(divide="ignore"):
            across = 0.75 * self.resolution_m / (step * r)
        half = np.minimum(across, MAX_HALF_WINDOW - 1).astype(np.intp) + 1
        nearest = _window_min(free, np.maximum(centre - half, 0), np.minimum(centre + half, count - 1))
        return visible & (nearest >= r - tol)

    def _insert(self, pose: tuple[float, float, float], x: np.ndarray, y: np.ndarray, now_ns: int) -> None:
        """Step 4: stamp the cells of the scan's returns."""
        if len(x) == 0:
            return
        n = self.cells_per_side
        a, b, tx, c, d, ty = _compose(_inverse(self._cells_to_odom()), _pose(pose))
        # + 0.5: from "a cell's centre at 0" to "a cell starts at 0", so that floor gives the cell
        to_cells = np.array(((a, b, tx + 0.5), (c, d, ty + 0.5)))
        xy1 = np.array((x, y, np.ones(len(x))))
        ij = np.floor(to_cells @ xy1).astype(np.int64)
        inside = ((ij >= 0) & (ij < n)).all(axis=0)
        flat = (ij[1] * n + ij[0])[inside]
        self._seen.reshape(-1)[flat] = max(now_ns, 1)  # 0 marks an empty cell
        odom = np.array(_pose(pose)).reshape(2, 3) @ xy1[:, inside]
        self._where.reshape(-1)[flat] = odom[0] + 1j * odom[1]  # of several, the last in the scan

    def _cells_to_odom(self) -> Affine:
        """A cell's (column, row) to the odom point at its centre."""
        assert self._origin is not None
        res = self.resolution_m
        oi, oj = self._origin
        return (res, 0.0, (oi + 0.5) * res, 0.0, res, (oj + 0.5) * res)

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
        self._seen, self._where = (_shifted(grid, di, dj) for grid in (self._seen, self._where))
        self._origin = want


def _shifted(grid: np.ndarray, di: int, dj: int) -> np.ndarray:
    """``grid`` moved by (di, dj) cells: new[j, i] = old[j + dj, i + di] where both are inside,
    empty (0) elsewhere."""
    n = grid.shape[0]
    shifted = np.zeros_like(grid)
    if abs(di) < n and abs(dj) < n:
        shifted[max(-dj, 0):n - max(dj, 0), max(-di, 0):n - max(di, 0)] = \
            grid[max(dj, 0):n - max(-dj, 0), max(di, 0):n - max(-di, 0)]
    return shifted


def _window_min(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``min(values[lo[k]:hi[k] + 1])`` for every k (lo <= hi, windows of at most 64 values).

    A sparse table: level L holds the minimum of each run of 2**L values; a window is covered by
    two runs of the largest level that fits, overlapping in the middle. Only the levels the
    widest window needs are built (cells a few metres off span a handful of beams: three levels,
    not six).
    """
    count = len(values)
    level = _LEVEL_OF[hi - lo + 1]
    levels = int(level.max()) + 1 if level.size else 1
    table = np.full((levels, count), np.inf)
    table[0] = values
    for built in range(1, levels):
        half = 1 << (built - 1)
        if half >= count:
            break
        np.minimum(table[built - 1, :-half], table[built - 1, half:], out=table[built, :-half])
    start = level * count
    flat = table.reshape(-1)
    return np.minimum(flat.take(start + lo), flat.take(start + hi - _RUN[level] + 1))


def _pose(pose: tuple[float, float, float]) -> Affine:
    """The planar transform of a pose (x, y, yaw): its frame to the parent's."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return (c, -s, x, s, c, y)


def _compose(p: Affine, q: Affine) -> Affine:
    """``p`` after ``q`` (plain floats: cheaper than numpy for six numbers)."""
    a, b, tx, c, d, ty = p
    e, f, ux, g, h, uy = q
    return (a * e + b * g, a * f + b * h, a * ux + b * uy + tx,
            c * e + d * g, c * f + d * h, c * ux + d * uy + ty)


def _inverse(p: Affine) -> Affine:
    """The inverse transform (any invertible linear part: a mirrored laser too)."""
    a, b, tx, c, d, ty = p
    det = a * d - b * c
    ia, ib, ic, id_ = d / det, -b / det, -c / det, a / det
    return (ia, ib, -(ia * tx + ib * ty), ic, id_, -(ic * tx + id_ * ty))
