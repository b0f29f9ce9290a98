"""Every shipped hazard scenario against its control: without the safety controller the car
collides, with the shipped config it does not.

A hazard scenario is one whose point is that the safety controller prevents a collision
(docs/sim.md, "Hazard scenarios and their controls"). Its "no collision" only means something if
the same scenario with ``safety.mode=off`` (no limit at all: no braking for obstacles, no stop for a
stale scan, no reverse cap) does collide, so each one is run twice. Both runs are lockstep
(:mod:`racecar_hw.runtime.lockstep`): the daemon and the fakes on the simulation's virtual clock,
as fast as the machine allows and the same on an idle or a loaded machine, so the outcomes are
asserted exactly. The run with the shipped config is the scenario's shared run
(tests/lockstep_sim.py, :func:`~lockstep_sim.shipped_run`), which the determinism and scenario
tests check too.

Every shipped scenario is either in :data:`HAZARDS` or in :data:`NOT_HAZARDS` with the reason:
a new scenario fails :func:`test_every_shipped_scenario_is_classified` until someone decides, and
a new hazard scenario gets its control from the parametrized test.
"""

from __future__ import annotations

import json

import pytest
from lockstep_sim import run_lockstep, shares_run, shipped_run, trajectory

from racecar_hw.sim.scenario import scenario_names

#: lockstep in this process, interfaces off, or pure computation: may run beside an alone test
pytestmark = pytest.mark.quiet

#: The hazard scenarios, each with the reason the shipped safety controller intervenes for.
HAZARDS: dict[str, str] = {
    "wall": "obstacle",             # the far wall, seen by the live scan
    "obstacle": "obstacle",         # a disc dropped 1.5 m ahead of the bumper
    "crossing-person": "obstacle",  # a person stepping into the path, timed to meet the car
    "sliding-box": "obstacle",      # a box sliding into the path and staying there
    "reverse-wall": "obstacle",     # a wall behind the car, known only to the obstacle memory
    "lidar-dropout": "stale_scan",  # a person crossing while the lidar is unplugged
}

#: The other shipped scenarios, and why they are not hazard scenarios.
NOT_HAZARDS: dict[str, str] = {
    "corridor": "the opposite check: the safety controller must not brake (no false stop)",
    "figure8": "open floor; it shows the car drives a figure-8",
    "teleop-override": "open floor; it shows the mux's priorities",
    "vesc-replug": "open floor; it shows the VESC driver reconnecting",
    "miscalibrated": "the car stands for racecar-hw calibrate --sim",
    "miscalibrated-figure8": "odometry error of a miscalibrated car (docs/sim.md says why it "
                             "still brakes at a wall)",
    "two-cars": "several cars (a Fleet, not a Loopback): tests/test_sim_fleet.py runs it and its "
                "control, the follower with safety off hitting the leader",
    "track": "nobody drives: the step API's track (tests/test_sim_env.py) and code over Zenoh",
}

#: The clearance (m) the shipped config keeps at least: the controller stops 0.25 m
#: (``safety.margin_m``) short; less than 0.1 m would be a near miss, not a margin.
CLEAR_MARGIN_M = 0.1


def show(name: str, config: str, report: dict) -> dict:
    """``report``, printed (shown with a failure)."""
    print(name, config, json.dumps({k: report.get(k) for k in (
        "collided", "collisions", "min_clearance_m", "final_pose", "distance_m",
        "safety_interventions_by_reason", "interventions")}))
    return report


def test_every_shipped_scenario_is_classified():
    assert not set(HAZARDS) & set(NOT_HAZARDS)
    assert set(scenario_names()) == set(HAZARDS) | set(NOT_HAZARDS)


@pytest.mark.parametrize("name", [pytest.param(name, marks=shares_run(name)) for name in sorted(HAZARDS)])
def test_a_hazard_collides_without_the_safety_controller_and_not_with_it(name):
    off = show(name, "safety.mode=off", run_lockstep(name, overrides=["safety.mode=off"])[0].report)
    assert off["collided"] is True
    assert off["safety_interventions"] == 0  # nothing limited the car
    assert off["min_clearance_m"] == 0.0

    shipped = show(name, "shipped", shipped_run(name)[0])
    assert shipped["collided"] is False, shipped["collisions"]
    assert shipped["min_clearance_m"] > CLEAR_MARGIN_M
    # it was the controller, for the reason the scenario is about, that kept the car clear
    assert shipped["safety_interventions_by_reason"] == {HAZARDS[name]: 1}


def test_a_steering_command_beyond_full_lock_turns_the_wheels_back_at_once(tmp_path):
    """The reviewer's case (docs/safety.md): circling at 3 m/s on a command of 1 rad (the car steers
    0.26), then 1 rad the other way at 3.0 s. The wheels start back within 0.1 s of the new command
    (the script's, the mux's and the VESC's periods), as they do for a command of 0.26; before, the
    mux's limiter first unwound from 1 rad to 0.26, and the wheels stayed at full lock until 3.285 s,
    on an arc the safety controller was no longer checking."""
    scenario = tmp_path / "windup.yaml"
    steps = "[[0.0, 3.0, 1.0], [3.0, 3.0, -1.0]]"
    scenario.write_text("map: room\nstart: [2.0, -2.0, 0.0]\nduration_s: 3.5\n"
                        f"drivers:\n  - {{type: script, input: nav_0, steps: {steps}}}\n")
    _result, lb = run_lockstep(str(scenario))
    samples = trajectory(lb)
    lock = max(s.steering for s in samples)
    assert 0.2 < lock < 0.3  # driven at full lock before the switch
    back = next(s.t for s in samples if s.t > 3.0 and s.steering < lock - 0.01)
    assert back < 3.1, back


def test_a_speed_command_beyond_the_top_speed_stops_as_fast_as_one_at_it(tmp_path):
    """10 m/s commanded for 3 s down the corridor (the car is sent at most 5), then a stop: the car
    slows as soon as after a command of 5 m/s. The limiter once held 7.5 m/s and spent 0.3 s
    ramping down to 5 before the wheels slowed."""
    def first_slowing(speed: float) -> float:
        scenario = tmp_path / f"fast-{speed:g}.yaml"
        scenario.write_text("map: corridor\nstart: [0.0, 0.0, 0.0]\nduration_s: 4.0\n"
                            f"drivers:\n  - {{type: script, input: nav_0, steps: [[0.0, {speed}, 0.0], "
                            "[3.0, 0.0, 0.0]]}\n")
        _result, lb = run_lockstep(str(scenario), overrides=("safety.mode=off",))
        samples = trajectory(lb)
        top = max(s.speed for s in samples if s.t < 3.0)
        assert top > 4.9  # the VESC's 5 m/s either way
        return next(s.t for s in samples if s.t > 3.0 and s.speed < top - 0.2)

    assert first_slowing(10.0) == pytest.approx(first_slowing(5.0), abs=0.03)
