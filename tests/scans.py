"""Synthetic lidar scans of wall segments, and car paths, for the safety controller's and the
memory's tests.

Segments are ((x0, y0), (x1, y1)) in metres, in whatever frame the caller's poses are in; paths
are lists of (x, y, yaw) poses, one per scan at 40 Hz.
"""

from __future__ import annotations

import math

import numpy as np

from racecar_hw.base.messages import Header, LaserScan, Time

LASER_X = 0.265  # the default laser position in base_link

Segment = tuple[tuple[float, float], tuple[float, float]]


def raycast(origin: tuple[float, float], angles: np.ndarray, segments: list[Segment],
            range_max: float) -> np.ndarray:
    """Distance from ``origin`` along each angle to the nearest segment; inf past range_max."""
    ox, oy = origin
    dx, dy = np.cos(angles), np.sin(angles)
    best = np.full(angles.shape, np.inf)
    for (ax, ay), (bx, by) in segments:
        ex, ey = bx - ax, by - ay
        den = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((ax - ox) * ey - (ay - oy) * ex) / den
            u = ((ax - ox) * dy - (ay - oy) * dx) / den
        ok = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        best = np.where(ok & (t < best), t, best)
    return np.where(best <= range_max, best, np.inf)


def ust10lx_scan(segments: list[Segment], laser: tuple[float, float] = (LASER_X, 0.0),
                 n: int = 1081, fov_deg: float = 270.0, range_max: float = 30.0,
                 stamp_ns: int = 0, heading: float = 0.0) -> LaserScan:
    """A scan of wall segments from a laser at ``laser`` facing ``heading`` (rad), in the segments'
    frame (base_link unless the caller places the laser elsewhere)."""
    half = math.radians(fov_deg) / 2.0
    angle_min, angle_max = -half, half
    inc = (angle_max - angle_min) / (n - 1)
    angles = angle_min + inc * np.arange(n)
    ranges = raycast(laser, angles + heading, segments, range_max)
    return LaserScan(header=Header(Time.from_ns(stamp_ns), "laser"), angle_min=angle_min,
                     angle_max=angle_max, angle_increment=inc, scan_time=0.025,
                     time_increment=0.025 / 1440, range_min=0.06, range_max=range_max,
                     ranges=ranges.astype(np.float32))


def scan_at(pose: tuple[float, float, float], segments: list[Segment], stamp_ns: int = 0,
            **kwargs: float) -> LaserScan:
    """The scan a laser LASER_X ahead of base_link sees with base_link at ``pose`` (x, y, yaw) in
    the segments' frame (odom)."""
    x, y, yaw = pose
    laser = (x + LASER_X * math.cos(yaw), y + LASER_X * math.sin(yaw))
    return ust10lx_scan(segments, laser, stamp_ns=stamp_ns, heading=yaw, **kwargs)


def base_points(scan: LaserScan) -> tuple[np.ndarray, np.ndarray]:
    """The scan's finite returns in base_link (the laser LASER_X ahead, facing forward)."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    angles = scan.angles()
    ok = np.isfinite(r) & (r >= scan.range_min)
    return LASER_X + r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])


def square(cx: float, cy: float, half: float = 0.05) -> list[Segment]:
    """The four sides of a square post centred at (cx, cy)."""
    a, b = (cx - half, cy - half), (cx + half, cy - half)
    c, d = (cx + half, cy + half), (cx - half, cy + half)
    return [(a, b), (b, c), (c, d), (d, a)]


def straight(start: tuple[float, float, float], distance: float, speed: float = 1.0) -> list:
    """Poses at 40 Hz along a straight line (negative distance: reversing)."""
    x, y, yaw = start
    steps = max(1, int(abs(distance) / (abs(speed) * 0.025)))
    return [(x + distance * k / steps * math.cos(yaw), y + distance * k / steps * math.sin(yaw), yaw)
            for k in range(1, steps + 1)]


def left_arc(start: tuple[float, float, float], radius: float, turn: float, speed: float = 1.0) -> list:
    """Poses at 40 Hz along a left turn of ``radius`` m through ``turn`` rad of heading."""
    x, y, yaw = start
    cx, cy = x - radius * math.sin(yaw), y + radius * math.cos(yaw)  # the centre of the turn
    steps = max(1, int(turn * radius / (speed * 0.025)))
    headings = [yaw + turn * k / steps for k in range(1, steps + 1)]
    return [(cx + radius * math.sin(h), cy - radius * math.cos(h), h) for h in headings]
