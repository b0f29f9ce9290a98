"""The periodic loop timer: absolute deadlines, skipped (never burst) late ticks, errors, cancel."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import pytest

from racecar_hw.runtime.ticker import PeriodicTimer, _catch_up


def test_catch_up_skips_whole_missed_periods() -> None:
    assert _catch_up(0, 5, 10) == (0, 0)           # early or on time: run this deadline
    assert _catch_up(0, 9, 10) == (0, 0)           # late by less than a period: run it late
    assert _catch_up(0, 10, 10) == (10, 1)         # a whole period late: skip one
    assert _catch_up(100, 135, 10) == (130, 3)


def test_periodic_timer_ticks_on_absolute_deadlines() -> None:
    calls: list[tuple[int, int]] = []

    async def scenario() -> PeriodicTimer:
        done = asyncio.get_running_loop().create_future()

        def tick(due: int, periods: int) -> None:
            calls.append((due, periods))
            if len(calls) == 3:
                time.sleep(0.12)  # stall the loop across two deadlines
            if len(calls) == 6:
                done.set_result(None)

        timer = PeriodicTimer(50.0, tick)
        timer.start()
        await asyncio.wait_for(done, 10)
        timer.cancel()
        return timer

    timer = asyncio.run(scenario())
    dues = [d for d, _ in calls]
    period = timer.period_ns
    start = dues[0]
    assert all((d - start) % period == 0 for d in dues)  # on the grid, no drift
    assert dues == sorted(set(dues))
    steps = [(b - a) // period for a, b in zip(dues, dues[1:], strict=False)]
    assert [p for _, p in calls[1:]] == steps  # periods counts the skipped deadlines
    assert sum(s - 1 for s in steps) == timer.missed >= 1  # the stall skipped ticks...
    assert timer.count == len(calls) == 6  # ...and replayed none
    assert not timer.running


def test_periodic_timer_error_stops_it_and_reaches_the_handler() -> None:
    errors: list[BaseException] = []
    calls = 0

    async def scenario() -> PeriodicTimer:
        def tick(due: int, periods: int) -> None:
            nonlocal calls
            calls += 1
            if calls == 2:
                raise RuntimeError("boom")

        timer = PeriodicTimer(200.0, tick, on_error=errors.append)
        timer.start()
        deadline = time.monotonic() + 10
        while not errors and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)  # several periods: no tick may follow the error
        return timer

    timer = asyncio.run(scenario())
    assert [type(e) for e in errors] == [RuntimeError]
    assert calls == 2 and not timer.running


def test_periodic_timer_rejects_a_bad_rate() -> None:
    with pytest.raises(ValueError):
        PeriodicTimer(0.0, lambda due, periods: None)


def test_timers_of_related_rates_share_their_deadlines() -> None:
    dues: dict[str, list[int]] = {"a": [], "b": [], "slow": []}

    async def scenario() -> None:
        done = asyncio.get_running_loop().create_future()

        def tick(name: str) -> Callable[[int, int], None]:
            def record(due: int, periods: int) -> None:
                dues[name].append(due)
                if len(dues["b"]) >= 6 and not done.done():
                    done.set_result(None)
            return record

        timers = [PeriodicTimer(50.0, tick("a")), PeriodicTimer(20.0, tick("slow"))]
        for timer in timers:
            timer.start()
        await asyncio.sleep(0.013)  # a later start, off the first timers' phase
        timers.append(PeriodicTimer(50.0, tick("b")))
        timers[-1].start()
        await asyncio.wait_for(done, 10)
        for timer in timers:
            timer.cancel()

    asyncio.run(scenario())
    assert all(d % 20_000_000 == 0 for d in dues["a"] + dues["b"])  # one 50 Hz grid
    assert all(d % 50_000_000 == 0 for d in dues["slow"])
    assert set(dues["b"][1:]) <= set(dues["a"])  # the later timer wakes with the first one
