"""Cost of several cars in one world (issue 27): lockstep runs of one and of two cars, and the
coupling between their worlds.

A fleet runs in one lockstep loop (one process, one thread), so what it costs is CPU time per
second of sim time: under 1 s per sim second keeps up with real time (``racecar-hw sim --scenario
two-cars`` without ``--speed`` is paced at real time; clients over Zenoh drive at that pace). The
rows: process CPU time per sim second of a single car (the corridor at 1.5 m/s, a UST-10LX; the
same with the leader's RPLIDAR A2M8) and of the shipped two-cars scenario (both daemons, both
worlds, each seeing the other), with the network interfaces off; and, on two bare worlds, the
cost of one :class:`~racecar_hw.sim.fleet.CarShadow` lookup (the other car's footprint at a time)
and of one footprint-to-footprint gap (what each world step and clearance pays per other car).
CPU times (``time.process_time``, ``time.thread_time_ns``), so a busy machine does not inflate them.

Run ``python benchmarks/bench_fleet.py``; ``run()`` returns the rows.
"""

from __future__ import annotations

import time

from table import print_rows

from racecar_hw.runtime import lockstep
from racecar_hw.sim.car import CarParams, footprint
from racecar_hw.sim.fleet import CarShadow, Fleet
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.scenario import load_scenario
from racecar_hw.sim.world import World

QUIET = ["zenoh.enabled=false", "dds.enabled=false", "foxglove.port=0", "web.port=0"]
RPLIDAR = ["safety.scan_timeout_s=0.3", "safety.scan_period_s=0.1"]


def _cpu_per_sim_s(make) -> float:  # noqa: ANN001 - a factory of Loopback or Fleet
    c0 = time.process_time()
    report = lockstep.run(make().run(), None).report
    return (time.process_time() - c0) / report["sim_time_s"]


def _one_car(*sets: str, config: tuple[str, ...] = ()) -> Loopback:
    scenario = load_scenario("corridor", ["duration_s=10", "drivers.0.speed_mps=1.5", *sets])
    return Loopback(scenario, overrides=[*QUIET, *config], lockstep=True)


def _coupling_us(rounds: int) -> tuple[float, float]:
    p = CarParams()
    occ = load_shipped_map("corridor")
    lead = World(occ, p, (3.0, 0.0, 0.0), lambda: 1.5 * p.speed_to_erpm_gain)
    follow = World(occ, p, (0.0, 0.0, 0.0))
    for _ in range(200):
        lead.step(0.005)
        follow.step(0.005)
    shadow = CarShadow("leader", lambda: follow, lambda: lead)
    t0 = time.thread_time_ns()
    for k in range(rounds):
        shape = shadow.at(0.5 + k * 1e-4)
    lookup = (time.thread_time_ns() - t0) / 1e3 / rounds
    corners = footprint(follow.pose, p)
    t0 = time.thread_time_ns()
    for _ in range(rounds):
        shape.distance_to(corners)
    gap = (time.thread_time_ns() - t0) / 1e3 / rounds
    return lookup, gap


def run() -> list[dict]:
    """Rows: CPU s per sim s of one car, one RPLIDAR car and two cars; the coupling's costs."""
    lookup, gap = _coupling_us(5000)
    return [
        {"name": "fleet_one_car_ust10lx_cpu_per_sim_s", "value": _cpu_per_sim_s(lambda: _one_car()),
         "unit": "s/s", "target": None, "higher_is_better": False},
        {"name": "fleet_one_car_a2m8_cpu_per_sim_s",
         "value": _cpu_per_sim_s(lambda: _one_car("lidar={model: a2m8, transport: pty}",
                                                  config=tuple(RPLIDAR))),
         "unit": "s/s", "target": None, "higher_is_better": False},
        {"name": "fleet_two_cars_cpu_per_sim_s",
         "value": _cpu_per_sim_s(lambda: Fleet(load_scenario("two-cars"), overrides=QUIET)),
         "unit": "s/s", "target": 1.0, "higher_is_better": False},
        {"name": "fleet_shadow_lookup", "value": lookup, "unit": "us", "target": None},
        {"name": "fleet_footprint_gap", "value": gap, "unit": "us", "target": None},
    ]


def main() -> None:
    """Print the table."""
    print_rows(run())


if __name__ == "__main__":
    main()
