"""Scenario runs in lockstep for the tests: the real daemon, drivers, codecs and fakes on the
simulation's virtual clock (:mod:`racecar_hw.runtime.lockstep`), in this process, as fast as the
machine allows. The same inputs give the same run on an idle or a loaded machine, so a test can
expect exact outcomes where a real-time run needed bands for the scheduler's hold-ups."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from conftest import NO_DDS, NO_ZENOH

from racecar_hw.runtime import lockstep
from racecar_hw.sim.loopback import Loopback, SimResult
from racecar_hw.sim.scenario import load_scenario

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
