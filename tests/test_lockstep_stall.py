"""``VirtualTimeLoop.stall``: a hold-up of the process on virtual time, for tests of hold-ups."""

from __future__ import annotations

import asyncio
import math

import pytest

from racecar_hw.base.clock import SIM_EPOCH_NS, monotonic_ns
from racecar_hw.runtime import lockstep


def test_a_stall_moves_time_at_once_and_the_overdue_timers_run_in_one_pass_in_deadline_order():
    async def scenario() -> tuple[list[tuple[str, int]], int, int]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, lockstep.VirtualTimeLoop)
        ran: list[tuple[str, int]] = []
        start = loop.now_ns()
        for name, after in (("c", 0.08), ("a", 0.01), ("b", 0.03), ("late", 0.2)):
            loop.call_later(after, lambda name=name: ran.append((name, monotonic_ns() - start)))
        loop.stall(0.09)
        stalled = monotonic_ns() - start  # the clock moved with nothing run
        assert ran == []
        await asyncio.sleep(0)
        return ran, stalled, loop.now_ns() - start

    ran, stalled, after = lockstep.run(scenario())
    assert stalled == after == 90_000_000
    # every timer that fell due ran at the end of the stall, in the order of its deadline
    assert ran == [("a", 90_000_000), ("b", 90_000_000), ("c", 90_000_000)]


@pytest.mark.parametrize("seconds", [-0.1, math.nan, math.inf])
def test_a_stall_lasts_zero_or_more_finite_seconds(seconds):
    loop = lockstep.VirtualTimeLoop()
    try:
        with pytest.raises(ValueError, match="zero or more seconds"):
            loop.stall(seconds)
        loop.stall(0.0)
        assert loop.now_ns() == SIM_EPOCH_NS
    finally:
        loop.close()
