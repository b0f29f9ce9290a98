"""Vectorized lidar ray casting against an occupancy grid by sphere tracing a distance field.

At map load :func:`distance_field` computes, for every cell, the Euclidean distance (in cells) from
its square to the nearest occupied cell's square, capped at ``cap`` cells (a capped distance
transform in two separable numpy passes). A ray then advances from any point by the value of the
cell it is in, a step that cannot reach an obstacle. Next to walls the step falls back to half a
cell, and a hit (a sample inside an occupied cell) is refined by bisection,
so a range is within 1/32 of a cell of the cell boundary it hits. Walls one cell thick
on a diagonal can let a grazing ray through between two corner-touching cells; draw walls at least
two cells thick.

All beams advance together; beams that hit or leave range are dropped every few iterations.
Rays leave the grid freely: outside the map is empty space.
"""

from __future__ import annotations

import numpy as np

from racecar_hw.sim.occupancy import OccupancyMap

#: Smallest step near obstacles, in cells.
MIN_STEP_CELLS = 0.5
#: Bisection rounds refining a hit (precision MIN_STEP_CELLS / 2**rounds).
REFINE_ROUNDS = 3
#: Iterations between compactions of the set of beams still travelling (4x when few are left).
BLOCK = 4


def distance_field(occupied: np.ndarray, cap: int, between_squares: bool = False) -> np.ndarray:
    """Distance in cells from each cell centre to the nearest occupied cell centre, capped at ``cap``.

    Exact below the cap (a capped Euclidean distance transform); ``0`` on occupied cells, ``cap``
    where nothing occupied is within ``cap`` cells (or where there is no occupied cell at all).
    With ``between_squares`` the distance is measured between the cells' squares instead (centre
    offsets shrunk by one cell on each axis): the free distance from any point of the cell.
    """
    shrink = 1 if between_squares else 0
    occ = np.asarray(occupied, dtype=bool)
    h, w = occ.shape
    big = cap + 1
    cols = np.arange(w, dtype=np.int64)
    # pass 1: distance along each row to the nearest occupied cell in that row
    left = np.where(occ, cols, -10 * big - w)
    np.maximum.accumulate(left, axis=1, out=left)
    right = np.where(occ, cols, 10 * big + 2 * w)[:, ::-1]
    right = np.minimum.accumulate(right, axis=1)[:, ::-1]
    g = np.minimum(np.minimum(cols - left, right - cols), big).astype(np.float64)
    if shrink:
        g = np.maximum(g - shrink, 0.0)
    g2 = g * g
    # pass 2: combine rows within the cap: d2(r, c) = min over |dr| <= cap of dr^2 + g2(r + dr, c)
    d2 = g2.copy()
    for dr in range(1, min(cap, h - 1) + 1):
        cost = float((dr - shrink) ** 2)
        np.minimum(d2[dr:], g2[:-dr] + cost, out=d2[dr:])
        np.minimum(d2[:-dr], g2[dr:] + cost, out=d2[:-dr])
    field = np.minimum(np.sqrt(d2), float(cap))
    if shrink:
        field[occ] = 0.0
    return field


