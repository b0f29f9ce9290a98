"""The driven trajectory: samples, the CSV file, and the numbers a scenario report quotes.

A sample is the car's state after a world step: ``t`` seconds of sim time since the world's start
or last reset, rear-axle pose ``x``, ``y`` (m) and ``yaw`` (rad) in the map frame, ``speed`` (m/s,
negative in reverse) and front-wheel ``steering`` (rad, + left).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from racecar_hw.base.errors import RacecarError

CSV_FIELDS = ("t", "x", "y", "yaw", "speed", "steering")
#: Speeds below this (m/s) count as standing still.
STOPPED_SPEED = 0.05


class TrajectorySample(NamedTuple):
    """One state of the car: s, m, m, rad, m/s, rad."""

    t: float
    x: float
    y: float
    yaw: float
    speed: float
    steering: float


def write_csv(path: str | Path, samples: Iterable[TrajectorySample]) -> int:
    """Write samples to a CSV file with a ``t,x,y,yaw,speed,steering`` header; returns the row count."""
    n = 0
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_FIELDS)
        for s in samples:
            writer.writerow([f"{s.t:.6f}", f"{s.x:.6f}", f"{s.y:.6f}", f"{s.yaw:.6f}", f"{s.speed:.6f}",
                             f"{s.steering:.6f}"])
            n += 1
    return n


def read_csv(path: str | Path) -> list[TrajectorySample]:
    """Samples from a file written by :func:`write_csv`."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None or tuple(header) != CSV_FIELDS:
                raise RacecarError(f"{path}: not a trajectory CSV (header {header!r}, "
                                   f"expected {','.join(CSV_FIELDS)})")
            return [TrajectorySample(*(float(v) for v in row)) for row in reader if row]
    except (OSError, ValueError, TypeError) as err:
        raise RacecarError(f"{path}: cannot read trajectory CSV: {err}") from err


@dataclass(frozen=True)
class TrajectoryReport:
    """Summary numbers of a run (SI units). ``min_clearance_m`` is nan when not measured."""

    duration_s: float
    distance_m: float
    max_speed_mps: float
    mean_speed_mps: float
    max_abs_steering_rad: float
    max_lateral_accel_mps2: float
    start_pose: tuple[float, float, float]
    end_pose: tuple[float, float, float]
    displacement_m: float
    min_clearance_m: float

    def as_dict(self) -> dict[str, object]:
        """Plain data for JSON or YAML."""
        return asdict(self)


def report(samples: Sequence[TrajectorySample], wheelbase: float = 0.25,
           clearance: Callable[[tuple[float, float, float]], float] | None = None,
           clearance_every: int = 1) -> TrajectoryReport:
    """Numbers describing a run. ``clearance`` (pose -> metres), if given, is evaluated on every
    ``clearance_every``-th sample for ``min_clearance_m`` (a World measures it itself, every step)."""
    if not samples:
        nan = math.nan
        return TrajectoryReport(0.0, 0.0, nan, nan, nan, nan, (nan, nan, nan), (nan, nan, nan), nan, nan)
    a = np.asarray(samples, dtype=np.float64)
    t, x, y, speed, steer = a[:, 0], a[:, 1], a[:, 2], a[:, 4], a[:, 5]
    duration = float(t[-1] - t[0])
    distance = float(np.hypot(np.diff(x), np.diff(y)).sum())
    lateral = speed * speed * np.abs(np.tan(steer)) / wheelbase
    min_clear = math.nan
    if clearance is not None:
        min_clear = min(clearance((s.x, s.y, s.yaw)) for s in samples[::max(clearance_every, 1)])
    first, last = samples[0], samples[-1]
    return TrajectoryReport(
        duration_s=duration,
        distance_m=distance,
        max_speed_mps=float(np.max(np.abs(speed))),
        mean_speed_mps=distance / duration if duration > 0 else 0.0,
        max_abs_steering_rad=float(np.max(np.abs(steer))),
        max_lateral_accel_mps2=float(np.max(lateral)),
        start_pose=(first.x, first.y, first.yaw),
        end_pose=(last.x, last.y, last.yaw),
        displacement_m=float(math.hypot(last.x - first.x, last.y - first.y)),
        min_clearance_m=float(min_clear),
    )


def stop_time(samples: Sequence[TrajectorySample], after_t: float) -> float | None:
    """Sim time of the first sample at or after ``after_t`` with |speed| below STOPPED_SPEED."""
    for s in samples:
        if s.t >= after_t and abs(s.speed) < STOPPED_SPEED:
            return s.t
    return None


def rest_time(samples: Sequence[TrajectorySample], t0: float, t1: float | None = None) -> float | None:
    """Sim time at which the car came to rest between ``t0`` and ``t1`` (None: the last sample):
    the first standstill after it moved in that span, or its first sample when the car stood still
    throughout; None when it was moving at ``t1``.

    Unlike :func:`stop_time`, a car standing at ``t0`` that then drives has not stopped yet."""
    moved = False
    first = None
    for s in samples:
        if s.t < t0:
            continue
        if t1 is not None and s.t > t1:
            break
        if first is None:
            first = s.t
        if abs(s.speed) >= STOPPED_SPEED:
            moved = True
        elif moved:
            return s.t
    return None if moved else first


def stopping_distance(samples: Sequence[TrajectorySample], after_t: float,
                      stopped_t: float | None = None) -> float | None:
    """Path length (m) driven from ``after_t`` (e.g. a stop command) until the car stood still
    (at ``stopped_t`` when given, else at :func:`stop_time`); ``None`` if it never stopped."""
    t_stop = stop_time(samples, after_t) if stopped_t is None else stopped_t
    if t_stop is None:
        return None
    pts = [(s.x, s.y) for s in samples if after_t <= s.t <= t_stop]
    before = [s for s in samples if s.t < after_t]
    if before:
        pts.insert(0, (before[-1].x, before[-1].y))
    if len(pts) < 2:
        return 0.0
    arr = np.asarray(pts)
    return float(np.hypot(*np.diff(arr, axis=0).T).sum())


def distance_travelled(samples: Sequence[TrajectorySample]) -> float:
    """Path length (m) of the samples."""
    if len(samples) < 2:
        return 0.0
    a = np.asarray([(s.x, s.y) for s in samples])
    return float(np.hypot(*np.diff(a, axis=0).T).sum())
