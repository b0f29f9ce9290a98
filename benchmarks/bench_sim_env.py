"""Steps per second of the step API (``racecar_hw.sim.env.RaceEnv``) on the track scenario.

Each step is one control period (20 ms of virtual time at ``mux.rate_hz`` 50): the world steps four
times (200 Hz), the fake UST-10LX casts 1081 beams every 25 ms, and the real daemon takes the scan,
the VESC telemetry and one control tick, in lockstep. Policies: ``idle`` (the car stands: no
command) and ``wall follower`` (the test's right-wall follower, driving the first corners of a
lap). Rates are per wall-clock second and per CPU second of this process (``time.process_time``:
less sensitive to other load on a shared machine); ``x real time`` is virtual over wall time.
A reset (the previous episode's daemon stopped and its fakes unplugged, a new one started until
the car is ready) is timed on its own.

Run ``python benchmarks/bench_sim_env.py [STEPS]`` (default 1000); ``run()`` returns the rows for
run_all.py.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable

import numpy as np
from table import print_rows

from racecar_hw.sim.env import RaceEnv

STEERING_MAX_RAD = 0.26
Policy = Callable[[np.ndarray, np.ndarray], tuple[float, float]]


def _range_at(ranges: np.ndarray, angles: np.ndarray, angle: float, width: float = 0.04) -> float:
    values = ranges[np.abs(angles - angle) <= width]
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else math.inf


def wall_follower(ranges: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """0.8 m from the right-hand wall, left where a wall comes up ahead (as tests/test_sim_env.py)."""
    theta = math.radians(50.0)
    b = _range_at(ranges, angles, -math.pi / 2)
    a = _range_at(ranges, angles, -math.pi / 2 + theta)
    front = _range_at(ranges, angles, 0.0, 0.15)
    b = b if math.isfinite(b) else 3.0
    a = a if math.isfinite(a) else b / math.cos(theta)
    alpha = math.atan2(a * math.cos(theta) - b, a * math.sin(theta))
    steering = 1.2 * (0.8 - (b * math.cos(alpha) + 0.6 * math.sin(alpha)))
    if front < 2.5:
        steering += 0.6 * (2.5 - front)
    steering = max(-STEERING_MAX_RAD, min(STEERING_MAX_RAD, steering))
    speed = min(2.0, max(0.6, 0.7 * (front - 0.8)))
    return speed * (1.0 - 0.5 * abs(steering) / STEERING_MAX_RAD), steering


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
        for name, policy in (("idle", idle), ("wall_follower", wall_follower)):
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