class RayCaster:
    """Casts beams from a sensor pose against one occupancy map; thread-safe (read-only state).

    ``cap_m`` bounds the precomputed distance (longer steps in open space cost a bigger precompute).
    """

    def __init__(self, occ_map: OccupancyMap, cap_m: float = 3.0) -> None:
        self.map = occ_map
        cap = max(2, int(round(cap_m / occ_map.resolution)))
        free = distance_field(occ_map.occupied, cap, between_squares=True)
        # a safe step from anywhere in the cell; 0 marks an occupied cell
        step = np.where(occ_map.occupied, 0.0, np.maximum(free, MIN_STEP_CELLS))
        self._step = np.ascontiguousarray(step, dtype=np.float64).ravel()
        self._occ = np.ascontiguousarray(occ_map.occupied).ravel()
        self._w, self._h = occ_map.width, occ_map.height
        #: free distance (cells, capped) from any point of each cell to the nearest occupied cell
        self.free_cells = free

    def cast(self, x: float, y: float, yaw: float, angles: np.ndarray, max_range: float) -> np.ndarray:
        """Ranges (metres) along ``angles`` (radians, CCW, sensor frame) from a sensor at map-frame
        pose (``x``, ``y``, ``yaw``); ``inf`` where no obstacle is within ``max_range`` metres."""
        res = self.map.resolution
        gx, gy = self.map.world_to_grid_frame(x, y)
        x0, y0 = float(gx), float(gy)
        theta = np.asarray(angles, dtype=np.float64) + (yaw - self.map.origin[2])
        c, s = np.cos(theta), np.sin(theta)
        n = theta.size
        limit_cells = max_range / res
        t_in, t_out = _slab(x0, y0, c, s, self._w, self._h)
        eps = 1e-6
        t = np.maximum(t_in, 0.0) + eps
        limit = np.minimum(t_out - eps, limit_cells)
        out = np.full(n, np.inf)
        active = np.flatnonzero(t < limit)
        ta, ca, sa, la = t[active], c[active], s[active], limit[active]
        w = self._w
        step_field = self._step
        hits: list[tuple[np.ndarray, np.ndarray]] = []
        while active.size:
            # a beam landing in an occupied cell takes zero steps: it stays on its hit
            for _ in range(BLOCK if active.size > 64 else 4 * BLOCK):
                idx = (y0 + ta * sa).astype(np.intp) * w + (x0 + ta * ca).astype(np.intp)
                ta = np.minimum(ta + step_field.take(idx, mode="clip"), la)
            idx = (y0 + ta * sa).astype(np.intp) * w + (x0 + ta * ca).astype(np.intp)
            hit = self._occ.take(idx, mode="clip")
            if hit.any():
                hits.append((active[hit], ta[hit]))
            going = ~hit & (ta < la)
            active, ta, ca, sa, la = active[going], ta[going], ca[going], sa[going], la[going]
        if hits:
            beams = np.concatenate([b for b, _ in hits])
            t_hit = np.concatenate([t for _, t in hits])
            out[beams] = self._refine(x0, y0, t_hit, c[beams], s[beams]) * res
        out[out > max_range] = np.inf
        return out

    def _refine(self, x0: float, y0: float, t: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Bisect between a free point MIN_STEP_CELLS back and the occupied sample ``t``."""
        hi = t
        lo = np.maximum(t - MIN_STEP_CELLS, 0.0)
        free = ~self._hit(x0, y0, lo, c, s)
        lo = np.where(free, lo, hi)  # started inside an obstacle: keep the sample
        for _ in range(REFINE_ROUNDS):
            mid = 0.5 * (lo + hi)
            m_hit = self._hit(x0, y0, mid, c, s)
            hi = np.where(m_hit, mid, hi)
            lo = np.where(m_hit, lo, mid)
        return 0.5 * (lo + hi)

    def _hit(self, x0: float, y0: float, t: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        px, py = x0 + t * c, y0 + t * s
        inside = (px >= 0) & (px < self._w) & (py >= 0) & (py < self._h)
        idx = py.astype(np.intp) * self._w + px.astype(np.intp)
        return inside & self._occ.take(idx, mode="clip")


def _slab(x0: float, y0: float, c: np.ndarray, s: np.ndarray, w: int,
          h: int) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit distances of rays from (x0, y0) along (c, s) through the box [0, w] x [0, h]."""
    # a ray (nearly) parallel to an axis: inside the slab means (-inf, inf), outside means empty
    along_x, along_y = np.abs(c) > 1e-12, np.abs(s) > 1e-12
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv_c = 1.0 / np.where(along_x, c, 1.0)
        inv_s = 1.0 / np.where(along_y, s, 1.0)
    tx1, tx2 = (0.0 - x0) * inv_c, (w - x0) * inv_c
    ty1, ty2 = (0.0 - y0) * inv_s, (h - y0) * inv_s
    inside_x = (x0 >= 0) & (x0 <= w)
    inside_y = (y0 >= 0) & (y0 <= h)
    tx_lo = np.where(along_x, np.minimum(tx1, tx2), -np.inf if inside_x else np.inf)
    tx_hi = np.where(along_x, np.maximum(tx1, tx2), np.inf if inside_x else -np.inf)
    ty_lo = np.where(along_y, np.minimum(ty1, ty2), -np.inf if inside_y else np.inf)
    ty_hi = np.where(along_y, np.maximum(ty1, ty2), np.inf if inside_y else -np.inf)
    return np.maximum(tx_lo, ty_lo), np.minimum(tx_hi, ty_hi)
