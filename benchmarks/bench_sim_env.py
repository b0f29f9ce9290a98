"""Steps per second of the step API (``racecar_hw.sim.env.RaceEnv``) on the track scenario.

Each step is one control period (20 ms of virtual time at ``mux.rate_hz`` 50): the world steps four
times (200 Hz), the fake UST-10LX casts 1081 beams every 25 ms, and the real daemon takes the scan,
the VESC telemetry and one control tick, in lockstep. Policies: ``idle`` (the car stands: no
command) and ``wall follower`` (``racecar_hw.sim.policies.follow_right_wall``, driving the first corners of a
lap). Rates are per wall-clock second and per CPU second of this process (``time.process_time``:
less sensitive to other load on a shared machine); ``x real time`` is virtual over wall time.
A reset (the previous episode's daemon stopped and its fakes unplugged, a new one started until
the car is ready) is timed on its own.

Run ``python benchmarks/bench_sim_env.py [STEPS]`` (default 1000); ``run()`` returns the rows for
run_all.py.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import numpy as np
from table import print_rows

from racecar_hw.sim.env import RaceEnv
from racecar_hw.sim.policies import follow_right_wall

Policy = Callable[[np.ndarray, np.ndarray], tuple[float, float]]


def idle(ranges: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """The car stands."""
    return 0.0, 0.0


def _episode(env: RaceEnv, policy: Policy, steps: int) -> tuple[float, float, float]:
    """(reset wall s, steps per wall s, steps per CPU s) of one episode."""
    t0 = time.perf_counter()
    obs, _ = env.reset("track", seed=1)
    reset_s = time.perf_counter() - t0
    angles = env.scan_angles
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        obs, *_ = env.step(policy(obs["scan"], angles))
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return reset_s, steps / wall, steps / max(cpu, 1e-9)


def run(steps: int = 1000) -> list[dict]:
    """Rows: steps/s (wall and CPU) and x real time per policy; the reset's wall time."""
    rows: list[dict] = []
    resets = []
    with RaceEnv("track") as env:
        _episode(env, idle, 50)  # warm up: imports, the map's caches
        for name, policy in (("idle", idle), ("wall_follower", follow_right_wall)):
            reset_s, per_wall, per_cpu = _episode(env, policy, steps)
            resets.append(reset_s)
            rows += [
                {"name": f"sim_env_track_{name}_steps_per_s", "value": per_wall, "unit": "steps/s",
                 "target": None},
                {"name": f"sim_env_track_{name}_steps_per_cpu_s", "value": per_cpu, "unit": "steps/s",
                 "target": None},
                {"name": f"sim_env_track_{name}_x_real_time", "value": per_wall * env.period_s,
                 "unit": "x", "target": None},
            ]
    rows.append({"name": "sim_env_reset", "value": min(resets), "unit": "s", "target": None})
    return rows


if __name__ == "__main__":
    print_rows(run(int(sys.argv[1]) if len(sys.argv) > 1 else 1000))
