"""A component that fails while the daemon runs ends the run: logged, the car braked, the failure
named in the report and the exit status (it was logged only if it was among the first tasks to
end, and the car drove on without it). In lockstep, in this process."""

from __future__ import annotations

import asyncio
import logging

import pytest
from lockstep_sim import run_lockstep

from racecar_hw.sim.loopback import Loopback

pytestmark = pytest.mark.quiet  # lockstep, interfaces off


class Broken(RuntimeError):
    pass


def test_a_component_failing_mid_run_stops_the_run_and_brakes(caplog):
    def setup(loopback: Loopback) -> None:
        daemon = loopback.daemon
        assert daemon is not None

        async def ends_early() -> None:  # a component that finishes on its own first (a figure-8)
            await asyncio.sleep(0.5)

        async def breaks() -> None:
            await asyncio.sleep(3.0)
            raise Broken("the ground-station link broke")

        daemon.add_task(ends_early())
        daemon.add_task(breaks())

    with caplog.at_level(logging.ERROR, logger="racecar_hw.daemon"):
        result, loopback = run_lockstep("figure8", duration_s=20.0, setup=setup)
    report = result.report
    assert loopback.daemon is not None and isinstance(loopback.daemon.failure[1], Broken)
    assert report["interrupted"] and "breaks" in report["stop_reason"]
    assert "the ground-station link broke" in report["stop_reason"]
    assert 3.0 <= report["sim_time_s"] < 5.0  # stopped at the failure, not at 20 s
    assert any("component failed, stopping" in r.getMessage() for r in caplog.records)
    assert loopback.vesc is not None and loopback.vesc.erpm == 0  # braked: rolled to rest
