"""RPLIDAR samples (clockwise, time order) into ROS LaserScans (counter-clockwise, fixed grid).

The device turns clockwise seen from above and reports angles θ in degrees clockwise from its
front. A ROS angle is counter-clockwise, so a sample's ROS angle is ``φ = -θ`` normalised to
[-π, π). Each revolution becomes one scan on a fixed grid of ``N`` beams::

    angle_min = -π, angle_increment = 2π/N > 0, angle_max = π - 2π/N,
    beam i at φ_i = -π + i·2π/N (N is even, so beam N/2 points straight ahead).

Every sample goes to its nearest beam (the latest wins when two share one); a beam that got no
sample in this revolution is ``nan``; a sample with distance 0 (no return) or beyond ``range_max``
is ``inf``.

Time order: the sensor sweeps the grid from high to low index. A revolution is cut behind the
sensor, at the boundary between beam 0 and beam N-1 (device angle 180° + half a beam), so beam
N-1 is measured first and beam 0 last. Hence ``time_increment = -scan_time / N`` (negative) and
``header.stamp`` is the measurement time of beam 0, the last one: beam i was measured at
``stamp + i·time_increment``. ``scan_time`` is the revolution's sample count times the sample
period the device reports (the device's own clock, not arrival jitter).

``N`` is fixed for a session from the first complete revolution: 96 % of its sample count,
rounded down to even, so beams are slightly wider than the sample spacing and none stays empty
while the motor speed wobbles by a few percent. Every scan of a session has the same length; if
the motor speed changes a lot afterwards, beams are skipped (``nan``) until the next reconnect.
"""

from __future__ import annotations

import math

import numpy as np

from lidar_drivers.base import ScanGeometry
from lidar_drivers.rplidar_codec import Measurements
from racecar_hw.base.messages import Header, LaserScan, Time

MIN_BEAMS = 16
#: Beams per samples of the first revolution: beams a little wider than the sample spacing, so
#: every beam gets a sample even when the motor runs up to 1/BEAM_MARGIN - 1 (~4 %) faster.
BEAM_MARGIN = 0.96


