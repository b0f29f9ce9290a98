"""Scenario runs in lockstep for the tests: the real daemon, drivers, codecs and fakes on the
simulation's virtual clock (:mod:`racecar_hw.runtime.lockstep`), in this process, as fast as the
machine allows. The same inputs give the same run on an idle or a loaded machine, so a test can
expect exact outcomes where a real-time run needed bands for the scheduler's hold-ups."""

from __future__ import annotations

import copy
import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import NO_DDS, NO_ZENOH

from racecar_hw.runtime import lockstep
from racecar_hw.sim.fleet import Fleet
from racecar_hw.sim.loopback import Loopback, SimResult
from racecar_hw.sim.scenario import load_scenario
from racecar_hw.sim.trajectory import TrajectorySample

#: What a lockstep run that is not about the network sets: every network interface off (no
#: sockets at all; the fakes sit behind in-memory links).
OFFLINE = (NO_ZENOH, NO_DDS, "foxglove.enabled=false", "web.enabled=false")

#: The report's keys printed with each run (shown with a failure).
SHOWN = ("final_pose", "distance_m", "collided", "safety_interventions_by_reason", "interventions",
         "mux_switches", "control", "vesc", "lidar", "sim_time_s")


def run_lockstep(scenario: str, *scenario_overrides: str, overrides: tuple[str, ...] | list[str] = (),
                 out_dir: str | Path | None = None, duration_s: float | None = None,
                 setup: Callable[[Loopback], None] | None = None,
                 **loopback: Any) -> tuple[SimResult, Loopback]:
    """Run the shipped ``scenario`` (or a scenario file) in lockstep with every network interface
    off; returns the result and the loopback (its world, daemon and fakes, after the run).
    ``out_dir``: write the trajectory CSV and the plot there (none by default: the trajectory is
    ``loopback.world.samples``)."""
    lb = Loopback(load_scenario(scenario, list(scenario_overrides)), out_dir=out_dir,
                  duration_s=duration_s, overrides=[*OFFLINE, *overrides], setup=setup, lockstep=True,
                  **loopback)
    result = lockstep.run(lb.run())
    r = result.report
    print(scenario, json.dumps({k: r.get(k) for k in SHOWN}))
    return result, lb


def trajectory(loopback: Loopback) -> list:
    """The run's trajectory (what the CSV holds), from the world."""
    assert loopback.world is not None
    return loopback.world.samples


def shipped_run(scenario: str) -> tuple[dict, list[TrajectorySample]]:
    """The shipped ``scenario`` as it is, in lockstep with every network interface off (as
    :func:`run_lockstep`): its report and its trajectory (a fleet's: every car's, one car after
    the other). Run once per test process and shared by the tests that check the same run
    (tests/test_sim_lockstep.py's determinism, tests/test_sim_hazards.py's shipped config,
    tests/test_sim_scenarios.py's outcomes): a lockstep run is the same every time (that is what
    the determinism test proves, against a run of its own), so running it again for each would
    prove nothing more. Each caller gets its own copy of the report. Tests that share a run carry
    :func:`shares_run`'s mark, so that pytest-xdist's ``--dist loadgroup`` sends them to one worker."""
    report, samples = _shipped_run(scenario)
    return copy.deepcopy(report), list(samples)


@functools.cache
def _shipped_run(scenario: str) -> tuple[dict, tuple[TrajectorySample, ...]]:
    loaded = load_scenario(scenario)
    if loaded.cars:
        fleet = Fleet(loaded, overrides=[*OFFLINE])
        report = lockstep.run(fleet.run()).report
        samples = [s for car in fleet.cars.values() if car.world for s in car.world.samples]
    else:
        result, lb = run_lockstep(scenario)
        report, samples = result.report, trajectory(lb)
    return report, tuple(samples)


def shares_run(scenario: str) -> pytest.MarkDecorator:
    """The mark of a test that uses :func:`shipped_run` (``scenario``): its xdist group, one per
    scenario, so that every test of one shared run lands on the same worker."""
    return pytest.mark.xdist_group(f"lockstep-{scenario}")
