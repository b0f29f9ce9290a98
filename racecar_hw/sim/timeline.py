"""A sim run's two clocks: sim time since the world started, scenario time since the car was ready.

Sim time (s) is the world's (real, monotonic time since it started); the report and the
trajectory use it. Scenario time (s) starts when the car is ready to drive (the VESC answered and
the first scan is in); drivers, faults, obstacles and the duration count from there.
"""

from __future__ import annotations

import asyncio
import logging
import math
from typing import Any

from racecar_hw.daemon import Daemon
from racecar_hw.sim.world import World

log = logging.getLogger(__name__)


class ScenarioClock:
    """Sim and scenario time of one run: set :attr:`world` and :attr:`daemon` once they exist."""

    def __init__(self) -> None:
        self.world: World | None = None
        self.daemon: Daemon | None = None
        #: world time (s) when the car was ready to drive: the scenario's time zero
        self.ready_at_s: float | None = None

    def sim_time(self) -> float:
        """Seconds since the world started (the time in the report and the trajectory)."""
        return self.world.sim_time if self.world is not None else 0.0

    def scenario_time(self) -> float:
        """Seconds since the car was ready: drivers, faults and the duration count from there."""
        return self.sim_time() - (self.ready_at_s if self.ready_at_s is not None else math.inf)

    async def wait_until(self, t_s: float) -> None:
        """Wait until scenario time ``t_s`` (after the car is ready)."""
        await self.wait_ready()
        # a sleep for what is left, then a look: the world's time moves in steps, so the last
        # wait is at most a step (1 ms sleeps), and a long wait wakes the loop once, not every 20 ms
        while (left := t_s - self.scenario_time()) > 0:
            await asyncio.sleep(max(0.001, left))

    async def wait_ready(self, timeout_s: float = 15.0) -> None:
        """Wait until the car is ready to drive: the VESC answered and the first scan is in.

        A driver on a real car waits for the same; commanding earlier only makes the safety
        controller hold the car (no scan yet), which would count as an intervention.
        """
        assert self.daemon is not None
        daemon = self.daemon
        deadline = asyncio.get_running_loop().time() + timeout_s
        while self.ready_at_s is None:
            vesc_ok = daemon.vesc is None or daemon.vesc.connected
            lidar_ok = daemon.lidar is None or daemon.lidar.stats.scans > 0
            if (vesc_ok and lidar_ok) or asyncio.get_running_loop().time() > deadline:
                if not (vesc_ok and lidar_ok):
                    log.warning("sim: devices not ready after %.0f s; starting anyway", timeout_s)
                self.ready_at_s = self.sim_time()
                return
            await asyncio.sleep(0.01)

    async def until(self, coro: Any, until_s: float | None) -> None:
        """Run ``coro`` until it ends or, with ``until_s``, until that scenario time."""
        task = asyncio.ensure_future(coro)
        if until_s is None:
            await task
            return
        waiter = asyncio.ensure_future(self.wait_until(until_s))
        await asyncio.wait([task, waiter], return_when=asyncio.FIRST_COMPLETED)
        for t in (task, waiter):
            t.cancel()
        await asyncio.gather(task, waiter, return_exceptions=True)


__all__ = ["ScenarioClock"]
