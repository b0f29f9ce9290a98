"""Cost of the loopback world: lidar ray casting and world steps on the shipped maps.

A 1081-beam UST-10LX scan (-135..135 degrees) every 25 ms must cost well under the period:
the target is a mean below 3 ms per scan on the track along a lap. A world step at 200 Hz
(bicycle, footprint collision check, clearance) should stay well below 1 ms.
Times are CPU time of the calling thread (``time.thread_time_ns``), so other processes on a busy
machine do not inflate them; map load is wall time.

Run ``python benchmarks/bench_sim.py``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import math
import time

import numpy as np
from table import print_rows

from racecar_hw.sim.car import CarParams
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.raycast import RayCaster
from racecar_hw.sim.world import World

BEAMS = 1081
TARGET_SCAN_MS = 3.0
ANGLES = np.linspace(-math.radians(135), math.radians(135), BEAMS)

#: sensor poses along each map's drivable space (map frame, m and rad)
POSES = {
    "track": [(0.0, 0.0, 0.0), (5.0, 0.5, 0.05), (14.75, 5.0, math.pi / 2), (8.0, 11.25, math.pi),
              (-2.75, 6.0, -math.pi / 2), (9.0, 7.5, 1.0)],
    "corridor": [(0.0, 0.0, 0.0), (10.0, 0.4, 0.02), (20.0, -0.3, -0.05)],
    "room": [(0.0, 0.0, 0.0), (3.0, 2.0, 2.0), (-2.0, -3.0, -0.7)],
}


def _scan_ms(name: str, max_range: float, rounds: int) -> tuple[float, float]:
    caster = RayCaster(load_shipped_map(name))
    poses = POSES[name]
    samples = []
    for k in range(rounds + 20):
        x, y, yaw = poses[k % len(poses)]
        t0 = time.thread_time_ns()
        caster.cast(x, y, yaw, ANGLES, max_range)
        if k >= 20:
            samples.append(time.thread_time_ns() - t0)
    a = np.asarray(samples) / 1e6
    return float(a.mean()), float(np.percentile(a, 99))


def _map_load_ms(name: str) -> float:
    t0 = time.perf_counter_ns()
    RayCaster(load_shipped_map(name))
    return (time.perf_counter_ns() - t0) / 1e6


def _step_ms(rounds: int) -> float:
    p = CarParams()
    world = World(load_shipped_map("corridor"), p, erpm_source=lambda: 2.0 * p.speed_to_erpm_gain)
    t0 = time.thread_time_ns()
    for _ in range(rounds):
        world.step(0.005)
    return (time.thread_time_ns() - t0) / 1e6 / rounds


def run(rounds: int = 300) -> list[dict]:
    """Rows: scan cost per map (mean and p99, 10 m and 30 m range), map load, world step."""
    rows = []
    for name in ("track", "corridor", "room"):
        for max_range in (10.0, 30.0):
            mean, p99 = _scan_ms(name, max_range, rounds)
            target = TARGET_SCAN_MS if (name, max_range) == ("track", 10.0) else None
            rows.append({"name": f"sim_scan_{BEAMS}_{name}_{max_range:.0f}m_mean", "value": mean,
                         "unit": "ms", "target": target})
            rows.append({"name": f"sim_scan_{BEAMS}_{name}_{max_range:.0f}m_p99", "value": p99,
                         "unit": "ms", "target": None})
        rows.append({"name": f"sim_map_load_{name}", "value": _map_load_ms(name), "unit": "ms",
                     "target": None})
    rows.append({"name": "sim_world_step_2mps", "value": _step_ms(2000), "unit": "ms", "target": 1.0})
    return rows


def main() -> None:
    """Print the table."""
    rows = run()
    print_rows(rows)


if __name__ == "__main__":
    main()
