"""The calibration's fits on synthetic data with known answers: a wall in a scan, the ERPM gain from
the wall distance against the tachometer, and the servo offset and gains from arcs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from racecar_hw.sources.calibration_fit import fit_erpm_gain, fit_steering, fit_wall

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


def _scan_of_wall(distance: float, normal: float, noise: float, rng: np.random.Generator):
    angles = np.linspace(-2.35, 2.35, 1081)
    with np.errstate(divide="ignore"):
        r = distance / np.cos(angles - normal)
    r = np.where((np.cos(angles - normal) > 0.05) & (r < 30), r, np.inf)
    return r + rng.normal(0.0, noise, r.shape), float(angles[0]), float(angles[1] - angles[0])


@pytest.mark.parametrize(("distance", "normal"), [(3.0, 0.0), (1.2, 0.1), (2.5, -0.2)])
def test_a_wall_is_found_at_its_distance_and_angle(distance, normal):
    ranges, a0, inc = _scan_of_wall(distance, normal, 0.01, np.random.default_rng(1))
    wall = fit_wall(ranges, a0, inc)
    assert wall is not None
    assert wall.distance_m == pytest.approx(distance, abs=0.005)
    assert wall.normal_rad == pytest.approx(normal, abs=0.01)
    assert wall.rms_m == pytest.approx(0.01, rel=0.3)


def test_no_wall_without_enough_beams_ahead():
    ranges = np.full(1081, np.inf)
    assert fit_wall(ranges, -2.35, 4.7 / 1080) is None


def test_a_corner_is_not_flat():
    angles = np.linspace(-2.35, 2.35, 1081)
    ranges = np.where(angles > 0, 2.0, 3.0) / np.cos(angles)
    wall = fit_wall(np.where(np.abs(angles) < 1.2, ranges, np.inf), -2.35, angles[1] - angles[0])
    assert wall is not None and wall.rms_m > 0.1


def _leg(gain: float, start: float, metres: float, normal: float, lag_m: float, rng) -> tuple:
    """Tachometer and wall distance every 2.5 cm driven, the scan lagging ``lag_m`` behind."""
    s = np.arange(0.0, abs(metres), 0.0125)
    tach = np.sign(metres) * s * gain / 10.0 + 1000.0
    dist = start - np.sign(metres) * (s - lag_m) * math.cos(normal) + rng.normal(0, 0.002, s.shape)
    return tach, dist, np.full_like(s, normal)


def test_the_erpm_gain_from_two_legs_with_a_lag_and_a_skewed_wall():
    rng = np.random.default_rng(2)
    true = 5075.4
    legs = [_leg(true, 3.0, 1.6, 0.08, 0.01, rng), _leg(true, 1.4, -1.6, 0.08, -0.01, rng)]
    est = fit_erpm_gain(legs)
    assert est.value == pytest.approx(true, rel=0.002)
    assert est.std_error < 0.005 * true and est.residual_rms < 0.004 and est.samples == 256


def test_the_erpm_gain_is_nan_without_a_usable_leg():
    est = fit_erpm_gain([(np.arange(3.0), np.arange(3.0), np.zeros(3))])
    assert math.isnan(est.value) and est.samples == 0


def test_offset_and_both_gains_from_arcs():
    wheelbase, offset, left, right = 0.25, 0.5804, -1.33485, -1.25
    deltas = np.array([0.08, 0.15, 0.22, -0.08, -0.15, -0.22, 0.1, -0.1])
    servo = np.where(deltas > 0, offset + left * deltas, offset + right * deltas)
    curvature = np.tan(deltas) / wheelbase * (1 + np.random.default_rng(3).normal(0, 0.002, deltas.shape))
    fit = fit_steering(servo, curvature, wheelbase)
    assert fit.offset.value == pytest.approx(offset, abs=0.001)
    assert fit.gain_left.value == pytest.approx(left, rel=0.01)
    assert fit.gain_right.value == pytest.approx(right, rel=0.01)
    assert fit.gains_differ


def test_equal_gains_do_not_differ():
    deltas = np.array([0.08, 0.15, 0.22, -0.08, -0.15, -0.22])
    servo = 0.53 - 1.2135 * deltas
    fit = fit_steering(servo, np.tan(deltas) / 0.25, 0.25)
    assert fit.offset.value == pytest.approx(0.53, abs=1e-9)
    assert not fit.gains_differ
