"""The fits behind ``racecar-hw calibrate``: pure functions of recorded samples, no I/O.

- :func:`fit_wall`: a straight wall in one scan (total least squares over the beams ahead), its
  perpendicular distance from the laser and its normal's direction in the laser frame.
- :func:`fit_erpm_gain`: the motor's ERPM per m/s from the wall distance against the tachometer.
  The VESC counts 6 tachometer steps per electrical revolution, so a distance ``s`` driven at
  ``gain`` ERPM per m/s is ``10 * tach / gain`` metres; toward a wall whose normal is ``phi`` off
  the car's heading the perpendicular distance shrinks by ``s cos(phi)``. So the slope of the wall
  distance against ``u = sum(dtach * cos(phi))`` is ``-10 / gain``.
- :func:`fit_steering`: the servo offset and gains from arcs. Each arc gives the servo position
  sent and the curvature the gyro measured (yaw rate over speed); the kinematic bicycle turns at
  ``tan(delta) = curvature * wheelbase``, and the servo map is linear, ``servo = offset + gain *
  delta``, with its own gain for each side. The offset is where the curvature is zero.

Each fit returns its value, a standard error from the least-squares residuals and the residuals'
RMS, so the procedure can refuse to write a poor fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Tachometer steps per electrical revolution, and seconds per minute: distance = 10 * tach / gain.
TACH_TO_METRES_X_GAIN = 60.0 / 6.0


@dataclass(frozen=True)
class WallFit:
    """A wall in a scan: ``distance_m`` from the laser along the normal, ``normal_rad`` the normal's
    direction in the laser frame (0: straight ahead), ``rms_m`` the points' RMS off the line."""

    distance_m: float
    normal_rad: float
    rms_m: float
    points: int


def fit_wall(ranges: np.ndarray, angle_min: float, angle_increment: float, *, half_width_rad: float = 0.35,
             range_max: float = 30.0) -> WallFit | None:
    """The straight wall ahead in a scan (laser frame), or None with fewer than 10 valid beams."""
    r = np.asarray(ranges, dtype=np.float64)
    angles = angle_min + angle_increment * np.arange(len(r))
    keep = (np.abs(angles) <= half_width_rad) & np.isfinite(r) & (r > 0.02) & (r < range_max)
    if np.count_nonzero(keep) < 10:
        return None
    x, y = r[keep] * np.cos(angles[keep]), r[keep] * np.sin(angles[keep])
    cx, cy = x.mean(), y.mean()
    # total least squares: the normal is the direction of least spread
    cov = np.cov(np.vstack([x - cx, y - cy]))
    values, vectors = np.linalg.eigh(cov)
    nx, ny = vectors[:, 0]
    distance = nx * cx + ny * cy
    if distance < 0:
        nx, ny, distance = -nx, -ny, -distance
    rms = math.sqrt(max(values[0], 0.0) * (len(x) - 1) / len(x))
    return WallFit(float(distance), math.atan2(ny, nx), rms, int(len(x)))


@dataclass(frozen=True)
class Estimate:
    """A fitted value with its standard error and the fit's residual RMS (in the fit's unit)."""

    value: float
    std_error: float
    residual_rms: float
    samples: int


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Slope, intercept, the slope's standard error and the residual RMS of y = a x + b."""
    a_mat = np.vstack([x, np.ones_like(x)]).T
    (a, b), *_ = np.linalg.lstsq(a_mat, y, rcond=None)
    res = y - (a * x + b)
    dof = max(len(x) - 2, 1)
    s2 = float(res @ res) / dof
    sxx = float(((x - x.mean()) ** 2).sum())
    se = math.sqrt(s2 / sxx) if sxx > 0 else math.inf
    return float(a), float(b), se, math.sqrt(float(res @ res) / len(x))


def fit_erpm_gain(legs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> Estimate:
    """ERPM per m/s from straight legs toward or away from a wall.

    Each leg is ``(tach, wall distance m, wall normal rad)`` sampled at the same times while the
    car drove at a steady speed. Each leg is fitted on its own (a constant lag between the scan and
    the telemetry shifts a leg's intercept, and its sign flips with the direction) and the gains
    are combined weighted by their variance. The residual RMS is in metres.
    """
    gains, weights, rms, n = [], [], [], 0
    for tach, dist, normal in legs:
        if len(tach) < 5:
            continue
        u = np.concatenate([[0.0], np.cumsum(np.diff(tach) * np.cos(normal[1:]))])
        slope, _, se, res = _line(u, dist)
        if slope >= 0 or not math.isfinite(se):
            continue
        gain = TACH_TO_METRES_X_GAIN / -slope
        gains.append(gain)
        weights.append(1.0 / max((gain * se / -slope) ** 2, 1e-12))
        rms.append(res)
        n += len(tach)
    if not gains:
        return Estimate(math.nan, math.inf, math.inf, 0)
    w = np.array(weights)
    value = float(np.average(gains, weights=w))
    spread = float(np.std(gains)) if len(gains) > 1 else 0.0
    se = max(math.sqrt(1.0 / w.sum()), spread / math.sqrt(len(gains)))
    return Estimate(value, se, float(max(rms)), n)


@dataclass(frozen=True)
class SteeringFit:
    """Servo offset (servo for straight ahead) and the gains for left (delta > 0) and right turns."""

    offset: Estimate
    gain_left: Estimate
    gain_right: Estimate

    @property
    def gains_differ(self) -> bool:
        """Whether the two sides' gains differ by more than three of their standard errors and 2 %."""
        left, right = self.gain_left, self.gain_right
        diff = abs(left.value - right.value)
        return (diff > 3 * math.hypot(left.std_error, right.std_error)
                and diff > 0.02 * abs(0.5 * (left.value + right.value)))


def fit_steering(servo: np.ndarray, curvature: np.ndarray, wheelbase_m: float) -> SteeringFit:
    """Offset and gains from arcs: ``servo[i]`` sent while the car turned at ``curvature[i]`` (1/m,
    positive left). Needs arcs on both sides. The residual RMS is in servo units."""
    s = np.asarray(servo, dtype=np.float64)
    delta = np.arctan(np.asarray(curvature, dtype=np.float64) * wheelbase_m)
    left, right = np.where(delta > 0, delta, 0.0), np.where(delta < 0, delta, 0.0)
    a_mat = np.vstack([np.ones_like(delta), left, right]).T
    coef, *_ = np.linalg.lstsq(a_mat, s, rcond=None)
    res = s - a_mat @ coef
    dof = max(len(s) - 3, 1)
    s2 = float(res @ res) / dof
    try:
        cov = s2 * np.linalg.inv(a_mat.T @ a_mat)
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        se = np.full(3, math.inf)
    rms = math.sqrt(float(res @ res) / len(s)) if len(s) else math.inf
    n_left, n_right = int(np.count_nonzero(delta > 0)), int(np.count_nonzero(delta < 0))
    return SteeringFit(Estimate(float(coef[0]), float(se[0]), rms, len(s)),
                       Estimate(float(coef[1]), float(se[1]), rms, n_left),
                       Estimate(float(coef[2]), float(se[2]), rms, n_right))
