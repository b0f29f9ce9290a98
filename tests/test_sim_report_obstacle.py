"""The report's intervention point, what is there and the distance left, against the world's
geometry, when the car moves fast or turns: a scan's points are where the lidar measured them,
up to a sweep (18.75 ms of a UST-10LX) before the scan reached the daemon."""

from __future__ import annotations

import math

import pytest
from lockstep_sim import run_lockstep

WALL_FACE_X = 8.0  # the room's far wall, ahead of the `wall` scenario's start


def stopped_clearance(loopback, entry: dict) -> float:  # noqa: ANN001
    """The world's clearance of the car where the report says it stood still."""
    world = loopback.world
    at = next(s for s in world.samples if s.t >= entry["stopped_at_s"])
    return world.clearance((at.x, at.y, at.yaw))


def test_a_stop_from_5_mps_reports_the_wall_face_and_the_gap_the_world_measures() -> None:
    result, lb = run_lockstep("wall", "drivers.0.speed_mps=5.0")
    r = result.report
    assert not r["collided"]
    (stop,) = r["interventions"]
    assert stop["reason"] == "obstacle" and stop["source"] == "scan" and stop["object"] == "map"
    assert stop["speed_mps"] > 4.0 and stop["stopped_at_s"] is not None
    # on the wall face (range noise 1 cm), not 9 cm behind it as placed from the scan's arrival
    assert stop["obstacle"]["x"] == pytest.approx(WALL_FACE_X, abs=0.03)
    assert stop["distance_left_m"] == pytest.approx(stopped_clearance(lb, stop), abs=1e-3)


def test_a_stop_in_a_full_lock_turn_reports_the_pole_it_saw() -> None:
    # left at full lock at 5 m/s, then full right lock towards a 0.1 m pole: the car turns 0.1 rad
    # in a sweep, so a point placed from the scan's arrival lands 0.3 m off the pole (nothing there)
    pole = (-0.824, -0.795, 0.05)
    result, lb = run_lockstep(
        "wall", "start=[2.0, -2.0, 0.0]", "duration_s=5.0",
        "drivers=[{type: script, input: nav_0, steps: [[0.0, 5.0, 0.26], [3.0, 5.0, -0.26]]}]",
        f"obstacles=[{{name: pole, shape: disc, radius_m: {pole[2]}, at: [{pole[0]}, {pole[1]}]}}]")
    r = result.report
    assert not r["collided"]
    (stop,) = r["interventions"]
    assert stop["source"] == "scan" and stop["object"] == "pole" and stop["stopped_at_s"] is not None
    o = stop["obstacle"]
    assert math.hypot(o["x"] - pole[0], o["y"] - pole[1]) == pytest.approx(pole[2], abs=0.03)
    assert stop["distance_left_m"] == pytest.approx(stopped_clearance(lb, stop), abs=1e-3)