class ScanAssembler:
    """Collects :class:`Measurements` batches and returns each finished revolution as a LaserScan.

    Pure: the caller gives every batch the measurement time of its last sample (integer ns).
    ``crop_min``/``crop_max`` (rad) keep only beams inside that range.
    """

    def __init__(self, *, range_min: float, range_max: float, sample_period_s: float,
                 frame_id: str = "laser", intensities: bool = False,
                 crop_min: float | None = None, crop_max: float | None = None) -> None:
        self.range_min = range_min
        self.range_max = range_max
        self.sample_period_s = sample_period_s
        self.frame_id = frame_id
        self.intensities = intensities
        self.crop_min = crop_min
        self.crop_max = crop_max
        self.beams: int | None = None  # N, fixed after the first complete revolution
        self.geometry: ScanGeometry | None = None
        self._prev_u: float | None = None
        self._seen_cut = False
        self._ang: list[np.ndarray] = []
        self._dist: list[np.ndarray] = []
        self._qual: list[np.ndarray] = []
        self._time: list[np.ndarray] = []

    @property
    def _cut_deg(self) -> float:
        half = 0.0 if self.beams is None else 180.0 / self.beams
        return 180.0 + half

    def add(self, m: Measurements, last_sample_ns: int) -> list[LaserScan]:
        """Add samples in time order; returns the scans of every revolution they complete."""
        n = len(m)
        if n == 0:
            return []
        period_ns = self.sample_period_s * 1e9
        times = last_sample_ns - (n - 1 - np.arange(n)) * period_ns
        out: list[LaserScan] = []
        angle = np.asarray(m.angle_deg, dtype=np.float64)
        begin = 0
        prev_u = self._prev_u
        while begin < n:
            # a cut is where the angle past the cut line wraps from ~360 back to ~0
            u = np.mod(angle[begin:] - self._cut_deg, 360.0)
            prev = np.concatenate([[u[0] if prev_u is None else prev_u], u[:-1]])
            hits = np.flatnonzero(u < prev - 180.0)
            if len(hits) == 0:
                break
            cut = begin + int(hits[0])
            self._collect(m, angle, times, begin, cut)
            scan = self._finish()  # may fix N, which moves the cut line by half a beam
            if scan is not None:
                out.append(scan)
            begin, prev_u = cut, None
        self._collect(m, angle, times, begin, n)
        self._prev_u = float(np.mod(angle[-1] - self._cut_deg, 360.0))
        return out

    def _collect(self, m: Measurements, angle: np.ndarray, times: np.ndarray, a: int, b: int) -> None:
        if b > a:
            self._ang.append(angle[a:b])
            self._dist.append(np.asarray(m.distance_mm[a:b], dtype=np.float64))
            self._qual.append(np.asarray(m.quality[a:b], dtype=np.float32))
            self._time.append(times[a:b])

    def _finish(self) -> LaserScan | None:
        ang, dist, qual, times = (np.concatenate(x) if x else np.zeros(0)
                                  for x in (self._ang, self._dist, self._qual, self._time))
        self._ang, self._dist, self._qual, self._time = [], [], [], []
        if not self._seen_cut:
            self._seen_cut = True  # the samples before the first cut are a partial revolution
            return None
        count = len(ang)
        if self.beams is None:
            if count < MIN_BEAMS:
                return None
            self.beams = 2 * math.floor(count * BEAM_MARGIN / 2)
            return None  # this revolution was cut at 180°, not at the grid boundary
        if count < self.beams // 2:
            return None  # a sliver left when the cut line moved, or a stream that broke off
        return self._scan(ang, dist, qual, times, count)

    def _scan(self, ang: np.ndarray, dist: np.ndarray, qual: np.ndarray, times: np.ndarray,
              count: int) -> LaserScan:
        n = self.beams
        assert n is not None
        inc = 2 * math.pi / n
        inc_deg = 360.0 / n
        u = np.mod(ang - self._cut_deg, 360.0)
        idx = np.clip(n - 1 - np.floor(u / inc_deg).astype(np.int64), 0, n - 1)
        metres = dist / 1000.0
        metres = np.where((dist <= 0) | (metres > self.range_max), np.inf, metres)
        ranges = np.full(n, np.nan, dtype=np.float32)
        inten = np.zeros(n, dtype=np.float32)
        # the latest sample of a beam wins: assign in reverse after keeping the last occurrence
        rev_idx = idx[::-1]
        _, first_in_rev = np.unique(rev_idx, return_index=True)
        keep = len(idx) - 1 - first_in_rev
        ranges[idx[keep]] = metres[keep]
        inten[idx[keep]] = qual[keep]
        scan_time = count * self.sample_period_s
        time_inc = -scan_time / n
        lo, hi = 0, n - 1
        angles = -math.pi + inc * np.arange(n)
        if self.crop_min is not None:
            lo = int(np.searchsorted(angles, self.crop_min - 1e-9))
        if self.crop_max is not None:
            hi = int(np.searchsorted(angles, self.crop_max + 1e-9, side="right")) - 1
        hi = max(hi, lo)
        stamp_ns = int(times[-1]) + round(lo * time_inc * 1e9)
        self.geometry = ScanGeometry(float(angles[lo]), float(angles[hi]), inc, self.range_min,
                                     self.range_max, scan_time, time_inc)
        return LaserScan(
            header=Header(stamp=Time.from_ns(stamp_ns), frame_id=self.frame_id),
            angle_min=float(angles[lo]), angle_max=float(angles[hi]), angle_increment=inc,
            time_increment=time_inc, scan_time=scan_time, range_min=self.range_min,
            range_max=self.range_max, ranges=ranges[lo:hi + 1].copy(),
            intensities=inten[lo:hi + 1].copy() if self.intensities else np.zeros(0, np.float32))
